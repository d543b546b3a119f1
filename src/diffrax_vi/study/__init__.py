"""Energy-drift and work-precision studies: many solvers, one scene, the same steps."""

from ._drift import (
    check_drift as check_drift,
    drift as drift,
    DriftRun as DriftRun,
    DriftStudy as DriftStudy,
)
from ._methods import (
    AbstractStepping as AbstractStepping,
    as_method as as_method,
    FixedSteps as FixedSteps,
    make_solver as make_solver,
    Method as Method,
    PIDSteps as PIDSteps,
    reversible_dt0 as reversible_dt0,
    ReversibleSteps as ReversibleSteps,
    SOLVERS as SOLVERS,
)
from ._work_precision import (
    check_work_precision as check_work_precision,
    reference_state as reference_state,
    work_precision as work_precision,
    WorkPrecision as WorkPrecision,
)
