import abc
import dataclasses
import math

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .._adaptive import ReversibleController
from .._solver import (
    Composition,
    GaussVPRK,
    LGVI,
    LinearizedVI,
    LobattoVPRK,
    MidpointVI,
    StormerVerlet,
    TrapezoidalVI,
)
from .._solver.base import is_symmetric
from .._term import terms_for
from ..scenes import Scene
from ._checks import tolerance


SOLVERS = {
    "MidpointVI": MidpointVI,
    "TrapezoidalVI": TrapezoidalVI,
    "StormerVerlet": StormerVerlet,
    "GaussVPRK2": lambda: GaussVPRK(2),
    "GaussVPRK3": lambda: GaussVPRK(3),
    "LobattoVPRK3": lambda: LobattoVPRK(3),
    "Yoshida4": lambda: Composition(StormerVerlet(), "yoshida4"),
    "KahanLi6": lambda: Composition(StormerVerlet(), "kahan_li6"),
    "KahanLi8": lambda: Composition(StormerVerlet(), "kahan_li8"),
    # Compositions of the midpoint step: general Lagrangians, constraints, groups.
    "MidpointVI-Yoshida4": lambda: Composition(MidpointVI(), "yoshida4"),
    "MidpointVI-KahanLi8": lambda: Composition(MidpointVI(), "kahan_li8"),
    "LinearizedVI": lambda: LinearizedVI(velocity="centered"),
    # Rigid bodies with constant inertia (an AbstractRigidBodyLagrangian).
    "LGVI": LGVI,
    "SemiImplicitEuler": dfx.SemiImplicitEuler,
    "Tsit5": dfx.Tsit5,
    "Dopri5": dfx.Dopri5,
    "Dopri8": dfx.Dopri8,
}
"""Every solver a study and `diffrax-vi --solvers` accept by name, each with a
function of no arguments that makes it; the suffix `+PID` steps a Runge-Kutta one
with a `diffrax.PIDController`, `+Adaptive` a symmetric one with a
[`diffrax_vi.ReversibleController`][]."""

ADAPTIVE_SUFFIX = "+PID"
REVERSIBLE_SUFFIX = "+Adaptive"


# An adaptive method may take on average at most this many steps per save interval
# (as diffrax's default `max_steps`), so that a step size collapsing to nothing fails
# the run rather than spinning.
MAX_ADAPTIVE_STEPS_PER_SAVE = 4096


class AbstractStepping(abc.ABC):
    """How a study's method steps: a controller, the first step and the bound on
    the number of steps that a plain `diffeqsolve` of it gets. A new kind of method
    is a new subclass."""

    @abc.abstractmethod
    def controller(self, scene: Scene, name: str) -> dfx.AbstractStepSizeController:
        """The step-size controller on `scene` (`name`: the method's, for errors)."""

    @abc.abstractmethod
    def dt0(
        self, scene: Scene, method: "Method", t1: float, n_steps: int, y0, dtype
    ) -> Array | None:
        """The first step of a run to `t1` at the study's `n_steps` (its fixed step
        `t1 / n_steps`, or the step a controller starts from)."""

    @abc.abstractmethod
    def max_steps(self, n_steps: int, n_save: int) -> int | None:
        """`diffeqsolve`'s bound on the steps: `None` for fixed steps, which need
        none."""


@dataclasses.dataclass(frozen=True)
class FixedSteps(AbstractStepping):
    """The study's fixed step, `t1 / n_steps` (a `diffrax.ConstantStepSize`)."""

    def controller(self, scene, name):
        return dfx.ConstantStepSize()

    def dt0(self, scene, method, t1, n_steps, y0, dtype):
        return jnp.asarray(t1 / n_steps, dtype)

    def max_steps(self, n_steps, n_save):
        return None


@dataclasses.dataclass(frozen=True)
class PIDSteps(AbstractStepping):
    """A `diffrax.PIDController(rtol=rtol, atol=rtol)`, which picks its own first
    step."""

    rtol: float

    def controller(self, scene, name):
        return dfx.PIDController(rtol=self.rtol, atol=self.rtol)

    def dt0(self, scene, method, t1, n_steps, y0, dtype):
        return None

    def max_steps(self, n_steps, n_save):
        return MAX_ADAPTIVE_STEPS_PER_SAVE * n_save


@dataclasses.dataclass(frozen=True)
class ReversibleSteps(AbstractStepping):
    """A [`diffrax_vi.ReversibleController`][] on the scene's `monitor`, at the
    study's mean number of steps (the `dt0` of
    [`diffrax_vi.study.reversible_dt0`][])."""

    def controller(self, scene, name):
        return ReversibleController(monitor_of(scene, name))

    def dt0(self, scene, method, t1, n_steps, y0, dtype):
        return reversible_dt0(scene, method, t1, n_steps, y0, dtype)

    def max_steps(self, n_steps, n_save):
        # Room for the steps asked for, four times over (the calibration counts a
        # different trajectory where the motion is chaotic), as diffeqsolve needs
        # a bound.
        return max(MAX_ADAPTIVE_STEPS_PER_SAVE * n_save, 4 * n_steps)


@dataclasses.dataclass(frozen=True)
class Method:
    """A solver and how it steps, as a study runs it.

    **Fields:**

    - `name`: the name in tables and figures.
    - `solver`: any diffrax solver.
    - `stepping`: `FixedSteps()` (the default) for the study's fixed step,
        `PIDSteps(rtol)` for a `diffrax.PIDController(rtol=rtol, atol=rtol)`, or
        `ReversibleSteps()` for a [`diffrax_vi.ReversibleController`][] on the
        scene's `monitor` at the study's mean number of steps per period.
    """

    name: str
    solver: dfx.AbstractSolver
    stepping: AbstractStepping = FixedSteps()

    @property
    def fixed(self) -> bool:
        """Whether the method takes the study's fixed step."""
        return isinstance(self.stepping, FixedSteps)

    def controller(self, scene: Scene) -> dfx.AbstractStepSizeController:
        return self.stepping.controller(scene, self.name)

    def terms(self, scene: Scene):
        """The scene's terms as this solver takes them
        ([`diffrax_vi.terms_for`][]).

        **Raises:** `ValueError` if they do not fit, or if the method steps by the
        scene's monitor and the scene has none."""
        self.controller(scene)
        return terms_for(self.solver, scene.term())


def reversible_dt0(
    scene: Scene, method: Method, t1: float, n_steps: int, y0: PyTree, dtype
) -> Array:
    """The `dt0` at which `method`'s [`diffrax_vi.ReversibleController`][] takes
    `n_steps` steps over `[0, t1]` on average: its steps over the first ten periods
    (or `t1` if shorter) counted at a trial `dt0`, which is rescaled (the count is
    inversely proportional to `dt0`) and counted again. Separate solves: the
    measured run is a plain one at the `dt0` found."""
    span = min(t1, 10 * scene.period)
    wanted = n_steps * span / t1
    terms = method.terms(scene)
    controller = method.controller(scene)

    @eqx.filter_jit
    def count(dt0):
        sol = dfx.diffeqsolve(
            terms,
            method.solver,
            jnp.zeros((), dtype),
            jnp.asarray(span, dtype),
            dt0,
            y0,
            args=scene.args,
            stepsize_controller=controller,
            saveat=dfx.SaveAt(t1=True),
            max_steps=max(4096, 64 * math.ceil(wanted)),
            throw=False,
        )
        ok = sol.result == dfx.RESULTS.successful
        return jnp.where(ok, sol.stats["num_steps"], 0)

    # dt0 is the step where the density is 1, at the start: the mean step is a
    # trial that may be far too large there (at Kepler's pericentre), so shrink it
    # until the count succeeds, then rescale it twice.
    dt0, rescaled = t1 / n_steps, 0
    for _ in range(12):
        taken = int(count(jnp.asarray(dt0, dtype)))
        if taken == 0:
            dt0 /= 8
        elif rescaled == 2:
            break
        else:
            dt0, rescaled = dt0 * taken / wanted, rescaled + 1
    return jnp.asarray(dt0, dtype)


def monitor_of(scene: Scene, method: str):
    """The scene's step-size monitor, or a `ValueError` naming the scenes with one."""
    if scene.monitor is None:
        from ..scenes import MONITORED

        raise ValueError(
            f"{method} steps by a monitor of the motion, and the scene "
            f"{scene.name!r} has none. Scenes with one: {', '.join(MONITORED)}; "
            "or give a Scene a `monitor` (e.g. diffrax_vi.PotentialMonitor(L) for "
            "gravity)."
        )
    return scene.monitor


def make_solver(name: str) -> dfx.AbstractSolver:
    """A solver by name: one of `diffrax_vi.study.SOLVERS`."""
    try:
        return SOLVERS[name]()
    except KeyError:
        raise ValueError(
            f"Unknown solver {name!r}. Choose from: {', '.join(SOLVERS)}, with the "
            f"suffix {ADAPTIVE_SUFFIX!r} for an adaptive Runge-Kutta one (e.g. "
            f"'Tsit5+PID') or {REVERSIBLE_SUFFIX!r} for reversible adaptive steps "
            "of a symmetric one (e.g. 'KahanLi8+Adaptive')."
        ) from None


def as_method(spec: "str | dfx.AbstractSolver | Method", rtol: float = 1e-8) -> Method:
    """A study's method from a name in `SOLVERS` (with the suffix `+PID` for a
    `PIDController` at tolerance `rtol`, or `+Adaptive` for a
    [`diffrax_vi.ReversibleController`][] on the scene's monitor), a solver instance
    (fixed steps) or a [`diffrax_vi.study.Method`][].

    **Raises:** `ValueError` for an unknown name, an `rtol` outside (0, 1),
    `+PID` on a solver without an error estimate (our variational solvers have
    none: use `+Adaptive`), or `+Adaptive` on a solver that is not symmetric.
    """
    if isinstance(spec, Method):
        return spec
    if isinstance(spec, dfx.AbstractSolver):
        return Method(type(spec).__name__, spec)
    if spec.endswith(REVERSIBLE_SUFFIX):
        base = spec.removesuffix(REVERSIBLE_SUFFIX)
        solver = make_solver(base)
        if not is_symmetric(solver):
            raise ValueError(
                f"{spec!r}: reversible adaptive steps need a symmetric one-step "
                f"method, and {base} is not one. Symmetric names: "
                + ", ".join(
                    n + REVERSIBLE_SUFFIX
                    for n, make in SOLVERS.items()
                    if is_symmetric(make())
                )
                + "."
            )
        return Method(spec, solver, ReversibleSteps())
    base = spec.removesuffix(ADAPTIVE_SUFFIX)
    solver = make_solver(base)
    if base == spec:
        return Method(spec, solver)
    if not isinstance(solver, dfx.AbstractAdaptiveSolver):
        raise ValueError(
            f"{spec!r}: {base} has no error estimate, so it cannot be stepped by a "
            "PIDController. Adaptive names: "
            + ", ".join(
                n + ADAPTIVE_SUFFIX
                for n, make in SOLVERS.items()
                if isinstance(make(), dfx.AbstractAdaptiveSolver)
            )
            + (
                f"; or {base}{REVERSIBLE_SUFFIX} for reversible adaptive steps."
                if is_symmetric(solver)
                else "."
            )
        )
    return Method(spec, solver, PIDSteps(tolerance(rtol)))
