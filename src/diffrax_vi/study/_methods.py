import dataclasses

import diffrax as dfx

from .._adaptive import ReversibleController
from .._solver import (
    Composition,
    GaussVPRK,
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


# Name -> a function making the solver.
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
    "SemiImplicitEuler": dfx.SemiImplicitEuler,
    "Tsit5": dfx.Tsit5,
    "Dopri5": dfx.Dopri5,
    "Dopri8": dfx.Dopri8,
}
ADAPTIVE_SUFFIX = "+PID"
REVERSIBLE_SUFFIX = "+Adaptive"


@dataclasses.dataclass(frozen=True)
class Method:
    """A solver and how it steps, as a study runs it.

    **Fields:**

    - `name`: the name in tables and figures.
    - `solver`: any diffrax solver.
    - `rtol`: `None` for the study's fixed step; a tolerance for a
        `diffrax.PIDController(rtol=rtol, atol=rtol)` started at the study's step.
    - `reversible`: step with a [`diffrax_vi.ReversibleController`][] on the
        scene's `monitor` instead, at the study's mean number of steps per period.
    """

    name: str
    solver: dfx.AbstractSolver
    rtol: float | None = None
    reversible: bool = False

    @property
    def fixed(self) -> bool:
        """Whether the method takes the study's fixed step."""
        return self.rtol is None and not self.reversible

    def controller(self, scene: Scene) -> dfx.AbstractStepSizeController:
        if self.reversible:
            return ReversibleController(monitor_of(scene, self.name))
        if self.rtol is None:
            return dfx.ConstantStepSize()
        return dfx.PIDController(rtol=self.rtol, atol=self.rtol)

    def terms(self, scene: Scene):
        """The scene's terms as this solver takes them
        ([`diffrax_vi.terms_for`][]).

        **Raises:** `ValueError` if they do not fit, or if the method steps
        reversibly and the scene has no step-size monitor."""
        if self.reversible:
            monitor_of(scene, self.name)
        return terms_for(self.solver, scene.term())


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
        return Method(spec, solver, reversible=True)
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
    return Method(spec, solver, tolerance(rtol))
