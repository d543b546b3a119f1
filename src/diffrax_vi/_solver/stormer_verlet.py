from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import Args, P, Q, RealScalarLike
from .._misc import all_finite, perturbed_with, split_state, tree_add
from .base import (
    AbstractComposableSolver,
    AbstractSymplecticSolver,
    after_jump,
    check_times,
    compensated_add,
    initial_compensation,
    step_control,
    Substep,
)


def kick_drift_kick(
    p0: P,
    force0: P,
    *,
    kick: Callable[[P], P],
    drift: Callable[[P], Q],
    force: Callable[[Q], P],
    end_position: Callable[[Q], Q],
) -> tuple[Q, P, P, P]:
    r"""The Störmer–Verlet step as increments: $p_{1/2} = p_0 + \tfrac h2 g_0$,
    $q_1 = q_0 + h f(p_{1/2})$, $p_1 = p_{1/2} + \tfrac h2 g(q_1)$.

    `kick(g)` is the impulse of the force `g` over half the step, `drift(p)` the
    position increment over the step at momentum `p`, `force(q)` the force at the end
    of the step, `end_position(dq)` the position the step ends at. Returns
    `(q1 - q0, kick0, kick1, g(q1))`: the two half kicks add up to `p1 - p0`, and
    the last force starts the next step."""
    kick0 = kick(force0)
    dq = drift(tree_add(p0, kick0))
    force1 = force(end_position(dq))
    return dq, kick0, kick(force1), force1


def poisoned_force(force: P, y0: PyTree) -> P:
    """`force`, or NaN if the state `y0` is not finite: the first kick then carries
    the NaN into the momentum, which every step checks."""
    ok = all_finite(y0)
    return jtu.tree_map(lambda g: jnp.where(ok, g, jnp.nan), force)


class VerletState(eqx.Module):
    """The force at the end of the last step (the first kick of the next one) and the
    compensation of the summation (`None` when it is off)."""

    force: PyTree
    compensation: PyTree | None


class StormerVerlet(AbstractSymplecticSolver, AbstractComposableSolver):
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
    trapezoidal discrete Lagrangian ([`diffrax_vi.TrapezoidalVI`][]);
    [`diffrax_vi.terms_for`][] builds the pair from a separable Lagrangian.

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
    symmetric: ClassVar[bool] = True

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
    ) -> VerletState:
        _, term_p = terms
        q0, p0 = split_state(y0)
        force = poisoned_force(term_p.vf(t0, q0, args), y0)
        # The compensation depends on y0 after a step, and so from the start.
        compensation = perturbed_with(initial_compensation(y0, self.compensated), y0)
        return check_times(t0, t1, VerletState(force, compensation))

    def fractional_step(
        self,
        terms: tuple[dfx.AbstractTerm, dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
        solver_state: VerletState,
        made_jump: bool | Bool[ArrayLike, ""],
        substep: Substep,
        dense: bool = True,
    ) -> tuple[
        tuple[PyTree, PyTree], None, dict[str, PyTree] | None, VerletState, dfx.RESULTS
    ]:
        term_q, term_p = terms
        q0, p0 = y0
        # After a jump the cached force belongs to the state before the jump.
        force0 = after_jump(
            made_jump,
            lambda: poisoned_force(term_p.vf(t0, q0, args), y0),
            solver_state.force,
        )
        control_q = step_control(term_q, substep)
        control_p = step_control(term_p, substep)
        half_p = jtu.tree_map(lambda c: 0.5 * c, control_p)
        compensation = solver_state.compensation
        comp_q, comp_p = (None, None) if compensation is None else compensation
        dq, kick0, kick1, force1 = kick_drift_kick(
            p0,
            force0,
            kick=lambda g: term_p.prod(g, half_p),
            drift=lambda p: term_q.vf_prod(0.5 * (t0 + t1), p, args, control_q),
            force=lambda q: term_p.vf(t1, q, args),
            end_position=lambda dq: compensated_add(q0, dq, comp_q)[0],
        )
        q1, comp_q = compensated_add(q0, dq, comp_q)
        if compensation is None:
            p1 = tree_add(tree_add(p0, kick0), kick1)
        else:
            p1, comp_p = compensated_add(p0, tree_add(kick0, kick1), comp_p)
            compensation = (comp_q, comp_p)
        y1 = (q1, p1)
        result = dfx.RESULTS.where(
            all_finite(p1), dfx.RESULTS.successful, dfx.RESULTS.nonfinite
        )
        dense_info = None
        if dense:
            dense_info = dict(
                y0=y0,
                y1=y1,
                k0=(
                    term_q.vf_prod(t0, p0, args, control_q),
                    term_p.prod(force0, control_p),
                ),
                k1=(
                    term_q.vf_prod(t1, p1, args, control_q),
                    term_p.prod(force1, control_p),
                ),
            )
        return y1, None, dense_info, VerletState(force1, compensation), result

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
