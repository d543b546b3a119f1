"""The first call of the functions a user calls outside `jit`, on a solve's saved
states or its start: `diffrax_vi.energy` over 101 states (`jax.vmap`),
`diffrax_vi.velocity` at one, and `diffrax_vi.project_onto_constraints` of a start.

Each is one compiled program (`equinox.filter_jit`); the other column runs the same
function operation by operation (its `__wrapped__`), as it ran before. Every case
runs in a fresh process, the fastest of `--processes` (3) by its first call: the
first call (tracing, compiling and running), then a second call on new arrays of
the same shapes (other states for `energy` and `velocity`; the same start, copied,
for the projection). A trivial program is compiled first, so that the backend's start-up
is not charged to the case.

Run: `python benchmarks/helpers_first_call.py [--processes 3]` (recorded:
`results/helpers_first_call_cpu.txt`).
"""

import argparse
import pathlib
import sys


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from first_call import fastest  # noqa: E402


# (function, scene): for `energy` and `velocity`, scenes whose velocity is not a
# division by the mass; for the projection, a linkage and joined rigid bodies.
CASES = [
    ("energy", "double_pendulum"),
    ("energy", "bead_wire"),
    ("energy", "satellite"),
    ("energy", "four_bar"),
    ("velocity", "double_pendulum"),
    ("velocity", "bead_wire"),
    ("project_onto_constraints", "four_bar"),
    ("project_onto_constraints", "rigid_double_pendulum"),
]

CASE = """
import json, sys, time
import jax
import jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi

name, scene_name, mode = sys.argv[1:]
scene = dvi.scenes.SCENES[scene_name]()
fn = getattr(dvi, name)
if mode == "op by op":
    fn = fn.__wrapped__
if name == "energy":
    saved = lambda s: jax.tree.map(lambda x: jnp.stack([s * x] * 101), scene.y0)
    call = lambda y: jax.vmap(lambda y: fn(scene.lagrangian, 0.0, y, scene.args))(y)
elif name == "velocity":
    saved = lambda s: jax.tree.map(lambda x: s * x, scene.y0)
    call = lambda y: fn(scene.lagrangian, 0.0, y, scene.args)
else:
    saved = lambda s: jax.tree.map(lambda x: x + 0 * s, scene.y0)
    call = lambda y: fn(scene.term(), 0.0, y, scene.args)
first, second = saved(1.0), saved(1.01)
jax.block_until_ready((first, second))
jax.jit(lambda x: x + 1).lower(jnp.zeros(())).compile()
start = time.perf_counter()
jax.block_until_ready(call(first))
middle = time.perf_counter()
jax.block_until_ready(call(second))
end = time.perf_counter()
print(json.dumps(dict(first=middle - start, second=end - middle)))
"""


def measure(name: str, scene: str, mode: str, processes: int) -> dict:
    """The fastest of `processes` fresh processes (by the first call)."""
    return fastest(CASE, [name, scene, mode], processes, lambda run: run["first"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=3)
    processes = parser.parse_args().processes
    print(
        "Functions called outside jit: first and second call, seconds; each case the "
        f"fastest of {processes} fresh processes"
    )
    print(
        f"{'function':<25} {'scene':<22} {'compiled':>8} {'then':>7} "
        f"{'op by op':>8} {'then':>7}  first call, op by op / compiled"
    )
    for name, scene in CASES:
        ours = measure(name, scene, "compiled", processes)
        eager = measure(name, scene, "op by op", processes)
        print(
            f"{name:<25} {scene:<22} {ours['first']:8.2f} {ours['second']:7.3f} "
            f"{eager['first']:8.2f} {eager['second']:7.3f}  "
            f"{eager['first'] / ours['first']:5.1f}x"
        )


if __name__ == "__main__":
    main()
