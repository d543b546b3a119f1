"""Work-precision: largest energy error and final global error against wall time, for
our methods and diffrax's Runge-Kutta solvers (fixed steps and PIDController), on
Kepler (e = 0.6) and Henon-Heiles, over 10^2 and 10^4 periods, through
`diffrax_vi.study.work_precision` (the `diffrax-vi work-precision` command).

Writes `work_precision.csv` (all runs) and one PNG per problem and horizon into
`--out` (default `benchmarks/results`). Kepler's global error is against its exact
solution (Kepler's equation); Henon-Heiles is chaotic at this energy, so its global
error is against Dopri8 at rtol = atol = 1e-13 and means little past 10^2 periods
(reported as NaN there).

Run: `python benchmarks/work_precision.py [--quick]` (minutes to tens of minutes).
"""

import argparse
import csv
import math
import pathlib

import jax


jax.config.update("jax_enable_x64", True)
from diffrax_vi import scenes  # noqa: E402
from diffrax_vi.study import work_precision  # noqa: E402
from diffrax_vi.study._plot import plot_work_precision  # noqa: E402


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
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in (scenes.kepler(), scenes.henon_heiles()):
        for periods in (int(h) for h in args.horizons.split(",")):
            studies = [
                work_precision(
                    scene,
                    [solver],
                    periods=periods,
                    steps_per_period=grid[1::2] if args.quick else grid,
                    n_save=1000,
                )
                for solver, grid in FIXED.items()
            ]
            studies.append(
                work_precision(
                    scene,
                    ADAPTIVE,
                    periods=periods,
                    rtols=RTOLS[1::2] if args.quick else RTOLS,
                    n_save=1000,
                )
            )
            study = studies[0]
            records = [r for s in studies for r in s.records]
            if scene.exact is None and periods > 100:
                records = [dict(r, global_error=math.nan) for r in records]
            for r in records:
                print(scene.name, periods, *r.values(), flush=True)
            rows += [dict(problem=scene.name, periods=periods, **r) for r in records]
            combined = type(study)(study.scene, periods, study.dtype, records)
            plot_work_precision(
                combined, out / f"work_precision_{scene.name}_{periods}.png"
            )
    with open(out / "work_precision.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
