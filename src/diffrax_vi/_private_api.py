"""Every private API of diffrax, equinox and JAX that this package relies on, in one
place.

`tests/test_surface.py::test_private_api_assumptions` checks each assumption made
here, so that an upgrade that changes one fails there, loudly, rather than somewhere
inside a solve.
"""

import diffrax as dfx
import equinox.internal as eqxi
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
from jax._src.xla_bridge import backends_are_initialized  # XLA_FLAGS are read then.
from jaxtyping import ArrayLike, Bool


__all__ = [
    "AdjointTerm",
    "assert_term_compatible",
    "backends_are_initialized",
    "clip_to_end",
    "is_subsaveat",
    "nondiff_solver_controller_state",
    "promote_result",
    "reset_compilation_cache",
    "only_transpose_ys",
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
