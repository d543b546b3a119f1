import diffrax as dfx
import optimistix as optx
from diffrax._term import WrapTerm  # diffeqsolve wraps every term in it (private).
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike
from .._discrete import TrapezoidalRule
from .._lagrangian import AbstractSeparableLagrangian
from .._term import separable_terms
from .base import (
    AbstractSymmetricSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    implicit_vi_init,
    implicit_vi_step,
    Substep,
    unwrap_term,
)
from .stormer_verlet import StormerVerlet


def _partitioned(terms: dfx.AbstractTerm):
    """For a separable Lagrangian: its partitioned terms, wrapped like the input."""
    term, direction = unwrap_term(terms, "TrapezoidalVI")
    lagrangian = term.lagrangian
    if not isinstance(lagrangian, AbstractSeparableLagrangian):
        return None
    pair = separable_terms(lagrangian)
    if isinstance(terms, WrapTerm):
        pair = tuple(WrapTerm(t, direction) for t in pair)
    return pair


class TrapezoidalVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractSymmetricSolver
):
    r"""Trapezoidal variational integrator.

    2nd order symmetric symplectic variational integrator. Explicit (Störmer–Verlet,
    one force evaluation per step) for an
    [`diffrax_vi.AbstractSeparableLagrangian`][]; one nonlinear solve per step
    otherwise. Fixed step sizes only. Cubic Hermite interpolation for dense output.

    Discrete Lagrangian, with $v = (q_1 - q_0)/h$:

    $$L_d(q_0, q_1) = \tfrac h2\big[L(t_0, q_0, v) + L(t_0 + h, q_1, v)\big],$$

    stepped in position–momentum form on $y = (q, p)$. For
    $L = \tfrac12 v^\top M v - V(t, q)$ the step equations are explicit and are exactly
    [`diffrax_vi.StormerVerlet`][] on Hamilton's equations.

    ??? cite "Reference"

        ```bibtex
        @article{marsden2001discrete,
            title={Discrete mechanics and variational integrators},
            author={Marsden, Jerrold E. and West, Matthew},
            journal={Acta Numerica},
            volume={10},
            pages={357--514},
            year={2001},
        }
        ```
    """

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    def order(self, terms):
        return 2

    def init(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
    ) -> PyTree:
        pair = _partitioned(terms)
        if pair is not None:
            return StormerVerlet(self.compensated).init(pair, t0, t1, y0, args)
        return implicit_vi_init(terms, "TrapezoidalVI", t0, y0, args, self.compensated)

    def step(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
        *,
        substep: Substep | None = None,
    ):
        pair = _partitioned(terms)
        if pair is not None:
            return StormerVerlet(self.compensated).step(
                pair, t0, t1, y0, args, solver_state, made_jump, substep=substep
            )
        return implicit_vi_step(
            TrapezoidalRule(),
            self.root_finder,
            self.root_find_max_steps,
            terms,
            "TrapezoidalVI",
            t0,
            t1,
            y0,
            args,
            solver_state,
            made_jump,
            substep,
        )

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


TrapezoidalVI.__init__.__doc__ = """**Arguments:**

- `root_finder`: an `optimistix.AbstractRootFinder` for the implicit step of a
    non-separable Lagrangian. Defaults to `optimistix.Newton` with
    `rtol = atol = sqrt(eps)` of the state's dtype.
- `root_find_max_steps`: iterations after which a step is reported as failed.
- `compensated`: compensated (Kahan) summation of each step's increment (default).
"""
