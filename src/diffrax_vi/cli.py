"""The `diffrax-vi` command line: `diffrax-vi drift`, `diffrax-vi work-precision`,
`diffrax-vi seed`; also `python -m diffrax_vi ...`. `main(argv)` runs it from Python
and returns the exit code."""

import argparse
import sys

import jax


DEFAULT_SOLVERS = "MidpointVI,StormerVerlet,Tsit5,Dopri8"
DTYPES = ("float64", "float32")


def _scene(name: str):
    from .scenes import SCENES

    if name not in SCENES:
        raise SystemExit(
            f"diffrax-vi: unknown scene {name!r}. Choose from: {', '.join(SCENES)}."
        )
    return SCENES[name]()


def _methods(solvers: str, rtol: float):
    from .study import as_method

    names = [s.strip() for s in solvers.split(",") if s.strip()]
    if not names:
        raise SystemExit("diffrax-vi: --solvers names no solver.")
    try:
        return [as_method(name, rtol) for name in names]
    except ValueError as e:
        raise SystemExit(f"diffrax-vi: {e}") from None


def _numbers(text: str, kind):
    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"diffrax-vi: expected comma-separated numbers, got {text!r}")


def _report(study, out: str) -> int:
    print(study.table())
    for path in study.write(out):
        print(f"wrote {path}")
    return 0


def _drift(args: argparse.Namespace) -> int:
    from .study import drift

    scene = _scene(args.scene)
    methods = _methods(args.solvers, args.rtol)
    members = f", ensemble of {args.ensemble}" if args.ensemble else ""
    print(
        f"{scene.name}: {args.periods:g} periods, {args.steps_per_period} steps per "
        f"period, {args.dtype}{members}; solvers: "
        + ", ".join(m.name for m in methods),
        flush=True,
    )
    try:
        study = drift(
            scene,
            methods,
            periods=args.periods,
            steps_per_period=args.steps_per_period,
            n_save=args.save,
            dtype=args.dtype,
            ensemble=args.ensemble,
            spread=args.spread,
            progress=args.progress,
        )
    except ValueError as e:
        raise SystemExit(f"diffrax-vi: {e}") from None
    return _report(study, args.out)


def _work_precision(args: argparse.Namespace) -> int:
    from .study import work_precision

    scene = _scene(args.scene)
    methods = _methods(args.solvers, 1e-8)
    print(f"{scene.name}: {args.periods:g} periods, {args.dtype}", flush=True)
    study = work_precision(
        scene,
        methods,
        periods=args.periods,
        steps_per_period=_numbers(args.steps_per_period, int),
        rtols=_numbers(args.rtols, float),
        dtype=args.dtype,
    )
    return _report(study, args.out)


def _seed(args: argparse.Namespace) -> int:
    from .thesis import chapter5

    print(chapter5(args.out))
    return 0


def _common(parser: argparse.ArgumentParser, solvers: str, out: str) -> None:
    parser.add_argument("--scene", default="kepler", help="scene to integrate")
    parser.add_argument(
        "--solvers",
        default=solvers,
        help="comma-separated solver names; the suffix +PID steps an adaptive "
        "solver with a PIDController (e.g. Tsit5+PID)",
    )
    parser.add_argument("--dtype", choices=DTYPES, default="float64")
    parser.add_argument("--out", default=out, help="folder for tables and figures")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffrax-vi",
        description="Variational integrators for diffrax: energy-drift studies.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    formatter = argparse.ArgumentDefaultsHelpFormatter

    drift = sub.add_parser(
        "drift",
        help="energy drift of several solvers at equal steps (the main job)",
        description=(
            "Integrate one scene with several solvers at the same fixed step and "
            "number of steps; print the largest error of each conserved quantity and "
            "the wall time, and write drift.csv, drift.json and PNG figures."
        ),
        formatter_class=formatter,
    )
    _common(drift, DEFAULT_SOLVERS, "diffrax-vi-results")
    drift.add_argument("--periods", type=float, default=1000, help="horizon, periods")
    drift.add_argument(
        "--steps-per-period", type=int, default=200, help="fixed steps per period"
    )
    drift.add_argument(
        "--save",
        type=int,
        default=1000,
        help="number of intervals to record the largest errors over",
    )
    drift.add_argument(
        "--rtol", type=float, default=1e-8, help="tolerance of +PID solvers"
    )
    drift.add_argument(
        "--ensemble",
        type=int,
        default=None,
        help="run this many nearby initial states at once (vmapped, sharded over "
        "devices) and report the worst",
    )
    drift.add_argument(
        "--spread", type=float, default=1e-3, help="relative spread of the ensemble"
    )
    drift.add_argument(
        "--progress", action="store_true", help="show a progress bar for each solve"
    )
    drift.set_defaults(run=_drift)

    wp = sub.add_parser(
        "work-precision",
        help="wall time against energy error and global error",
        description=(
            "Run each fixed-step solver at several steps per period, and each +PID "
            "solver at several tolerances, over the same horizon; write "
            "work_precision.csv, .json and .png."
        ),
        formatter_class=formatter,
    )
    _common(
        wp,
        "StormerVerlet,MidpointVI,KahanLi6,Tsit5,Tsit5+PID,Dopri8+PID",
        "diffrax-vi-results",
    )
    wp.add_argument("--periods", type=float, default=100, help="horizon, periods")
    wp.add_argument(
        "--steps-per-period", default="50,100,200,400", help="comma-separated grid"
    )
    wp.add_argument(
        "--rtols", default="1e-6,1e-8,1e-10", help="comma-separated tolerances"
    )
    wp.set_defaults(run=_work_precision)

    seed = sub.add_parser(
        "seed",
        help="reproduce the seed thesis's Chapter 5 tables and figures",
        description=(
            "Reproduce Tables 5.1/5.2, Figures 5.1-5.3 and 1.1/1.2 of Hirani (2000) "
            "beside the thesis's numbers; write chapter5.md and PNG figures."
        ),
        formatter_class=formatter,
    )
    seed.add_argument("--out", default="seed-results", help="folder for the results")
    seed.set_defaults(run=_seed, dtype="float64")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line on `argv` (default: `sys.argv[1:]`); returns the exit
    code."""
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
