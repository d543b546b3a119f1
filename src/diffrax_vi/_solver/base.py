r"""The engine shared by every variational solver, and the capability markers.

A variational solver is its *method*: how one step turns $(q_0, p_0)$ into increments
$(\Delta q, \Delta p)$, and what it remembers between steps
([`diffrax_vi.AbstractVariationalSolver`][]'s `method_init` and `method_step`).
Everything around that is done once, here: reaching the Lagrangian inside diffrax's
wrapped term, the physical times and the signed step, compensated summation of the
increments, folding every check into one `diffrax.RESULTS`, and the data of the cubic
Hermite dense output.
"""

import abc
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import diffrax as dfx
import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from equinox import AbstractVar
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import Args, P, Q, RealScalarLike, V
from .._lagrangian import momentum_offset
from .._misc import (
    all_finite,
    at_trace_time,
    error_if,
    perturbed_with,
    split_state,
    state_dtype,
)
from .._private_api import (
    AdjointTerm,
    known_value,
    NoForwardingSolverMeta,
    unvmap_any,
    WrapTerm,
)
from .._space import departure, is_euclidean, retract, velocity
from .._term import LagrangianTerm
from .._tolerance import newton_tolerance


_markers = dict(metaclass=NoForwardingSolverMeta)


class Substep(NamedTuple):
    """A step that is the fraction `fraction` of the whole step from `t0` to `t1`, as
    [`diffrax_vi.Composition`][] takes them.

    Its size is `fraction * contr(t0, t1)`, not the difference of its own (rounded)
    start and end times: near a large `t` that difference carries an ulp of `t` into
    every substep, which breaks a high-order composition's order conditions (at
    t = 2^30, kahan_li8's energy error on Kepler grew from 2.5e-12 to 2.3e-8 within
    ten orbits)."""

    fraction: float | Array
    t0: RealScalarLike
    t1: RealScalarLike


class AbstractStepsByFraction(dfx.AbstractSolver):
    """A solver whose step is its `fractional_step` with `Substep(1.0, t0, t1)`."""

    def step(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
    ) -> tuple[PyTree, None, dict[str, PyTree], PyTree, dfx.RESULTS]:
        return self.fractional_step(
            terms, t0, t1, y0, args, solver_state, made_jump, Substep(1.0, t0, t1)
        )


class AbstractSymplecticSolver(dfx.AbstractSolver, **_markers):
    """Marker for solvers whose step map is symplectic on `y = (q, p)`.

    Symplecticity, and with it bounded energy error over exponentially long times, holds
    for fixed step sizes only. A wrapper such as `diffrax.HalfSolver` (step doubling
    for adaptive steps) destroys it, and is not an instance of this class, although
    diffrax forwards `isinstance` through wrappers for its own classes.
    """


class AbstractComposableSolver(AbstractStepsByFraction, **_markers):
    """Base class for solvers that [`diffrax_vi.Composition`][] can take as its
    base: they take steps as fractions of a composition's step (`fractional_step`),
    and say whether their step is symmetric (time-reversible: a step of `h` followed
    by a step of `-h` returns to the start). Only a symmetric one can be raised to
    higher order, stepped reversibly or differentiated by
    [`diffrax_vi.ReversibleAdjoint`][].

    `symmetric` comes from the method's data: a VPRK method is symmetric exactly
    when its tableau is."""

    symmetric: AbstractVar[bool]

    def resume(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
    ) -> PyTree:
        """The state to step on from `y0`, a state that this solver's own steps
        reached from a start that `init` checked, ending in `solver_state`: what
        `init(terms, t0, t1, y0, args)` returns, without checking that start again
        where the solver can (`ReversibleAdjoint`'s inverse steps start so from the
        end of the forward solve). By default `init`'s."""
        return self.init(terms, t0, t1, y0, args)

    @abc.abstractmethod
    def fractional_step(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
        substep: Substep,
        dense: bool = True,
    ) -> tuple[PyTree, None, dict[str, PyTree] | None, PyTree, dfx.RESULTS]:
        """A step from `t0` to `t1` whose size is `substep.fraction` times the control
        of the whole step from `substep.t0` to `substep.t1`. Returns what `step`
        returns; `step` is the fractional step with `Substep(1.0, t0, t1)`. With
        `dense=False` the dense output data is `None`, not traced: for a caller that
        discards it (a composition's substeps, `ReversibleAdjoint`'s backward steps),
        whose derivatives JAX would otherwise take before XLA removed them."""


def step_control(term: dfx.AbstractTerm, substep: Substep) -> PyTree:
    """The control (signed step) of a substep, `fraction * contr(t0, t1)`."""
    control = term.contr(substep.t0, substep.t1)
    if isinstance(substep.fraction, float) and substep.fraction == 1.0:
        return control
    return jtu.tree_map(lambda c: substep.fraction * c, control)


def after_jump(
    made_jump: bool | Bool[ArrayLike, ""],
    recompute: Callable[[], PyTree],
    cached: PyTree,
) -> PyTree:
    """What a step starts from: `cached` (kept from the last step), or `recompute()`
    after a jump, when the cache belongs to the state before it. Where that is known
    at trace time there is no branch: `made_jump` is the Python `False` where diffrax
    knows that no jump happens (no events, no jump times), which saves the loop a
    conditional per step, and the Python `True` in `ReversibleAdjoint`'s backward
    steps, which then trace and differentiate one branch instead of two."""
    if made_jump is False:
        return cached
    if made_jump is True:
        return recompute()
    return lax.cond(unvmap_any(made_jump), recompute, lambda: cached)


def initial_compensation(y: PyTree, enabled: bool) -> PyTree | None:
    """Zero compensation for `y`, or `None` (no state to carry) when disabled."""
    return jtu.tree_map(jnp.zeros_like, y) if enabled else None


def compensated_add(
    y0: PyTree, increment: PyTree, compensation: PyTree | None
) -> tuple[PyTree, PyTree | None]:
    """`y0 + increment` with compensated (Kahan) summation.

    `compensation` carries the rounding error of the previous additions, fed back into
    the next increment; `None` means a plain sum. It is at most an ulp of `y0`, so it
    needs no reset after a jump.
    """
    if compensation is None:
        return jtu.tree_map(lambda a, b: a + b, y0, increment), None
    corrected = jtu.tree_map(lambda d, c: d - c, increment, compensation)
    y1 = jtu.tree_map(lambda a, d: a + d, y0, corrected)
    compensation = jtu.tree_map(lambda a, b, d: (b - a) - d, y0, y1, corrected)
    return y1, compensation


def advance(
    space: PyTree,
    y0: PyTree,
    increment: PyTree,
    compensation: PyTree | None,
    q1: PyTree | None = None,
) -> tuple[PyTree, PyTree | None]:
    r"""`y0 = (q0, p0)` moved by the step's increments `(dq, dp)`, every sum
    compensated. In a space with a group factor the position is not a sum: it is
    `q1`, $q_0 \oplus dq$, and moves without compensation, a product's vector factor
    included (its compensation stays zero); the momentum's sum is compensated."""
    if is_euclidean(space):
        return compensated_add(y0, increment, compensation)
    p0, dp = y0[1], increment[1]
    if compensation is None:
        return (q1, jtu.tree_map(lambda a, b: a + b, p0, dp)), None
    p1, compensation_p = compensated_add(p0, dp, compensation[1])
    return (q1, p1), (compensation[0], compensation_p)


def unwrap_term(terms: dfx.AbstractTerm, solver: str) -> tuple[LagrangianTerm, Array]:
    """The user's `LagrangianTerm` inside diffrax's `WrapTerm`, and the time direction
    (`+1`, or `-1` when integrating backwards)."""
    direction = jnp.array(1)
    if isinstance(terms, WrapTerm):
        direction = jnp.asarray(terms.direction)
        terms = terms.term
    if isinstance(terms, AdjointTerm):
        raise ValueError(
            f"diffrax.BacksolveAdjoint solves an adjoint ODE backwards with the "
            f"solver, and {solver} integrates a Lagrangian, not an ODE: this "
            "package's solvers do not support it. Differentiate with "
            "adjoint=diffrax.RecursiveCheckpointAdjoint() (the default) or "
            "diffrax.DirectAdjoint()."
        )
    if not isinstance(terms, LagrangianTerm):
        raise ValueError(
            f"{solver} integrates a Lagrangian and needs a "
            f"`diffrax_vi.LagrangianTerm`, but got {type(terms).__name__}. "
            "Wrap the Lagrangian: "
            f"`diffeqsolve(diffrax_vi.LagrangianTerm(L), {solver}(), ...)` with "
            "`y0 = (q0, p0)`, or build the terms with "
            f"`diffrax_vi.terms_for({solver}(), L)`."
        )
    return terms, direction


NON_FINITE_TIMES = (
    "The first step from t0 to t0 + dt0 (or to t1) is NaN or infinite: check that "
    "t0, t1 and dt0 are finite numbers. diffeqsolve would otherwise take no step and "
    "report success."
)


def check_times(t0: RealScalarLike, t1: RealScalarLike, state: PyTree) -> PyTree:
    """`state`, or an error if the first step is not finite: diffeqsolve then takes
    no step at all and would report success. Times known when traced are checked
    then: those `solve_fixed_steps` gives, and those `diffeqsolve` computes from
    Python floats (`known_value`), so that the solve holds no host callback and
    JAX's persistent cache can keep it. Others are checked at run time, through the
    solver state (so that the check cannot be dropped as unused)."""
    a, b = known_value(t0), known_value(t1)
    if a is None or b is None:
        failed = ~jnp.isfinite(t1 - t0)
    else:
        with np.errstate(all="ignore"):
            failed = not np.isfinite(b - a)
    return error_if(state, failed, NON_FINITE_TIMES)


OFF_GROUP = (
    "The initial position is not on its group: a rotation matrix R0 (SO3, SO2) "
    "must have R0^T R0 = I to within sqrt(eps) of its dtype (1.5e-8 in float64, "
    "3.5e-4 in float32; a pure number, in any units) and det R0 = +1 (a "
    "reflection is not a rotation). A solve from it would stay off the group and "
    "report success. Project it onto the nearest rotation first: "
    "`U, _, Vt = jnp.linalg.svd(R0); R0 = U @ Vt` (and flip a column of U if "
    "det(U @ Vt) < 0), or build it from an angle or an exponential map."
)


def check_on_space(space: PyTree, q0: PyTree, state: PyTree) -> PyTree:
    """`state`, or an error if a start position is off its group (see
    `_space.departure`), when traced where `q0` is known then; nothing to check in
    a vector space."""
    if is_euclidean(space):
        return state
    dtype = jnp.result_type(*jtu.tree_leaves(q0))
    off = at_trace_time(lambda q: departure(space, q) > newton_tolerance(dtype), q0)
    return error_if(state, off, OFF_GROUP)


class StepInputs(eqx.Module):
    """One step as a method sees it: the term, the physical start and end times, the
    signed step `h` (all in the state's dtype), the state, `args`, the
    compensation of the summation (`None` when it is off), and `momentum_offset`
    at `q0` for the scale of the implicit residuals (computed once per step; XLA
    drops it where no method reads it)."""

    term: LagrangianTerm
    t0: Array
    t1: Array
    h: Array
    q0: Q
    p0: P
    args: Args
    compensation: PyTree | None
    momentum_offset: P
    dtype: np.dtype = eqx.field(static=True)

    def end_position(self, dq: Q) -> Q:
        """The position `q0 + dq` that the step will end at, summed as the engine
        sums it: for a method that evaluates a force there (Störmer–Verlet)."""
        compensation = None if self.compensation is None else self.compensation[0]
        return compensated_add(self.q0, dq, compensation)[0]


def step_inputs(
    terms: dfx.AbstractTerm,
    t0: RealScalarLike,
    t1: RealScalarLike,
    y0: PyTree,
    args: Args,
    compensation: PyTree | None,
    substep: Substep,
    solver: str,
) -> StepInputs:
    term, direction = unwrap_term(terms, solver)
    q0, p0 = split_state(y0, "y0", term.lagrangian.space)
    dtype = state_dtype(y0)
    h = jnp.asarray(step_control(terms, substep), dtype=dtype)
    t0 = jnp.asarray(direction * t0, dtype=dtype)
    return StepInputs(
        term=term,
        t0=t0,
        t1=jnp.asarray(direction * t1, dtype=dtype),
        h=h,
        q0=q0,
        p0=p0,
        args=args,
        compensation=compensation,
        momentum_offset=momentum_offset(term.lagrangian, t0, q0, args),
        dtype=dtype,
    )


def without_force(step: StepInputs) -> StepInputs:
    """The same step with the term's applied force removed."""
    if step.term.force is None:
        return step
    return eqx.tree_at(lambda s: s.term.force, step, None)


class MethodStep(eqx.Module):
    """What a method's step produces: the increments of the state, a velocity of the
    step (the guess for the Legendre inversions of the dense output), the method's new
    state, whether the step succeeded, for a term with an applied force the work of
    the method's discrete forces over the step (`None` without one), and the space
    whose retraction moves the position by `dq`, where the method has its own
    (`None`: the Lagrangian's), and on a group the position that retraction reaches,
    where the method has computed it for its own equations (`None`: the engine
    retracts)."""

    dq: Q
    dp: P
    v: V
    state: PyTree
    result: dfx.RESULTS
    work: Array | None = None
    space: PyTree | None = None
    q1: Q | None = None


class VIState(eqx.Module):
    """The solver state of a variational solver: the method's own state, the
    compensation of the summation (`None` when it is off), and for a term with an
    applied force the work of the discrete forces since the start (`None` without
    one): the $W$ of the energy balance $E(t) - E(0) = W(t)$, accumulated as the
    method's own quadrature of the force accumulates the momentum."""

    method: PyTree
    compensation: PyTree | None
    work: Array | None = None


def unless_failed(result: dfx.RESULTS, tree: PyTree) -> PyTree:
    """`tree`, or NaN throughout if the method failed: diffrax keeps the output of
    the step that failed, and an unconverged iterate must never pass for a state.

    It depends on the method's result alone, not on the check of the new state
    (`step_result`), so that the check's reductions stay out of the chain from one
    step's state to the next's (the unconstrained Cartesian pendulum's
    TrapezoidalVI: 18 -> 13 ns a step). The engine applies it where it costs least,
    measured: in a vector space to the summed state (on the increments, before the
    sum, a MidpointVI step took up to 11% longer), on a group to the momentum's
    increment and the position reached (LGVI on the heavy top: 128 ns a step,
    against 136 ns after the step)."""
    ok = result == dfx.RESULTS.successful
    return jtu.tree_map(lambda x: jnp.where(ok, x, jnp.nan), tree)


def step_result(result: dfx.RESULTS, y1: PyTree) -> dfx.RESULTS:
    """The step's result: the method's, or `RESULTS.nonfinite` for a step that
    succeeded but produced NaN or inf (which a non-finite start always does; a method
    that can fail by itself reports a non-finite start as such, see
    `start_result`)."""
    nonfinite = (result == dfx.RESULTS.successful) & ~all_finite(y1)
    return dfx.RESULTS.where(nonfinite, dfx.RESULTS.nonfinite, result)


def hermite_dense_info(
    step: StepInputs, y0: PyTree, y1: PyTree, v_guess: V
) -> dict[str, PyTree]:
    """Dense output data: the states and `h` times Hamilton's vector field at both ends.

    Only evaluated if the output is interpolated: otherwise it is dead code that XLA
    removes.
    """

    def scaled_field(t, y):
        f = hamilton_field(step.term, t, y, step.args, v_guess)
        return jtu.tree_map(lambda x: step.h * x, f)

    return dict(
        y0=y0, y1=y1, k0=scaled_field(step.t0, y0), k1=scaled_field(step.t1, y1)
    )


def hamilton_field(
    term: LagrangianTerm,
    t: RealScalarLike,
    y: PyTree,
    args: Args,
    v_guess: V | None = None,
) -> PyTree:
    """Hamilton's equations as the term's vector field (on a group, $\\dot q$ from
    the velocity), with the quadratic marker taken on trust: without `vf`'s check,
    a host callback that would break the time-stepping loop into kernels where a
    solve interpolates, after its start has checked the marker."""
    (v, dp), _ = term.hamilton(t, y, args, v_guess=v_guess)
    return velocity(term.lagrangian.space, y[0], v), dp


def is_symmetric(solver) -> bool:
    """Whether `solver` is a symmetric method of this package, whose step with $-h$
    inverts its step with $h$."""
    return isinstance(solver, AbstractComposableSolver) and bool(solver.symmetric)


class AbstractTracedOnce(AbstractStepsByFraction):
    """A solver whose step is `fractional_step` with `Substep(1.0, t0, t1)`, and
    whose `fractional_step` is traced once per program (`_traced_once`): a subclass
    writes the step itself as `_fractional_step`."""

    def fractional_step(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
        substep: Substep,
        dense: bool = True,
    ) -> tuple[PyTree, None, dict[str, PyTree] | None, PyTree, dfx.RESULTS]:
        return _traced_once(
            terms,
            t0,
            t1,
            y0,
            args,
            solver_state,
            made_jump,
            substep,
            solver=self,
            dense=dense,
            settings=self.trace_settings(),
        )

    def trace_settings(self) -> object:
        """What the step's trace depends on beyond its arguments (a setting of the
        process), as part of the key under which it is traced once: none by
        default."""
        return None

    @abc.abstractmethod
    def _fractional_step(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
        substep: Substep,
        dense: bool = True,
    ) -> tuple[PyTree, None, dict[str, PyTree] | None, PyTree, dfx.RESULTS]:
        """`fractional_step` (`AbstractComposableSolver.fractional_step`)."""


class AbstractVariationalSolver(AbstractTracedOnce):
    """Base class for variational integrators: solvers that read the Lagrangian of a
    [`diffrax_vi.LagrangianTerm`][] and step its discrete Euler–Lagrange equations on
    `y = (q, p)`. The one-step ones are also
    [`diffrax_vi.AbstractSymplecticSolver`][]s; the multistep
    [`diffrax_vi.LinearizedVI`][] is only presymplectic.

    A subclass supplies its method: `method_init` (the state it keeps between steps)
    and `method_step` (the increments of one step). This class owns `init`, `step`,
    compensated summation, the folding of checks into one `diffrax.RESULTS`, and the
    dense output: cubic Hermite interpolation through the states and Hamilton's vector
    field at both ends of each step.
    """

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar = dfx.ThirdOrderHermitePolynomialInterpolation

    compensated: AbstractVar[bool]

    def __check_init__(self):
        steps = getattr(self, "root_find_max_steps", 1)
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(
                f"{type(self).__name__}(root_find_max_steps=...) must be an integer "
                f"of at least 1; got {steps!r}."
            )

    @abc.abstractmethod
    def method_init(self, step: StepInputs) -> PyTree:
        """The method's state before its first step (a history, a Newton guess)."""

    def method_resume(self, step: StepInputs, state: PyTree) -> PyTree:
        """The method's state to step on from `step`'s start, which its own steps
        reached, ending in the method state `state` (see `resume`): by default
        `method_init`'s, with its checks of the start."""
        return self.method_init(step)

    @abc.abstractmethod
    def method_step(
        self, step: StepInputs, state: PyTree, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        """One step of the method. After a jump (`made_jump`) `state` belongs to the
        trajectory before it."""

    def init(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
    ) -> VIState:
        step, state = self._start(terms, t0, t1, y0, args, self.method_init)
        if not step.term.start_checked:
            state = check_on_space(step.term.lagrangian.space, y0[0], state)
        return check_times(t0, t1, state)

    def resume(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: VIState,
    ) -> VIState:
        """`AbstractComposableSolver.resume`: the method's state from
        `method_resume`, without `init`'s checks that the start lies on its group
        and that its first step is finite."""
        method_state = solver_state.method
        return self._start(
            terms, t0, t1, y0, args, lambda s: self.method_resume(s, method_state)
        )[1]

    def _start(self, terms, t0, t1, y0, args, method_state) -> tuple:
        """The inputs of a step from `y0`, and the solver state before it, whose
        method's state `method_state(step)` gives."""
        compensation = initial_compensation(y0, self.compensated)
        step = step_inputs(
            terms,
            t0,
            t1,
            y0,
            args,
            compensation,
            Substep(1.0, t0, t1),
            type(self).__name__,
        )
        work = None if step.term.force is None else jnp.zeros((), step.dtype)
        # Both depend on y0 after a step, and so from the start (`perturbed_with`);
        # not a group's position's compensation, which stays zero (`advance`).
        if compensation is None or is_euclidean(step.term.lagrangian.space):
            compensation, work = perturbed_with((compensation, work), y0)
        else:
            compensation_p, work = perturbed_with((compensation[1], work), y0)
            compensation = (compensation[0], compensation_p)
        return step, VIState(method_state(step), compensation, work)

    def _fractional_step(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: VIState,
        made_jump: bool | Bool[ArrayLike, ""],
        substep: Substep,
        dense: bool = True,
    ) -> tuple[PyTree, None, dict[str, PyTree] | None, VIState, dfx.RESULTS]:
        compensation = solver_state.compensation
        step = step_inputs(
            terms, t0, t1, y0, args, compensation, substep, type(self).__name__
        )
        out = self.method_step(step, solver_state.method, made_jump)
        space = step.term.lagrangian.space if out.space is None else out.space
        if is_euclidean(space):
            y1, compensation = advance(space, y0, (out.dq, out.dp), compensation)
            y1 = unless_failed(out.result, y1)
        else:
            # Retracted before a failed step's NaN replaces it: the retraction is
            # then the one the method's increments took (the Lie midpoint rule
            # transports its momentum by the same exponential), which XLA computes
            # once (the free body's MidpointVI step: 0.262 against 0.287 us).
            q1 = retract(space, y0[0], out.dq) if out.q1 is None else out.q1
            dp, q1 = unless_failed(out.result, (out.dp, q1))
            y1, compensation = advance(space, y0, (out.dq, dp), compensation, q1)
        result = step_result(out.result, y1)
        dense_info = hermite_dense_info(step, y0, y1, out.v) if dense else None
        work = solver_state.work
        if work is not None:
            work = work + out.work
        return y1, None, dense_info, VIState(out.state, compensation, work), result

    def func(
        self, terms: dfx.AbstractTerm, t0: RealScalarLike, y0: PyTree, args: Args
    ) -> PyTree:
        """`hamilton_field`, as a step's dense output evaluates it (a
        composition's, through this)."""
        term, direction = unwrap_term(terms, type(self).__name__)
        return hamilton_field(term, t0 * direction, y0, args)

    def root_of_inverse(
        self, terms: dfx.AbstractTerm, solver_state: VIState
    ) -> PyTree | None:
        """The unknowns of the step that the step just taken inverts, from its
        `solver_state`: a symmetric implicit step from $y_1$ with $-h$ solves for the
        same velocities as the step from $y_0$ with $h$ that it undoes (their stages
        in reverse order), so [`diffrax_vi.ReversibleAdjoint`][] takes them as that
        step's root rather than solving for it again; a constrained step's
        multipliers are those of the inverse step's momentum projection
        (`unknowns.inverse_root`). `None` where the step has no such root (an
        explicit step, RATTLE's multipliers alone)."""
        return None


# A step traced once per program: diffrax traces a solver's step up to three times
# (twice under `eval_shape` to find what stays static, then in its loop), and a
# composition's scan over its substeps twice (`Composition._fractional_step`). JAX
# reuses the trace of a nested jit for the same abstract inputs, and XLA inlines it,
# so the compiled loop is the same (tracing MidpointVI on four_bar: 6.9 -> 2.2 s).
# The reuse spans programs too: a study's tracked solve (`solve_fixed_steps`) and its
# timed one (`diffeqsolve`) of the same method trace its step once.
@eqx.filter_jit
def _traced_once(
    terms, t0, t1, y0, args, state, made_jump, substep, solver, dense, settings
):
    del settings
    return solver._fractional_step(
        terms, t0, t1, y0, args, state, made_jump, substep, dense
    )
