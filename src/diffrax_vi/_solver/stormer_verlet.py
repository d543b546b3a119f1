from typing import ClassVar

import diffrax as dfx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike
from .._misc import all_finite, unvmap_any
from .base import (
    AbstractSymmetricSolver,
    AbstractSymplecticSolver,
    compensated_add,
    initial_compensation,
    step_control,
    Substep,
)


# dp/dt at the start of the step, reused from the last one, and the compensation of
# the summation.
_SolverState = tuple[PyTree, PyTree]


def _start_force(term_p, t0, y0, args):
    """`dp/dt` at the start, poisoned with NaN if the state is not finite: the first
    kick then carries the NaN into the momentum, which every step checks."""
    q0, _ = y0
    ok = all_finite(y0)
    return jtu.tree_map(lambda g: jnp.where(ok, g, jnp.nan), term_p.vf(t0, q0, args))


def _momentum_finite(p) -> Bool[Array, ""]:
    # One sum per leaf, the cheapest reduction: NaN and inf survive a sum.
    return jnp.isfinite(sum(jnp.sum(x) for x in jtu.tree_leaves(p)))


def _half(control):
    return jtu.tree_map(lambda c: 0.5 * c, control)


def _add(a, b):
    return jtu.tree_map(lambda x, y: x + y, a, b)


class StormerVerlet(AbstractSymplecticSolver, AbstractSymmetricSolver):
    r"""Störmer–Verlet (velocity Verlet, leapfrog) method for partitioned systems.

    2nd order symmetric symplectic explicit method. One evaluation of each vector
    field per step. Fixed step sizes only. Cubic Hermite interpolation for dense
    output.

    It takes the same terms as `diffrax.SemiImplicitEuler`, a pair
    `(ODETerm(f), ODETerm(g))` for `y = (q, p)` with
    $\dot q = f(t, p, \text{args})$, $\dot p = g(t, q, \text{args})$, and is a drop-in
    second-order replacement for it. The step is kick–drift–kick:

    $$p_{1/2} = p_0 + \tfrac h2 g(t_0, q_0),\quad
    q_1 = q_0 + h f(t_{1/2}, p_{1/2}),\quad
    p_1 = p_{1/2} + \tfrac h2 g(t_1, q_1).$$

    The kick $g(t_1, q_1)$ that ends a step starts the next one, so it is evaluated
    once. A NaN or inf anywhere in the initial state, or arising in a step, ends the
    solve with `RESULTS.nonfinite`: each step checks the momentum, into which a
    non-finite position passes through the next kick. (The one case this misses is a
    position that turns non-finite while $g$ does not depend on it, which needs
    $f$ to return NaN or inf for a finite momentum.)

    For $f = M^{-1}p$, $g = -\nabla V$ this is the variational integrator of the
    trapezoidal discrete Lagrangian ([`diffrax_vi.TrapezoidalVI`][]).

    ??? cite "Reference"

        ```bibtex
        @article{hairer2003geometric,
            title={Geometric numerical integration illustrated by the
                   St{\"o}rmer--Verlet method},
            author={Hairer, Ernst and Lubich, Christian and Wanner, Gerhard},
            journal={Acta Numerica},
            volume={12},
            pages={399--450},
            year={2003},
        }
        ```
    """

    term_structure: ClassVar = (dfx.AbstractTerm, dfx.AbstractTerm)
    interpolation_cls: ClassVar = dfx.ThirdOrderHermitePolynomialInterpolation

    compensated: bool = True

    def order(self, terms):
        return 2

    def init(
        self,
        terms: tuple[dfx.AbstractTerm, dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
    ) -> _SolverState:
        _, term_p = terms
        return _start_force(term_p, t0, y0, args), initial_compensation(
            y0, self.compensated
        )

    def step(
        self,
        terms: tuple[dfx.AbstractTerm, dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
        solver_state: _SolverState,
        made_jump: bool | Bool[ArrayLike, ""],
        *,
        substep: Substep | None = None,
    ) -> tuple[
        tuple[PyTree, PyTree], None, dict[str, PyTree], _SolverState, dfx.RESULTS
    ]:
        term_q, term_p = terms
        q0, p0 = y0
        # After a jump the cached force belongs to the state before the jump.
        cached, compensation = solver_state
        g0 = jax.lax.cond(
            unvmap_any(made_jump),
            lambda: _start_force(term_p, t0, y0, args),
            lambda: cached,
        )
        control_q = step_control(term_q, t0, t1, substep)
        control_p = step_control(term_p, t0, t1, substep)
        half_p = _half(control_p)
        kick0 = term_p.prod(g0, half_p)
        p_half = _add(p0, kick0)
        dq = term_q.vf_prod(0.5 * (t0 + t1), p_half, args, control_q)
        if compensation is None:
            q1 = _add(q0, dq)
            g1 = term_p.vf(t1, q1, args)
            p1 = _add(p_half, term_p.prod(g1, half_p))
        else:
            comp_q, comp_p = compensation
            q1, comp_q = compensated_add(q0, dq, comp_q)
            g1 = term_p.vf(t1, q1, args)
            dp = _add(kick0, term_p.prod(g1, half_p))
            p1, comp_p = compensated_add(p0, dp, comp_p)
            compensation = (comp_q, comp_p)
        y1 = (q1, p1)

        result = dfx.RESULTS.where(
            _momentum_finite(p1), dfx.RESULTS.successful, dfx.RESULTS.nonfinite
        )
        dense_info = dict(
            y0=y0,
            y1=y1,
            k0=(term_q.vf_prod(t0, p0, args, control_q), term_p.prod(g0, control_p)),
            k1=(term_q.vf_prod(t1, p1, args, control_q), term_p.prod(g1, control_p)),
        )
        return y1, None, dense_info, (g1, compensation), result

    def func(
        self,
        terms: tuple[dfx.AbstractTerm, dfx.AbstractTerm],
        t0: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
    ) -> tuple[PyTree, PyTree]:
        term_q, term_p = terms
        q0, p0 = y0
        return term_q.vf(t0, p0, args), term_p.vf(t0, q0, args)


StormerVerlet.__init__.__doc__ = """**Arguments:**

- `compensated`: compensated (Kahan) summation of each step's increment (default), so
    that round-off in the energy grows like the square root of the number of steps.
"""
