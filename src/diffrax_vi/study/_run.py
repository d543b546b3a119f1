import dataclasses
import time

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, PyTree

from .._misc import all_finite
from ..scenes import Scene
from ._methods import Method
from ._track import TrackWorstError


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What one method's solve of one scene (or one ensemble of it) produced, as
    NumPy arrays with ensemble members along a leading axis (of size 1 for a single
    solve).

    `max_errors[name][m, i]` is member `m`'s largest `|I(t) - I(0)|` of invariant
    `name` (over the components of a vector invariant) over the steps in the `i`-th
    interval between save times; index 0 is the start, where it is 0. After the
    interval in which a solve failed, it is NaN."""

    max_errors: dict[str, np.ndarray]
    final: PyTree[np.ndarray]
    steps: int
    wall_time: float
    results: list[str]

    @property
    def result(self) -> str:
        """`"successful"`, diffrax's message, or how many ensemble members failed."""
        failed = [r for r in self.results if r != "successful"]
        if not failed:
            return "successful"
        if len(self.results) == 1:
            return failed[0]
        return f"{len(failed)} of {len(self.results)} members failed: {failed[0]}"

    def errors(self) -> dict[str, np.ndarray]:
        """The largest error of each invariant in each interval between save times,
        over the ensemble members."""
        return {name: err.max(axis=0) for name, err in self.max_errors.items()}


def cast_scene(scene: Scene, dtype) -> Scene:
    """The scene with every floating array (state and Lagrangian parameters) in
    `dtype`, so that nothing promotes the state back to another precision."""
    return jax.tree.map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, scene
    )


def shard_ensemble(y0s: PyTree[Array], members: int) -> PyTree[Array]:
    """Place an ensemble's initial states across all devices along its leading axis
    (a no-op on one device)."""
    devices = jax.devices()
    if len(devices) == 1:
        return y0s
    if members % len(devices):
        raise ValueError(
            f"An ensemble of {members} members cannot be split evenly across "
            f"{len(devices)} devices: choose a multiple of {len(devices)}, or pass "
            "shard=False."
        )
    mesh = Mesh(np.asarray(devices), ("ensemble",))
    return jax.device_put(y0s, NamedSharding(mesh, PartitionSpec("ensemble")))


# An adaptive method may take at most this many steps between two save times (as
# diffrax's default `max_steps`), so that a step size collapsing to nothing fails the
# run rather than spinning.
MAX_ADAPTIVE_STEPS_PER_SAVE = 4096


def run(
    scene: Scene,
    method: Method,
    *,
    t1: float,
    n_steps: int,
    n_save: int,
    dtype,
    y0: PyTree[Array],
    ensemble: bool = False,
    progress: bool = False,
) -> Outcome:
    """Solve `scene` from `y0` with `method` to `t1`, recording the largest error of
    each conserved quantity over each of `n_save` equal intervals, and the final
    state. Fixed steps take exactly `n_steps` (which `n_save` must divide); adaptive
    ones choose their own (diffrax picks the first step of each interval, then the
    controller, whose state carries over) and take at most
    `MAX_ADAPTIVE_STEPS_PER_SAVE` steps per interval. With `ensemble=True`, `y0` has a
    leading axis of members and the solve is vmapped over it (and runs on every
    device `y0` is sharded over). Wall time is of a second, compiled, call.

    The errors are taken at every step, not sampled: a sample every k-th step
    aliases with the motion (one save per period sees one phase of the orbit, and
    misses the pendulum's peak energy error by a factor of 10^6). Each interval is
    one `diffeqsolve` inside a `lax.scan`, resumed from the last one's solver and
    controller state, with a solver wrapped in `TrackWorstError`, which keeps the
    running maximum in its solver state: memory is O(`n_save`), not O(steps)."""
    conserved = scene.conserved()
    terms = method.terms(scene)
    solver = method.solver
    controller = method.controller()
    fixed = method.rtol is None
    per_save = n_steps // n_save
    max_steps = per_save if fixed else MAX_ADAPTIVE_STEPS_PER_SAVE
    ts = jnp.linspace(0, t1, n_save + 1, dtype=dtype)
    h = jnp.asarray(t1 / n_steps, dtype)
    # Driven once per interval, so one bar for the whole run.
    meter = (
        dfx.TqdmProgressMeter(refresh_steps=1) if progress else dfx.NoProgressMeter()
    )

    def solve(y0):
        tracked = TrackWorstError(
            solver, conserved, {k: f(ts[0], y0, None) for k, f in conserved.items()}
        )
        saveat = dfx.SaveAt(t1=True, solver_state=True, controller_state=True)
        solver_state = solver.init(terms, ts[0], ts[0] + h, y0, None)
        if fixed:
            controller_state = None
        else:
            error_order = solver.error_order(terms)
            _, controller_state = controller.init(
                terms, ts[0], ts[1], y0, h, None, solver.func, error_order
            )

        def interval(carry, t_span):
            y, solver_state, controller_state, result, steps, meter_state = carry
            sol = dfx.diffeqsolve(
                terms,
                tracked,
                t_span[0],
                t_span[1],
                # diffrax places fixed steps at t0 + (t1 - t0) k / n, ending exactly
                # on the save time; a sum of steps would leave a last step of a few
                # ulps (and StepTo indexing a time grid costs ~1 us per step on CPU).
                (t_span[1] - t_span[0]) / per_save if fixed else None,
                y,
                saveat=saveat,
                stepsize_controller=controller,
                solver_state=(solver_state, tracked.reset()),
                controller_state=controller_state,
                max_steps=max_steps,
                throw=False,
            )
            solver_state, errors = sol.solver_state
            final = jax.tree.map(lambda x: x[-1], sol.ys)
            n = sol.stats["num_steps"]
            ok = result == dfx.RESULTS.successful
            # diffrax's Runge-Kutta solvers do not check fixed steps for NaN: a
            # blow-up would otherwise be tabled as a success.
            new = dfx.RESULTS.where(
                (sol.result == dfx.RESULTS.successful) & ~all_finite((errors, final)),
                dfx.RESULTS.nonfinite,
                sol.result,
            )
            result = dfx.RESULTS.where(ok, new, result)
            errors = jax.tree.map(lambda e: jnp.where(ok, e, jnp.nan), errors)
            steps = steps + jnp.where(ok, n, 0)
            meter_state = meter.step(
                meter_state, (t_span[1] - ts[0]) / (ts[-1] - ts[0])
            )
            carry = (
                final,
                solver_state,
                None if fixed else sol.controller_state,
                result,
                steps,
                meter_state,
            )
            return carry, errors

        carry = (
            y0,
            solver_state,
            controller_state,
            dfx.RESULTS.successful,
            jnp.zeros((), int),
            meter.init(),
        )
        spans = jnp.stack([ts[:-1], ts[1:]], axis=1)
        (final, *_, result, steps, meter_state), errors = jax.lax.scan(
            interval, carry, spans
        )
        meter.close(meter_state)
        zero = jax.tree.map(lambda e: jnp.zeros((1,), e.dtype), errors)
        errors = jax.tree.map(lambda z, e: jnp.concatenate([z, e]), zero, errors)
        return errors, final, steps, result

    solve = eqx.filter_jit(jax.vmap(solve) if ensemble else solve)
    jax.block_until_ready(solve(y0))
    start = time.perf_counter()
    errors, final, steps, result = jax.block_until_ready(solve(y0))
    wall_time = time.perf_counter() - start
    if not ensemble:
        errors, final, steps, result = jax.tree.map(
            lambda x: jnp.expand_dims(x, 0), (errors, final, steps, result)
        )
    # diffrax's messages run to paragraphs; a table cell gets the first sentence.
    results = [
        dfx.RESULTS[jax.tree.map(lambda x: x[i], result)].split(". ")[0] or "successful"
        for i in range(steps.shape[0])
    ]
    return Outcome(
        # In the scene's order (energy first), not the sorted order of a JAX dict.
        max_errors={k: np.asarray(errors[k], np.float64) for k in conserved},
        final=jax.tree.map(np.asarray, final),
        steps=int(np.max(steps)),
        wall_time=wall_time,
        results=results,
    )
