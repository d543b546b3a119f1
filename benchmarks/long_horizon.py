"""Long horizons: 10^7 steps on Kepler (e = 0.6, 200 steps per orbit, 50 000 orbits)
in float64, streaming the energy and angular momentum through the drift study.
Prints, per solver, the largest energy error over the first and the last tenth of the
run (bounded: equal; drifting: the last is larger) and the wall time.

Run: `python benchmarks/long_horizon.py [--steps 10000000] [--xla-default]` (a few
minutes on one core).
"""

import argparse

import diffrax
import jax


jax.config.update("jax_enable_x64", True)
from diffrax_vi.scenes import kepler  # noqa: E402
from diffrax_vi.study import drift  # noqa: E402
from step_cost import add_xla_option, apply_xla_option  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10_000_000)
    parser.add_argument("--solvers", default="StormerVerlet,MidpointVI,KahanLi8,Tsit5")
    add_xla_option(parser)
    args = parser.parse_args()
    setting = apply_xla_option(args)
    print(f"jax {jax.__version__}, diffrax {diffrax.__version__}, {setting}")
    periods = args.steps // 200
    study = drift(
        kepler(),
        args.solvers.split(","),
        periods=periods,
        steps_per_period=200,
        n_save=1000,
    )
    print(f"Kepler e=0.6, {args.steps:.0e} steps ({periods} orbits), float64")
    print(
        "| solver | steps | wall time (s) | energy error, first tenth | last tenth |"
        " angular momentum error |"
    )
    print("|---|---|---|---|---|---|")
    for run in study.runs:
        err = run.errors["energy"][1:]
        k = len(err) // 10
        print(
            f"| {run.solver} | {run.steps} | {run.wall_time:.1f} | {err[:k].max():.3e} "
            f"| {err[-k:].max():.3e} | {run.max_error('angular_momentum'):.1e} |"
        )


if __name__ == "__main__":
    main()
