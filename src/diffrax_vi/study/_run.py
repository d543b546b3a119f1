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


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What one method's solve of one scene (or one ensemble of it) produced, as
    NumPy arrays with ensemble members along a leading axis (of size 1 for a single
    solve)."""

    invariants: dict[str, np.ndarray]
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
        """`|I(t) - I(0)|` per invariant at each save time: the largest over the
        components of a vector invariant and over ensemble members."""
        out = {}
        for name, values in self.invariants.items():
            err = np.abs(values - values[:, :1])
            out[name] = err.reshape(*err.shape[:2], -1).max(axis=(0, 2))
        return out


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
    """Solve `scene` from `y0` with `method` to `t1`, streaming the conserved
    quantities at `n_save + 1` equally spaced times through `SaveAt(fn=...)` and
    keeping the final state. Fixed steps take exactly `n_steps` (which `n_save` must
    divide) and save every `n_steps / n_save` steps; adaptive ones start at step
    `t1 / n_steps` and save by interpolation. With `ensemble=True`, `y0` has a leading
    axis of members and the solve is vmapped over it (and runs on every device `y0`
    is sharded over). Wall time is of a second, compiled, call."""
    conserved = scene.conserved()

    def invariants(t, y, args):
        return {k: f(t, y, args) for k, f in conserved.items()}

    # Saving every k-th step costs nothing per step; `SaveAt(ts=...)` interpolates
    # and costs ~0.25 us a step plus more per save time (diffrax 0.7), 10x the whole
    # step of StormerVerlet on Kepler. Adaptive steps have no other choice.
    if method.rtol is None:
        every = dfx.SubSaveAt(t0=True, steps=n_steps // n_save, fn=invariants)
        max_steps = n_steps + 1
    else:
        ts = jnp.linspace(0, t1, n_save + 1, dtype=dtype)
        every = dfx.SubSaveAt(ts=ts, fn=invariants)
        max_steps = 10_000_000
    saveat = dfx.SaveAt(subs=[every, dfx.SubSaveAt(t1=True)])
    terms = method.terms(scene)
    controller = method.controller()
    meter = dfx.TqdmProgressMeter() if progress else dfx.NoProgressMeter()

    def solve(y0):
        sol = dfx.diffeqsolve(
            terms,
            method.solver,
            jnp.zeros((), dtype),
            jnp.asarray(t1, dtype),
            jnp.asarray(t1 / n_steps, dtype),
            y0,
            saveat=saveat,
            stepsize_controller=controller,
            max_steps=max_steps,
            throw=False,
            progress_meter=meter,
        )
        invariants, final = sol.ys
        # `max_steps = n_steps + 1` leaves one padded slot when saving every step.
        invariants = jax.tree.map(lambda x: x[: n_save + 1], invariants)
        final = jax.tree.map(lambda x: x[-1], final)
        # diffrax's Runge-Kutta solvers do not check fixed steps for NaN: a blow-up
        # would otherwise be tabled as a success.
        finite = all_finite((invariants, final))
        result = dfx.RESULTS.where(
            (sol.result == dfx.RESULTS.successful) & ~finite,
            dfx.RESULTS.nonfinite,
            sol.result,
        )
        return invariants, final, sol.stats["num_steps"], result

    solve = eqx.filter_jit(jax.vmap(solve) if ensemble else solve)
    jax.block_until_ready(solve(y0))
    start = time.perf_counter()
    invariants, final, steps, result = jax.block_until_ready(solve(y0))
    wall_time = time.perf_counter() - start
    if not ensemble:
        invariants, final, steps, result = jax.tree.map(
            lambda x: jnp.expand_dims(x, 0), (invariants, final, steps, result)
        )
    # diffrax's messages run to paragraphs; a table cell gets the first sentence.
    results = [
        dfx.RESULTS[jax.tree.map(lambda x: x[i], result)].split(". ")[0] or "successful"
        for i in range(steps.shape[0])
    ]
    return Outcome(
        # In the scene's order (energy first), not the sorted order of a JAX dict.
        invariants={k: np.asarray(invariants[k], np.float64) for k in conserved},
        final=jax.tree.map(np.asarray, final),
        steps=int(np.max(steps)),
        wall_time=wall_time,
        results=results,
    )
