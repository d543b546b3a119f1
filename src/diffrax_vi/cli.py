"""The `diffrax-vi` command line: `diffrax-vi drift`, `diffrax-vi work-precision`,
`diffrax-vi seed`; also `python -m diffrax_vi ...`. `main(argv)` runs it from Python
and returns the exit code."""

import argparse
import math
import pathlib
import sys

import jax


DEFAULT_SOLVERS = "MidpointVI,StormerVerlet,KahanLi8,Tsit5,Dopri8,Dopri8+PID"
DEFAULT_OUT = "diffrax-vi-results"
DTYPES = ("float64", "float32")
# The files each command writes, removed from `--out` by `--force` before it writes.
OUTPUTS = {
    "drift": ("drift.csv", "drift.json", "drift_*.png"),
    "work-precision": ("work_precision.*",),
    "seed": ("chapter5.md", "figure_*.png"),
}


class UsageError(Exception):
    """A bad option: reported on one line with exit code 2, before any work."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        # One line, not argparse's usage block: `prog: error: message`.
        self.exit(2, f"{self.prog}: error: {message}\n")


def _number(kind, name: str, low: float, high: float = math.inf, strict=True):
    """An argparse type: a finite `kind` in (low, high) (or [low, high))."""

    def parse(text: str):
        try:
            x = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{name} must be {'an integer' if kind is int else 'a number'}, "
                f"got {text!r}"
            ) from None
        inside = (x > low if strict else x >= low) and x < high
        if not (math.isfinite(x) and inside):
            bound = f"> {low:g}" if strict else f">= {low:g}"
            above = "" if high == math.inf else f" and < {high:g}"
            raise argparse.ArgumentTypeError(
                f"{name} must be finite, {bound}{above}; got {text!r}"
            )
        return x

    return parse


def _list(item):
    def parse(text: str):
        values = [item(x.strip()) for x in text.split(",") if x.strip()]
        if not values:
            raise argparse.ArgumentTypeError(f"names no value: {text!r}")
        return values

    return parse


POSITIVE = _number(float, "a horizon", 0.0)
COUNT = _number(int, "a count", 0.0)
RTOL = _number(float, "a tolerance", 0.0, 1.0)
SPREAD = _number(float, "a spread", 0.0, strict=False)


def _parameter_value(text: str, value: str, default):
    """`value` read as the type of the parameter's default: an integer for a count or
    a seed (a float would make a shape), comma-separated numbers for a tuple (the
    moments of inertia), else a float."""
    parts = value.split(",")
    kind = int if isinstance(default, int) and not isinstance(default, bool) else float
    try:
        numbers = tuple(kind(x) for x in parts)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise UsageError(f"--param {text!r}: {value!r} is not {what}.") from None
    if not all(math.isfinite(x) for x in numbers):
        raise UsageError(f"--param {text!r}: the value must be finite.")
    if isinstance(default, tuple):
        if len(numbers) != len(default):
            raise UsageError(
                f"--param {text!r}: expected {len(default)} comma-separated numbers."
            )
        return numbers
    if len(numbers) != 1:
        raise UsageError(f"--param {text!r}: expected one number.")
    return numbers[0]


def _scene(name: str, params: list[str] | None = None):
    """The scene `name` made with `--param NAME=VALUE` keyword arguments."""
    import inspect

    from .scenes import SCENES

    if name not in SCENES:
        raise UsageError(f"unknown scene {name!r}. Choose from: {', '.join(SCENES)}.")
    make = SCENES[name]
    known = inspect.signature(make).parameters
    kwargs = {}
    for text in params or []:
        key, sep, value = text.partition("=")
        key = key.strip()
        if not sep or key not in known:
            takes = ", ".join(known) if known else "no parameters"
            raise UsageError(
                f"--param {text!r}: expected NAME=VALUE with NAME a parameter of "
                f"the scene {name!r} ({takes})."
            )
        kwargs[key] = _parameter_value(text, value, known[key].default)
    try:
        return make(**kwargs)
    except ValueError as e:
        raise UsageError(f"--param: {e}") from None


def _methods(solvers: str, rtol: float, scene):
    """The methods named, each checked to take the scene's Lagrangian."""
    from .study import as_method

    names = [s.strip() for s in solvers.split(",") if s.strip()]
    if not names:
        raise UsageError("--solvers names no solver.")
    try:
        methods = [as_method(name, rtol) for name in names]
        for method in methods:
            method.terms(scene)
    except ValueError as e:
        raise UsageError(str(e)) from None
    return methods


def _out(args: argparse.Namespace, scene: str) -> pathlib.Path:
    """The folder this run writes into, made and tested for writing before any
    work. By default a fresh `diffrax-vi-results/<command>-<scene>-<k>`; a folder
    named with `--out` must be empty, unless `--force` (which removes the files this
    command wrote there before, so that no stale figure is left beside new ones)."""
    if args.out is None:
        root = pathlib.Path(DEFAULT_OUT)
        k = 1
        while (root / f"{args.command}-{scene}-{k}").exists():
            k += 1
        out = root / f"{args.command}-{scene}-{k}"
    else:
        out = pathlib.Path(args.out)
        if out.exists() and not out.is_dir():
            raise UsageError(f"--out {out} is a file, not a folder.")
        if out.is_dir() and any(out.iterdir()):
            if not args.force:
                raise UsageError(
                    f"--out {out} is not empty: pass --force to replace the results "
                    "there, or name another folder (without --out, each run writes "
                    f"a new folder in {DEFAULT_OUT}/)."
                )
            for pattern in OUTPUTS[args.command]:
                for stale in out.glob(pattern):
                    stale.unlink()
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".diffrax-vi-write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise UsageError(f"cannot write into --out {out}: {e.strerror}.") from None
    return out


def _report(study, out: pathlib.Path, verdict: str | None = None) -> int:
    print(study.table())
    if verdict is not None:
        print(verdict)
    for path in study.write(out):
        print(f"wrote {path}")
    return 0


def _study(call, **kwargs):
    """Check or run a study: a setting it rejects before any work is a usage
    error."""
    try:
        return call(**kwargs)
    except ValueError as e:
        raise UsageError(str(e)) from None


def _drift(args: argparse.Namespace) -> int:
    from .study import check_drift, drift

    scene = _scene(args.scene, args.param)
    methods = _methods(args.solvers, args.rtol, scene)
    _study(
        check_drift,
        scene=scene,
        methods=methods,
        periods=args.periods,
        steps_per_period=args.steps_per_period,
        n_save=args.save,
        dtype=args.dtype,
        ensemble=args.ensemble,
    )
    out = _out(args, scene.name)
    members = f", ensemble of {args.ensemble}" if args.ensemble else ""
    print(
        f"{scene.name}: {args.periods:g} periods, {args.steps_per_period} steps per "
        f"period, {args.dtype}{members}; solvers: "
        + ", ".join(m.name for m in methods),
        flush=True,
    )
    study = _study(
        drift,
        scene=scene,
        solvers=methods,
        periods=args.periods,
        steps_per_period=args.steps_per_period,
        n_save=args.save,
        dtype=args.dtype,
        ensemble=args.ensemble,
        spread=args.spread,
        progress=args.progress,
    )
    return _report(study, out, study.verdict())


def _work_precision(args: argparse.Namespace) -> int:
    from .study import check_work_precision, work_precision

    scene = _scene(args.scene, args.param)
    methods = _methods(args.solvers, 1e-8, scene)
    _study(
        check_work_precision,
        periods=args.periods,
        steps_per_period=args.steps_per_period,
    )
    out = _out(args, scene.name)
    print(f"{scene.name}: {args.periods:g} periods, {args.dtype}", flush=True)
    study = _study(
        work_precision,
        scene=scene,
        solvers=methods,
        periods=args.periods,
        steps_per_period=args.steps_per_period,
        rtols=args.rtols,
        dtype=args.dtype,
    )
    return _report(study, out)


def _seed(args: argparse.Namespace) -> int:
    from .thesis import chapter5

    print(chapter5(_out(args, "chapter5")))
    return 0


def _output(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        default=None,
        help=f"folder for tables and figures (default: a new folder in {DEFAULT_OUT}/"
        " for each run); it must be empty unless --force",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace the results of this command already in --out",
    )


def _common(parser: argparse.ArgumentParser, solvers: str) -> None:
    parser.add_argument("--scene", default="kepler", help="scene to integrate")
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a parameter of the scene (repeatable), e.g. eccentricity=0.9 for kepler",
    )
    parser.add_argument(
        "--solvers",
        default=solvers,
        help="comma-separated solver names; the suffix +PID steps an adaptive "
        "Runge-Kutta solver with a PIDController (e.g. Tsit5+PID), +Adaptive a "
        "symmetric one with reversible steps on the scene's monitor (e.g. "
        "KahanLi8+Adaptive; --steps-per-period is then the mean)",
    )
    parser.add_argument("--dtype", choices=DTYPES, default="float64")
    _output(parser)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
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
    _common(drift, DEFAULT_SOLVERS)
    drift.add_argument(
        "--periods",
        type=POSITIVE,
        default=1000,
        help="horizon, periods (periods x steps-per-period must be a whole number)",
    )
    drift.add_argument(
        "--steps-per-period",
        type=COUNT,
        default=200,
        help="fixed steps per period (the mean for +Adaptive solvers)",
    )
    drift.add_argument(
        "--save",
        type=COUNT,
        default=1000,
        help="number of intervals to record the largest errors over",
    )
    drift.add_argument(
        "--rtol", type=RTOL, default=1e-8, help="tolerance of +PID solvers"
    )
    drift.add_argument(
        "--ensemble",
        type=COUNT,
        default=None,
        help="run this many nearby initial states at once (vmapped, sharded over "
        "devices) and report the worst",
    )
    drift.add_argument(
        "--spread", type=SPREAD, default=1e-3, help="relative spread of the ensemble"
    )
    drift.add_argument(
        "--progress", action="store_true", help="show a progress bar for each solve"
    )
    drift.set_defaults(run=_drift)

    wp = sub.add_parser(
        "work-precision",
        help="wall time against energy error and global error",
        description=(
            "Run each fixed-step or +Adaptive solver at several (mean) steps per "
            "period, and each +PID solver at several tolerances, over the same "
            "horizon; write "
            "work_precision.csv, .json and .png."
        ),
        formatter_class=formatter,
    )
    _common(wp, "StormerVerlet,MidpointVI,KahanLi6,Tsit5,Tsit5+PID,Dopri8+PID")
    wp.add_argument("--periods", type=POSITIVE, default=100, help="horizon, periods")
    wp.add_argument(
        "--steps-per-period",
        type=_list(COUNT),
        default=[50, 100, 200, 400],
        help="comma-separated grid",
    )
    wp.add_argument(
        "--rtols",
        type=_list(RTOL),
        default=[1e-6, 1e-8, 1e-10],
        help="comma-separated tolerances",
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
    _output(seed)
    seed.set_defaults(run=_seed, dtype="float64")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line on `argv` (default: `sys.argv[1:]`); returns the exit
    code: 0 on success, 2 for a bad option (one line on stderr, before any work).

    It runs at the XLA setting that `import diffrax_vi` chose
    ([`diffrax_vi.compile_small_loops_whole`][]), the same for every method."""
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, or a bad option (already printed)
        return int(e.code or 0)
    if args.command is None:
        parser.print_help()
        return 2
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    try:
        return args.run(args)
    except UsageError as e:
        print(f"diffrax-vi {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
