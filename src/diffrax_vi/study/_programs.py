"""Compiled programs kept within a process, and between runs of the command line.

JAX's persistent compilation cache skips XLA on a repeated study, not the tracing
and lowering before it, which JAX repeats in every process to find the program's
key. A study run under `keep_programs` keeps each solve it compiles, XLA's
executable itself (`jax.experimental.serialize_executable`), in a file named by a
key of everything the program depends on, and a later run with the same key loads
the executable from the file instead of tracing, lowering and compiling: the timed
program is the one the first run compiled.

The key is the code (the size and modification time of every source file of this
package and of diffrax, equinox, optimistix, lineax and JAX, and jaxlib's version),
the caller's `context` (the command line passes its options, from which it builds
the scene and the methods), the program's name, its arguments' structure, shapes and
dtypes, JAX's settings (64-bit floats, `JAX_*` variables, the devices), and what XLA
compiles for (`XLA_FLAGS`, the backend's version, the processor and its features). A
program that holds a host callback cannot be kept (its executable calls back into
this process); it is traced every time, as without this cache. The studies compile
their solves without the callbacks that check a start, and check it apart
(`compiled`'s `check`), before a program is kept.

The folder is bounded: after each program it keeps, the files least recently written
or read go until the folder holds at most `max_bytes` (`keep_programs`, by default
512 MiB), so that programs whose key no run asks for again (after an upgrade, an
edited source file, other options) do not pile up.

Within one process, `compiled` also keeps the programs it compiles last, keyed by the
values of what they are closed over (`_Memo`): a study run again (a notebook's cell
rerun on the same scene, with new but equal objects) reuses them, as `jax.jit` reuses
a compiled function called again with the same static arguments."""

import collections
import contextlib
import dataclasses
import functools
import hashlib
import importlib.metadata
import importlib.util
import math
import os
import pathlib
import pickle
import platform
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator

import jax
import numpy as np
from jax.experimental import serialize_executable
from jaxtyping import PyTree

from .._misc import holds
from .._private_api import initialize_lapack, persistent_cache_min_time


# Whose source files the traced programs depend on.
_PACKAGES = (
    "diffrax_vi",
    "diffrax",
    "equinox",
    "optimistix",
    "lineax",
    "jax",
    "jaxlib",
)


@functools.cache
def _code() -> str:
    """What identifies the code that traces a program: the size and modification
    time of every Python file of `_PACKAGES` (an edited or reinstalled file changes
    it), and the versions of jaxlib and of Python."""
    digest = hashlib.sha256()
    for name in _PACKAGES:
        root = pathlib.Path(importlib.util.find_spec(name).origin).parent
        for directory, dirs, files in os.walk(root):
            dirs.sort()
            for file in sorted(f for f in files if f.endswith(".py")):
                stat = os.stat(os.path.join(directory, file))
                entry = f"{directory}/{file}:{stat.st_size}:{stat.st_mtime_ns};"
                digest.update(entry.encode())
    digest.update(importlib.metadata.version("jaxlib").encode())
    digest.update(repr(tuple(sys.version_info)).encode())
    return digest.hexdigest()


@functools.cache
def _machine() -> str:
    """What XLA compiles for: `XLA_FLAGS`, the backend's version, the processor and,
    on Linux, its model and features (an executable compiled for one processor's
    instructions may not run on another's, in a cache folder shared between
    machines)."""
    backend = jax.devices()[0].client
    parts = [os.environ.get("XLA_FLAGS", ""), backend.platform_version]
    parts += [platform.machine(), platform.processor()]
    try:
        with open("/proc/cpuinfo") as info:
            lines = [line for line in info if line.startswith(("model name", "flags"))]
        parts += sorted(set(lines))
    except OSError:
        pass
    return "\n".join(parts)


# The size of the folder of kept programs, by default.
MAX_BYTES = 512 * 2**20

# A file being written (`_write`) that is older than this was left by a run that
# stopped before it finished.
_ABANDONED_SECONDS = 3600.0


@dataclasses.dataclass(frozen=True)
class _Programs:
    """The folder of kept programs, the context of their keys and the folder's
    largest size."""

    directory: pathlib.Path
    context: str
    max_bytes: int = MAX_BYTES

    def path(self, name: str, args: tuple) -> pathlib.Path:
        shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), args)
        devices = jax.devices()
        key = "\n".join(
            [
                _code(),
                _machine(),
                self.context,
                name,
                str(jax.tree.structure(args)),
                str(jax.tree.leaves(shapes)),
                str(jax.config.jax_enable_x64),
                # JAX's settings from the environment, some of which change a trace.
                str(sorted((k, v) for k, v in os.environ.items() if k[:4] == "JAX_")),
                f"{devices[0].platform} x{len(devices)}",
            ]
        )
        return self.directory / f"{hashlib.sha256(key.encode()).hexdigest()}.xla"

    def sweep(self) -> None:
        """Delete the kept programs least recently written or read (`_read` marks
        a file it loads) until the folder holds at most `max_bytes`, and the files
        that runs stopped before they finished writing. Every other file written
        here counts as a kept program (this version's `.xla` files, an earlier
        one's `.jaxexport`). Another run may delete the same files at once: a file
        gone already is skipped, and a program deleted as it is read is compiled
        again."""
        kept, now = [], time.time()
        try:
            entries = list(os.scandir(self.directory))
        except OSError:
            return
        for entry in entries:
            try:
                if not entry.is_file(follow_symlinks=False):
                    continue
                stat = entry.stat(follow_symlinks=False)
                if entry.name.endswith(".part"):
                    if now - stat.st_mtime > _ABANDONED_SECONDS:
                        os.unlink(entry.path)
                    continue
            except OSError:
                continue
            kept.append((stat.st_mtime, stat.st_size, entry.path))
        size = sum(bytes_ for _, bytes_, _ in kept)
        for _, bytes_, path in sorted(kept):
            if size <= self.max_bytes:
                break
            try:
                os.unlink(path)
            except OSError:
                continue
            size -= bytes_


# XLA's options for a kept program: one at its default value (no IR in the
# executable), which only JAX's cache key sees.
_KEPT_OPTIONS = {"xla_embed_ir_in_executable": False}

# Set by `keep_programs` (as JAX's own configuration is, for the process): the
# studies trace their solves on worker threads.
_kept: _Programs | None = None


def _read(path: pathlib.Path) -> Callable | None:
    """The compiled program kept in `path`, loaded; `None` if there is none."""
    try:
        data, in_tree, out_tree = pickle.loads(path.read_bytes())
        if b"lapack_" in data:
            # Its LAPACK kernels (an eigensolver at a solve's start) run SciPy's
            # LAPACK once it is set up, which lowering one does: unset in a process
            # that lowered none, they would call a null pointer.
            initialize_lapack()
        program = serialize_executable.deserialize_and_load(data, in_tree, out_tree)
    except Exception:
        # None kept yet; or a file cut short, or written by another version of JAX,
        # for which pickle, JAX and XLA raise several kinds of error: compiled
        # again and replaced.
        return None
    try:
        os.utime(path)  # Used now: the last that `_Programs.sweep` deletes.
    except OSError:
        pass  # A folder the user may read but not write.
    return program


def _write(path: pathlib.Path, data: bytes) -> None:
    """Write `data` so that no reader sees part of it (another run may read the
    same key at once)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".part")
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


class _Memo:
    """The programs `compiled` made last in this process (at most `size`), keyed by
    everything a trace depends on: the program's name and function, the value of
    every array and scalar it is closed over (a digest of its bytes, dtype, shape
    and weak type), every other leaf by its own equality and hash (a function's
    are its identity, as `jax.jit` keys its own cache), the tree's structure (with
    its static fields), its arguments' structure, shapes and dtypes, JAX's
    configuration and the kept programs' folder. Closures whose leaves cannot be
    keyed (an unhashable leaf) are compiled every time."""

    def __init__(self, size: int):
        self.size = size
        self.programs: collections.OrderedDict = collections.OrderedDict()
        self.lock = threading.Lock()  # The studies compile on worker threads.

    @staticmethod
    def key(name: str, fn: Callable, constants: PyTree, args: tuple, vmapped: bool):
        leaves, structure = jax.tree.flatten(constants)
        values = []
        for leaf in leaves:
            if isinstance(leaf, (jax.Array, np.ndarray, np.generic)):
                value = np.asarray(leaf)
                digest = hashlib.sha256(value.tobytes()).hexdigest()
                weak = getattr(leaf, "weak_type", False)
                values.append((value.dtype.str, value.shape, weak, digest))
            elif isinstance(leaf, (bool, int, float, complex)):
                values.append((type(leaf), leaf))  # 1 == 1.0 == True.
            else:
                values.append(leaf)
        shapes = tuple(
            (x.dtype, x.shape, getattr(x, "sharding", None))
            for x in jax.tree.leaves(args)
        )
        config = tuple(sorted(jax.config.values.items()))
        key = (name, fn, vmapped, structure, tuple(values))
        key += (jax.tree.structure(args), shapes, config, _kept)
        try:
            hash(key)
        except TypeError:
            return None
        return key

    def clear(self) -> None:
        with self.lock:
            self.programs.clear()

    def get(self, key) -> Callable | None:
        if key is None:
            return None
        with self.lock:
            program = self.programs.get(key)
            if program is not None:
                self.programs.move_to_end(key)
            return program

    def get_or_make(self, key, make: Callable[[], Callable]) -> tuple[Callable, bool]:
        """The program under `key`, or `make()` kept under it; and whether it was
        made now."""
        program = self.get(key)
        if program is not None:
            return program, False
        program = make()
        self.put(key, program)
        return program, True

    def put(self, key, program: Callable) -> None:
        if key is None:
            return
        with self.lock:
            self.programs[key] = program
            while len(self.programs) > self.size:
                self.programs.popitem(last=False)


# A drift study of six methods compiles twelve programs.
_memo = _Memo(size=48)


def compiled(
    name: str,
    fn: Callable,
    constants: PyTree,
    *args: PyTree,
    vmapped: bool = False,
    check: Callable[..., None] | None = None,
) -> Callable:
    """`fn(constants, *args)` compiled for `args`, the arrays of `constants`
    constants of the program (as a closure's are), and vmapped over `args` if
    `vmapped`. The same program compiled before in this process for equal
    `constants` and arguments of the same shapes is reused (`_Memo`). Under
    `keep_programs`, the compiled program is loaded from its file where a run with
    the same key kept it, and kept there otherwise. `fn` takes and returns arrays
    in tuples, lists and dicts (a kept program's structures are pickled); `name`
    tells apart the programs of one context.

    `check(*args)`, if given, raises where the program must not run on `args` (a
    check the program leaves out). It runs before the program is kept or reused,
    except where the program is read from its file or reused under
    `keep_programs`: its context determines the arguments' values, and a program is
    kept only once they passed the check."""
    key = _memo.key(name, fn, constants, args, vmapped)
    program, made = _memo.get_or_make(
        key, lambda: _compile(name, fn, constants, args, vmapped, check)
    )
    if not made and check is not None and _kept is None:
        check(*args)
    return program


def memoised(name: str, make: Callable, constants: PyTree, *args: PyTree) -> Callable:
    """`make(constants, *args)`, a function of arguments like `args` (a compiled
    program), made once in this process for equal `constants` and arguments of the
    same shapes (`_Memo`), as `compiled` reuses its programs; never kept between
    runs."""
    key = _memo.key(name, make, constants, args, False)
    return _memo.get_or_make(key, lambda: make(constants, *args))[0]


def _compile(
    name: str,
    fn: Callable,
    constants: PyTree,
    args: tuple,
    vmapped: bool,
    check: Callable[..., None] | None,
) -> Callable:
    closure = functools.partial(fn, constants)
    jitted = jax.jit(jax.vmap(closure) if vmapped else closure)
    path = None if _kept is None else _kept.path(name, args)
    program = None if path is None else _read(path)
    if program is not None:
        return program
    if check is not None:
        check(*args)
    if path is None:
        return jitted.lower(*args).compile()
    traced = jitted.trace(*args)
    if holds_callback(traced.jaxpr.jaxpr):
        return traced.lower().compile()
    # Compiled by XLA, never loaded from JAX's persistent cache: an executable
    # loaded from it, serialised again, is kept without some of its kernels (XLA's
    # "Function ... not found" when it runs). A kept program is not written to that
    # cache, and an option at its default value gives its compilation a key of its
    # own there, apart from the same program compiled elsewhere.
    with persistent_cache_min_time(math.inf):
        program = traced.lower().compile(_KEPT_OPTIONS)
    try:
        data = pickle.dumps(serialize_executable.serialize(program))
    except (ValueError, NotImplementedError, TypeError, pickle.PicklingError):
        # A backend that cannot serialise its executables, or a program holding
        # what JAX does not serialise (constants passed as arguments).
        return program
    try:
        _write(path, data)
        _kept.sweep()
    except OSError as e:
        warnings.warn(
            f"diffrax-vi cannot keep the solves it compiles in {path.parent} "
            f"({e.strerror}): a repeated study compiles them again. Make the "
            "folder writable, set XDG_CACHE_HOME to one that is, or pass "
            "--no-cache.",
            RuntimeWarning,
            stacklevel=2,
        )
    return program


def holds_callback(jaxpr) -> bool:
    """Whether `jaxpr` (or one nested in it) calls back into Python: its executable
    calls into this process, and cannot be loaded in another."""
    return holds(jaxpr, lambda eqn: "callback" in eqn.primitive.name)


@contextlib.contextmanager
def keep_programs(
    directory: str | os.PathLike, context: str, max_bytes: int = MAX_BYTES
) -> Iterator[None]:
    """Within it, the studies' compiled solves are kept in and loaded from
    `directory` (see the module's docstring), keyed by the code, the machine,
    `context` and each program's name and arguments. `context` must determine
    everything the studies build (the command line's options). After each program
    it keeps, the folder is cut to `max_bytes`, the least recently used first
    (`_Programs.sweep`)."""
    global _kept
    # The key's code and machine, read once here, on the caller's thread: on the
    # studies' worker threads, beside the figures' import of matplotlib, each of
    # the thousand `stat` calls of `_code` waited for Python's lock.
    _code(), _machine()
    before, _kept = _kept, _Programs(pathlib.Path(directory), context, max_bytes)
    try:
        yield
    finally:
        _kept = before
