"""Traced programs kept between runs of the command line.

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
traced every time, as without this cache."""

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
import warnings
from collections.abc import Callable, Iterator

import jax
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


def compiled(name: str, fn: Callable, *args: PyTree) -> Callable:
    """`fn` compiled for `args`; under `keep_programs`, the program is
    read back from its file where a run with the same key exported it, and exported
    there otherwise. `fn` takes and returns arrays in tuples, lists and dicts (what
    `jax.export` serialises); `name` tells apart the programs of one context."""
    jitted = jax.jit(fn)
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
