"""The `diffrax-vi` command line: `diffrax-vi drift`, `diffrax-vi work-precision`,
`diffrax-vi seed`; also `python -m diffrax_vi ...`. `main(argv)` runs it from Python
and returns the exit code. The options are parsed in `_diffrax_vi_cli`, without
JAX; this module runs the commands."""

import argparse
import contextlib
import dataclasses
import math
import os
import pathlib
import sys

import jax
from _diffrax_vi_cli import DEFAULT_OUT, DEFAULT_SOLVERS, main as _main, refused_out

from ._private_api import reset_compilation_cache
from .study._programs import keep_programs


# The files each command writes, removed from `--out` by `--force` before it writes.
OUTPUTS = {
    "drift": ("drift.csv", "drift.json", "drift_*.png"),
    "work-precision": ("work_precision.*",),
    "seed": ("chapter5.md", "figure_*.png"),
}


class UsageError(Exception):
    """A bad option: reported on one line with exit code 2, before any work."""


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


def _methods(args: argparse.Namespace, rtol: float, scene):
    """The methods `--solvers` names (by default those the scene declares, else the
    command's own list), each checked to take the scene's Lagrangian."""
    from .study import as_method, SOLVERS

    solvers = args.solvers or ",".join(
        scene.solvers or DEFAULT_SOLVERS[args.command].split(",")
    )
    names = [s.strip() for s in solvers.split(",") if s.strip()]
    if not names:
        raise UsageError("--solvers names no solver.")
    try:
        methods = [as_method(name, rtol) for name in names]
        for method in methods:
            _first_step(method, scene)
    except ValueError as e:
        fits = [name for name in SOLVERS if _takes(as_method(name), scene)]
        raise UsageError(
            f"{e} Name others with --solvers; the scene {scene.name!r} takes "
            f"{', '.join(fits)} (and the suffixes +PID, +Adaptive where they apply)."
        ) from None
    return methods


def _first_step(method, scene) -> None:
    """Raise the `ValueError` of a method that cannot step the scene: its terms do
    not fit, or its first step refuses when traced (a method that needs a vector
    space, or a rigid body), or the study cannot measure what it records (a forced
    scene's energy balance under partitioned terms). Traced only, nothing
    compiled."""
    from .study._drift import check_methods

    check_methods(scene, [method])
    terms = method.terms(scene)
    jax.eval_shape(
        lambda y0: method.solver.init(terms, 0.0, scene.period, y0, scene.args),
        scene.y0,
    )


def _takes(method, scene) -> bool:
    try:
        _first_step(method, scene)
    except ValueError:
        return False
    return True


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
        refused = refused_out(args)
        if refused is not None:
            raise UsageError(refused)
        if out.is_dir():
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


def _report(
    args: argparse.Namespace, study, out: pathlib.Path, verdict: str | None = None
) -> int:
    """Print the study and write it into `out`, titled with the `--param` values."""
    study = dataclasses.replace(study, parameters=", ".join(args.param))
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


def checked(args: argparse.Namespace):
    """Every check a command makes before any work, on parsed options: the scene
    with its `--param` values and the methods (each one's first step traced), and
    the study's settings. Returns `(scene, methods)` (`(None, [])` for `seed`).

    **Raises:** `UsageError` naming the bad option."""
    from .study import check_drift, check_work_precision

    if args.command == "seed":
        return None, []
    scene = _scene(args.scene, args.param)
    if args.command == "drift":
        methods = _methods(args, args.rtol, scene)
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
    else:
        methods = _methods(args, 1e-8, scene)
        _study(
            check_work_precision,
            periods=args.periods,
            steps_per_period=args.steps_per_period,
        )
    return scene, methods


def _drift(args: argparse.Namespace) -> int:
    from .study import drift

    scene, methods = checked(args)
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
    return _report(args, study, out, study.verdict())


def _work_precision(args: argparse.Namespace) -> int:
    from .study import work_precision

    scene, methods = checked(args)
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
    return _report(args, study, out)


def _seed(args: argparse.Namespace) -> int:
    from .thesis import chapter5

    print(chapter5(_out(args, "chapter5")))
    return 0


RUNS = {"drift": _drift, "work-precision": _work_precision, "seed": _seed}


def cache_dir() -> pathlib.Path:
    """Where the command line keeps JAX's persistent compilation cache:
    `$XDG_CACHE_HOME/diffrax-vi/jax`, by default `~/.cache/diffrax-vi/jax`."""
    root = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(root) / "diffrax-vi" / "jax"


@contextlib.contextmanager
def compilation_cache(enabled: bool = True):
    """JAX's persistent compilation cache in [`diffrax_vi.cli.cache_dir`][] for
    the duration of one command, every compilation kept, so that a repeated study
    skips XLA's compilation; the process's settings are restored afterwards (the
    library never turns the cache on for a user's own code). A cache the user set
    up (`jax_compilation_cache_dir`) is used as it is."""
    if not enabled or jax.config.jax_compilation_cache_dir is not None:
        yield
        return
    min_time = jax.config.jax_persistent_cache_min_compile_time_secs
    reset_compilation_cache()
    jax.config.update("jax_compilation_cache_dir", str(cache_dir()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    try:
        yield
    finally:
        jax.config.update("jax_compilation_cache_dir", None)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_time)
        reset_compilation_cache()


def programs_dir() -> pathlib.Path:
    """Where the command line keeps the solves its studies compile, XLA's
    executables, so that a repeated study loads them instead of tracing and
    compiling them: `$XDG_CACHE_HOME/diffrax-vi/programs`, beside
    [`diffrax_vi.cli.cache_dir`][]. Each is keyed by the command's options, the
    shapes of its arguments, the source files of diffrax_vi and of the libraries it
    traces through, and what XLA compiles for (`XLA_FLAGS`, the processor);
    `--no-cache` neither reads nor writes them. The folder holds at most 512 MiB:
    each time a command keeps a solve, the programs it and earlier commands read or
    wrote least recently go first. Like JAX's own cache, the folder holds machine
    code that the command runs: keep it your own."""
    return cache_dir().parent / "programs"


def _kept_programs(args: argparse.Namespace):
    """The studies' compiled programs kept in `programs_dir`, keyed by the options
    that build the scene and the methods (not where the results go)."""
    if args.no_cache:
        return contextlib.nullcontext()
    options = {
        k: v for k, v in vars(args).items() if k not in ("out", "force", "no_cache")
    }
    return keep_programs(programs_dir(), repr(sorted(options.items())))


def run(args: argparse.Namespace) -> int:
    """Run a parsed command (from `_diffrax_vi_cli`); returns the exit code."""
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    try:
        with compilation_cache(not args.no_cache), _kept_programs(args):
            return RUNS[args.command](args)
    except UsageError as e:
        print(f"diffrax-vi {args.command}: error: {e}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    """Run the command line on `argv` (default: `sys.argv[1:]`); returns the exit
    code: 0 on success, 2 for a bad option (one line on stderr, before any work).

    It runs at the XLA setting that `import diffrax_vi` chose
    ([`diffrax_vi.compile_small_loops_whole`][]), the same for every method, and
    keeps its compiled programs in JAX's persistent compilation cache
    ([`diffrax_vi.cli.compilation_cache`][]) and its studies' compiled solves in
    [`diffrax_vi.cli.programs_dir`][] unless `--no-cache` is given."""
    return _main(argv)


if __name__ == "__main__":
    sys.exit(main())
