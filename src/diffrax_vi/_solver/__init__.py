from .base import (
    AbstractComposableSolver as AbstractComposableSolver,
    AbstractSymplecticSolver as AbstractSymplecticSolver,
    AbstractVariationalSolver as AbstractVariationalSolver,
)
from .composition import (
    Composition as Composition,
    CompositionScheme as CompositionScheme,
)
from .implicit import AbstractImplicitVI as AbstractImplicitVI
from .lgvi import LGVI as LGVI
from .linearized import LinearizedVI as LinearizedVI
from .midpoint import MidpointVI as MidpointVI
from .stormer_verlet import StormerVerlet as StormerVerlet
from .trapezoidal import TrapezoidalVI as TrapezoidalVI
from .vprk import (
    AbstractVPRK as AbstractVPRK,
    GaussVPRK as GaussVPRK,
    LobattoVPRK as LobattoVPRK,
    VPRK as VPRK,
    VPRKTableau as VPRKTableau,
)
