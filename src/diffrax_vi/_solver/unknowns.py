r"""The unknowns of one implicit step: the guess extrapolated from the last two steps,
their solve, and the checks of the start and of the root found (that it continues
the motion)."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import V
from .._lagrangian import (
    AbstractSeparableLagrangian,
    broadcast_mass,
    mass_regular,
    momentum,
)
from .._misc import all_finite, sum_is_finite, tree_size
from .._private_api import unvmap_any
from .._root_finders import AbstractVIRootFinder, FixedPoint, Newton, solve
from .._spectrum import symmetric_extremes
from .._tolerance import FIXED_POINT_STEPS_FACTOR, singular_threshold
from .base import MethodStep, StepInputs


class Start(eqx.Module):
    """What the start tells about the Lagrangian: the velocity there (NaN if the
    Legendre map could not be inverted), why not (`result`), and whether
    $\\partial^2 L/\\partial v^2$ is positive definite (then every step's root must
    keep the Newton matrix positive along the way from its guess)."""

    v0: V
    result: dfx.RESULTS
    positive: Bool[Array, ""]


def check_start(step: StepInputs) -> Start:
    """Invert the Legendre map at the start and check the Lagrangian there: that
    $\\partial^2 L/\\partial v^2$ is invertible to working precision (its extreme
    eigenvalues: dense up to 64 degrees of freedom, Lanczos beyond; the masses of a
    separable Lagrangian). (`velocity` checks that one marked quadratic keeps its
    promise.)"""
    lagrangian, t, q, p, args = (
        step.term.lagrangian,
        step.t0,
        step.q0,
        step.p0,
        step.args,
    )
    (v0, _), result = step.term.hamilton(t, (q, p), args)
    n = tree_size(p)
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        mass = broadcast_mass(lagrangian.mass, p)
        regular = mass_regular(mass, p)
        positive = jnp.all(jnp.stack([jnp.all(m > 0) for m in jtu.tree_leaves(mass)]))
    else:
        flat_v, unravel = jax.flatten_util.ravel_pytree(v0)

        def hessian_vector(u):
            grad = lambda w: jax.flatten_util.ravel_pytree(
                momentum(lagrangian, t, q, unravel(w), args)
            )[0]
            return jax.jvp(grad, (flat_v,), (u,))[1]

        smallest, largest, least = symmetric_extremes(hessian_vector, n, flat_v.dtype)
        size = jnp.maximum(jnp.abs(smallest), jnp.abs(largest))
        regular = least > singular_threshold(n, flat_v.dtype) * size
        positive = smallest > 0
    ok = result == dfx.RESULTS.successful
    result = dfx.RESULTS.where(
        ok & ~regular & all_finite(v0), dfx.RESULTS.singular, result
    )
    ok = result == dfx.RESULTS.successful
    v0 = jtu.tree_map(lambda v: jnp.where(ok, v, jnp.nan), v0)
    return Start(v0, result, positive)


class Unknowns(eqx.Module):
    """The unknowns of the last two steps, `last` and `before_last`: the next step's
    guess is their second-order extrapolation `2 last - before_last`. Also what the
    root finder hands from one step to the next (a factorisation), and whether the
    Newton matrix must stay positive definite (`Start.positive`), and why the start
    failed where it did (`Start.result`: the state is then NaN)."""

    last: PyTree
    before_last: PyTree
    carry: PyTree
    positive: Bool[Array, ""]
    start: dfx.RESULTS


def init_unknowns(step: StepInputs, stage_guess, root_finder) -> Unknowns:
    """The state of an implicit method before its first step."""
    start = check_start(step)
    guess = stage_guess(start.v0)
    carry = (
        root_finder.carry_init(guess)
        if isinstance(root_finder, AbstractVIRootFinder)
        else None
    )
    return Unknowns(guess, guess, carry, start.positive, start.result)


def _curvature(residual, w, d) -> Array:
    """`d . J(w) d` for the Jacobian `J` of `residual` at `w`."""
    _, jd = jax.jvp(lambda x: residual(x)[0], (w,), (d,))
    return sum(jnp.sum(a * b) for a, b in zip(jtu.tree_leaves(d), jtu.tree_leaves(jd)))


def solve_step(
    step: StepInputs,
    state: Unknowns,
    made_jump: Bool[ArrayLike, ""],
    residual,
    increments,
    root_finder: optx.AbstractRootFinder | None,
    max_steps: int,
    inverse_mass: PyTree | None,
    tags: frozenset,
    fold_residual,
    work=None,
) -> MethodStep:
    """One implicit step: solve `residual(w) = 0` (with `residual` returning the
    residual and the size of its terms) from the extrapolated guess, check the root,
    and take the step's `increments(w)` (and, given `work`, the work `work(w)` of
    its discrete forces).

    `fold_residual`, where the unknowns are one velocity, is the residual of the
    same step without applied forces, whose Jacobian is the Hessian of the discrete
    action up to an antisymmetric part: its curvature along the Newton path tells a
    root that continues the motion from one across a fold. A force has no action
    (strong damping in a composition's backward substep makes the full Jacobian
    indefinite at the one root of a linear step), so it is left out of the test.
    `None` for stage equations with no such structure.

    `root_finder=None` chooses: for a separable Lagrangian (`inverse_mass` given),
    the fixed-point iteration, falling back to Newton's method from the same guess
    where it does not contract (stiff steps); else Newton's method. The midpoint
    fallback is matrix-free at every size: a dense LU is a LAPACK call, and a loop
    containing one is never compiled whole by XLA on CPU, even where the branch is
    never taken (`MidpointVI` on Kepler: 1.05 against 0.21 us per step)."""
    # Conjugate gradients where the Newton matrix is symmetric (the midpoint step of
    # a Lagrangian whose momentum is free of q) keep the loop free of LAPACK calls
    # at every size; other stage equations keep the dense LU of small systems
    # (BiCGStab with its fallback costs seconds of compilation for a branch that
    # stiff steps alone take).
    conjugate_gradients = lx.positive_semidefinite_tag in tags
    # Second-order extrapolation; after a jump only the last step is trusted.
    guess = jtu.tree_map(
        lambda a, b: jnp.where(made_jump, a, 2 * a - b), state.last, state.before_last
    )
    newton = lambda: solve(
        residual,
        guess,
        Newton(linear_solver="krylov" if conjugate_gradients else "auto"),
        max_steps,
        preconditioner=inverse_mass,
        tags=tags,
    )
    if root_finder is not None:
        solved = solve(
            residual,
            guess,
            root_finder,
            max_steps,
            preconditioner=inverse_mass,
            tags=tags,
            carry=state.carry,
        )
        checked = not isinstance(root_finder, FixedPoint)
    elif inverse_mass is not None:
        fixed = solve(
            residual,
            guess,
            FixedPoint(),
            FIXED_POINT_STEPS_FACTOR * max_steps,
            preconditioner=inverse_mass,
        )
        failed = fixed.result != dfx.RESULTS.successful
        solved = lax.cond(unvmap_any(failed), newton, lambda: fixed)
        checked = True
    else:
        solved = newton()
        checked = True
    unknowns = solved.value
    result = solved.result
    # A NaN or inf applied force (or Lagrangian) makes the residual non-finite at a
    # finite guess: `nonfinite`, not a diverged iteration (an iteration that stops
    # at its last finite iterate would say so). Evaluated on failure only.
    failed = result != dfx.RESULTS.successful
    poisoned = lax.cond(
        unvmap_any(failed),
        lambda: ~all_finite(unknowns) | ~all_finite(residual(guess)[0]),
        lambda: jnp.array(False),
    )
    result = dfx.RESULTS.where(
        failed & poisoned & all_finite(guess), dfx.RESULTS.nonfinite, result
    )
    if checked and fold_residual is not None:
        # The root must continue the motion: along the way from the guess the Newton
        # matrix keeps the positive curvature that d2L/dv2 has as h -> 0. A root
        # across a fold (the bound pendulum at h = 5 lands on an energy of 82) has
        # the opposite. The fixed-point iteration certifies this by converging.
        d = jtu.tree_map(lambda a, b: a - b, unknowns, guess)
        spurious = state.positive & (_curvature(fold_residual, unknowns, d) < 0)
        result = dfx.RESULTS.where(
            (result == dfx.RESULTS.successful) & spurious,
            dfx.RESULTS.nonlinear_divergence,
            result,
        )
    dq, dp = increments(unknowns)
    result = start_result(step, all_finite(state.last), result, state.start)
    v = jtu.tree_map(lambda x: x / step.h, dq)
    new = Unknowns(unknowns, state.last, solved.carry, state.positive, state.start)
    return MethodStep(dq, dp, v, new, result, None if work is None else work(unknowns))


def start_result(
    step: StepInputs,
    state_ok: Bool[ArrayLike, ""],
    result: dfx.RESULTS,
    why: dfx.RESULTS = dfx.RESULTS.singular,
) -> dfx.RESULTS:
    """`RESULTS.nonfinite` for a NaN or inf start; else, if the method's state was
    poisoned where it was built, `why` (the Legendre map could not be inverted,
    d2L/dv2 is singular, or the Lagrangian gave NaN); else `result`."""
    failed = unvmap_any(~state_ok | (result != dfx.RESULTS.successful))
    start_ok = lax.cond(
        failed, lambda: sum_is_finite((step.q0, step.p0)), lambda: jnp.array(True)
    )
    result = dfx.RESULTS.where(state_ok, result, why)
    return dfx.RESULTS.where(start_ok, result, dfx.RESULTS.nonfinite)
