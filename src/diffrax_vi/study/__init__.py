"""Energy-drift and work-precision studies: many solvers, one scene, the same steps."""

import pathlib

from ._drift import drift as drift, DriftRun as DriftRun, DriftStudy as DriftStudy
from ._methods import (
    as_method as as_method,
    make_solver as make_solver,
    Method as Method,
    SOLVERS as SOLVERS,
)
from ._work_precision import (
    reference_state as reference_state,
    work_precision as work_precision,
    WorkPrecision as WorkPrecision,
)


def seed(out: str | pathlib.Path) -> str:
    """Reproduce the seed thesis's Chapter 5 tables and figures (and Figures 1.1/1.2)
    beside the thesis's own numbers: writes `chapter5.md` and PNG figures into the
    folder `out` and returns the Markdown. Needs float64 (`jax_enable_x64`) and
    matplotlib; about 15 s on a 2-core CPU."""
    from ._seed import chapter5

    return chapter5(pathlib.Path(out))
