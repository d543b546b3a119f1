"""Compiled programs kept within a process, and traced ones kept between runs of the
command line.

JAX's persistent compilation cache skips XLA on a repeated study, not the tracing
before it, which JAX repeats in every process: with XLA's work read back, tracing
was most of what a repeated main job spent readying its solves. A study run under
`keep_programs` exports each solve it traces (`jax.export`, StableHLO) into a file
named by a key of everything the program depends on, and a later run with the same
key reads the file back instead of tracing. The program it then compiles is the
exported one in both runs, so the compilation cache holds it too, and XLA makes of
it the program it makes of the trace.

The key is the code (the size and modification time of every source file of this
package and of diffrax, equinox, optimistix, lineax and JAX, and jaxlib's version),
the caller's `context` (the command line passes its options, from which it builds
the scene and the methods), the program's name, its arguments' structure, shapes and
dtypes, and JAX's settings (64-bit floats, `JAX_*` variables, the devices). A
program that holds a host callback cannot be exported (JAX serialises none); it is
traced every time, as without this cache.

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
import os
import pathlib
import sys
import tempfile
import threading
import warnings
from collections.abc import Callable, Iterator

import jax
import numpy as np
from jaxtyping import PyTree


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


@dataclasses.dataclass(frozen=True)
class _Programs:
    """The folder of exported programs and the context of their keys."""

    directory: pathlib.Path
    context: str

    def path(self, name: str, args: tuple) -> pathlib.Path:
        shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), args)
        devices = jax.devices()
        key = "\n".join(
            [
                _code(),
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
        return self.directory / f"{hashlib.sha256(key.encode()).hexdigest()}.jaxexport"


# Set by `keep_programs` (as JAX's own configuration is, for the process): the
# studies trace their solves on worker threads.
_kept: _Programs | None = None


def _read(path: pathlib.Path) -> "jax.export.Exported | None":
    try:
        return jax.export.deserialize(bytearray(path.read_bytes()))
    except Exception:
        # None kept yet; or a file cut short, or written by another version of JAX,
        # for which flatbuffers and JAX raise several kinds of error: traced again
        # and replaced.
        return None


def _write(path: pathlib.Path, data: bytearray) -> None:
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
    and weak type), the identity of every other leaf (a function, as `jax.jit`
    keys its own cache), the tree's structure (with its static fields), its
    arguments' structure, shapes and dtypes, JAX's configuration and the kept
    programs' folder. Closures whose leaves cannot be keyed (an unhashable leaf)
    are compiled every time."""

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
    name: str, fn: Callable, constants: PyTree, *args: PyTree, vmapped: bool = False
) -> Callable:
    """`fn(constants, *args)` compiled for `args`, the arrays of `constants`
    constants of the program (as a closure's are), and vmapped over `args` if
    `vmapped`. The same program compiled before in this process for equal
    `constants` and arguments of the same shapes is reused (`_Memo`). Under
    `keep_programs`, the program is read back from its file where a run with the
    same key exported it, and exported there otherwise. `fn` takes and returns
    arrays in tuples, lists and dicts (what `jax.export` serialises); `name` tells
    apart the programs of one context."""
    key = _memo.key(name, fn, constants, args, vmapped)
    program = _memo.get(key)
    if program is None:
        program = _compile(name, fn, constants, args, vmapped)
        _memo.put(key, program)
    return program


def _compile(
    name: str, fn: Callable, constants: PyTree, args: tuple, vmapped: bool
) -> Callable:
    closure = functools.partial(fn, constants)
    jitted = jax.jit(jax.vmap(closure) if vmapped else closure)
    if _kept is None:
        return jitted.lower(*args).compile()
    path = _kept.path(name, args)
    exported = _read(path)
    if exported is None:
        traced = jitted.trace(*args)
        if _holds_callback(traced.jaxpr.jaxpr):
            return traced.lower().compile()
        try:
            # Traced already: the export lowers the same trace.
            exported = jax.export.export(jitted)(*args)
            data = exported.serialize()
        except (NotImplementedError, ValueError):
            # A host callback not seen above, or a custom call without JAX's
            # guarantee of compatibility.
            return traced.lower().compile()
        try:
            _write(path, data)
        except OSError as e:
            warnings.warn(
                f"diffrax-vi cannot keep the solves it traces in {path.parent} "
                f"({e.strerror}): a repeated study traces them again. Make the "
                "folder writable, set XDG_CACHE_HOME to one that is, or pass "
                "--no-cache.",
                RuntimeWarning,
                stacklevel=2,
            )
    return jax.jit(exported.call).lower(*args).compile()


def _holds_callback(jaxpr) -> bool:
    """Whether `jaxpr` (or one nested in it) calls back into Python: JAX exports
    no such program, and trying would lower it once more for nothing."""
    for eqn in jaxpr.eqns:
        if "callback" in eqn.primitive.name:
            return True
        for value in eqn.params.values():
            for item in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(item, "jaxpr", item)  # A closed jaxpr's own.
                if hasattr(inner, "eqns") and _holds_callback(inner):
                    return True
    return False


@contextlib.contextmanager
def keep_programs(directory: str | os.PathLike, context: str) -> Iterator[None]:
    """Within it, the studies' solves are exported to and read back from
    `directory` (see the module's docstring), keyed by the code, `context` and each
    program's name and arguments. `context` must determine everything the studies
    build (the command line's options)."""
    global _kept
    before, _kept = _kept, _Programs(pathlib.Path(directory), context)
    try:
        yield
    finally:
        _kept = before
