r"""RATTLE: the constrained trapezoidal step of a separable Lagrangian, solved for the
multipliers alone.

For $L = \tfrac12 v^\top M v - V(t, q)$ (plus an applied force of the positions and
time alone, $F$ the sum of both) and holonomic constraints $g(t, q) = 0$ with
Jacobian $G$, the discrete Lagrange–d'Alembert equations of the trapezoidal rule with
the constraint forces are RATTLE (Hairer, Lubich & Wanner (2006), VII.1.4; Marsden &
West (2001), §3.5):

$$p_{1/2} = p_0 + \tfrac h2 F(t_0, q_0) + G(q_0)^\top\lambda,\qquad
q_1 = q_0 + h M^{-1} p_{1/2},\qquad g(t_1, q_1) = 0,$$

$$p_1 = p_{1/2} + \tfrac h2 F(t_1, q_1) - G(q_1)^\top\mu,\qquad
G(q_1) M^{-1} p_1 + \partial_t g(t_1, q_1) = 0.$$

The positions are explicit in the $m$ multipliers $\lambda$, so Newton's method runs
on the $m$ equations $g(t_1, q_1(\lambda)) = 0$ rather than on the $n + m$ unknowns
of the general constrained step, and $\mu$ solves one linear $m \times m$ system
(`project_constant_mass`). The force and the constraint Jacobian at $q_1$ start the
next step: one evaluation of each per step. These are the equations the general path
solves, so the states agree to the root finder's tolerance.
"""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import optimistix as optx
from jaxtyping import Array, PyTree

from .._constraint import (
    check_start as check_constraint_start,
    constraint_jacobian,
    constraint_rate,
    constraint_scale,
    constraint_values,
    project_constant_mass,
)
from .._lagrangian import broadcast_mass, mass_regular
from .._misc import all_finite
from .._root_finders import known_root, solve
from .base import after_jump, MethodStep, StepInputs
from .unknowns import KnownRoot


class RattleState(eqx.Module):
    """What a step hands to the next: the force and the constraint Jacobian at the
    end of the last step (the next one starts there), how the start ended
    (`RESULTS.nonfinite` for a NaN or inf state, `singular` for a mass that is not
    invertible; checked once, at the start: each step's end is checked by the
    engine), the position multipliers of the last two steps
    (the next step's guess extrapolates them), and the multipliers of the last
    momentum projection (the step it inverts takes them as its position
    multipliers, `unknowns.inverse_root`)."""

    force: PyTree
    jacobian: Array
    start: dfx.RESULTS
    multipliers: Array
    previous: Array
    projection: Array

    def __init__(self, force, jacobian, start, multipliers, previous, projection):
        self.force = force
        self.jacobian = jacobian
        self.start = start
        # Guesses (`unknowns.Unknowns`): held without a derivative.
        self.multipliers, self.previous, self.projection = lax.stop_gradient(
            (multipliers, previous, projection)
        )


def rattle_init(step: StepInputs, force) -> RattleState:
    """The state before the first step, after checking that the start lies on the
    constraint manifold. `force(t, q)` is $F$."""
    term = step.term
    mass = broadcast_mass(term.lagrangian.mass, step.p0)
    v0 = jtu.tree_map(lambda p, m: p / m, step.p0, mass)
    jacobian = constraint_jacobian(term.constraint, step.t0, step.q0, step.args)
    multipliers = check_constraint_start(
        term,
        step.t0,
        step.q0,
        step.p0,
        v0,
        step.args,
        jnp.zeros(jacobian.shape[:1], step.dtype),
    )
    start = dfx.RESULTS.where(
        mass_regular(mass, step.p0), dfx.RESULTS.successful, dfx.RESULTS.singular
    )
    start = dfx.RESULTS.where(
        all_finite((step.q0, step.p0)), start, dfx.RESULTS.nonfinite
    )
    return RattleState(
        force(step.t0, step.q0),
        jacobian,
        start,
        multipliers,
        multipliers,
        jnp.zeros_like(multipliers),
    )


def rattle_step(
    step: StepInputs,
    state: RattleState,
    made_jump,
    force: Callable[[Array, PyTree], PyTree],
    work: Callable[[PyTree], Array] | None,
    root_finder: optx.AbstractRootFinder | KnownRoot,
    max_steps: int,
) -> MethodStep:
    """One RATTLE step; `force(t, q)` is $F$, `work(v)` the work of the applied
    force's discrete forces at the step's velocity (`None` without one: the
    constraint forces do no work on the constrained motion). A `KnownRoot` gives
    the multipliers (the inverse step's, `ReversibleAdjoint`)."""
    term, t0, t1, h, q0, p0, args = (
        step.term,
        step.t0,
        step.t1,
        step.h,
        step.q0,
        step.p0,
        step.args,
    )
    g = term.constraint
    # After a jump the cached force and Jacobian belong to the state before it.
    force0, jacobian0 = after_jump(
        made_jump,
        lambda: (force(t0, q0), constraint_jacobian(g, t0, q0, args)),
        (state.force, state.jacobian),
    )
    mass = broadcast_mass(term.lagrangian.mass, p0)
    flat_p0, unravel = jax.flatten_util.ravel_pytree(p0)
    kicked = flat_p0 + 0.5 * h * jax.flatten_util.ravel_pytree(force0)[0]
    flat_mass = jax.flatten_util.ravel_pytree(
        jtu.tree_map(lambda p, m: jnp.broadcast_to(m, jnp.shape(p)), p0, mass)
    )[0]

    def half_step(lam):
        """$p_{1/2}$, flat."""
        return kicked + jacobian0.T @ lam

    def increment(lam):
        return unravel(h * half_step(lam) / flat_mass)

    def residual(lam):
        q1 = step.end_position(increment(lam))
        return constraint_values(g, t1, q1, args), constraint_scale(jacobian0, q1)

    # Linear extrapolation of the multipliers (error O(h^2) against O(h) for the
    # last step's: one Newton iteration fewer at moderate steps); after a jump only
    # the last step is trusted.
    guess = after_jump(
        made_jump, lambda: state.multipliers, 2 * state.multipliers - state.previous
    )
    if isinstance(root_finder, KnownRoot):
        solved = known_root(residual, root_finder.root)
    else:
        solved = solve(residual, guess, root_finder, max_steps)
    lam = solved.value
    dq = increment(lam)
    q1 = step.end_position(dq)
    force1 = force(t1, q1)
    jacobian1 = constraint_jacobian(g, t1, q1, args)
    end = unravel(half_step(lam) + 0.5 * h * jax.flatten_util.ravel_pytree(force1)[0])
    projected = project_constant_mass(
        term.lagrangian,
        jacobian1,
        constraint_rate(g, t1, q1, args),
        end,
        term.mass_definite,
    )
    dp = jtu.tree_map(lambda a, b: a - b, projected.p, p0)
    result = dfx.RESULTS.where(
        solved.result == dfx.RESULTS.successful, projected.result, solved.result
    )
    # A NaN or inf start makes the multipliers' solve diverge: the start's result
    # says why.
    result = dfx.RESULTS.where(
        state.start == dfx.RESULTS.successful, result, state.start
    )
    v = jtu.tree_map(lambda x: x / h, dq)
    new = RattleState(
        force1,
        jacobian1,
        state.start,
        lam,
        state.multipliers,
        projected.multiplier,
    )
    return MethodStep(dq, dp, v, new, result, None if work is None else work(v))
