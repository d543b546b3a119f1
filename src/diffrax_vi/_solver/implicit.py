r"""One-step implicit variational integrators: a method is its stage equations.

A subclass says what its unknowns are (the step velocity of a discrete Lagrangian, the
stage velocities of a VPRK method), the equations they satisfy, and the increments of
$(q, p)$ they give. This class solves the equations, from a guess extrapolated from the
last two steps' unknowns.
"""

import abc

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import optimistix as optx
from equinox import AbstractVar
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import P, Q, V
from .._misc import all_finite, momentum_scale, sum_is_finite
from .._nonlinear import solve_implicit
from .base import (
    AbstractSymmetricSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    MethodStep,
    StepInputs,
)


class Unknowns(eqx.Module):
    """The unknowns of the last two steps, `last` and `before_last`: the next step's
    Newton guess is their second-order extrapolation `2 last - before_last`."""

    last: PyTree
    before_last: PyTree


def init_unknowns(step: StepInputs, stage_guess) -> Unknowns:
    """The state of an implicit method before its first step: the unknowns of a step
    at the start's velocity, `stage_guess(v0)`."""
    (v0, _), result = step.term.hamilton(step.t0, (step.q0, step.p0), step.args)
    # A Legendre map that cannot be inverted at the start leaves a NaN guess, which the
    # first step reports as `RESULTS.singular`.
    ok = result == dfx.RESULTS.successful
    v0 = jtu.tree_map(lambda v: jnp.where(ok, v, jnp.nan), v0)
    guess = stage_guess(v0)
    return Unknowns(guess, guess)


def solve_step(
    step: StepInputs,
    state: Unknowns,
    made_jump: Bool[ArrayLike, ""],
    residual,
    increments,
    root_finder: optx.AbstractRootFinder | None,
    max_steps: int,
) -> MethodStep:
    """One implicit step: solve `residual(unknowns) = 0` from the extrapolated guess,
    and take the step's `increments(unknowns)`."""
    # Second-order extrapolation; after a jump only the last step is trusted.
    guess = jtu.tree_map(
        lambda a, b: jnp.where(made_jump, a, 2 * a - b), state.last, state.before_last
    )
    # The residuals are momenta: divided by `1 + max|p0|`, Newton's absolute tolerance
    # becomes relative to the size of the momentum.
    scale = momentum_scale(step.p0)
    unknowns, result = solve_implicit(
        lambda w: jtu.tree_map(lambda r: r / scale, residual(w)),
        guess,
        root_finder,
        max_steps,
    )
    dq, dp = increments(unknowns)
    v = jtu.tree_map(lambda x: x / step.h, dq)
    result = start_result(step, all_finite(state.last), result)
    return MethodStep(dq, dp, v, Unknowns(unknowns, state.last), result)


def start_result(
    step: StepInputs, state_ok: Bool[ArrayLike, ""], result: dfx.RESULTS
) -> dfx.RESULTS:
    """`RESULTS.nonfinite` for a NaN or inf start; else `RESULTS.singular` if the
    method's state was poisoned (the Legendre map could not be inverted where it was
    built); else `result`."""
    result = dfx.RESULTS.where(state_ok, result, dfx.RESULTS.singular)
    start_ok = sum_is_finite((step.q0, step.p0))
    return dfx.RESULTS.where(start_ok, result, dfx.RESULTS.nonfinite)


class AbstractImplicitVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractSymmetricSolver
):
    """Base class for one-step implicit variational integrators on a
    [`diffrax_vi.LagrangianTerm`][]: symmetric and symplectic, one nonlinear solve per
    step for the method's unknowns.

    A subclass implements `stage_guess`, `stage_residual` and `stage_increments`.
    """

    root_finder: AbstractVar[optx.AbstractRootFinder | None]
    root_find_max_steps: AbstractVar[int]

    @abc.abstractmethod
    def stage_guess(self, step: StepInputs, v: V) -> PyTree:
        """The unknowns of a step at the constant velocity `v`: the first guess."""

    @abc.abstractmethod
    def stage_residual(self, step: StepInputs, unknowns: PyTree) -> PyTree:
        """The step's equations, in units of momentum: zero at the solution."""

    @abc.abstractmethod
    def stage_increments(self, step: StepInputs, unknowns: PyTree) -> tuple[Q, P]:
        """The increments `(q1 - q0, p1 - p0)` of the step with these unknowns."""

    def method_init(self, step: StepInputs) -> Unknowns:
        return init_unknowns(step, lambda v: self.stage_guess(step, v))

    def method_step(
        self, step: StepInputs, state: Unknowns, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        return solve_step(
            step,
            state,
            made_jump,
            lambda w: self.stage_residual(step, w),
            lambda w: self.stage_increments(step, w),
            self.root_finder,
            self.root_find_max_steps,
        )


IMPLICIT_ARGS_DOC = """- `root_finder`: an `optimistix.AbstractRootFinder` for the
    implicit step. Defaults to `optimistix.Newton` with `rtol = atol = sqrt(eps)` of
    the state's dtype: with Newton's quadratic convergence this leaves the solve's
    error at round-off in float32 and float64 alike.
- `root_find_max_steps`: iterations after which a step is reported as failed
    (`RESULTS.nonlinear_max_steps_reached`): usually a sign that the step is too large.
- `compensated`: compensated (Kahan) summation of each step's increment (default),
    so that round-off in the energy grows like the square root of the number of steps
    rather than linearly (Brouwer's law). Costs a few additions per step.
"""
