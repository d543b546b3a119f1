"""Per-step cost of LinearizedVI (one linear solve) over MidpointVI (Newton) on a
nonlinear chain, as ratios measured in one run.

Run: `python benchmarks/linearized_cost.py`.
"""

import pathlib
import sys
import time

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from step_cost import Chain  # noqa: E402


def per_step(solver, y0, h, n, repeats=3):
    f = jax.jit(
        lambda y: (
            dfx.diffeqsolve(
                dvi.LagrangianTerm(Chain()),
                solver,
                0.0,
                h * n,
                h,
                y,
                saveat=dfx.SaveAt(t1=True),
                max_steps=n,
            ).ys
        )
    )
    jax.block_until_ready(f(y0))
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f(y0))
        best = min(best, time.perf_counter() - start)
    return 1e6 * best / n


def main():
    print(f"device {jax.devices()[0]}")
    for dof, n in [(32, 4000), (64, 2000)]:
        y0 = (jnp.sin(jnp.linspace(0, jnp.pi, dof)), jnp.zeros(dof))
        h = 0.02
        mid = per_step(dvi.MidpointVI(), y0, h, n)
        fwd = per_step(dvi.LinearizedVI(), y0, h, n)
        cen = per_step(dvi.LinearizedVI(velocity="centered"), y0, h, n)
        print(f"\nchain, {dof} DOF, {n} steps, per step:")
        print(f"  MidpointVI               {mid:9.2f} us")
        print(
            f"  LinearizedVI forward     {fwd:9.2f} us   ({fwd / mid:.2f}x MidpointVI)"
        )
        print(
            f"  LinearizedVI centered    {cen:9.2f} us   ({cen / mid:.2f}x MidpointVI)"
        )


if __name__ == "__main__":
    main()
