import dataclasses
import math
import pathlib
from collections.abc import Sequence

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from ..scenes import Scene
from ._checks import non_empty, step_count, tolerance
from ._methods import as_method, Method, PIDSteps
from ._run import cast_scene, run
from ._table import markdown_table, write_records


def reference_state(scene: Scene, t1: float) -> PyTree[Array]:
    """The state at `t1` from the scene's default `y0`: its exact solution where it has
    one, else Dopri8 on the scene's term (its force and constraint included) with a
    `PIDController` at `rtol = atol = 1e-13` (use float64;
    for a chaotic scene this is only meaningful over a few Lyapunov times)."""
    if scene.exact is not None:
        return scene.exact(jnp.asarray(t1))
    # The scene's own term: with its force and constraint (the index-reduced
    # equations), and its args.
    sol = dfx.diffeqsolve(
        scene.term(),
        dfx.Dopri8(),
        0.0,
        t1,
        scene.period / 100,
        scene.y0,
        args=scene.args,
        stepsize_controller=dfx.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=10_000_000,
    )
    return jax.tree.map(lambda x: x[-1], sol.ys)


@dataclasses.dataclass(frozen=True)
class WorkPrecision:
    """The result of [`diffrax_vi.study.work_precision`][]: one record per method and
    setting (steps per period for fixed steps, tolerance for `+PID` methods), with
    its wall time, steps, largest energy error over the horizon and global error at
    its end. `parameters` names the scene's parameters set apart from its defaults,
    as for [`diffrax_vi.study.DriftStudy`][]."""

    scene: str
    periods: int | float
    dtype: str
    records: list[dict]
    parameters: str = ""

    def table(self) -> str:
        """The records as a Markdown table, one row per run."""
        return markdown_table(self.records)

    def write(self, out: str | pathlib.Path) -> list[pathlib.Path]:
        """Write `work_precision.csv`, `work_precision.json` and, if matplotlib is
        installed, `work_precision.png` into the folder `out`."""
        out = pathlib.Path(out)
        written = write_records(
            out,
            "work_precision",
            self.records,
            scene=self.scene,
            parameters=self.parameters,
            periods=self.periods,
            dtype=self.dtype,
        )
        try:
            from ._plot import plot_work_precision
        except ImportError:
            return written
        written.append(plot_work_precision(self, out / "work_precision.png"))
        return written


def check_work_precision(
    periods: int | float, steps_per_period: Sequence[int]
) -> dict[int, int]:
    """Check a work-precision study's horizon and step grid without running
    anything, raising what [`diffrax_vi.study.work_precision`][] would raise; returns
    the number of fixed steps for each entry of `steps_per_period`."""
    steps_per_period = non_empty("steps_per_period", steps_per_period)
    return {spp: step_count(periods, spp) for spp in steps_per_period}


def work_precision(
    scene: Scene,
    solvers: Sequence[str | dfx.AbstractSolver | Method],
    *,
    periods: int | float = 100,
    steps_per_period: Sequence[int] = (50, 100, 200, 400),
    rtols: Sequence[float] = (1e-6, 1e-8, 1e-10, 1e-12),
    n_save: int | None = None,
    dtype=jnp.float64,
    reference: PyTree[Array] | None = None,
) -> WorkPrecision:
    """Wall time against accuracy: each fixed-step method at every
    `steps_per_period`, each `+PID` method at every tolerance in `rtols`, over the
    same horizon.

    Accuracy is measured two ways: the largest energy error over every step, and
    the global error (largest component of `|y(t_1) - y_\\mathrm{ref}(t_1)|`) against
    [`diffrax_vi.study.reference_state`][]. Failed runs are kept, with `NaN` errors
    and the failure in `result`.

    **Arguments:** as [`diffrax_vi.study.drift`][] (except that `n_save` defaults to
    one interval per period, and is reduced to a divisor of each run's number of
    steps), plus the grids `steps_per_period` and `rtols`, and `reference`: the state
    at the end of the horizon to measure the global error against (default:
    [`diffrax_vi.study.reference_state`][]; pass it to reuse one across calls).
    """
    solvers = non_empty("solvers", solvers)
    methods = [as_method(spec) for spec in solvers]
    grid = check_work_precision(periods, steps_per_period)
    if any(isinstance(m.stepping, PIDSteps) for m in methods):
        rtols = [tolerance(r) for r in non_empty("rtols", rtols)]
    t1 = scene.period * periods
    if reference is None:
        reference = reference_state(scene, t1)
    exact = jax.tree.map(np.asarray, reference)
    scene = cast_scene(scene, dtype)
    records = []
    for base in methods:
        adaptive = isinstance(base.stepping, PIDSteps)
        for setting in rtols if adaptive else steps_per_period:
            method = (
                dataclasses.replace(base, stepping=PIDSteps(setting))
                if adaptive
                else base
            )
            spp = steps_per_period[0] if adaptive else setting
            n_steps = grid[spp]
            outcome = run(
                scene,
                method,
                t1=t1,
                n_steps=n_steps,
                n_save=math.gcd(n_save or max(1, round(periods)), n_steps),
                dtype=dtype,
                y0=scene.y0,
            )
            ok = outcome.result == "successful"
            global_error = max(
                float(np.max(np.abs(a[0] - b)))
                for a, b in zip(jax.tree.leaves(outcome.final), jax.tree.leaves(exact))
            )
            records.append(
                dict(
                    solver=method.name,
                    steps_per_period=None if adaptive else setting,
                    rtol=setting if adaptive else None,
                    steps=outcome.steps,
                    wall_time_s=outcome.wall_time,
                    result=outcome.result,
                    max_energy_error=float(outcome.errors()["energy"].max())
                    if ok
                    else math.nan,
                    global_error=global_error if ok else math.nan,
                )
            )
    return WorkPrecision(scene.name, periods, jnp.dtype(dtype).name, records)
