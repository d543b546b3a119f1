"""What a small matrix product costs a compiled loop on CPU, and what turning XLA's
YNNPACK fusions off would cost a large one: the numbers behind the choice to write the
library's small products as sums rather than set an XLA flag for the whole process.

In two fresh processes, XLA's default and `--xla_cpu_experimental_ynn_fusion_type=`
(no YNNPACK fusion), each at the small-loop threshold `import diffrax_vi` sets:

- a `lax.scan` of 10^5 steps whose body multiplies a 3 x 3 state by a 3 x 9 matrix
  (what a Jacobian makes of a small `R @ x`), the same with the product written as a
  sum, and with a 3 x 3 matrix (never a custom fusion): us per step, and the custom
  fusions `diffrax_vi.diagnostics.compiled_loop_breakers` finds in the loop;
- a 512 x 512 float64 matrix product outside any loop: ms per product.

Run: `taskset -c 1 python benchmarks/loop_fusion.py`.
"""

import json
import os
import subprocess
import sys


OFF = "--xla_cpu_experimental_ynn_fusion_type="


def measure() -> dict:
    import time

    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import diffrax_vi as dvi

    def best(fn, *args, repeats=5):
        jax.block_until_ready(fn(*args))
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            times.append(time.perf_counter() - start)
        return min(times)

    n = 100_000

    def loop(product):
        def run(a, b):
            body = lambda c, _: (jnp.tanh(product(c, b))[:, :3] + c, None)
            return jax.lax.scan(body, a, None, length=n)[0]

        return run

    a = 0.1 * jnp.ones((3, 3))
    out = {}
    for name, product, b in (
        ("3x9 product", jnp.matmul, 0.3 * jnp.ones((3, 9))),
        (
            "3x9 product as a sum",
            lambda c, b: jnp.sum(c[:, :, None] * b[None], axis=1),
            0.3 * jnp.ones((3, 9)),
        ),
        ("3x3 product", jnp.matmul, 0.3 * jnp.ones((3, 3))),
    ):
        fn = jax.jit(loop(product))
        breakers = dvi.diagnostics.compiled_loop_breakers(loop(product), a, b)
        out[name] = (1e6 * best(fn, a, b) / n, len(breakers))
    big = jnp.ones((512, 512))
    out["512x512 product"] = (1e3 * best(jax.jit(lambda x: x @ x), big, repeats=20), 0)
    return out


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        print(json.dumps(measure()))
        return
    results = {}
    for setting, extra in (("default", ""), ("YNN fusion off", OFF)):
        env = dict(os.environ)
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + extra).strip()
        child = subprocess.run(
            [sys.executable, __file__, "--child"],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        results[setting] = json.loads(child.stdout.strip().splitlines()[-1])
    import jax

    print(f"jax {jax.__version__}, cpu; each setting in a fresh process")
    default, off = results["default"], results["YNN fusion off"]
    for name in default:
        unit = "ms per product" if name.startswith("512") else "us per step"
        (t0, k0), (t1, _) = default[name], off[name]
        fusions = "" if name.startswith("512") else f" ({k0} custom fusions in loop)"
        print(
            f"  {name:20s} default {t0:7.3f} {unit}{fusions}, YNN off {t1:7.3f}: "
            f"{t1 / t0:5.2f}x"
        )


if __name__ == "__main__":
    main()
