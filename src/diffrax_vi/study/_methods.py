import dataclasses

import diffrax as dfx

from .._solver import (
    Composition,
    GaussVPRK,
    LinearizedVI,
    LobattoVPRK,
    MidpointVI,
    StormerVerlet,
    TrapezoidalVI,
)
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
    "LinearizedVI": lambda: LinearizedVI(velocity="centered"),
    "SemiImplicitEuler": dfx.SemiImplicitEuler,
    "Tsit5": dfx.Tsit5,
    "Dopri5": dfx.Dopri5,
    "Dopri8": dfx.Dopri8,
}
ADAPTIVE_SUFFIX = "+PID"


@dataclasses.dataclass(frozen=True)
class Method:
    """A solver and how it steps, as a study runs it.

    **Fields:**

    - `name`: the name in tables and figures.
    - `solver`: any diffrax solver.
    - `rtol`: `None` for the study's fixed step; a tolerance for a
        `diffrax.PIDController(rtol=rtol, atol=rtol)` started at the study's step.
    """

    name: str
    solver: dfx.AbstractSolver
    rtol: float | None = None

    def controller(self) -> dfx.AbstractStepSizeController:
        if self.rtol is None:
            return dfx.ConstantStepSize()
        return dfx.PIDController(rtol=self.rtol, atol=self.rtol)

    def terms(self, scene: Scene):
        """The scene's terms as this solver takes them
        ([`diffrax_vi.terms_for`][])."""
        return terms_for(self.solver, scene.term())


def make_solver(name: str) -> dfx.AbstractSolver:
    """A solver by name: one of `diffrax_vi.study.SOLVERS`."""
    try:
        return SOLVERS[name]()
    except KeyError:
        raise ValueError(
            f"Unknown solver {name!r}. Choose from: {', '.join(SOLVERS)}, or an "
            f"adaptive one with the suffix {ADAPTIVE_SUFFIX!r} (e.g. 'Tsit5+PID')."
        ) from None


def as_method(spec: "str | dfx.AbstractSolver | Method", rtol: float = 1e-8) -> Method:
    """A study's method from a name in `SOLVERS` (with the suffix `+PID` for a
    `PIDController` at tolerance `rtol`), a solver instance (fixed steps) or a
    [`diffrax_vi.study.Method`][].

    **Raises:** `ValueError` for an unknown name, an `rtol` outside (0, 1), or
    `+PID` on a solver without an error estimate (our variational solvers take
    fixed steps; wrap one in `diffrax.HalfSolver` yourself to step it adaptively, at
    the price of symplecticity).
    """
    if isinstance(spec, Method):
        return spec
    if isinstance(spec, dfx.AbstractSolver):
        return Method(type(spec).__name__, spec)
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
            + "."
        )
    return Method(spec, solver, tolerance(rtol))
