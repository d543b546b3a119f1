"""How XLA compiles the time-stepping loop on CPU, which decides the speed of small
systems.

XLA's CPU compiler (JAX >= 0.7) runs a `while` loop either as one compiled function
or as a sequence of separately dispatched kernels, one per fused operation. It takes
the first only for a loop whose body accesses fewer than
`xla_cpu_small_while_loop_byte_threshold` bytes, 1 kB by default. The loop of a
`diffeqsolve` on a few degrees of freedom is usually just above that: its solver
state, a save buffer, compensated summation or a Newton fallback take it over, and
each step then pays a dispatch for each of tens of kernels, which on a small system
costs several times the step's arithmetic (`benchmarks/step_cost.py` and
`benchmarks/study_cost.py` measure both settings).

The threshold is read once, when JAX starts its CPU backend, from the environment
variable `XLA_FLAGS`; it cannot be set per compilation. So `import diffrax_vi` raises
it (`raise_on_import`), unless the user opted out or set it, or JAX already started.
"""

import os
import re
import warnings

from ._private_api import backends_are_initialized


# Bytes a loop body may access and still be compiled as one function. 4 MiB covers
# the Newton and Krylov loops of the implicit solvers up to about a thousand degrees
# of freedom (64 KiB stopped at about 60), and leaves the loops of 4096-mass chains,
# whose kernels are large enough to pay for their dispatch, as they were (a far
# larger threshold made them slower); `benchmarks/scaling.py` measures both.
SMALL_LOOP_BYTES = 1 << 22

# XLA's own threshold, bytes.
XLA_DEFAULT_BYTES = 1024

# XLA on CPU hands a floating-point reduction of this many elements or more to
# YNNPACK as a custom fusion, which breaks the loop around it into kernels
# (`diagnostics.loop_breakers`; `benchmarks/ynn_reductions.py`).
YNN_REDUCTION_MIN = 4096

# Set (to anything but "" or "0") before `import diffrax_vi` to keep XLA's default.
OPT_OUT = "DIFFRAX_VI_XLA_DEFAULT"

_OPTION = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options="

# The option this package put into `XLA_FLAGS` (`name=value`), or None: it changes
# only that entry, never the user's flags, whenever they were set.
_ours: str | None = None


def small_loop_flag(threshold_bytes: int) -> str:
    """The `XLA_FLAGS` entry that sets the threshold."""
    return f"{_EXTRA}{_OPTION}={threshold_bytes}"


def _with_entry(flags: str, entry: str) -> str:
    # XLA takes one set of backend options: join an existing one rather than add a
    # second flag, which would replace it.
    match = re.search(rf"{_EXTRA}(\S+)", flags)
    if match is None:
        return f"{flags} {_EXTRA}{entry}".strip()
    return flags[: match.end()] + "," + entry + flags[match.end() :]


def _without_ours(flags: str) -> str:
    """`flags` with this package's entry taken out of the backend options (and the
    flag itself if that entry was its only option); everything else as it is."""
    match = re.search(rf"{_EXTRA}(\S+)", flags)
    if _ours is None or match is None:
        return flags
    options = match.group(1).split(",")
    if _ours not in options:
        return flags
    options.remove(_ours)
    kept = f"{_EXTRA}{','.join(options)}" if options else ""
    return " ".join((flags[: match.start()] + kept + flags[match.end() :]).split())


def _raised_by_user(flags: str) -> bool:
    return re.search(rf"\b{_OPTION}=", _without_ours(flags)) is not None


def small_loops_compiled_whole() -> bool:
    """Whether the CPU threshold in `XLA_FLAGS` (this package's or the user's) is
    above XLA's default, so that loops of more than a kilobyte's worth of state are
    compiled as one function."""
    match = re.search(rf"\b{_OPTION}=(\d+)", os.environ.get("XLA_FLAGS", ""))
    return match is not None and int(match.group(1)) > XLA_DEFAULT_BYTES


def _too_late(what: str, fix: str) -> RuntimeError:
    return RuntimeError(
        f"{what} must be called before JAX starts its backend (before the first "
        "array is created or computation run): XLA reads XLA_FLAGS only then. Call "
        f"it right after the imports, or {fix} before starting Python."
    )


def compile_small_loops_whole(threshold_bytes: int = SMALL_LOOP_BYTES) -> bool:
    """Let XLA compile every CPU loop whose body accesses fewer than
    `threshold_bytes` bytes as one function: faster steps on systems of a few
    degrees of freedom, and faster implicit steps on 64 to 1024 degrees of freedom,
    whose Newton and Krylov loops cross XLA's threshold (the ratios are on the
    [Benchmarks](../benchmarks.md) page). No effect on GPUs.

    `import diffrax_vi` already does this with the default `threshold_bytes`
    (see [`diffrax_vi.keep_xla_default`][] to undo it); call it to choose another
    threshold, before JAX runs anything (the first array created or computation run
    starts the backend, which reads the setting once).

    Returns `False` and changes nothing if the user's own `XLA_FLAGS` sets the
    threshold (their choice stands); `True` once set. It changes only this
    package's own entry in `XLA_FLAGS`: flags the user set, before or after
    `import diffrax_vi`, stay.

    **Raises:** `RuntimeError` if JAX's backend has already started, as the setting
    would then be silently ignored.
    """
    global _ours
    if (
        isinstance(threshold_bytes, bool)
        or not isinstance(threshold_bytes, int)
        or threshold_bytes < 0
    ):
        raise ValueError(
            f"threshold_bytes must be a non-negative integer; got {threshold_bytes!r}."
        )
    flags = os.environ.get("XLA_FLAGS", "")
    if _raised_by_user(flags):
        return False
    if backends_are_initialized():
        flag = small_loop_flag(threshold_bytes)
        raise _too_late(
            "compile_small_loops_whole()",
            f"set the environment variable XLA_FLAGS={flag}",
        )
    flags = _without_ours(flags)
    _ours = f"{_OPTION}={threshold_bytes}"
    os.environ["XLA_FLAGS"] = _with_entry(flags, _ours)
    return True


def keep_xla_default() -> bool:
    """Undo the threshold that `import diffrax_vi` (or
    [`diffrax_vi.compile_small_loops_whole`][]) set: XLA's own default, 1 kB. Call
    it before JAX runs anything, or set the environment variable
    `DIFFRAX_VI_XLA_DEFAULT=1` before the import, which keeps the package from
    setting it at all.

    Returns `True` if it removed this package's setting, `False` if there was none
    (a threshold in the user's own `XLA_FLAGS` stays). Only this package's entry
    is removed: every other flag in `XLA_FLAGS`, set before or after the import,
    stays.

    **Raises:** `RuntimeError` if this package's setting is in force and JAX's
    backend has already started, so it can no longer be undone.
    """
    global _ours
    if _ours is None:
        return False
    if backends_are_initialized():
        raise _too_late(
            "keep_xla_default()", f"set the environment variable {OPT_OUT}=1"
        )
    os.environ["XLA_FLAGS"] = _without_ours(os.environ.get("XLA_FLAGS", ""))
    _ours = None
    return True


def raise_on_import() -> None:
    """What `import diffrax_vi` does: `compile_small_loops_whole()`, unless
    `DIFFRAX_VI_XLA_DEFAULT` is set or the user's `XLA_FLAGS` sets the threshold.
    If JAX's backend has already started, the setting cannot apply: it warns once,
    saying how to apply it, and changes nothing."""
    if os.environ.get(OPT_OUT, "") not in ("", "0"):
        return
    if _raised_by_user(os.environ.get("XLA_FLAGS", "")):
        return
    if backends_are_initialized():
        warnings.warn(
            "diffrax_vi was imported after JAX started its backend, so its faster "
            "setting for small CPU loops (XLA_FLAGS="
            f"{small_loop_flag(SMALL_LOOP_BYTES)}) cannot apply to this process. "
            "Import diffrax_vi before the first JAX array or computation, or set "
            f"that XLA_FLAGS before starting Python; set {OPT_OUT}=1 to keep XLA's "
            "default and silence this warning.",
            stacklevel=2,
        )
        return
    compile_small_loops_whole()
