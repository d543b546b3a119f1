import importlib.metadata as _metadata

from . import diagnostics as diagnostics, scenes as scenes, study as study
from ._adaptive import (
    PotentialMonitor as PotentialMonitor,
    ReversibleController as ReversibleController,
    ReversibleState as ReversibleState,
)
from ._adjoint import ReversibleAdjoint as ReversibleAdjoint
from ._constraint import project_onto_constraints as project_onto_constraints
from ._discrete import (
    AbstractDiscreteLagrangian as AbstractDiscreteLagrangian,
    discrete_lagrangian as discrete_lagrangian,
    MidpointRule as MidpointRule,
    TrapezoidalRule as TrapezoidalRule,
)
from ._joints import (
    BallJoint as BallJoint,
    HingeJoint as HingeJoint,
    Joints as Joints,
    joints as joints,
)
from ._lagrangian import (
    AbstractLagrangian as AbstractLagrangian,
    AbstractMultibodyLagrangian as AbstractMultibodyLagrangian,
    AbstractQuadraticLagrangian as AbstractQuadraticLagrangian,
    AbstractRigidBodyLagrangian as AbstractRigidBodyLagrangian,
    AbstractSeparableLagrangian as AbstractSeparableLagrangian,
    energy as energy,
    Lagrangian as Lagrangian,
    momentum as momentum,
    SeparableLagrangian as SeparableLagrangian,
    TangentLift as TangentLift,
    velocity as velocity,
)
from ._root_finders import (
    FixedPoint as FixedPoint,
    Newton as Newton,
    SimplifiedNewton as SimplifiedNewton,
)
from ._scan import (
    FixedStepSolution as FixedStepSolution,
    solve_fixed_steps as solve_fixed_steps,
)
from ._so2 import SO2 as SO2
from ._so3 import SO3 as SO3
from ._solver import (
    AbstractComposableSolver as AbstractComposableSolver,
    AbstractImplicitVI as AbstractImplicitVI,
    AbstractSymplecticSolver as AbstractSymplecticSolver,
    AbstractVariationalSolver as AbstractVariationalSolver,
    AbstractVPRK as AbstractVPRK,
    Composition as Composition,
    CompositionScheme as CompositionScheme,
    GaussVPRK as GaussVPRK,
    LGVI as LGVI,
    LinearizedVI as LinearizedVI,
    LobattoVPRK as LobattoVPRK,
    MidpointVI as MidpointVI,
    StormerVerlet as StormerVerlet,
    TrapezoidalVI as TrapezoidalVI,
    VPRK as VPRK,
    VPRKTableau as VPRKTableau,
)
from ._space import AbstractSpace as AbstractSpace, Euclidean as Euclidean
from ._term import (
    LagrangianTerm as LagrangianTerm,
    separable_terms as separable_terms,
    terms_for as terms_for,
)
from ._xla import (
    compile_small_loops_whole as compile_small_loops_whole,
    keep_xla_default as keep_xla_default,
    raise_on_import as _raise_on_import,
)


__version__ = _metadata.version("diffrax_vi")

# Small loops compiled whole on CPU; the reasons and the opt-out are in `_xla`.
_raise_on_import()
