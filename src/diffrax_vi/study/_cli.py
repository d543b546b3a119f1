"""The `diffrax-vi` command line."""

import argparse
import sys

import jax


DEFAULT_SOLVERS = "MidpointVI,StormerVerlet,Tsit5,Dopri8"


def _drift(args: argparse.Namespace) -> int:
    import jax.numpy as jnp

    from ..scenes import SCENES
    from ._drift import drift, SOLVERS

    if args.scene not in SCENES:
        raise SystemExit(
            f"diffrax-vi: unknown scene {args.scene!r}. Choose from: "
            f"{', '.join(SCENES)}."
        )
    names = [s.strip() for s in args.solvers.split(",") if s.strip()]
    unknown = [n for n in names if n not in SOLVERS]
    if unknown or not names:
        raise SystemExit(
            f"diffrax-vi: unknown solver(s) {', '.join(unknown) or '(none given)'}. "
            f"Choose from: {', '.join(SOLVERS)}."
        )
    dtype = {"float64": jnp.float64, "float32": jnp.float32}[args.dtype]
    scene = SCENES[args.scene]()
    print(
        f"{scene.name}: {args.periods:g} periods, {args.steps_per_period} steps per "
        f"period, {args.dtype}; solvers: {', '.join(names)}",
        flush=True,
    )
    study = drift(
        scene,
        names,
        periods=args.periods,
        steps_per_period=args.steps_per_period,
        n_save=args.save,
        dtype=dtype,
        progress=args.progress,
    )
    print(study.table())
    for path in study.write(args.out):
        print(f"wrote {path}")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffrax-vi",
        description="Variational integrators for diffrax: energy-drift studies.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    drift = sub.add_parser(
        "drift",
        help="energy drift of several solvers at equal step counts (the main job)",
        description=(
            "Integrate one scene with several solvers at the same fixed step and "
            "number of steps; print the maximum error of each conserved quantity and "
            "the wall time, and write drift.csv, drift.json and PNG figures."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    drift.add_argument("--scene", default="kepler", help="scene to integrate")
    drift.add_argument(
        "--solvers", default=DEFAULT_SOLVERS, help="comma-separated solver names"
    )
    drift.add_argument("--periods", type=float, default=1000, help="horizon, periods")
    drift.add_argument(
        "--steps-per-period", type=int, default=200, help="fixed steps per period"
    )
    drift.add_argument(
        "--save", type=int, default=1000, help="number of times to record errors at"
    )
    drift.add_argument(
        "--dtype", choices=["float64", "float32"], default="float64", help="precision"
    )
    drift.add_argument(
        "--out", default="diffrax-vi-results", help="folder for tables and figures"
    )
    drift.add_argument(
        "--progress", action="store_true", help="show a progress bar for each solve"
    )
    drift.set_defaults(run=_drift)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
