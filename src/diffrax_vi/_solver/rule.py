"""The step of a discrete Lagrangian given as a quadrature rule
(`_discrete.AbstractDiscreteLagrangian`), on a step's inputs: its
equation in the step's velocity, its increments and the work of its discrete forces.
`TrapezoidalVI` steps the trapezoidal rule this way, and `MidpointVI` the Lie
midpoint rule on a group."""

import jax.tree_util as jtu
from jaxtyping import Array, PyTree

from .._custom_types import P, Q, V
from .._discrete import (
    AbstractDiscreteLagrangian,
    step_increments,
    step_residual,
    step_work,
)
from .base import StepInputs


def rule_residual(
    rule: AbstractDiscreteLagrangian, step: StepInputs, v: V
) -> tuple[PyTree, PyTree]:
    term = step.term
    return step_residual(
        rule,
        term.lagrangian,
        step.t0,
        step.h,
        step.q0,
        step.p0,
        v,
        step.args,
        step.momentum_offset,
        term.force,
    )


def rule_step(step: StepInputs, v: V) -> Q:
    r"""The position increment of the step with velocity `v` ($q_1 = q_0 \oplus h v$):
    the first of `rule_increments`, without tracing the momenta's derivatives."""
    return jtu.tree_map(lambda x: step.h * x, v)


def rule_increments(
    rule: AbstractDiscreteLagrangian, step: StepInputs, v: V
) -> tuple[Q, P]:
    term = step.term
    return step_increments(
        rule,
        term.lagrangian,
        step.t0,
        step.h,
        step.q0,
        step.p0,
        v,
        step.args,
        term.force,
    )


def rule_work(rule: AbstractDiscreteLagrangian, step: StepInputs, v: V) -> Array:
    term = step.term
    return step_work(
        rule, term.lagrangian, term.force, step.t0, step.h, step.q0, v, step.args
    )
