import csv
import dataclasses
import json
import pathlib
import time
from collections.abc import Sequence

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._solver import (
    Composition,
    GaussVPRK,
    LinearizedVI,
    LobattoVPRK,
    MidpointVI,
    StormerVerlet,
    TrapezoidalVI,
)
from .._term import LagrangianTerm, separable_terms
from ..scenes import Scene


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


def make_solver(name: str) -> dfx.AbstractSolver:
    """A solver by name: one of `diffrax_vi.study.SOLVERS`."""
    try:
        return SOLVERS[name]()
    except KeyError:
        raise ValueError(
            f"Unknown solver {name!r}. Choose from: {', '.join(SOLVERS)}."
        ) from None


def _terms(scene: Scene, solver: dfx.AbstractSolver):
    # Partitioned solvers (StormerVerlet, SemiImplicitEuler) take Hamilton's equations
    # as a pair of terms; everything else takes the Lagrangian term.
    if isinstance(solver.term_structure, tuple):
        return separable_terms(scene.lagrangian)
    return LagrangianTerm(scene.lagrangian)


@dataclasses.dataclass(frozen=True)
class DriftRun:
    """One solver's run in a drift study.

    **Fields:**

    - `solver`: the solver's name.
    - `steps`: the number of steps taken.
    - `wall_time`: seconds for the solve, after compilation.
    - `result`: `"successful"` or diffrax's message for the failure.
    - `ts`: the times at which the invariants were saved.
    - `errors`: invariant name -> `|I(t) - I(0)|` at `ts`.
    """

    solver: str
    steps: int
    wall_time: float
    result: str
    ts: np.ndarray
    errors: dict[str, np.ndarray]

    def max_error(self, name: str) -> float:
        return float(np.max(self.errors[name]))


@dataclasses.dataclass(frozen=True)
class DriftStudy:
    """The result of [`diffrax_vi.study.drift`][]: one
    [`diffrax_vi.study.DriftRun`][] per solver."""

    scene: str
    periods: int | float
    steps_per_period: int
    dtype: str
    runs: list[DriftRun]

    @property
    def invariants(self) -> list[str]:
        return list(self.runs[0].errors) if self.runs else []

    def rows(self) -> list[dict]:
        """The summary table as a list of records."""
        return [
            dict(
                solver=run.solver,
                steps=run.steps,
                wall_time_s=run.wall_time,
                result=run.result,
                **{f"max_{k}_error": run.max_error(k) for k in self.invariants},
            )
            for run in self.runs
        ]

    def table(self) -> str:
        """The summary as a Markdown table."""
        rows = self.rows()
        header = list(rows[0])
        lines = [
            "| " + " | ".join(header) + " |",
            "|" + "|".join("---" for _ in header) + "|",
        ]
        for row in rows:
            cells = [
                f"{v:.3e}"
                if isinstance(v, float) and k != "wall_time_s"
                else (f"{v:.3f}" if isinstance(v, float) else str(v))
                for k, v in row.items()
            ]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def write(self, out: str | pathlib.Path) -> list[pathlib.Path]:
        """Write `drift.csv` (summary), `drift.json` (summary and series) and, if
        matplotlib is installed, `drift_<invariant>.png` into the folder `out`."""
        out = pathlib.Path(out)
        out.mkdir(parents=True, exist_ok=True)
        rows = self.rows()
        with open(out / "drift.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        series = {
            run.solver: dict(
                ts=run.ts.tolist(), **{k: v.tolist() for k, v in run.errors.items()}
            )
            for run in self.runs
        }
        meta = dict(
            scene=self.scene,
            periods=self.periods,
            steps_per_period=self.steps_per_period,
            dtype=self.dtype,
        )
        with open(out / "drift.json", "w") as f:
            json.dump(dict(meta, summary=rows, series=series), f)
        written = [out / "drift.csv", out / "drift.json"]
        try:
            from ._plot import plot_drift
        except ImportError:
            return written
        for name in self.invariants:
            path = out / f"drift_{name}.png"
            plot_drift(self, name, path)
            written.append(path)
        return written


def drift(
    scene: Scene,
    solvers: Sequence[str | dfx.AbstractSolver],
    *,
    periods: int | float = 1000,
    steps_per_period: int = 200,
    n_save: int = 1000,
    dtype=jnp.float64,
    progress: bool = False,
) -> DriftStudy:
    """Run each solver on the same scene, the same step and the same number of steps,
    and record the error in every conserved quantity against time.

    The invariants are streamed through `diffrax.SaveAt(ts=..., fn=...)` at `n_save`
    times that fall on step boundaries, so memory is O(`n_save`), not O(steps), and no
    interpolation error enters. Wall time is measured on a second, compiled, call.

    **Arguments:**

    - `scene`: a [`diffrax_vi.scenes.Scene`][].
    - `solvers`: names from `diffrax_vi.study.SOLVERS`, or solver instances.
    - `periods`: horizon, in the scene's periods.
    - `steps_per_period`: fixed steps per period, the same for every solver.
    - `n_save`: how many times to record the invariants at.
    - `dtype`: the floating dtype of the state and the times.
    - `progress`: show diffrax's tqdm progress meter (the timed run then includes its
        overhead).

    **Returns:**

    A [`diffrax_vi.study.DriftStudy`][].
    """
    n_steps = int(round(periods * steps_per_period))
    if n_save < 1 or n_steps % n_save != 0:
        raise ValueError(
            f"n_save={n_save} must divide the number of steps {n_steps} so that the "
            "invariants are saved on step boundaries."
        )
    t1 = jnp.asarray(scene.period * periods, dtype=dtype)
    t0 = jnp.zeros((), dtype=dtype)
    ts = jnp.linspace(t0, t1, n_save + 1, dtype=dtype)
    y0 = jax.tree.map(lambda x: jnp.asarray(x, dtype=dtype), scene.y0)
    conserved = scene.conserved()

    def invariants(t, y, args):
        return {name: fn(t, y, args) for name, fn in conserved.items()}

    runs = []
    for spec in solvers:
        solver = make_solver(spec) if isinstance(spec, str) else spec
        name = spec if isinstance(spec, str) else type(spec).__name__
        terms = _terms(scene, solver)

        @eqx.filter_jit
        def solve(y0, meter):
            return dfx.diffeqsolve(
                terms,
                solver,
                t0,
                t1,
                (t1 - t0) / n_steps,
                y0,
                saveat=dfx.SaveAt(ts=ts, fn=invariants),
                max_steps=n_steps + 1,
                throw=False,
                progress_meter=meter,
            )

        meter = dfx.TqdmProgressMeter() if progress else dfx.NoProgressMeter()
        jax.block_until_ready(solve(y0, meter))
        start = time.perf_counter()
        sol = jax.block_until_ready(solve(y0, meter))
        wall_time = time.perf_counter() - start
        # In the scene's order (energy first), not the sorted order of a JAX dict.
        values = {k: np.asarray(sol.ys[k], dtype=np.float64) for k in conserved}
        runs.append(
            DriftRun(
                solver=name,
                steps=int(sol.stats["num_steps"]),
                wall_time=wall_time,
                result="successful"
                if sol.result == dfx.RESULTS.successful
                else str(sol.result),
                ts=np.asarray(ts, dtype=np.float64),
                errors={k: np.abs(v - v[0]) for k, v in values.items()},
            )
        )
    return DriftStudy(
        scene=scene.name,
        periods=periods,
        steps_per_period=steps_per_period,
        dtype=jnp.dtype(dtype).name,
        runs=runs,
    )
