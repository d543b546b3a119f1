r"""Holonomic constraints in a one-step variational integrator: the step's equations
with their multipliers, then RATTLE's projection of the momentum.

For constraints $g(q) = 0$ with Jacobian $G$, the constrained discrete
Lagrange–d'Alembert principle in position–momentum form is (Marsden & West (2001),
§3.5; Hairer, Lubich & Wanner (2006), VII.1.4; Leyendecker, Marsden & Ortiz (2008))

$$p_0 = -D_1 L_d(q_0, q_1) - f^-_0 - G(q_0)^\top\lambda,\qquad g(q_1) = 0,$$
$$p_1 = D_2 L_d(q_0, q_1) + f^+_0 - G(q_1)^\top\mu,\qquad G(q_1)\,v(q_1, p_1) = 0.$$

The first line is the unconstrained step's equation with $p_0$ shifted by the impulse
$G(q_0)^\top\lambda$: the step's unknowns and $\lambda$ are solved together, one
Newton system. The second projects the momentum onto the hidden constraint. On a
Lie group $q_1 = q_0 \oplus \Delta q$ and $G$ is left-trivialised
(`_constraint.py`), so that the impulses join the momentum in the dual algebra,
where the unconstrained step's forces act (Leyendecker, Marsden & Ortiz (2008)). For the
trapezoidal $L_d$ of a separable Lagrangian this is RATTLE, whose positions are
explicit in $\lambda$: `rattle.py` solves it for the multipliers alone. The step is
symmetric
when the unconstrained one is (so compositions raise its order) and symplectic on the
constrained phase space $\{g(q) = 0,\ G(q)\,v(q, p) = 0\}$.
"""

import dataclasses
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._constraint import (
    check_start as check_constraint_start,
    constraint_jacobian,
    constraint_scale,
    constraint_values,
    project_momentum,
    transpose_product,
)
from .._custom_types import P, Q
from .._misc import tree_add
from .._root_finders import WithMultipliers
from .._space import retract
from .base import MethodStep, StepInputs
from .unknowns import (
    AbstractStepRootFinding,
    check_start,
    solve_step,
    StepEquations,
    Unknowns,
)


def init_constrained(
    step: StepInputs,
    stage_guess: Callable[[PyTree], PyTree],
    root_finding: AbstractStepRootFinding,
) -> Unknowns:
    """The state of a constrained implicit method before its first step: the
    unconstrained unknowns and the multipliers (zero), after checking that the start
    lies on the constraint manifold."""
    start = check_start(step)
    m = constraint_values(step.term.constraint, step.t0, step.q0, step.args).shape[0]
    guess = (stage_guess(start.v0), jnp.zeros((m,), step.dtype))
    guess = check_constraint_start(
        step.term, step.t0, step.q0, step.p0, start.v0, step.args, guess
    )
    carry = root_finding.carry_init(guess)
    projection = jnp.zeros((m,), step.dtype)
    return Unknowns(guess, guess, carry, start.positive, start.result, projection)


def constrained_step(
    step: StepInputs,
    state: Unknowns,
    made_jump: Bool[ArrayLike, ""],
    residual_at: Callable[[StepInputs, PyTree], tuple[PyTree, PyTree]],
    increments_at: Callable[[StepInputs, PyTree], tuple[Q, P]],
    step_at: Callable[[StepInputs, PyTree], Q],
    root_finding: AbstractStepRootFinding,
    max_steps: int,
    work_at: Callable[[StepInputs, PyTree], Array] | None = None,
    inverse_mass: PyTree | None = None,
) -> MethodStep:
    """One constrained step of the method whose unconstrained equations, increments,
    position increment alone and (with a force) work of its discrete forces are
    `residual_at(step, w)`, `increments_at(step, w)`, `step_at(step, w)` and
    `work_at(step, w)`, and whose unknowns have the
    inverse masses `inverse_mass` (a separable Lagrangian; `None` otherwise): the
    default policy then iterates as without constraints, solving for the
    multipliers in each iteration (`FixedPoint`). The constraint forces do no work
    on the constrained motion and are not counted."""
    g, t0, t1, q0, args = (
        step.term.constraint,
        step.t0,
        step.t1,
        step.q0,
        step.args,
    )
    # On a group the Jacobian is left-trivialised: its impulse is a force and a
    # body torque, in the dual algebra where the momentum p0 lives.
    space = step.term.lagrangian.space
    push = transpose_product(g, t0, q0, args, space)
    jacobian0 = constraint_jacobian(g, t0, q0, args, space)

    def shifted(lam) -> StepInputs:
        return eqx.tree_at(lambda s: s.p0, step, tree_add(step.p0, push(lam)))

    def residual(unknowns):
        w, lam = unknowns
        moved = shifted(lam)
        r, s = residual_at(moved, w)
        q1 = retract(space, q0, step_at(moved, w))
        return (r, constraint_values(g, t1, q1, args)), (
            s,
            constraint_scale(jacobian0, q1, space),
        )

    def increments(unknowns):
        w, lam = unknowns
        dq, dp = increments_at(shifted(lam), w)
        return dq, tree_add(dp, push(lam))

    equations = StepEquations(
        residual,
        increments,
        inverse_mass=None if inverse_mass is None else WithMultipliers(inverse_mass),
        # The joint Jacobian of a saddle-point system is indefinite: no curvature
        # test (no `fold_residual`).
        constrained=True,
        work=None
        if work_at is None
        else (lambda unknowns: work_at(shifted(unknowns[1]), unknowns[0])),
    )
    out = solve_step(step, state, made_jump, equations, root_finding, max_steps)
    q1 = retract(space, q0, out.dq)
    projected = project_momentum(step.term, t1, q1, tree_add(step.p0, out.dp), args)
    result = dfx.RESULTS.where(
        out.result == dfx.RESULTS.successful, projected.result, out.result
    )
    # The inverse step's projection gives this step's multipliers
    # (`unknowns.inverse_root`).
    state = dataclasses.replace(out.state, projection=projected.multiplier)
    return MethodStep(
        out.dq,
        tree_add(out.dp, projected.impulse),
        out.v,
        state,
        result,
        out.work,
        q1=q1,
    )
