from typing import ClassVar

import diffrax as dfx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from diffrax._term import WrapTerm  # diffeqsolve wraps every term in it (private).
from equinox import AbstractVar
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike, V
from .._discrete import AbstractDiscreteLagrangian, discrete_hamiltonian_map
from .._misc import all_finite, default_root_finder, split_state, state_dtype
from .._term import hamilton_vector_field, LagrangianTerm


class AbstractSymplecticSolver(dfx.AbstractSolver):
    """Marker for solvers whose step map is symplectic on `y = (q, p)`.

    Symplecticity, and with it bounded energy error over exponentially long times, holds
    for fixed step sizes only: adaptive stepping (e.g. through `diffrax.HalfSolver`)
    destroys it.
    """


class AbstractSymmetricSolver(dfx.AbstractSolver):
    """Marker for solvers whose step is symmetric (time-reversible): a step of `h`
    followed by a step of `-h` returns to the start. Only these can be raised to higher
    order by [`diffrax_vi.Composition`][]."""


class AbstractVariationalSolver(dfx.AbstractSolver):
    """Base class for variational integrators: solvers that read the Lagrangian of a
    [`diffrax_vi.LagrangianTerm`][] and step its discrete Euler–Lagrange equations on
    `y = (q, p)`. The one-step ones are also
    [`diffrax_vi.AbstractSymplecticSolver`][]s; the multistep
    [`diffrax_vi.LinearizedVI`][] is only presymplectic.

    Dense output is cubic Hermite interpolation through the states and Hamilton's
    vector field at both ends of each step.
    """

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar = dfx.ThirdOrderHermitePolynomialInterpolation

    root_finder: AbstractVar[optx.AbstractRootFinder | None]
    root_find_max_steps: AbstractVar[int]
    compensated: AbstractVar[bool]


def initial_compensation(y: PyTree, enabled: bool) -> PyTree | None:
    """Zero compensation for `y`, or `None` (no state to carry) when disabled."""
    return jtu.tree_map(jnp.zeros_like, y) if enabled else None


def compensated_add(
    y0: PyTree, increment: PyTree, compensation: PyTree | None
) -> tuple[PyTree, PyTree | None]:
    """`y0 + increment` with compensated (Kahan) summation.

    `compensation` carries the rounding error of the previous additions, fed back into
    the next increment; `None` means a plain sum. It is at most an ulp of `y0`, so it
    needs no reset after a jump.
    """
    if compensation is None:
        return jtu.tree_map(lambda a, b: a + b, y0, increment), None
    corrected = jtu.tree_map(lambda d, c: d - c, increment, compensation)
    y1 = jtu.tree_map(lambda a, d: a + d, y0, corrected)
    compensation = jtu.tree_map(lambda a, b, d: (b - a) - d, y0, y1, corrected)
    return y1, compensation


def unwrap_term(terms: dfx.AbstractTerm, solver: str) -> tuple[LagrangianTerm, Array]:
    """The user's `LagrangianTerm` inside diffrax's `WrapTerm`, and the time direction
    (`+1`, or `-1` when integrating backwards)."""
    direction = jnp.array(1)
    if isinstance(terms, WrapTerm):
        direction = jnp.asarray(terms.direction)
        terms = terms.term
    if not isinstance(terms, LagrangianTerm):
        raise ValueError(
            f"{solver} integrates a Lagrangian and needs a "
            f"`diffrax_vi.LagrangianTerm`, but got {type(terms).__name__}. "
            "Wrap the Lagrangian: "
            f"`diffeqsolve(diffrax_vi.LagrangianTerm(L), {solver}(), ...)` with "
            "`y0 = (q0, p0)`. For Hamilton's equations given as a pair "
            "`(ODETerm(dq/dt), ODETerm(dp/dt))`, use `diffrax_vi.StormerVerlet()`."
        )
    return terms, direction


# A substep of a composition: the fraction `gamma` of the step from `T0` to `T1`.
Substep = tuple[float, RealScalarLike, RealScalarLike]


def step_control(
    term: dfx.AbstractTerm,
    t0: RealScalarLike,
    t1: RealScalarLike,
    substep: Substep | None = None,
) -> PyTree:
    """`term.contr(t0, t1)`; for a substep of a composition, `gamma` times the control
    of the whole step. The difference `t1 - t0` of two sub-times near a large `t`
    carries their rounding, an ulp of `t`, into the substep's size: at t = 2^30 that
    breaks kahan_li8's order conditions at 4e-5 and its energy error grows from
    2.5e-12 to 2.3e-8 in ten Kepler orbits."""
    if substep is None:
        return term.contr(t0, t1)
    gamma, step_t0, step_t1 = substep
    return jtu.tree_map(lambda c: gamma * c, term.contr(step_t0, step_t1))


def step_times(
    terms: dfx.AbstractTerm,
    direction: Array,
    t0: RealScalarLike,
    t1: RealScalarLike,
    dtype: np.dtype,
    substep: Substep | None = None,
) -> tuple[Array, Array, Array]:
    """Physical start and end times and the signed step, in the state's dtype."""
    h = jnp.asarray(step_control(terms, t0, t1, substep), dtype=dtype)
    tp0 = jnp.asarray(direction * t0, dtype=dtype)
    tp1 = jnp.asarray(direction * t1, dtype=dtype)
    return tp0, tp1, h


def step_result(
    result: dfx.RESULTS, y0: PyTree, y1: PyTree, start_ok: Bool[Array, ""]
) -> dfx.RESULTS:
    """Fold the checks every variational step makes into one `RESULTS`.

    A NaN or inf state (at the start, or produced by a step that otherwise succeeded)
    is `RESULTS.nonfinite`; a finite start at which the Legendre map could not be
    inverted is `RESULTS.singular`.
    """
    y0_ok = all_finite(y0)
    result = dfx.RESULTS.where(y0_ok & ~start_ok, dfx.RESULTS.singular, result)
    became_nonfinite = (result == dfx.RESULTS.successful) & ~all_finite(y1)
    result = dfx.RESULTS.where(~y0_ok | became_nonfinite, dfx.RESULTS.nonfinite, result)
    return result


def hermite_dense_info(
    lagrangian,
    tp0: Array,
    tp1: Array,
    h: Array,
    y0: PyTree,
    y1: PyTree,
    args: Args,
    v_guess: V,
) -> dict[str, PyTree]:
    """Dense output data: the states and `h` times Hamilton's vector field at both ends.

    Only evaluated if the output is interpolated: otherwise it is dead code that XLA
    removes.
    """
    f0, _ = hamilton_vector_field(lagrangian, tp0, *y0, args, v_guess=v_guess)
    f1, _ = hamilton_vector_field(lagrangian, tp1, *y1, args, v_guess=v_guess)
    scale = lambda f: jtu.tree_map(lambda x: h * x, f)
    return dict(y0=y0, y1=y1, k0=scale(f0), k1=scale(f1))


# The implicit position–momentum step shared by every variational solver built on a
# discrete Lagrangian. Its state is the velocity of the last two steps, `(v_{k-1/2},
# v_{k-3/2})`, from which the next step's Newton guess is extrapolated, and the
# compensation of the summation.
_VIState = tuple[tuple[V, V], PyTree]


def implicit_vi_init(
    terms: dfx.AbstractTerm,
    solver: str,
    t0: RealScalarLike,
    y0: PyTree,
    args: Args,
    compensated: bool,
) -> _VIState:
    term, direction = unwrap_term(terms, solver)
    q0, p0 = split_state(y0)
    dtype = state_dtype(y0)
    tp0 = jnp.asarray(direction * t0, dtype=dtype)
    (v0, _), result = hamilton_vector_field(term.lagrangian, tp0, q0, p0, args)
    # A Legendre map that cannot be inverted at the start leaves a NaN guess, which the
    # first step reports as `RESULTS.singular`.
    ok = result == dfx.RESULTS.successful
    v0 = jtu.tree_map(lambda v: jnp.where(ok, v, jnp.nan), v0)
    return (v0, v0), initial_compensation(y0, compensated)


def implicit_vi_step(
    rule: AbstractDiscreteLagrangian,
    root_finder: optx.AbstractRootFinder | None,
    max_steps: int,
    terms: dfx.AbstractTerm,
    solver: str,
    t0: RealScalarLike,
    t1: RealScalarLike,
    y0: PyTree,
    args: Args,
    solver_state: _VIState,
    made_jump: bool | Bool[ArrayLike, ""],
    substep: Substep | None = None,
):
    term, direction = unwrap_term(terms, solver)
    q0, p0 = split_state(y0)
    dtype = state_dtype(y0)
    tp0, tp1, h = step_times(terms, direction, t0, t1, dtype, substep)
    if root_finder is None:
        root_finder = default_root_finder(dtype)
    (v_prev, v_prev2), compensation = solver_state
    # Second-order extrapolation of the step velocity; after a jump only the last
    # velocity is trusted.
    v_guess = jtu.tree_map(
        lambda a, b: jnp.where(made_jump, a, 2 * a - b), v_prev, v_prev2
    )
    dq, dp, v, result = discrete_hamiltonian_map(
        rule, term.lagrangian, tp0, h, q0, p0, args, v_guess, root_finder, max_steps
    )
    y1, compensation = compensated_add(y0, (dq, dp), compensation)
    result = step_result(result, y0, y1, all_finite(v_prev))
    dense_info = hermite_dense_info(term.lagrangian, tp0, tp1, h, y0, y1, args, v)
    return y1, None, dense_info, ((v, v_prev), compensation), result
