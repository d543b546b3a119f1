from .base import (
    AbstractSymplecticSolver as AbstractSymplecticSolver,
    AbstractVariationalSolver as AbstractVariationalSolver,
)
from .linearized import LinearizedVI as LinearizedVI
from .midpoint import MidpointVI as MidpointVI
from .stormer_verlet import StormerVerlet as StormerVerlet
from .trapezoidal import TrapezoidalVI as TrapezoidalVI
