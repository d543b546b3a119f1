"""Ensemble throughput: trajectories x steps per second for `jax.vmap` over many
initial conditions, through the study API (`drift(..., ensemble=n)`), on whatever
devices JAX sees (CPU here; a GPU when one is available; several devices shard the
ensemble with `jax.sharding`).

For each solver and ensemble size it prints the throughput and its ratio to the
single-trajectory run, i.e. how much of the batch dimension the hardware turns into
speed. The study times a vmapped `diffeqsolve`, as a user runs one. For StormerVerlet
without compensated summation ("StormerVerlet(plain)") it also prints a vmapped
`diffrax_vi.solve_fixed_steps` of the same solver (the solver's own step in an
unrolled scan, which the study's tracked solve runs in), the same `diffeqsolve` with
the step's check for a non-finite momentum taken out (what that check costs under
`jax.vmap`: a batched result makes the loop's stopping test batched), and two
floors: a bare `jax.vmap` of a `jax.lax.scan` of the kick-drift-kick update, and the
same scan with `unroll=32`.

Run: `python benchmarks/ensemble_throughput.py [--sizes 1,64,1024,4096]`.
"""

import argparse
import time

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

from diffrax_vi import separable_terms, solve_fixed_steps, StormerVerlet  # noqa: E402
from diffrax_vi._solver import stormer_verlet  # noqa: E402
from diffrax_vi.scenes import kepler  # noqa: E402
from diffrax_vi.study import drift, Method  # noqa: E402
from step_cost import add_xla_option, apply_xla_option, versions  # noqa: E402


# The bare scan has no compensated summation; this is its like-for-like solver.
EXTRA = {"StormerVerlet(plain)": Method("StormerVerlet(plain)", StormerVerlet(False))}


def throughput(trajectory, scene, n, steps):
    """Trajectory-steps per second of `jax.vmap(trajectory)` over `n` perturbed
    starts, compiled, one timed call."""
    solve = jax.jit(jax.vmap(trajectory))
    y0s = scene.perturbed(jax.random.key(0), n)
    jax.block_until_ready(solve(y0s))
    start = time.perf_counter()
    jax.block_until_ready(solve(y0s))
    return n * steps / (time.perf_counter() - start)


def bare_trajectory(force, steps, h, unroll=1):
    """A bare `lax.scan` of the uncompensated kick-drift-kick update, `y0` to the
    state after `steps` steps of `h`."""

    def trajectory(y0):
        def step(carry, _):
            q, p = carry
            p = p + 0.5 * h * force(q)
            q = q + h * p
            return (q, p + 0.5 * h * force(q)), None

        return jax.lax.scan(step, y0, length=steps, unroll=unroll)[0]

    return trajectory


def solve_trajectory(terms, solver, steps, h):
    """A plain `diffeqsolve` of `steps` fixed steps of `h`, `y0` to its final state."""

    def trajectory(y0):
        sol = dfx.diffeqsolve(
            terms,
            solver,
            0.0,
            steps * h,
            h,
            y0,
            saveat=dfx.SaveAt(t1=True),
            max_steps=steps,
        )
        return sol.ys

    return trajectory


def bare_scan_throughput(scene, n, steps, h, unroll=1):
    force = jax.grad(lambda q: -scene.lagrangian.potential(0.0, q, None))
    return throughput(bare_trajectory(force, steps, h, unroll), scene, n, steps)


def diffeqsolve_throughput(scene, n, steps, h, checked=True):
    terms = separable_terms(scene.lagrangian)
    trajectory = solve_trajectory(terms, StormerVerlet(False), steps, h)
    if checked:
        return throughput(trajectory, scene, n, steps)
    # For this measurement only: the step reports success whatever its momentum.
    original = stormer_verlet.all_finite
    stormer_verlet.all_finite = lambda _: jnp.array(True)
    try:
        return throughput(trajectory, scene, n, steps)
    finally:
        stormer_verlet.all_finite = original


def fixed_steps_throughput(scene, n, steps, h):
    terms = separable_terms(scene.lagrangian)

    def trajectory(y0):
        sol = solve_fixed_steps(terms, StormerVerlet(False), 0.0, steps * h, h, y0)
        return jax.tree.map(lambda x: x[-1], sol.ys)

    return throughput(trajectory, scene, n, steps)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1,64,1024,4096")
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument(
        "--solvers", default="StormerVerlet(plain),StormerVerlet,MidpointVI,Tsit5"
    )
    add_xla_option(parser)
    args = parser.parse_args()
    print(apply_xla_option(args))
    sizes = [int(s) for s in args.sizes.split(",")]
    scene = kepler()
    periods = args.steps / 200
    print(f"{versions()}, devices: {jax.devices()}")
    print(f"Kepler e=0.6, {args.steps} steps (200 per orbit), float64")
    print(f"{'solver':>14} {'members':>8} {'traj*steps/s':>14} {'vs 1 member':>12}")
    plain = {}
    for name in args.solvers.split(","):
        single = None
        for n in sizes:
            study = drift(
                scene,
                [EXTRA.get(name, name)],
                periods=periods,
                steps_per_period=200,
                n_save=10,
                ensemble=None if n == 1 else n,
            )
            run = study.runs[0]
            throughput = n * run.steps / run.wall_time
            single = single or throughput
            if name == "StormerVerlet(plain)":
                plain[n] = throughput
            print(
                f"{name:>14} {n:>8} {throughput:>14.3e} {throughput / single:>11.1f}x"
                + ("" if run.result == "successful" else f"  ({run.result})")
            )
    h = scene.period / 200
    print(
        "\nStormerVerlet(plain): the study (a vmapped diffeqsolve), the same without "
        "the step's non-finite check, a vmapped solve_fixed_steps, and the floors (a "
        "bare jax.vmap of a lax.scan of the same uncompensated update)"
    )
    print(
        f"{'members':>8} {'study':>10} {'unchecked':>10} {'fixed_steps':>12} "
        f"{'bare scan':>10} {'unroll=32':>10} {'study/bare':>11} "
        f"{'unchecked/bare':>15} {'fixed/bare':>11} {'fixed/unrolled':>15}"
    )
    for n in sizes:
        unchecked = diffeqsolve_throughput(scene, n, args.steps, h, checked=False)
        fixed = fixed_steps_throughput(scene, n, args.steps, h)
        rate = bare_scan_throughput(scene, n, args.steps, h)
        unrolled = bare_scan_throughput(scene, n, args.steps, h, unroll=32)
        study = f"{plain[n]:>10.3e}" if n in plain else f"{'':>10}"
        study_ratio = f"{plain[n] / rate:>10.2f}x" if n in plain else f"{'':>11}"
        print(
            f"{n:>8} {study} {unchecked:>10.3e} {fixed:>12.3e} {rate:>10.3e} "
            f"{unrolled:>10.3e} {study_ratio} {unchecked / rate:>14.2f}x "
            f"{fixed / rate:>10.2f}x {fixed / unrolled:>14.2f}x"
        )
    print(
        "targets: solve_fixed_steps >= 0.5x the bare scan at 1024 members on CPU; "
        ">= 0.5x the unrolled scan at >= 131072 members on a GPU"
    )


if __name__ == "__main__":
    main()
