r"""One-step implicit variational integrators: a method is its stage equations.

A subclass says what its unknowns are (the step velocity of a discrete Lagrangian, the
stage velocities of a VPRK method), the equations they satisfy with the size of the
momenta each equation balances, and the increments of $(q, p)$ they give. This module
checks the Lagrangian at the start, solves the equations from a guess extrapolated
from the last two steps, and checks that the root found continues the motion.
"""

import abc

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

from .._custom_types import P, Q, V
from .._lagrangian import (
    AbstractSeparableLagrangian,
    broadcast_mass,
    mass_regular,
    momentum,
)
from .._misc import all_finite, sum_is_finite
from .._nonlinear import (
    AbstractVIRootFinder,
    FixedPoint,
    Newton,
    singular_threshold,
    solve,
    symmetric_extremes,
    tree_size,
)
from .._private_api import unvmap_any
from .base import (
    AbstractSymmetricSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    MethodStep,
    StepInputs,
)


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
    Newton matrix must stay positive definite (`Start.positive`)."""

    last: PyTree
    before_last: PyTree
    carry: PyTree
    positive: Bool[Array, ""]


def init_unknowns(step: StepInputs, stage_guess, root_finder) -> Unknowns:
    """The state of an implicit method before its first step."""
    start = check_start(step)
    guess = stage_guess(start.v0)
    carry = (
        root_finder.carry_init(guess)
        if isinstance(root_finder, AbstractVIRootFinder)
        else None
    )
    return Unknowns(guess, guess, carry, start.positive)


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
    one_stage: bool,
    work=None,
) -> MethodStep:
    """One implicit step: solve `residual(w) = 0` (with `residual` returning the
    residual and the size of its terms) from the extrapolated guess, check the root,
    and take the step's `increments(w)` (and, given `work`, the work `work(w)` of
    its discrete forces).

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
            3 * max_steps,
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
    if checked and one_stage:
        # The root must continue the motion: along the way from the guess the Newton
        # matrix keeps the positive curvature that d2L/dv2 has as h -> 0. A root
        # across a fold (the bound pendulum at h = 5 lands on an energy of 82) has
        # the opposite. The fixed-point iteration certifies this by converging.
        d = jtu.tree_map(lambda a, b: a - b, unknowns, guess)
        spurious = state.positive & (_curvature(residual, unknowns, d) < 0)
        result = dfx.RESULTS.where(
            (result == dfx.RESULTS.successful) & spurious,
            dfx.RESULTS.nonlinear_divergence,
            result,
        )
    dq, dp = increments(unknowns)
    result = start_result(step, all_finite(state.last), result)
    v = jtu.tree_map(lambda x: x / step.h, dq)
    new = Unknowns(unknowns, state.last, solved.carry, state.positive)
    return MethodStep(dq, dp, v, new, result, None if work is None else work(unknowns))


def start_result(
    step: StepInputs, state_ok: Bool[ArrayLike, ""], result: dfx.RESULTS
) -> dfx.RESULTS:
    """`RESULTS.nonfinite` for a NaN or inf start; else, if the method's state was
    poisoned where it was built (the Legendre map could not be inverted, or
    d2L/dv2 is singular), why; else `result`."""
    failed = unvmap_any(~state_ok | (result != dfx.RESULTS.successful))
    start_ok = lax.cond(
        failed, lambda: sum_is_finite((step.q0, step.p0)), lambda: jnp.array(True)
    )
    result = dfx.RESULTS.where(state_ok, result, dfx.RESULTS.singular)
    return dfx.RESULTS.where(start_ok, result, dfx.RESULTS.nonfinite)


class AbstractImplicitVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractSymmetricSolver
):
    """Base class for one-step implicit variational integrators on a
    [`diffrax_vi.LagrangianTerm`][]: symmetric and symplectic, one nonlinear solve per
    step for the method's unknowns.

    A subclass implements `stage_guess`, `stage_residual`, `stage_increments`,
    `stage_work`, `inverse_mass` and `jacobian_tags`.
    """

    root_finder: AbstractVar[optx.AbstractRootFinder | None]
    root_find_max_steps: AbstractVar[int]

    @abc.abstractmethod
    def stage_guess(self, step: StepInputs, v: V) -> PyTree:
        """The unknowns of a step at the constant velocity `v`: the first guess."""

    @abc.abstractmethod
    def stage_residual(
        self, step: StepInputs, unknowns: PyTree
    ) -> tuple[PyTree, PyTree]:
        """The step's equations (momenta, zero at the solution) and the size of the
        momenta each balances."""

    @abc.abstractmethod
    def stage_increments(self, step: StepInputs, unknowns: PyTree) -> tuple[Q, P]:
        """The increments `(q1 - q0, p1 - p0)` of the step with these unknowns."""

    @abc.abstractmethod
    def stage_work(self, step: StepInputs, unknowns: PyTree) -> Array:
        """The work of the step's discrete applied forces with these unknowns, by
        the quadrature that the method applies to the force."""

    @abc.abstractmethod
    def inverse_mass(self, step: StepInputs) -> PyTree | None:
        """One over the mass of each unknown for a separable Lagrangian (the
        fixed-point iteration's preconditioner), or `None`."""

    @abc.abstractmethod
    def jacobian_tags(self, step: StepInputs) -> frozenset:
        """`lineax` tags of the stage equations' Jacobian (e.g. symmetric positive
        definite for the midpoint step of a separable Lagrangian)."""

    def method_init(self, step: StepInputs) -> Unknowns:
        # constrained.py builds on this module's step.
        from .constrained import init_constrained

        if step.term.constraint is not None:
            if not self.one_stage:
                raise ValueError(
                    f"{type(self).__name__} has several stages, whose positions "
                    "would need constraints of their own; holonomic constraints are "
                    "supported by MidpointVI, TrapezoidalVI and compositions of them "
                    "(for higher order, e.g. "
                    "`Composition(MidpointVI(), 'kahan_li8')`)."
                )
            return init_constrained(
                step, lambda v: self.stage_guess(step, v), self.root_finder
            )
        return init_unknowns(
            step, lambda v: self.stage_guess(step, v), self.root_finder
        )

    def method_step(
        self, step: StepInputs, state: Unknowns, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        from .constrained import constrained_step

        if step.term.constraint is not None:
            return constrained_step(
                step,
                state,
                made_jump,
                self.stage_residual,
                self.stage_increments,
                self.root_finder,
                self.root_find_max_steps,
                None if step.term.force is None else self.stage_work,
            )
        return solve_step(
            step,
            state,
            made_jump,
            lambda w: self.stage_residual(step, w),
            lambda w: self.stage_increments(step, w),
            self.root_finder,
            self.root_find_max_steps,
            self.inverse_mass(step),
            self.jacobian_tags(step),
            self.one_stage,
            None if step.term.force is None else (lambda w: self.stage_work(step, w)),
        )

    @property
    def one_stage(self) -> bool:
        """Whether the unknowns are one velocity, so that the Jacobian of the step's
        equation is, up to an antisymmetric part, the Hessian of the discrete action
        and its curvature along the Newton path tests the root. The stage equations
        of a multi-stage method have no such structure: their Jacobian can be
        indefinite at the one good root of a linear problem (Gauss and Lobatto
        methods on the oscillator past their stability interval)."""
        return False


SYMMETRIC_POSITIVE = frozenset({lx.symmetric_tag, lx.positive_semidefinite_tag})


IMPLICIT_ARGS_DOC = """- `root_finder`: how the implicit equations are solved: `None`
    (the default) chooses the fixed-point iteration for a separable Lagrangian, falling
    back to Newton's method where it does not converge (stiff steps; matrix-free,
    by conjugate gradients, for the midpoint step), and Newton's
    method otherwise: by conjugate gradients at every size where its matrix is
    symmetric (the midpoint step of a Lagrangian whose momentum does not depend on
    $q$), else with dense LU up to 16 unknowns and matrix-free Krylov iterations
    beyond; or [`diffrax_vi.Newton`][], [`diffrax_vi.SimplifiedNewton`][],
    [`diffrax_vi.FixedPoint`][], or any `optimistix.AbstractRootFinder` (given the
    residual relative to its largest term). Every tolerance is relative to the size
    of the momenta the equations balance, so results do not depend on the units.
- `root_find_max_steps`: iterations after which a step is reported as failed
    (`RESULTS.nonlinear_max_steps_reached`): usually a sign that the step is too large.
- `compensated`: compensated (Kahan) summation of each step's increment (default),
    so that round-off in the energy grows like the square root of the number of steps
    rather than linearly (Brouwer's law). Costs a few additions per step.
"""
