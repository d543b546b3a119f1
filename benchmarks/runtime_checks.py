"""What a Runge-Kutta step on a `LagrangianTerm` pays for the vector field's check,
and equinox's switch that removes it.

Where the momentum alone does not settle the velocity, or a constraint's forces must
be solved (a Lagrangian marked quadratic in `v`, a general one, a mechanism), the
term's vector field checks every evaluation by a host callback
(`eqx.branched_error_if`): the only way a vector field can say why it failed.
XLA on CPU then no longer compiles the time-stepping loop as one function.
Equinox's environment variable `EQX_ON_ERROR=nan`, which diffrax's own checks obey
too, turns every such check into a NaN in the output: no callback, so the loop
compiles whole.

For each scene, diffrax's `Tsit5` and `Dopri8` at a constant step run in fresh
processes with the default (`raise`) and with `EQX_ON_ERROR=nan`, in turns: the
time per step of a plain `diffeqsolve` saving only `t1` (the best of 5 calls after
one to compile), the host callbacks and custom calls that break its loops into
kernels (`diagnostics.loop_breakers`), and how far apart its final states under
the two settings are (in each leaf of the state, relative to its largest entry): the
same arithmetic, fused differently, so round-off grown over the steps. Each figure is
the fastest of `--rounds` (3) processes.

Run: `taskset -c 1 python benchmarks/runtime_checks.py [--rounds 3]`
(recorded: `results/runtime_checks_cpu.txt`).
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np


# (scene, steps): a Lagrangian marked quadratic in v, a planar mechanism, and two
# rigid bodies joined by ball joints (18 coordinates).
SCENES = [
    ("double_pendulum", 20000),
    ("four_bar", 20000),
    ("rigid_double_pendulum", 2000),
]
SOLVERS = ["Tsit5", "Dopri8"]

CASE = """
import json, sys, time
import diffrax as dfx
import jax
import numpy as np
jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi
from diffrax_vi.diagnostics import loop_breakers

scene_name, solver_name, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
scene = dvi.scenes.SCENES[scene_name]()
term, solver = scene.term(), getattr(dfx, solver_name)()
h = scene.period / 200


@jax.jit
def solve(y0):
    sol = dfx.diffeqsolve(
        term, solver, 0.0, h * steps, h, y0, args=scene.args,
        saveat=dfx.SaveAt(t1=True), max_steps=steps,
    )
    return sol.ys


compiled = solve.lower(scene.y0).compile()
final = jax.block_until_ready(compiled(scene.y0))
times = []
for _ in range(5):
    start = time.perf_counter()
    jax.block_until_ready(compiled(scene.y0))
    times.append(time.perf_counter() - start)
print(json.dumps(dict(
    us=min(times) / steps * 1e6,
    breakers=len(loop_breakers(compiled.as_text())),
    final=[np.asarray(x).ravel().tolist() for x in jax.tree.leaves(final)],
)))
"""


def run_once(scene: str, solver: str, steps: int, on_error: str) -> dict:
    """The case's JSON, run in a fresh process with `EQX_ON_ERROR=on_error`."""
    env = dict(os.environ, EQX_ON_ERROR=on_error)
    done = subprocess.run(
        [sys.executable, "-c", CASE, scene, solver, str(steps)],
        capture_output=True,
        text=True,
        env=env,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    rounds = parser.parse_args().rounds
    print(
        "Runge-Kutta on a LagrangianTerm whose vector field checks every evaluation: "
        f"us per step, the fastest of {rounds} fresh processes, the two settings "
        "taking turns"
    )
    print(
        f"{'scene':<22} {'solver':<7} {'checked (raise)':>16} {'EQX_ON_ERROR=nan':>17}"
        f" {'ratio':>7}  loop breakers (raise, nan), final states apart"
    )
    for scene, steps in SCENES:
        for solver in SOLVERS:
            runs = {"raise": [], "nan": []}
            for k in range(rounds):
                order = ("raise", "nan") if k % 2 == 0 else ("nan", "raise")
                for on_error in order:
                    runs[on_error].append(run_once(scene, solver, steps, on_error))
            best = {k: min(v, key=lambda r: r["us"]) for k, v in runs.items()}
            # The same arithmetic in both programs, fused differently by XLA: the
            # same final state up to round-off grown over the steps.
            # Each leaf's difference over its largest entry: in any units.
            apart = max(
                np.max(np.abs(np.subtract(a, b))) / np.max(np.abs(a))
                for a, b in zip(best["raise"]["final"], best["nan"]["final"])
            )
            assert apart < 1e-6, (scene, solver, apart)
            raised, nan = best["raise"]["us"], best["nan"]["us"]
            print(
                f"{scene:<22} {solver:<7} {raised:13.3f} us {nan:14.3f} us "
                f"{raised / nan:6.2f}x  {best['raise']['breakers']}, "
                f"{best['nan']['breakers']:<4} {apart:.1e}"
            )


if __name__ == "__main__":
    main()
