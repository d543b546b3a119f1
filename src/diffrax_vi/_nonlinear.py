"""The nonlinear solves of the implicit steps, in one place."""

import diffrax as dfx
import optimistix as optx
from jaxtyping import PyTree

from ._misc import default_root_finder, state_dtype


def solve_implicit(
    residual,
    guess: PyTree,
    root_finder: optx.AbstractRootFinder | None,
    max_steps: int,
) -> tuple[PyTree, dfx.RESULTS]:
    """The root of `residual(w)` from `guess`, and how the solve ended, as a
    `diffrax.RESULTS`. `root_finder=None` is Newton's method with tolerances that suit
    the dtype of `guess` ([`diffrax_vi._misc.default_root_finder`])."""
    if root_finder is None:
        root_finder = default_root_finder(state_dtype(guess))
    sol = optx.root_find(
        lambda w, _: residual(w), root_finder, guess, max_steps=max_steps, throw=False
    )
    return sol.value, dfx.RESULTS.promote(sol.result)
