r"""The unknowns of one implicit step: the guess extrapolated from the last two steps,
their solve, and the checks of the start and of the root found (that it continues
the motion)."""

import abc
from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import optimistix as optx
from equinox import AbstractVar
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import V
from .._lagrangian import (
    constant_mass,
    explicit_start,
    inverse_legendre,
    mass_regular,
    momentum,
    velocity_is_explicit,
)
from .._misc import all_finite, tree_size
from .._private_api import unvmap_any
from .._root_finders import (
    AbstractVIRootFinder,
    FixedPoint,
    known_root,
    Newton,
    solve,
    solve_with_fallback,
    Solved,
)
from .._spectrum import invertible, symmetric_extremes
from .._tolerance import (
    CONSTRAINED_DENSE_MAX,
    FIXED_POINT_STEPS_FACTOR,
)
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
    eigenvalues: dense up to 64 degrees of freedom, Lanczos beyond; the entries of
    a declared constant diagonal mass, a separable Lagrangian's or rigid bodies').
    (`velocity` checks that one marked quadratic keeps its promise.)"""
    lagrangian, t, q, p, args = (
        step.term.lagrangian,
        step.t0,
        step.q0,
        step.p0,
        step.args,
    )
    n = tree_size(p)
    dtype = step.dtype
    # A start checked already (`start_checked`) takes the marker on trust.
    promise = "trust" if step.term.start_checked else "raise"
    mass = constant_mass(lagrangian, p)
    if mass is not None:
        # A declared constant diagonal mass (separable, rigid bodies): its entries
        # are the eigenvalues. No eigensolver, whose LAPACK call is the only one
        # in a rigid body's program (and the first in a process imports SciPy's
        # linalg to lower it: 0.12 s of the free body's first call). Nor a check
        # of v0 = p0 / m: it is finite where p0 is (but for overflow), which the
        # first step's check of its start reports (`start_result`, and
        # `step_result` beyond it). XLA folds the check of a constant mass, but
        # compiled those of v0 as kernels of their own outside the loop: three on
        # Kepler and on the free body, 0.03 s of each one's MidpointVI compile.
        regular = mass_regular(mass, p)
        v0 = jtu.tree_map(lambda m, pi: jnp.where(regular, pi / m, jnp.nan), mass, p)
        result = dfx.RESULTS.where(
            regular, dfx.RESULTS.successful, dfx.RESULTS.singular
        )
        positive = jnp.all(jnp.stack([jnp.all(m > 0) for m in jtu.tree_leaves(mass)]))
        return Start(v0, result, positive)
    if velocity_is_explicit(lagrangian, p):
        # Marked quadratic: the velocity and the extremes from one matrix.
        v0, result, extremes = explicit_start(lagrangian, t, (q, p), args, promise)
    else:
        # The velocity alone: Hamilton's equations would also trace the force (and
        # a constraint's index-reduced forces), which the start does not need.
        v0, result = inverse_legendre(lagrangian, t, (q, p), args, None, promise)
        flat_v, unravel = jax.flatten_util.ravel_pytree(v0)

        def hessian_vector(u):
            grad = lambda w: jax.flatten_util.ravel_pytree(
                momentum(lagrangian, t, q, unravel(w), args)
            )[0]
            return jax.jvp(grad, (flat_v,), (u,))[1]

        extremes = symmetric_extremes(hessian_vector, n, dtype)
    regular = invertible(extremes, n, dtype)
    positive = extremes[0] > 0
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
    failed where it did (`Start.result`: the state is then NaN). A constrained step
    also keeps the multiplier `projection` of its last momentum projection (see
    `inverse_root`); `None` without constraints."""

    last: PyTree
    before_last: PyTree
    carry: PyTree
    positive: Bool[Array, ""]
    start: dfx.RESULTS
    projection: Array | None = None

    def __init__(self, last, before_last, carry, positive, start, projection=None):
        # Guesses and aids, none of them differentiated (a root's derivative is the
        # implicit function theorem's, `_root_finders._implicit_solve`): held
        # without one, they are not carries of a gradient's loop.
        self.last, self.before_last, self.carry, self.projection = lax.stop_gradient(
            (last, before_last, carry, projection)
        )
        self.positive = positive
        self.start = start


class StepEquations(eqx.Module):
    """The equations of one implicit step, as its method builds them.

    - `residual(w) -> (r, s)`: the equations in the unknowns `w` and the size of the
      terms each balances.
    - `increments(w) -> (dq, dp)`: the step the unknowns give.
    - `inverse_mass`: one over the mass of each unknown for a separable Lagrangian
      (the fixed-point iteration's preconditioner), or `None`.
    - `tags`: `lineax` tags of the Jacobian of `residual`.
    - `fold_residual`: where the unknowns are one velocity, the residual of the same
      step without applied forces, whose Jacobian is the Hessian of the discrete
      action up to an antisymmetric part: its curvature along the Newton path tells
      a root that continues the motion from one across a fold. A force has no
      action (strong damping in a composition's backward substep makes the full
      Jacobian indefinite at the one root of a linear step), so it is left out of
      the test. `residual` itself where the step has no applied force (the root
      finder's own Jacobian then measures the curvature: `fold_is_residual`). For
      a multi-stage step, whose stage equations have no such structure, the
      midpoint step's residual at the stages' mean velocity
      (`AbstractVPRK.fold_residual`). `None`: no test.
    - `work(w)`: the work of the step's discrete applied forces, or `None` without
      forces.
    - `constrained`: whether the unknowns are a step's and its constraint
      multipliers, whose Jacobian is a saddle point (`constrained_solver`).
    """

    residual: Callable[[PyTree], tuple[PyTree, PyTree]]
    increments: Callable[[PyTree], tuple[PyTree, PyTree]]
    inverse_mass: PyTree | None = None
    tags: frozenset = eqx.field(static=True, default=frozenset())
    fold_residual: Callable[[PyTree], tuple[PyTree, PyTree]] | None = None
    work: Callable[[PyTree], Array] | None = None
    constrained: bool = eqx.field(static=True, default=False)

    @property
    def fold_is_residual(self) -> bool:
        """Whether the fold test is on `residual` itself (a step without applied
        forces), whose Jacobian a Newton-type root finder forms anyway."""
        return self.fold_residual is not None and self.fold_residual is self.residual


def constrained_solver(guess: PyTree) -> str | lx.AbstractLinearSolver:
    """Newton's linear solver for constrained step equations, whose Jacobian is an
    indefinite saddle point: a dense factorisation at every size, without LAPACK up
    to `CONSTRAINED_DENSE_MAX` unknowns (`_linear.dense_lu_solve`: unrolled, then
    rolled into a loop) and LAPACK's beyond (a loop breaker, but a
    step of that size costs far more than the kernels' dispatch). Matrix-free
    solves (BiCGStab, then the normal equations) broke down on
    `scenes.rigid_chain(links=8)`, 72 unknowns, at every step size."""
    return "dense" if tree_size(guess) <= CONSTRAINED_DENSE_MAX else lx.LU()


def step_newton(constrained: bool, guess: PyTree) -> Newton:
    """Newton's method for a step's equations from `guess`: with
    `constrained_solver`'s linear solver where they are constrained."""
    return Newton(linear_solver=constrained_solver(guess) if constrained else "auto")


class AbstractStepRootFinding(eqx.Module):
    """How the equations of an implicit step are solved: a root-finding policy.
    `own`: whether it runs this package's root finders alone, which leave a
    non-finite root where the residual at the guess is not finite
    (`AbstractVIRootFinder`)."""

    own: AbstractVar[bool]

    @abc.abstractmethod
    def measures_curvature(self, equations: "StepEquations", guess: PyTree) -> bool:
        """Whether its solves of `equations` from `guess` measure the curvature
        along the way to the root (`Solved.curvature`)."""

    @abc.abstractmethod
    def carry_init(self, guess: PyTree) -> PyTree:
        """What the first step's solve starts from (a factorisation), or `None`."""

    @abc.abstractmethod
    def solve(
        self, equations: StepEquations, guess: PyTree, carry: PyTree, max_steps: int
    ) -> tuple[Solved, bool]:
        """The root from `guess`, and whether its convergence alone certifies that
        the root continues the motion (else the step tests the fold)."""


class GivenRootFinder(AbstractStepRootFinding):
    """The root finder a user chose, run as it is."""

    root_finder: optx.AbstractRootFinder

    @property
    def own(self) -> bool:
        return isinstance(self.root_finder, AbstractVIRootFinder)

    def measures_curvature(self, equations, guess):
        return self.own and self.root_finder.measures_curvature(guess)

    def carry_init(self, guess: PyTree) -> PyTree:
        return self.root_finder.carry_init(guess) if self.own else None

    def solve(self, equations, guess, carry, max_steps):
        solved = solve(
            equations.residual,
            guess,
            self.root_finder,
            max_steps,
            preconditioner=equations.inverse_mass,
            tags=equations.tags,
            carry=carry,
            curvature=equations.fold_is_residual,
        )
        return solved, self.own and self.root_finder.certifies_continuation


class FixedPointThenNewton(AbstractStepRootFinding):
    """The default policy: for a separable Lagrangian (`inverse_mass` given), the
    fixed-point iteration (`fixed_point_steps_factor` times the solver's
    `root_find_max_steps`, as it converges linearly), falling back to Newton's
    method from the same guess where it does not contract (stiff steps); else
    Newton's method.

    Newton's method solves its linear systems as `Newton(linear_solver="auto")`
    does: by an unrolled elimination (no LAPACK call, which XLA on CPU never compiles
    whole inside a loop) up to 16 unknowns, matrix-free beyond (conjugate gradients
    where the Jacobian is symmetric and definite, as for the midpoint step of a
    Lagrangian whose momentum is free of `q`). Constrained step equations take
    `constrained_solver`'s."""

    fixed_point_steps_factor: int = eqx.field(
        static=True, default=FIXED_POINT_STEPS_FACTOR
    )
    own: ClassVar[bool] = True

    def carry_init(self, guess: PyTree) -> PyTree:
        return None

    def newton(self, equations: StepEquations, guess: PyTree) -> Newton:
        return step_newton(equations.constrained, guess)

    def measures_curvature(self, equations, guess):
        # The fixed-point iteration's root is certified (`FixedPoint.curvature`).
        return self.newton(equations, guess).measures_curvature(guess)

    def solve(self, equations, guess, carry, max_steps):
        newton = self.newton(equations, guess)
        if equations.inverse_mass is None:
            solved = solve(
                equations.residual,
                guess,
                newton,
                max_steps,
                tags=equations.tags,
                curvature=equations.fold_is_residual,
            )
            return solved, False
        solved = solve_with_fallback(
            equations.residual,
            guess,
            (FixedPoint(), self.fixed_point_steps_factor * max_steps),
            (newton, max_steps),
            preconditioner=equations.inverse_mass,
            tags=equations.tags,
            curvature=equations.fold_is_residual,
        )
        return solved, False


class KnownRoot(AbstractStepRootFinding):
    """The policy of a step whose root is known: `root`, found elsewhere (by the
    inverse step of `ReversibleAdjoint`, `root_of_inverse`), taken as it is and
    differentiated by the implicit function theorem there. Its convergence was
    certified where it was found."""

    root: PyTree
    own: ClassVar[bool] = True

    def measures_curvature(self, equations, guess):
        return False

    def carry_init(self, guess: PyTree) -> PyTree:
        return None

    def solve(self, equations, guess, carry, max_steps):
        solved = known_root(
            equations.residual,
            self.root,
            preconditioner=equations.inverse_mass,
            carry=carry,
            newton=step_newton(equations.constrained, self.root),
            tags=equations.tags,
        )
        return solved, True


def inverse_root(
    solver_state, reverse: Callable[[PyTree], PyTree] = lambda w: w
) -> PyTree | None:
    r"""The root of the step that an inverse step has just undone, from the solver
    state (`VIState`) after that inverse step, for a symmetric method whose step's
    unknowns are `reverse` of its inverse step's; `None` where the state holds no
    `Unknowns` (an explicit step, RATTLE's multipliers alone).

    A constrained step (`constrained.py`) shifts $p_0$ by the impulse
    $G(q_0)^\top\lambda$, takes the unconstrained step, and projects the end
    momentum by $-G(q_1)^\top\mu$. The inverse step from $(q_1, p_1)$ undoes the
    projection with its own $\lambda' = \mu$, after which the unconstrained step
    back is exact and lands on the constraint, and its projection at $q_0$ then
    takes $\mu' = \lambda$ (for a start on the hidden constraint, as every state
    after a step is). So the step's multipliers are the inverse step's
    `projection`, and its unknowns those of the unconstrained step."""
    state = solver_state.method
    if not isinstance(state, Unknowns):
        return None
    if state.projection is None:  # Unconstrained.
        return reverse(state.last)
    w, _ = state.last
    return reverse(w), state.projection


def root_finding(
    root_finder: optx.AbstractRootFinder | AbstractStepRootFinding | None,
) -> AbstractStepRootFinding:
    """The policy of a solver's `root_finder` argument: `None` is the default
    policy."""
    if root_finder is None:
        return FixedPointThenNewton()
    if isinstance(root_finder, AbstractStepRootFinding):
        return root_finder
    return GivenRootFinder(root_finder)


def init_unknowns(
    step: StepInputs, stage_guess, root_finding: AbstractStepRootFinding
) -> Unknowns:
    """The state of an implicit method before its first step."""
    start = check_start(step)
    guess = stage_guess(start.v0)
    carry = root_finding.carry_init(guess)
    return Unknowns(guess, guess, carry, start.positive, start.result)


def resume_unknowns(
    step: StepInputs,
    stage_guess,
    root_finding: AbstractStepRootFinding,
    state: Unknowns,
) -> Unknowns:
    """`init_unknowns`'s state (`init_constrained`'s, where `state` has
    multipliers) at a start that the method's own steps reached, ending in `state`:
    the guess from the velocity there, and what the checks of the first start found
    (the Lagrangian's definiteness, how the start ended) carried over from `state`
    instead of checking again. A constrained step's multipliers start from zero, as
    at the first start."""
    v0, _ = inverse_legendre(
        step.term.lagrangian,
        step.t0,
        (step.q0, step.p0),
        step.args,
        None,
        promise="trust",
    )
    guess = stage_guess(v0)
    projection = state.projection
    if projection is not None:
        projection = jnp.zeros_like(projection)
        guess = (guess, projection)
    return Unknowns(
        guess,
        guess,
        root_finding.carry_init(guess),
        state.positive,
        state.start,
        projection,
    )


def _curvature(residual, w, d) -> Array:
    """`d . J(w) d` for the Jacobian `J` of `residual` at `w`."""
    _, jd = jax.jvp(lambda x: residual(x)[0], (w,), (d,))
    return sum(jnp.sum(a * b) for a, b in zip(jtu.tree_leaves(d), jtu.tree_leaves(jd)))


def solve_step(
    step: StepInputs,
    state: Unknowns,
    made_jump: Bool[ArrayLike, ""],
    equations: StepEquations,
    root_finding: AbstractStepRootFinding,
    max_steps: int,
) -> MethodStep:
    """One implicit step: solve `equations` from the extrapolated guess, check the
    root, and take the step's increments (and work, with forces)."""
    # Second-order extrapolation; after a jump only the last step is trusted.
    guess = jtu.tree_map(
        lambda a, b: jnp.where(made_jump, a, 2 * a - b), state.last, state.before_last
    )
    solved, certified = root_finding.solve(equations, guess, state.carry, max_steps)
    unknowns = solved.value
    result = solved.result
    # A NaN or inf applied force (or Lagrangian) makes the residual non-finite at a
    # finite guess: `nonfinite`, not a diverged iteration. This package's root
    # finders carry it into the root; another may stop at its last finite iterate,
    # so its equations are evaluated again at the guess. On failure only.
    failed = result != dfx.RESULTS.successful

    def poisoned_root():
        if root_finding.own:
            return ~all_finite(unknowns)
        return ~all_finite(unknowns) | ~all_finite(equations.residual(guess)[0])

    poisoned = lax.cond(unvmap_any(failed), poisoned_root, lambda: jnp.array(False))
    result = dfx.RESULTS.where(
        failed & poisoned & all_finite(guess), dfx.RESULTS.nonfinite, result
    )
    if not certified and equations.fold_residual is not None:
        # The root must continue the motion: along the way from the guess the Newton
        # matrix keeps the positive curvature that d2L/dv2 has as h -> 0. A root
        # across a fold (the bound pendulum at h = 5 lands on an energy of 82) has
        # the opposite. Without applied forces the root finder's own last dense
        # Jacobian measures it, one iterate before the root, which costs no
        # derivative of the equations (on the free rigid body's MidpointVI the
        # derivative at the root took 13% of a step).
        if equations.fold_is_residual and root_finding.measures_curvature(
            equations, guess
        ):
            curvature = solved.curvature
        else:
            d = jtu.tree_map(lambda a, b: a - b, unknowns, guess)
            curvature = _curvature(equations.fold_residual, unknowns, d)
        spurious = state.positive & (curvature < 0)
        result = dfx.RESULTS.where(
            (result == dfx.RESULTS.successful) & spurious,
            dfx.RESULTS.nonlinear_divergence,
            result,
        )
    dq, dp = equations.increments(unknowns)
    result = start_result(step, all_finite(state.last), result, state.start)
    v = jtu.tree_map(lambda x: x / step.h, dq)
    new = Unknowns(
        unknowns,
        state.last,
        solved.carry,
        state.positive,
        state.start,
        state.projection,
    )
    work = None if equations.work is None else equations.work(unknowns)
    return MethodStep(dq, dp, v, new, result, work)


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
        failed, lambda: all_finite((step.q0, step.p0)), lambda: jnp.array(True)
    )
    result = dfx.RESULTS.where(state_ok, result, why)
    return dfx.RESULTS.where(start_ok, result, dfx.RESULTS.nonfinite)
