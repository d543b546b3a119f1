"""Per-step cost of LinearizedVI (one linear solve) over MidpointVI (Newton) on a
nonlinear chain, as ratios measured in one run; and, for small systems, its solve by
dense elimination (the default up to `LINEARIZED_DENSE_MAX` unknowns where the
matrix is symmetric) against conjugate gradients, which take the larger ones.

Run: `python benchmarks/linearized_cost.py` (recorded:
`results/linearized_cost_cpu.txt`).
"""

import pathlib
import sys
import time

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi._solver import linearized  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from step_cost import Chain  # noqa: E402


def per_step(solver, y0, h, n, repeats=3, term=None, args=None):
    term = dvi.LagrangianTerm(Chain()) if term is None else term
    f = jax.jit(
        lambda y: (
            dfx.diffeqsolve(
                term,
                solver,
                0.0,
                h * n,
                h,
                y,
                args,
                saveat=dfx.SaveAt(t1=True),
                max_steps=n,
                throw=False,
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


def small_systems(n=4000):
    """LinearizedVI's step on small symmetric systems, its solve by dense
    elimination against conjugate gradients (each forced through
    `LINEARIZED_DENSE_MAX`), in turns."""
    default = linearized.LINEARIZED_DENSE_MAX
    print(
        f"\nsmall symmetric systems, {n} steps, per step (dense elimination up to "
        f"{default} unknowns by default):"
    )
    cases = []
    for name in ("oscillator", "kepler", "henon_heiles"):
        scene = dvi.scenes.SCENES[name]()
        cases.append((name, scene.term(), scene.y0, scene.period / 200, scene.args))
    for dof in (3, 4, 6, 8):
        y0 = (jnp.sin(jnp.linspace(0, jnp.pi, dof)), jnp.zeros(dof))
        cases.append((f"chain, {dof} DOF", dvi.LagrangianTerm(Chain()), y0, 0.02, None))
    try:
        for name, term, y0, h, args in cases:
            times = {}
            for label, limit in (("dense", 10**9), ("CG", 0)):
                linearized.LINEARIZED_DENSE_MAX = limit
                jax.clear_caches()  # diffeqsolve's trace read the limit
                times[label] = per_step(dvi.LinearizedVI(), y0, h, n, 5, term, args)
            dense, cg = times["dense"], times["CG"]
            print(
                f"  {name:<14} dense {dense:7.3f} us   CG {cg:7.3f} us"
                f"   ({dense / cg:.2f}x)"
            )
    finally:
        linearized.LINEARIZED_DENSE_MAX = default


def main():
    print(f"device {jax.devices()[0]}")
    small_systems()
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
