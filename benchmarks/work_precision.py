"""Work-precision: largest energy error and final global error against wall time, for
our methods and diffrax's Runge-Kutta solvers (fixed steps and PIDController), on
Kepler (e = 0.6) and Henon-Heiles, over 10^2 and 10^4 periods, through
`diffrax_vi.study.work_precision` (the `diffrax-vi work-precision` command).

Writes `work_precision.csv` (all runs) and one PNG per problem and horizon into
`--out` (default `benchmarks/results`). Kepler's global error is against its exact
solution (Kepler's equation); Henon-Heiles is chaotic at this energy, so its global
error is against Dopri8 at rtol = atol = 1e-13 and means little past 10^2 periods
(reported as NaN there).

The script runs at the small-loop threshold `import diffrax_vi` sets (as the
`diffrax-vi` command does); `--xla-default` keeps XLA's default.

Run: `python benchmarks/work_precision.py [--quick] [--scenes kepler] [--horizons 100]`
(minutes to tens of minutes); `--replot` redraws the figures from the csv in `--out`
without running anything.
"""

import argparse
import csv
import pathlib

import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)
from diffrax_vi import scenes  # noqa: E402
from diffrax_vi.study import (  # noqa: E402
    reference_state,
    work_precision,
    WorkPrecision,
)
from diffrax_vi.study._plot import plot_work_precision  # noqa: E402
from step_cost import add_xla_option, apply_xla_option  # noqa: E402


FIXED = {
    "StormerVerlet": [100, 200, 400, 800, 1600],
    "MidpointVI": [100, 200, 400, 800],
    "Yoshida4": [25, 50, 100, 200, 400],
    "KahanLi6": [25, 50, 100, 200, 400],
    "KahanLi8": [25, 50, 100, 200, 400],
    "GaussVPRK2": [25, 50, 100, 200, 400],
    "GaussVPRK3": [25, 50, 100, 200],
    "Tsit5": [50, 100, 200, 400, 800],
    "Dopri5": [50, 100, 200, 400, 800],
    "Dopri8": [50, 100, 200, 400, 800],
}
ADAPTIVE = ["Tsit5+PID", "Dopri5+PID", "Dopri8+PID"]
RTOLS = [1e-6, 1e-8, 1e-10, 1e-12]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--quick", action="store_true", help="a small grid")
    parser.add_argument("--horizons", default="100,10000")
    parser.add_argument("--scenes", default="kepler,henon_heiles")
    parser.add_argument(
        "--replot", action="store_true", help="redraw the figures from the csv"
    )
    add_xla_option(parser)
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    if args.replot:
        with open(out / "work_precision.csv", newline="") as f:
            plot(list(csv.DictReader(f)), out)
        return
    print(apply_xla_option(args), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in (scenes.SCENES[name]() for name in args.scenes.split(",")):
        for periods in (int(h) for h in args.horizons.split(",")):
            if scene.exact is None and periods > 100:
                # Chaotic: a reference this far out means nothing (NaN below).
                reference = jax.tree.map(lambda x: x * jnp.nan, scene.y0)
            else:
                reference = reference_state(scene, scene.period * periods)
            records = []
            runs = [([solver], grid, RTOLS) for solver, grid in FIXED.items()]
            runs.append((ADAPTIVE, [100], RTOLS))  # PID starts at period / 100
            for solvers, grid, rtols in runs:
                study = work_precision(
                    scene,
                    solvers,
                    periods=periods,
                    steps_per_period=grid[1::2] if args.quick and grid[1:] else grid,
                    rtols=rtols[1::2] if args.quick else rtols,
                    reference=reference,
                )
                for r in study.records:
                    print(scene.name, periods, *r.values(), flush=True)
                records += study.records
            rows += [dict(problem=scene.name, periods=periods, **r) for r in records]
    with open(out / "work_precision.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, out)


def plot(rows: list[dict], out: pathlib.Path) -> None:
    """One figure per problem and horizon (a csv's rows are read back as strings)."""
    number = ("wall_time_s", "max_energy_error", "global_error")
    groups = {}
    for row in rows:
        record = {k: v for k, v in row.items() if k not in ("problem", "periods")}
        record.update({k: float(row[k]) for k in number})
        groups.setdefault((row["problem"], int(row["periods"])), []).append(record)
    for (name, periods), records in groups.items():
        study = WorkPrecision(name, periods, "float64", records)
        plot_work_precision(study, out / f"work_precision_{name}_{periods}.png")


if __name__ == "__main__":
    main()
