import importlib.metadata

from ._diagnostics import (
    del_residuals as del_residuals,
    presymplectic_form as presymplectic_form,
    tangent_discrete_lagrangian as tangent_discrete_lagrangian,
    tangent_symplectic_form as tangent_symplectic_form,
)
from ._discrete import (
    AbstractDiscreteLagrangian as AbstractDiscreteLagrangian,
    del_residual as del_residual,
    discrete_lagrangian as discrete_lagrangian,
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
    TangentLift as TangentLift,
    velocity as velocity,
)
from ._solver import (
    AbstractSymmetricSolver as AbstractSymmetricSolver,
    AbstractSymplecticSolver as AbstractSymplecticSolver,
    AbstractVariationalSolver as AbstractVariationalSolver,
    AbstractVPRK as AbstractVPRK,
    Composition as Composition,
    GaussVPRK as GaussVPRK,
    LinearizedVI as LinearizedVI,
    LobattoVPRK as LobattoVPRK,
    MidpointVI as MidpointVI,
    StormerVerlet as StormerVerlet,
    TrapezoidalVI as TrapezoidalVI,
    VPRKTableau as VPRKTableau,
)
from ._stability import (
    oscillator_step_matrix as oscillator_step_matrix,
    spectral_radius as spectral_radius,
    stability_limit as stability_limit,
)
from ._term import LagrangianTerm as LagrangianTerm, separable_terms as separable_terms


__version__ = importlib.metadata.version("diffrax_vi")
