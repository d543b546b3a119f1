"""Compile time of a solve at one XLA setting: what raising the small-loop threshold
(`diffrax_vi.compile_small_loops_whole`) costs or saves before the first step.

Each case is a `jax.jit` of a `diffeqsolve` saving only `t1`, lowered first, then
compiled once; the time is the compilation alone. A trivial program is compiled
first, so that the backend's start-up is not charged to the first case.

Run: `python benchmarks/compile_cost.py [--xla-default]` (recorded:
`results/compile_cost_cpu.txt`, `results/compile_cost_default_cpu.txt`).
"""

import argparse
import pathlib
import sys
import time

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from step_cost import add_xla_option, apply_xla_option, Chain, Kepler  # noqa: E402


def compile_seconds(terms, solver, y0) -> float:
    @jax.jit
    def solve(y0):
        return dfx.diffeqsolve(
            terms, solver, 0.0, 1.0, 0.01, y0, saveat=dfx.SaveAt(t1=True)
        ).ys

    lowered = solve.lower(y0)
    start = time.perf_counter()
    lowered.compile()
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_xla_option(parser)
    args = parser.parse_args()
    print(f"jax {jax.__version__}, {apply_xla_option(args)}")
    jax.jit(lambda x: x + 1).lower(jnp.zeros(())).compile()
    kepler_y0 = dvi.scenes.kepler(eccentricity=0.6).y0
    chain_y0 = (jnp.sin(jnp.linspace(0, jnp.pi, 64)), jnp.zeros(64))
    pendulum = dvi.scenes.double_pendulum()
    kepler = dvi.LagrangianTerm(Kepler())
    cases = [
        ("MidpointVI, Kepler", kepler, dvi.MidpointVI(), kepler_y0),
        (
            "KahanLi8, Kepler",
            dvi.separable_terms(Kepler()),
            dvi.Composition(dvi.StormerVerlet(), "kahan_li8"),
            kepler_y0,
        ),
        ("Tsit5, Kepler", kepler, dfx.Tsit5(), kepler_y0),
        (
            "MidpointVI, chain (64)",
            dvi.LagrangianTerm(Chain()),
            dvi.MidpointVI(),
            chain_y0,
        ),
        (
            "TrapezoidalVI, double pendulum",
            pendulum.term(),
            dvi.TrapezoidalVI(),
            pendulum.y0,
        ),
    ]
    print("compile time of a diffeqsolve (lowered first), seconds")
    for name, terms, solver, y0 in cases:
        print(f"  {name:<32} {compile_seconds(terms, solver, y0):6.2f} s")


if __name__ == "__main__":
    main()
