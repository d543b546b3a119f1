"""Every private API of diffrax, equinox and JAX that this package relies on, in one
place.

`tests/test_surface.py::test_private_api_assumptions` checks each assumption made
here, so that an upgrade that changes one fails there, loudly, rather than somewhere
inside a solve.
"""

import diffrax as dfx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from diffrax._adjoint import (  # What a custom adjoint does as diffrax's own do.
    _is_subsaveat as is_subsaveat,
    _nondiff_solver_controller_state as nondiff_solver_controller_state,
    _only_transpose_ys as only_transpose_ys,
)
from diffrax._integrate import (
    _assert_term_compatible as assert_term_compatible,  # `diffeqsolve`'s own check.
    _clip_to_end as clip_to_end,  # How diffrax's loop ends a step on t1.
)

# An implicit solver whose tolerances are left to an adaptive controller.
from diffrax._root_finder import (
    use_stepsize_tol,
)
from diffrax._saveat import save_y  # The default SaveAt(fn=...).
from diffrax._term import (  # What `diffeqsolve` hands solvers instead of our term.
    AdjointTerm,  # BacksolveAdjoint's backward solve.
    WrapTerm,  # Every solve.
)
from equinox._enum import EnumerationItem  # An enumeration's item from its value.
from jax._src.compilation_cache import (  # The persistent cache, set up once.
    reset_cache as reset_compilation_cache,
)

# The shortest compilation the persistent cache keeps, in this thread alone
# (`with persistent_cache_min_time(math.inf):`).
from jax._src.config import (
    persistent_cache_min_compile_time_secs as persistent_cache_min_time,
)
from jax._src.core import Literal  # A constant operand of a traced equation.
from jax._src.interpreters.partial_eval import (  # A value being traced into a jaxpr.
    DynamicJaxprTracer,
)

# Points jaxlib's CPU LAPACK kernels at SciPy's LAPACK, as lowering an eigensolver
# does: an executable loaded in a process that lowered none would call nothing.
from jax._src.lax.linalg import initialize_lapack
from jax._src.xla_bridge import backends_are_initialized  # XLA_FLAGS are read then.
from jaxtyping import ArrayLike, Bool


__all__ = [
    "AdjointTerm",
    "assert_term_compatible",
    "backends_are_initialized",
    "clip_to_end",
    "initialize_lapack",
    "is_subsaveat",
    "known_value",
    "nondiff_solver_controller_state",
    "promote_result",
    "reset_compilation_cache",
    "only_transpose_ys",
    "persistent_cache_min_time",
    "save_y",
    "NoForwardingSolverMeta",
    "unvmap_any",
    "use_stepsize_tol",
    "WrapTerm",
]


_SolverMeta = type(dfx.AbstractSolver)


class NoForwardingSolverMeta(_SolverMeta):
    """The metaclass of this package's capability markers.

    diffrax's solver metaclass forwards `isinstance` through wrappers:
    `isinstance(diffrax.HalfSolver(s), C)` is true whenever `isinstance(s, C)` is. For
    a capability such as symplecticity that is wrong (step doubling with adaptive
    steps is not symplectic), so the markers answer for the object itself."""

    def __instancecheck__(cls, obj):
        return super(_SolverMeta, cls).__instancecheck__(obj)


def unvmap_any(x: bool | Bool[ArrayLike, "..."]) -> Bool[ArrayLike, ""]:
    """True if `x` is true in any batch element: lets a branch stay a real branch under
    `jax.vmap` instead of becoming a select that evaluates both sides."""
    return eqxi.unvmap_any(x)


def promote_result(
    cls: type, result: optx.RESULTS | lx.RESULTS
) -> dfx.RESULTS | optx.RESULTS:
    """`cls.promote(result)` (`cls` diffrax's or optimistix's results, `result` an
    optimistix or lineax one), without equinox's look-up of its table under
    `jax.ensure_compile_time_eval`, which compiles two small programs the first
    time a process promotes (20 ms of a first trace). Where the table
    (`_base_offsets`) maps each value to itself, as each of these does, the value
    is taken as it is."""
    offsets = cls._base_offsets[result._enumeration]
    value = result._value
    if not np.array_equal(offsets, np.arange(len(offsets))):
        value = jnp.asarray(offsets)[value]
    return EnumerationItem(value, cls)


# The operations by which diffrax computes a solve's first times from Python floats
# (`jnp.asarray`, the step's end `t0 + dt0`, `min(·, t1)`, the direction's sign),
# evaluated in NumPy: JAX's own evaluation of them at trace time compiles one small
# program per operation the first time a process meets it (13 ms of a first call).
_NUMPY_RULES = {
    "add": np.add,
    "sub": np.subtract,
    "mul": np.multiply,
    "neg": np.negative,
    "min": np.minimum,
    "max": np.maximum,
    "lt": np.less,
    "le": np.less_equal,
    "gt": np.greater,
    "ge": np.greater_equal,
    "eq": np.equal,
    "ne": np.not_equal,
    "select_n": lambda which, *cases: np.asarray(cases)[np.asarray(which, int)],
    "convert_element_type": lambda x: x,  # Cast to the output's dtype below.
}


def known_value(x, budget: int = 32) -> np.ndarray | None:
    """The value of a traced scalar `x` where it is computed only from constants
    (as `diffeqsolve` computes a solve's first times from Python floats: JAX stages
    even `jnp.asarray(0.1)` as a traced value), by at most `budget` of the simple
    operations above; else `None`. A value that is not traced is itself.

    It reads JAX's tracers (`get_const`, `parent`): where a JAX release changes
    them it gives `None`, and the callers check at run time as before
    (`tests/test_surface.py` then fails)."""
    if not isinstance(x, jax.core.Tracer):
        return np.asarray(x)
    try:
        return _evaluate(x, [budget])
    except (_Unknown, AttributeError, LookupError, TypeError, ValueError):
        return None


class _Unknown(Exception):
    pass


def _evaluate(x, budget: list[int]) -> np.ndarray:
    if not isinstance(x, DynamicJaxprTracer) or x.shape != ():
        raise _Unknown
    value = x.get_const()
    if value is not None:
        return np.asarray(value)
    eqn = x.parent
    if eqn is None:
        raise _Unknown
    args = [_evaluate(t, budget) for t in eqn.in_tracers]
    outs = _apply(eqn.primitive.name, eqn.params, args, budget)
    return np.asarray(outs[eqn.outvars.index(x.val)], x.dtype)


def _apply(name: str, params: dict, args: list, budget: list[int]) -> list:
    """The outputs of one equation on NumPy scalars; a nested `jit` (`jnp.where`
    is one) through its jaxpr."""
    budget[0] -= 1
    if budget[0] < 0:
        raise _Unknown
    if name in _NUMPY_RULES:
        with np.errstate(all="ignore"):
            return [_NUMPY_RULES[name](*args)]
    if name != "jit":
        raise _Unknown
    closed = params["jaxpr"]
    env = dict(zip(closed.jaxpr.constvars, map(np.asarray, closed.consts)))
    env.update(zip(closed.jaxpr.invars, args))
    read = lambda v: np.asarray(v.val) if isinstance(v, Literal) else env[v]
    for inner in closed.jaxpr.eqns:
        if any(v.aval.shape != () for v in inner.outvars):
            raise _Unknown
        operands = [read(v) for v in inner.invars]
        outs = _apply(inner.primitive.name, inner.params, operands, budget)
        for var, out in zip(inner.outvars, outs):
            env[var] = np.asarray(out, var.aval.dtype)
    return [read(v) for v in closed.jaxpr.outvars]
