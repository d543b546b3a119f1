"""The `diffrax-vi` command's entry point: it parses the command line with the
standard library alone, so that `--help` and a bad option answer before JAX is
imported, and then runs the command from `diffrax_vi.cli`. Its own top-level module,
as importing anything inside `diffrax_vi` imports JAX first. The Python API is
`diffrax_vi.cli.main`."""

import argparse
import atexit
import gc
import math
import os
import pathlib
import sys


# The methods each study compares on a scene that declares none of its own
# (`Scene.solvers`).
DEFAULT_SOLVERS = {
    "drift": "MidpointVI,StormerVerlet,KahanLi8,Tsit5,Dopri8,Dopri8+PID",
    "work-precision": "StormerVerlet,MidpointVI,KahanLi6,Tsit5,Tsit5+PID,Dopri8+PID",
}
# `diffrax_vi.scenes.SCENES`, named here so that `--help` lists them and a wrong
# name is refused without importing JAX (a test keeps the two the same).
SCENE_NAMES = (
    "kepler",
    "falling_particle",
    "oscillator",
    "duffing",
    "pendulum",
    "double_pendulum",
    "henon_heiles",
    "fpu",
    "outer_solar_system",
    "pythagorean_three_body",
    "learned",
    "bead_wire",
    "forced_duffing",
    "cartesian_pendulum",
    "four_bar",
    "free_rigid_body",
    "heavy_top",
    "pendulum_3d",
    "satellite",
    "rigid_double_pendulum",
    "rigid_chain",
)
DEFAULT_OUT = "diffrax-vi-results"
DTYPES = ("float64", "float32")


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


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    # An option whose default depends on the scene or the steps says so itself.
    def _get_help_string(self, action):
        if action.default is None:
            return action.help
        return super()._get_help_string(action)


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
    parser.add_argument(
        "--no-cache",
        action="store_true",
        help="do not keep traced and compiled programs in $XDG_CACHE_HOME/diffrax-vi "
        "(by default ~/.cache/diffrax-vi; JAX's persistent compilation cache in "
        "jax/, the studies' compiled solves in programs/), which let a repeated "
        "study skip tracing and compilation",
    )


def _common(parser: argparse.ArgumentParser, solvers: str) -> None:
    parser.add_argument(
        "--scene",
        default="kepler",
        choices=SCENE_NAMES,
        metavar="SCENE",
        help="scene to integrate: " + ", ".join(SCENE_NAMES),
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a parameter of the scene (repeatable), e.g. eccentricity=0.9 for kepler",
    )
    parser.add_argument(
        "--solvers",
        default=None,
        help="comma-separated solver names (default: the methods the scene "
        f"declares, else {solvers}); the suffix +PID steps an adaptive "
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
    formatter = _Formatter

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
    _common(drift, DEFAULT_SOLVERS["drift"])
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
        default=None,
        help="number of intervals to record the largest errors over; it must "
        "divide the number of steps (default: the largest divisor up to 1000)",
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
    _common(wp, DEFAULT_SOLVERS["work-precision"])
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
    seed.set_defaults(dtype="float64")
    return parser


def refused_out(args: argparse.Namespace) -> str | None:
    """Why the command refuses the folder `--out` names, or `None`: a file, or a
    folder that holds files, unless `--force`. Read before JAX is imported, so that
    the refusal answers as fast as argparse's own."""
    if args.out is None:
        return None
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file, not a folder."
    if out.is_dir() and not args.force and any(out.iterdir()):
        return (
            f"--out {out} is not empty: pass --force to replace the results there, "
            "or name another folder (without --out, each run writes a new folder in "
            f"{DEFAULT_OUT}/)."
        )
    return None


def main(argv: list[str] | None = None, *, own_process: bool = False) -> int:
    """Run the command line on `argv` (default: `sys.argv[1:]`); returns the exit
    code (see `diffrax_vi.cli.main`). `own_process`: see `command`."""
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, or a bad option (already printed)
        return int(e.code or 0)
    if args.command is None:
        parser.print_help()
        return 2
    refused = refused_out(args)
    if refused is not None:
        print(f"{parser.prog} {args.command}: error: {refused}", file=sys.stderr)
        return 2
    from diffrax_vi.cli import run

    if own_process:
        # Everything imported so far (JAX, diffrax, this package: some 2e5
        # objects, none of them garbage) lives as long as the process. Frozen,
        # Python's full collections no longer walk it, and JAX's tracing, which
        # allocates enough to set off several, runs that much faster: the main job
        # takes 0.5 s less (`benchmarks/startup.py`).
        gc.freeze()
    return run(args)


def command() -> int:
    """The `diffrax-vi` console script (and `python -m diffrax_vi`): `main` in a
    process of its own, which may keep the heap it imported out of the garbage
    collector's way and end without tearing it down (a caller of
    `diffrax_vi.cli.main` keeps its process as it is)."""
    code = main(own_process=True)
    exit_now(code)
    return code


def exit_now(code: int) -> None:
    """End this process with `code` once its output is flushed and its exit
    handlers (`atexit`) have run, without Python's teardown of every module and
    object, which takes 0.1-0.2 s after a study (`benchmarks/startup.py`). Where
    the output cannot be flushed (a closed pipe) it returns, and Python exits as
    usual, reporting that."""
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        return
    atexit._run_exitfuncs()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


if __name__ == "__main__":
    sys.exit(command())
