import diffrax as dfx
import optimistix as optx
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike
from .._discrete import MidpointRule
from .base import (
    AbstractSymmetricSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    implicit_vi_init,
    implicit_vi_step,
    Substep,
)


class MidpointVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractSymmetricSolver
):
    r"""Midpoint variational integrator.

    2nd order symmetric symplectic variational integrator. One nonlinear solve per step
    (Newton, from a second-order extrapolated guess). Fixed step sizes only. Cubic
    Hermite interpolation for dense output.

    Discrete Lagrangian (the seed's (3.3)):

    $$L_d(q_0, q_1) = h\,L\Big(t_0 + \tfrac h2, \tfrac{q_0 + q_1}2,
    \tfrac{q_1 - q_0}h\Big),$$

    stepped in position–momentum form on $y = (q, p)$: solve
    $p_0 = -D_1 L_d(q_0, q_1)$ for $q_1$, then $p_1 = D_2 L_d(q_0, q_1)$. It conserves
    every quadratic first integral and, by the discrete Noether theorem, the momentum
    of every symmetry of $L$.

    ??? cite "Reference"

        ```bibtex
        @mastersthesis{hirani2000linearization,
            title={Linearization methods for variational integrators and
                   {E}uler--{L}agrange equations},
            author={Hirani, Anil N.},
            school={California Institute of Technology},
            year={2000},
        }
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
        return implicit_vi_init(terms, "MidpointVI", t0, y0, args, self.compensated)

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
        return implicit_vi_step(
            MidpointRule(),
            self.root_finder,
            self.root_find_max_steps,
            terms,
            "MidpointVI",
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


MidpointVI.__init__.__doc__ = """**Arguments:**

- `root_finder`: an `optimistix.AbstractRootFinder` for the implicit step. Defaults to
    `optimistix.Newton` with `rtol = atol = sqrt(eps)` of the state's dtype: with
    Newton's quadratic convergence this leaves the solve's error at round-off in float32
    and float64 alike.
- `root_find_max_steps`: iterations after which a step is reported as failed
    (`RESULTS.nonlinear_max_steps_reached`): usually a sign that the step is too large.
- `compensated`: compensated (Kahan) summation of each step's increment (default),
    so that round-off in the energy grows like the square root of the number of steps
    rather than linearly (Brouwer's law). Costs a few additions per step.
"""
