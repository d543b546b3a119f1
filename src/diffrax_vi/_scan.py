r"""Fixed steps without `diffeqsolve`'s loop: the solver's own `step` in an unrolled
`jax.lax.scan`.

`diffrax.diffeqsolve` runs every solve, fixed-step or adaptive, in one general
`while` loop that carries a step-size controller, event handling, save buffers and
the bookkeeping of rejected steps. For a fixed step on a small system that loop costs
more than the step: a vmapped ensemble runs well below the throughput of a bare
`jax.vmap` of a `lax.scan` of the same update (`benchmarks/ensemble_throughput.py`).
A fixed number of steps needs none of it: [`diffrax_vi.solve_fixed_steps`][] calls
the same `solver.init` and
`solver.step`, at the same times, as `diffeqsolve` with `diffrax.ConstantStepSize`
does, in a scan whose trip count is known and whose body XLA can unroll.
"""

import diffrax as dfx
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from ._custom_types import Args, RealScalarLike
from ._misc import all_finite, has_loop
from ._private_api import assert_term_compatible, use_stepsize_tol, WrapTerm


class FixedStepSolution(eqx.Module):
    """What [`diffrax_vi.solve_fixed_steps`][] returns.

    - `ts`: the `n_save + 1` save times, from `t0` to `t1`, as the steps reach
        them.
    - `ys`: the states at `ts` (a leading axis of `n_save + 1`).
    - `solver_state`: the solver's state after the last step it took.
    - `result`: a `diffrax.RESULTS`; the first failure, if a step failed.
        `RESULTS.nonfinite` where a solver that does not check its steps
        (diffrax's Runge–Kutta solvers) left NaN or inf at a save time.
    - `t_reached`: the time the last successful step ended at (`t1` on success).
    - `num_steps`: the successful steps taken.

    After a failed step the states and solver state are those the failed step
    produced (a variational solver's NaN), as `diffeqsolve(..., throw=False)` leaves
    them; save times after it hold what the later steps computed from there, and
    are to be discarded, as `t_reached` says."""

    ts: Array
    ys: PyTree
    solver_state: PyTree
    result: dfx.RESULTS
    t_reached: Array
    num_steps: Array


def _count_steps(t0, t1, dt0, dtype) -> int:
    """The number of steps `diffrax.ConstantStepSize` takes: `ceil((t1 - t0) /
    nextafter(dt0))` in the time dtype."""
    try:
        t0, t1, dt0 = (np.asarray(x, dtype) for x in (t0, t1, dt0))
    except (
        TypeError,
        jax.errors.ConcretizationTypeError,
        jax.errors.TracerArrayConversionError,
    ) as e:
        raise ValueError(
            "solve_fixed_steps needs t0, t1 and dt0 known when it is traced (Python "
            "numbers or concrete arrays), to fix its number of steps; for traced "
            "times use diffrax.diffeqsolve."
        ) from e
    if not (np.isfinite(t0) and np.isfinite(t1) and np.isfinite(dt0)):
        raise ValueError(f"t0, t1 and dt0 must be finite; got {t0}, {t1}, {dt0}.")
    if not (t1 > t0 and dt0 > 0):
        raise ValueError(
            f"solve_fixed_steps integrates forwards with dt0 > 0 and t1 > t0; got "
            f"t0 = {t0}, t1 = {t1}, dt0 = {dt0}. Use diffrax.diffeqsolve to integrate "
            "backwards."
        )
    n = np.ceil((t1 - t0) / np.nextafter(dt0, np.asarray(np.inf, dtype)))
    if n > MAX_STEPS:
        raise ValueError(
            f"dt0 = {dt0} makes {n:.3g} steps from t0 = {t0} to t1 = {t1}, more than "
            f"solve_fixed_steps counts ({MAX_STEPS}, the int32 step counter's "
            "range). Take a larger dt0, or split the interval into several solves."
        )
    return int(n)


# The most steps one solve counts: its step counter and `num_steps` are int32.
MAX_STEPS = 2**31 - 1


def _check_solver(terms, solver, t0, y0, args) -> None:
    """What `diffrax.diffeqsolve` checks before it starts: the terms fit the solver,
    and an implicit diffrax solver has the tolerances a fixed step needs."""
    assert_term_compatible(
        t0, y0, args, terms, solver.term_structure, solver.term_compatible_contr_kwargs
    )
    if isinstance(solver, dfx.AbstractImplicitSolver) and any(
        getattr(solver.root_finder, name, None) is use_stepsize_tol
        for name in ("rtol", "atol", "norm")
    ):
        raise ValueError(
            f"{type(solver).__name__}'s root finder takes its tolerances from an "
            "adaptive step size controller, and solve_fixed_steps has none. Set them: "
            f"diffrax.{type(solver).__name__}(root_finder=diffrax.VeryChord(rtol=..., "
            "atol=..., norm=optimistix.max_norm)), or use diffrax.diffeqsolve with "
            "a PIDController."
        )


def _first_non_finite(ts, ys, reached, steps, result, per_interval):
    """Where a solver that does not check its own steps (diffrax's Runge-Kutta
    solvers at fixed steps) produced NaN or inf: `RESULTS.nonfinite`, with the time
    reached and the steps taken cut back to the last save with a finite state."""
    finite = jax.vmap(all_finite)(ys)
    # The number of finite saves before the first that is not.
    leading = jnp.sum(jnp.cumprod(finite.astype(jnp.int32)))
    bad = (result == dfx.RESULTS.successful) & (leading < finite.shape[0])
    last_good = jnp.maximum(leading - 1, 0)
    reached = jnp.where(bad, jnp.minimum(reached, ts[last_good]), reached)
    kept = last_good.astype(steps.dtype) * per_interval
    steps = jnp.where(bad, jnp.minimum(steps, kept), steps)
    result = dfx.RESULTS.where(bad, dfx.RESULTS.nonfinite, result)
    return reached, steps, result


# Steps per iteration of the scan for a step without a loop of its own. Measured for
# Stormer-Verlet on Kepler ensembles (trajectory-steps per second, one CPU, unroll 1 /
# 4 / 8): 64 members 2.2e8 / 2.7e8 / 9.6e7, 1024 members 1.5e8 / 2.2e8 / 2.4e8, 4096
# members 6.3e7 / 8.4e7 / 9.1e7: 4 is never far from the best, and 8 pushes a small
# ensemble's loop past the size XLA compiles whole.
UNROLL = 4


def solve_fixed_steps(
    terms: PyTree[dfx.AbstractTerm],
    solver: dfx.AbstractSolver,
    t0: RealScalarLike,
    t1: RealScalarLike,
    dt0: RealScalarLike,
    y0: PyTree,
    args: Args = None,
    *,
    n_save: int = 1,
    unroll: int | None = None,
) -> FixedStepSolution:
    r"""Integrate from `t0` to `t1` in fixed steps of `dt0` with any diffrax solver
    (this package's or diffrax's own), as
    `diffrax.diffeqsolve(terms, solver, t0, t1, dt0, y0, args,
    stepsize_controller=diffrax.ConstantStepSize(), throw=False)` would: the same
    `solver.init` and `solver.step` calls at the same times (those of
    `diffrax.ConstantStepSize`: `t0 + dt0` first, then fractions `k / n` of
    `t1 - t0`, and `t1` exactly last), so the states are `diffeqsolve`'s to
    round-off (XLA may fuse the unrolled arithmetic differently). Faster, because
    the steps run in an unrolled `jax.lax.scan` instead of `diffeqsolve`'s general
    loop
    ([Benchmarks](../benchmarks.md#ensembles)).

    No dense output, events or progress meter: use `diffeqsolve` for those.

    The solver checks the times when they are traced, so the program of a
    variational solve in a vector space holds no host callback and JAX's persistent
    compilation cache can store it (so does `diffeqsolve` from Python floats; from
    arrays it checks them with one; a start on a group is checked with one in
    both).

    **Arguments:**

    - `terms`, `solver`, `t0`, `t1`, `dt0`, `y0`, `args`: as for
        `diffrax.diffeqsolve`. `t0`, `t1` and `dt0` must be known at trace time,
        with `t1 > t0` and `dt0 > 0`; the number of steps `n` is
        `ConstantStepSize`'s, `ceil((t1 - t0) / dt0)`.
    - `n_save`: the number of intervals of `n / n_save` steps to save the state at
        the end of (it must divide `n`).
    - `unroll`: the steps per iteration of the scan (`jax.lax.scan`'s `unroll`).
        By default 4 for a step without a loop of its own (an explicit method),
        and 1 for one with a loop (a Newton iteration, a composition's substeps),
        whose cost dwarfs the scan's and whose compile time unrolling would
        multiply (`MidpointVI`: 4 s to compile at 1, 10 s at 8, for no gain).

    **Returns:**

    A [`diffrax_vi.FixedStepSolution`][].

    **Raises:**

    `ValueError` for times that are traced, not finite or backwards, more than
    2³¹ − 1 steps, an `n_save` that does not divide the number of steps, terms the
    solver cannot take, or an implicit diffrax solver without its own tolerances
    (as `diffrax.diffeqsolve` does).
    """
    # The time dtype diffeqsolve would use.
    dtype = jnp.result_type(t0, t1, dt0)
    dtype = dtype if jnp.issubdtype(dtype, jnp.floating) else jnp.result_type(float)
    n = _count_steps(t0, t1, dt0, dtype)
    if not isinstance(n_save, int) or n_save < 1 or n % n_save:
        raise ValueError(
            f"n_save = {n_save!r} must be a positive integer that divides the {n} "
            "steps."
        )
    if unroll is not None and (not isinstance(unroll, int) or unroll < 1):
        raise ValueError(f"unroll must be a positive integer; got {unroll!r}.")
    t0, t1, dt0 = (np.asarray(x, dtype) for x in (t0, t1, dt0))
    # diffeqsolve rounds a step end within 100 ulp of t1 to t1.
    t1_floor = t1
    for _ in range(100):
        t1_floor = np.nextafter(t1_floor, np.asarray(-np.inf, dtype))
    times = (t0, t1, dt0, t1_floor)
    # The solver's `init` is given its first step's times as static Python numbers
    # (exact in any float dtype), so that it checks them when traced: a check at run
    # time is a host callback, and JAX's persistent compilation cache stores no
    # program that holds one. Computed in NumPy, which compiles nothing (in JAX,
    # each operation here was a program of its own).
    first = _step_end(np.ones((), np.int32), *times, n, xp=np)
    first_step = (float(t0), float(first))
    _check_solver(terms, solver, t0, y0, args)
    # Compiled with equinox, as diffeqsolve is, so that an error raised inside the
    # loop (a LagrangianTerm's, under a Runge-Kutta solver) reads as its message,
    # not as a failed host callback.
    return _scan_steps(terms, solver, times, first_step, y0, args, n, n_save, unroll)


def _step_end(k, t0, t1, dt0, t1_floor, n, xp=jnp):
    """The end of step k = 1, ..., n as diffrax.ConstantStepSize places it: t0 + dt0
    first, then the fraction k / n of the interval, and t1 exactly last; in the
    array module `xp` (JAX, or NumPy for times known now)."""
    dtype = t0.dtype
    t = t0 + (t1 - t0) * (k.astype(dtype) / xp.asarray(n, dtype))
    t = xp.where(k == 1, t0 + dt0, xp.where(k == n, t1, t))
    return xp.where(t > t1_floor, t1, t)


@eqx.filter_jit
def _scan_steps(terms, solver, times, first_step, y0, args, n, n_save, unroll):
    t0, t1, _, _ = times
    dtype = t0.dtype
    per_interval = n // n_save
    # Known when traced, for the solver's checks, as NumPy numbers: no program to
    # compile for them.
    start, first = (np.asarray(x, dtype) for x in first_step)
    # The terms wrapped as diffeqsolve wraps them for its solver (forwards), so that
    # `init` and `step` get what they get there: a variational step traced for one
    # is reused by the other in the same process (`_traced_once`), as a study's
    # tracked and timed solves of the same method are.
    direction = jnp.where(t0 < t1, 1, -1)
    terms = jax.tree.map(
        lambda term: WrapTerm(term, direction),
        terms,
        is_leaf=lambda x: (
            isinstance(x, dfx.AbstractTerm) and not isinstance(x, dfx.MultiTerm)
        ),
    )
    state = solver.init(terms, start, first, y0, args)
    if unroll is None:
        step = jax.make_jaxpr(
            lambda y, s: solver.step(terms, t0, t1, y, args, s, False)
        )(y0, state)
        unroll = 1 if has_loop(step.jaxpr) else UNROLL

    def one(carry, _):
        t, k, y, state, result, steps, reached = carry
        k = k + 1
        t_next = _step_end(k, *times, n)
        y, _, _, state, step_result = solver.step(
            terms, t, t_next, y, args, state, False
        )
        ok = result == dfx.RESULTS.successful
        result = dfx.RESULTS.where(ok, step_result, result)
        succeeded = ok & (step_result == dfx.RESULTS.successful)
        reached = jnp.where(succeeded, t_next, reached)
        steps = steps + succeeded.astype(jnp.int32)
        return (t_next, k, y, state, result, steps, reached), None

    def interval(carry, _):
        carry, _ = lax.scan(one, carry, None, length=per_interval, unroll=unroll)
        return carry, (carry[0], carry[2])

    zero = jnp.zeros((), jnp.int32)
    init = (t0, zero, y0, state, dfx.RESULTS.successful, zero, t0)
    (_, _, _, state, result, steps, reached), (ts, ys) = lax.scan(
        interval, init, None, length=n_save
    )
    ts = jnp.concatenate([t0[None], ts])
    ys = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), y0, ys)
    reached, steps, result = _first_non_finite(
        ts, ys, reached, steps, result, per_interval
    )
    return FixedStepSolution(ts, ys, state, result, reached, steps)
