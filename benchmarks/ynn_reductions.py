"""Reductions inside compiled loops on CPU, under XLA's default and with YNNPACK kept
to matrix products.

XLA on CPU hands a floating-point reduction of 4096 or more elements (with the
elementwise operations that feed it) to YNNPACK as a custom fusion, and a loop that
contains a custom fusion runs as a sequence of separately dispatched kernels. The
solvers' own finiteness check counts finite entries in an integer sum, which XLA
keeps; a user's vector field may still hold such a reduction: Kepler's force sums
`q**2`, and in an ensemble of 4096 orbits (`jax.vmap`) that sum has 8192 elements.
`XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=dot` keeps YNNPACK for matrix
products only, for the whole process.

Each setting runs in a fresh process (XLA reads `XLA_FLAGS` once): time per step of
loops (Kepler ensembles of 1024 and 4096 orbits, a 4096-mass chain, each with its
bare `lax.scan`) with the custom fusions found in their loops, and the time of large
operations outside any loop (what the flag costs the rest of a program). Both
settings keep the small-loop threshold that `import diffrax_vi` sets.

Run: `taskset -c 1 python benchmarks/ynn_reductions.py [--repeats 7]`.
"""

import argparse
import json
import os
import subprocess
import sys


DOT_ONLY = "--xla_cpu_experimental_ynn_fusion_type=dot"


def child(repeats: int) -> None:
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import diffrax_vi as dvi
    from diffrax_vi.diagnostics import loop_breakers
    from ensemble_throughput import bare_trajectory, solve_trajectory
    from step_cost import best_time, Chain

    scene = dvi.scenes.kepler()
    h = scene.period / 200
    force = jax.grad(lambda q: -scene.lagrangian.potential(0.0, q, None))

    rows = []

    def loop(name, f, y0, steps):
        compiled = jax.jit(f).lower(y0).compile()
        breakers = len(loop_breakers(compiled.as_text()))
        t = best_time(compiled, y0, repeats=repeats)
        rows.append((name, 1e6 * t / steps, "us per step", breakers))

    for members in (1024, 4096):
        y0 = scene.perturbed(jax.random.key(0), members)
        pair = dvi.separable_terms(scene.lagrangian)
        term = dvi.LagrangianTerm(scene.lagrangian)
        name = f"{members} Kepler orbits (vmap)"
        loop(
            f"{name}, StormerVerlet(plain)",
            jax.vmap(solve_trajectory(pair, dvi.StormerVerlet(False), 2000, h)),
            y0,
            2000,
        )
        bare = jax.vmap(bare_trajectory(force, 2000, h))
        loop(f"{name}, its bare scan", bare, y0, 2000)
        loop(
            f"{name}, MidpointVI",
            jax.vmap(solve_trajectory(term, dvi.MidpointVI(), 200, h)),
            y0,
            200,
        )
    chain = Chain()
    chain_force = jax.grad(lambda q: -chain.potential(0.0, q, None))
    y0 = (jnp.sin(jnp.linspace(0, jnp.pi, 4096)), jnp.zeros(4096))
    pair = dvi.separable_terms(chain)
    steps = solve_trajectory(pair, dvi.StormerVerlet(), 2000, 0.02)
    loop("4096-mass chain, StormerVerlet", steps, y0, 2000)
    bare = bare_trajectory(chain_force, 2000, 0.02)
    loop("4096-mass chain, its bare scan", bare, y0, 2000)

    x = jnp.linspace(0.0, 1.0, 1 << 20)
    a = jnp.linspace(0.0, 1.0, 1 << 22).reshape(2048, 2048)
    m = a[:512, :512]
    standalone = {
        "sum(x * x), 2^20 elements": (lambda x: jnp.sum(x * x), x),
        "max |x|, 2^20 elements": (lambda x: jnp.max(jnp.abs(x)), x),
        "row sums of a * a, 2048 x 2048": (lambda a: jnp.sum(a * a, axis=1), a),
        "softmax over rows, 2048 x 2048": (lambda a: jax.nn.softmax(a, axis=-1), a),
        "exp(a), 2048 x 2048": (jnp.exp, a),
        "m @ m, 512 x 512": (lambda m: m @ m, m),
    }
    for name, (f, arg) in standalone.items():
        compiled = jax.jit(f).lower(arg).compile()
        rows.append((name, 1e3 * best_time(compiled, arg, repeats=repeats), "ms", None))
    print(json.dumps(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.repeats)
        return
    results = {}
    for setting, flags in (("default", ""), ("dot only", DOT_ONLY)):
        env = dict(os.environ)
        env["XLA_FLAGS"] = " ".join(f for f in (env.get("XLA_FLAGS", ""), flags) if f)
        out = subprocess.run(
            [sys.executable, __file__, "--child", "--repeats", str(args.repeats)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
            cwd=os.path.dirname(os.path.abspath(__file__)),
        )
        results[setting] = json.loads(out.stdout.strip().splitlines()[-1])
    import jax

    print(
        f"jax {jax.__version__}, float64, best of {args.repeats}; each column a fresh"
    )
    print(f"process: XLA's default, and XLA_FLAGS={DOT_ONLY} (YNNPACK for dot only)")
    print(
        f"{'':46s} {'default':>11s} {'dot only':>11s} {'ratio':>7s}   "
        "custom fusions in the loops (default / dot only)"
    )
    for (name, ours, unit, breakers), (_, other, _, other_breakers) in zip(
        results["default"], results["dot only"]
    ):
        fusions = "" if breakers is None else f"   {breakers} / {other_breakers}"
        print(
            f"{name:46s} {ours:8.3f} {unit[:2]:2s} {other:8.3f} {unit[:2]:2s} "
            f"{other / ours:6.2f}x{fusions}"
        )
    print(
        "(ratio: dot only / default; time per step of the whole ensemble, or of one "
        "call outside any loop)"
    )


if __name__ == "__main__":
    main()
