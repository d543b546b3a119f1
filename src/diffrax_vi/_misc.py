from collections.abc import Callable

import equinox as eqx
import jax
import jax.extend.core as jex
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Bool, PyTree

from ._custom_types import P, Q
from ._space import is_euclidean, tangent


def state_dtype(tree: PyTree) -> np.dtype:
    """The floating dtype that all arithmetic on `tree` is carried out in."""
    leaves = jtu.tree_leaves(tree)
    if len(leaves) == 0:
        raise ValueError("The state is empty: `q` must contain at least one array.")
    dtype = jnp.result_type(*leaves)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(
            f"The state has dtype {dtype}, but variational solvers need floating "
            "point positions and momenta. Pass e.g. `jnp.asarray(q0, dtype=float)`."
        )
    if jnp.finfo(dtype).bits < 32:
        raise ValueError(
            f"The state has dtype {dtype}: the implicit solves need float32 or "
            "float64 (their LU and eigenvalue routines do not take 16-bit floats, "
            "whose 3 digits could not resolve a step anyway). Cast y0 and the times "
            "to float32."
        )
    return dtype


def all_finite(tree: PyTree) -> Bool[Array, ""]:
    """Whether every entry of `tree` is finite, by counting the finite entries of
    each leaf in an integer sum. XLA on CPU hands a floating-point reduction of 4096
    or more elements (a large state, or a small one batched by `vmap`) to YNNPACK as
    a custom fusion, which breaks the loop around it into kernels dispatched one by
    one (`diagnostics.loop_breakers`); it keeps an integer sum in the loop. The sum
    is of 32 bits, which x64 would otherwise make 64. Below that size the count
    costs what a sum of the entries did (CHANGELOG)."""
    leaves = [
        jnp.sum(jnp.isfinite(x), dtype=jnp.int32) == x.size
        for x in jtu.tree_leaves(tree)
    ]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


def check_state(q: Q, p: P, name: str = "y0", space: PyTree = None) -> None:
    """Trace-time check that positions and momenta have matching structure, shapes
    (on a group, that the momenta have the structure of the space's velocities)."""
    if space is not None and not is_euclidean(space):
        like = jax.eval_shape(lambda: tangent(space, q))
        shapes = lambda tree: jtu.tree_map(jnp.shape, tree)
        if jtu.tree_structure(like) != jtu.tree_structure(p) or shapes(like) != shapes(
            p
        ):
            raise ValueError(
                f"`{name} = (q, p)` on this configuration space needs momenta shaped "
                f"like its velocities, {shapes(like)}; got {shapes(p)}. For SO3, "
                "`q` is a (3, 3) rotation matrix and `p` the body angular momentum "
                "of shape (3,)."
            )
        return
    q_struct = jtu.tree_structure(q)
    p_struct = jtu.tree_structure(p)
    if q_struct != p_struct:
        raise ValueError(
            f"`{name} = (q, p)` must have `q` and `p` of the same PyTree structure, as "
            f"`p = dL/dv` has the structure of `v`; got q: {q_struct} and p: "
            f"{p_struct}. Build `p` from `q`, e.g. `jax.tree.map(jnp.zeros_like, q)`."
        )
    for qi, pi in zip(jtu.tree_leaves(q), jtu.tree_leaves(p)):
        if jnp.shape(qi) != jnp.shape(pi):
            raise ValueError(
                f"`{name} = (q, p)` must have matching shapes in `q` and `p`; got "
                f"q leaf of shape {jnp.shape(qi)} and p leaf of shape "
                f"{jnp.shape(pi)}."
            )


def split_state(y: PyTree, name: str = "y0", space: PyTree = None) -> tuple[Q, P]:
    """Unpack `y = (q, p)` with a trace-time error that says how to build it."""
    if isinstance(y, list) and len(y) == 2:
        raise ValueError(
            "The state `(q, p)` must be a tuple, not a list: diffrax requires every "
            "step to return the structure of y0, and the solvers return a tuple. "
            "Pass `y0 = tuple(y0)`."
        )
    if not (isinstance(y, tuple) and len(y) == 2):
        raise ValueError(
            f"`{name}` must be a pair `(q, p)` of positions and momenta, got "
            f"{jtu.tree_structure(y)}. To start from a velocity `v0`, use "
            "`(q0, diffrax_vi.momentum(lagrangian, t0, q0, v0, args))`."
        )
    if any(jnp.iscomplexobj(x) for x in jtu.tree_leaves(y)):
        raise ValueError(
            f"`{name} = (q, p)` is complex, and this package's solvers step real "
            "positions and momenta (of a Lagrangian, or of the pair of terms "
            "dq/dt = f(p), dp/dt = g(q)): write each complex coordinate as two real "
            "ones (its real and imaginary parts)."
        )
    q, p = y
    check_state(q, p, name, space)
    return q, p


def tree_add(x: PyTree, y: PyTree) -> PyTree:
    """`x + y`, leafwise."""
    return jtu.tree_map(lambda xi, yi: xi + yi, x, y)


def tree_sub(x: PyTree, y: PyTree) -> PyTree:
    """`x - y`, leafwise."""
    return jtu.tree_map(lambda xi, yi: xi - yi, x, y)


def tree_axpy(a, x: PyTree, y: PyTree) -> PyTree:
    """`a * x + y`, leafwise."""
    return jtu.tree_map(lambda xi, yi: a * xi + yi, x, y)


def tree_size(tree: PyTree) -> int:
    """The number of entries over every leaf."""
    return sum(np.size(x) for x in jtu.tree_leaves(tree))


def tree_dtype(tree: PyTree):
    """The dtype that the leaves of `tree` promote to."""
    return jnp.result_type(*jtu.tree_leaves(tree))


def tree_max_abs(tree: PyTree) -> Array:
    """The largest `|x|` over every leaf."""
    leaves = [jnp.max(jnp.abs(x), initial=0.0) for x in jtu.tree_leaves(tree)]
    return jnp.max(jnp.stack(leaves))


def traced(tree: PyTree) -> bool:
    """Whether any leaf of `tree` is traced (not known until the program runs)."""
    return any(isinstance(x, jax.core.Tracer) for x in jtu.tree_leaves(tree))


def at_trace_time(fn, *xs):
    """`fn(*xs)`, computed when traced where every array in `xs` is known then (so
    that a check can read it), else traced as usual (under
    `jax.ensure_compile_time_eval` a traced argument costs far more tracing: 0.16 s
    for a rigid body's start check)."""
    if traced(xs):
        return fn(*xs)
    with jax.ensure_compile_time_eval():
        return fn(*xs)


def error_if(x: PyTree, failed: bool | Bool[Array, ""], message: str) -> PyTree:
    """`x`, or an error if `failed`: a `ValueError` now where `failed` is known when
    traced (computed from concrete values), else at run time (`eqx.error_if`, a host
    callback: XLA then no longer compiles a loop around it as one function, and JAX's
    persistent compilation cache stores no program that holds one). At run time
    the check is attached to the floating leaves of `x` alone where it has any:
    under `EQX_ON_ERROR=nan` equinox fills the leaves it is given instead of
    raising, NaN in a float but the largest value in an integer, which in a
    solver's state made a `RESULTS` that names no outcome; a NaN state is reported
    as `nonfinite` by the steps that take it."""
    if isinstance(failed, jax.core.Tracer):
        floats, rest = eqx.partition(x, eqx.is_inexact_array)
        if not jax.tree.leaves(floats):
            return eqx.error_if(x, failed, message)
        return eqx.combine(eqx.error_if(floats, failed, message), rest)
    if failed:
        raise ValueError(message)
    return x


def holds(jaxpr: jex.Jaxpr, found: Callable[[jex.JaxprEqn], bool]) -> bool:
    """Whether a traced program holds an operation that `found` accepts (at any
    depth)."""
    return any(
        found(eqn) or any(holds(sub, found) for sub in jex.jaxprs_in_params(eqn.params))
        for eqn in jaxpr.eqns
    )


def has_loop(jaxpr: jex.Jaxpr) -> bool:
    """Whether a traced program contains a `while` or `scan` (at any depth)."""
    return holds(jaxpr, lambda eqn: eqn.primitive.name in ("while", "scan"))


# `call_traced_once(f, *args, **kwargs)` is `f(*args, **kwargs)` through a nested
# jit: JAX traces `f` once per signature and then transforms its jaxpr (cached)
# wherever it is called or differentiated again. A general Lagrangian's implicit
# step differentiates the user's Lagrangian and constraint many times over (48
# evaluations of the Lagrangian in a reversible gradient of the double pendulum),
# and `ReversibleAdjoint` runs its forward loop twice; the first calls are in
# `benchmarks/first_call.py`. XLA inlines it: the steps cost the same. `reads`
# follows it inside.
call_traced_once = eqx.filter_jit(lambda f, *args, **kwargs: f(*args, **kwargs))


def reads(fn, x: PyTree, *rest) -> bool:
    """Whether `fn(x, *rest)` reads `x` at all, decided from its traced program: an
    output counts as reading `x` if any operation on the way to it takes a value
    computed from `x` (conservative: a primitive with a sub-program is followed as
    a whole, except a nested jit, which is followed inside). Structural, so a
    dependence that vanishes at this `x` but not elsewhere still counts."""
    jaxpr = jax.make_jaxpr(fn)(x, *rest).jaxpr
    n = len(jtu.tree_leaves(x))
    return any(_dependent(jaxpr, [i < n for i in range(len(jaxpr.invars))]))


def _dependent(jaxpr: jex.Jaxpr, inputs: list[bool]) -> list[bool]:
    """Which outputs of `jaxpr` depend on the inputs flagged in `inputs`. A nested
    jit (`call_traced_once`'s) is followed inside; any other primitive with a
    sub-program as a whole."""
    dependent = {v for v, flag in zip(jaxpr.invars, inputs) if flag}
    read = lambda y: isinstance(y, jex.Var) and y in dependent
    for eqn in jaxpr.eqns:
        flags = [read(y) for y in eqn.invars]
        if not any(flags):
            continue
        if eqn.primitive.name == "jit":
            outs = _dependent(eqn.params["jaxpr"].jaxpr, flags)
            dependent.update(y for y, flag in zip(eqn.outvars, outs) if flag)
        else:
            dependent.update(eqn.outvars)
    return [read(y) for y in jaxpr.outvars]


def perturbed_with(state: PyTree, y0: PyTree) -> PyTree:
    """`state`, whose floating-point leaves all carry a derivative (zero where they
    do not depend on it) wherever `state` or `y0` carries one.

    Parts of a solver's state start constant (the compensation of its sums, the
    work of its forces) and depend on `y0` after its first step.
    `RecursiveCheckpointAdjoint`'s loop (`equinox.internal.checkpointed_while_loop`)
    finds which of its carries it differentiates by linearising the step until that
    set stops growing: once more for each carry that a step perturbs but the start
    does not. A state perturbed from the start is that set at once, so the step is
    linearised once instead of two or three times; the compiled program is the
    same."""
    return _perturbed_with(state, y0)


@eqx.filter_custom_jvp
def _perturbed_with(state, y0):
    return state


@_perturbed_with.def_jvp
def _perturbed_with_jvp(primals, tangents):
    state, _ = primals
    t_state, _ = tangents
    given = [t for t in jtu.tree_leaves(tangents) if t.size]
    if not given:
        return state, t_state
    # A zero that JAX's linearisation sees depend on the given derivatives: a
    # constant zero would become a symbolic one, which marks nothing perturbed.
    zero = jnp.where(False, given[0].ravel()[0], 0)

    def tangent(t, x):
        if t is None and eqx.is_inexact_array(x):
            return jnp.broadcast_to(zero.astype(x.dtype), x.shape)
        return t

    return state, jtu.tree_map(tangent, t_state, state, is_leaf=lambda t: t is None)
