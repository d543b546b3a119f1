import importlib.metadata

from ._discrete import (
    AbstractDiscreteLagrangian as AbstractDiscreteLagrangian,
    MidpointRule as MidpointRule,
    TrapezoidalRule as TrapezoidalRule,
)
from ._lagrangian import (
    AbstractLagrangian as AbstractLagrangian,
    AbstractQuadraticLagrangian as AbstractQuadraticLagrangian,
    AbstractSeparableLagrangian as AbstractSeparableLagrangian,
    energy as energy,
    Lagrangian as Lagrangian,
    momentum as momentum,
    SeparableLagrangian as SeparableLagrangian,
    velocity as velocity,
)
from ._solver import (
    AbstractSymplecticSolver as AbstractSymplecticSolver,
    AbstractVariationalSolver as AbstractVariationalSolver,
    MidpointVI as MidpointVI,
    StormerVerlet as StormerVerlet,
    TrapezoidalVI as TrapezoidalVI,
)
from ._term import LagrangianTerm as LagrangianTerm, separable_terms as separable_terms


__version__ = importlib.metadata.version("diffrax_vi")
