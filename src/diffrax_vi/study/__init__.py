"""Energy-drift studies: many solvers, one scene, the same steps."""

from ._drift import (
    drift as drift,
    DriftRun as DriftRun,
    DriftStudy as DriftStudy,
    make_solver as make_solver,
    SOLVERS as SOLVERS,
)
