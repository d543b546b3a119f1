"""The first call of a solve: tracing and compiling, each against Tsit5's on the same
term, and each gradient against its forward solve.

Every case runs in a fresh process (as a user's first call does, with no trace
cached by an earlier case), the fastest of `--processes` (3) by its total, as a
single process's compile time moves by up to half from one to the next:
`jax.jit(solve).trace(y0)` is timed as the tracing,
`.lower()` and `.compile()` of the traced program as the compilation. A solve is a
`diffeqsolve` over 100 steps saving only `t1`; a gradient is `jax.grad` of the sum
of its final state with respect to `y0`, under `RecursiveCheckpointAdjoint` and
`ReversibleAdjoint`; Tsit5's gradient (under `RecursiveCheckpointAdjoint`) is the
reference for what diffrax's adjoint costs any solver. On Kepler, `MidpointVI` also
runs with `root_finder=FixedPoint()` alone: its default pairs the fixed-point
iteration with a Newton fallback, and the difference is what that fallback costs a
first call. A trivial program is compiled first, so that the backend's start-up is
not charged to the case.

Run: `python benchmarks/first_call.py [--processes 3] [--scenes kepler,four_bar]`
(recorded: `results/first_call_cpu.txt`).
"""

import argparse
import json
import subprocess
import sys


# (scene, its variational solvers); Tsit5 runs on the same term for each scene.
SCENES = [
    ("kepler", ["MidpointVI", "MidpointVI/FixedPoint"]),
    ("double_pendulum", ["TrapezoidalVI"]),
    ("free_rigid_body", ["MidpointVI", "LGVI"]),
    ("heavy_top", ["LGVI"]),
    ("four_bar", ["MidpointVI"]),
    ("rigid_double_pendulum", ["TrapezoidalVI"]),
]

CASE = """
import json, sys, time
import diffrax as dfx
import jax
import jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi
from diffrax_vi.study import make_solver

scene_name, solver_name, adjoint = sys.argv[1:]
scene = dvi.scenes.SCENES[scene_name]()
if solver_name == "MidpointVI/FixedPoint":
    solver = dvi.MidpointVI(root_finder=dvi.FixedPoint())
else:
    solver = make_solver(solver_name)
term = scene.term()
adjoints = {
    "none": dfx.RecursiveCheckpointAdjoint(),
    "checkpoint": dfx.RecursiveCheckpointAdjoint(),
    "reversible": dvi.ReversibleAdjoint(),
}


def solve(y0):
    sol = dfx.diffeqsolve(
        term, solver, 0.0, scene.period, scene.period / 100, y0, args=scene.args,
        saveat=dfx.SaveAt(t1=True), adjoint=adjoints[adjoint], max_steps=128,
    )
    return sol.ys


fn = solve
if adjoint != "none":
    fn = jax.grad(lambda y0: sum(jnp.sum(x) for x in jax.tree.leaves(solve(y0))))
jax.jit(lambda x: x + 1).lower(jnp.zeros(())).compile()
start = time.perf_counter()
traced = jax.jit(fn).trace(scene.y0)
lowered_at = time.perf_counter()
lowered = traced.lower()
compiled_at = time.perf_counter()
lowered.compile()
end = time.perf_counter()
print(json.dumps(dict(trace=lowered_at - start, lower=compiled_at - lowered_at,
                      compile=end - compiled_at)))
"""


def fastest(case: str, argv: list[str], processes: int, key) -> dict:
    """The times `case` prints last (a JSON object), run as a script with `argv` in
    `processes` fresh processes: the fastest run by `key`."""
    runs = []
    for _ in range(processes):
        done = subprocess.run(
            [sys.executable, "-c", case, *argv], capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr[-2000:]
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return min(runs, key=key)


def measure(scene: str, solver: str, adjoint: str, processes: int) -> dict:
    """The fastest of `processes` fresh processes' first calls (by their total)."""
    return fastest(
        CASE, [scene, solver, adjoint], processes, lambda run: sum(run.values())
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=3)
    parser.add_argument(
        "--scenes",
        default=",".join(name for name, _ in SCENES),
        help="comma-separated scenes to measure (default: all)",
    )
    options = parser.parse_args()
    processes, chosen = options.processes, options.scenes.split(",")
    unknown = set(chosen) - {name for name, _ in SCENES}
    if unknown:
        parser.error(f"unknown scenes: {', '.join(sorted(unknown))}")
    print(
        "First call: trace, lower and compile, seconds; each case the fastest of "
        f"{processes} fresh processes"
    )
    print(
        f"{'scene':<21} {'solver':<22} {'trace':>6} {'lower':>6} {'compile':>7} "
        f"{'total':>6}  vs Tsit5 (trace, total)  grad/forward (checkpoint, reversible)"
    )
    for scene, solvers in [
        (name, solvers) for name, solvers in SCENES if name in chosen
    ]:
        tsit5 = measure(scene, "Tsit5", "none", processes)
        t_total = sum(tsit5.values())
        t_grad = sum(measure(scene, "Tsit5", "checkpoint", processes).values())
        print(
            f"{scene:<21} {'Tsit5':<22} {tsit5['trace']:6.2f} {tsit5['lower']:6.2f} "
            f"{tsit5['compile']:7.2f} {t_total:6.2f}"
            f"{'':27}{t_grad / t_total:5.2f}x"
        )
        for solver in solvers:
            ours = measure(scene, solver, "none", processes)
            total = sum(ours.values())
            grads = [
                sum(measure(scene, solver, a, processes).values()) / total
                for a in ("checkpoint", "reversible")
            ]
            print(
                f"{scene:<21} {solver:<22} {ours['trace']:6.2f} {ours['lower']:6.2f} "
                f"{ours['compile']:7.2f} {total:6.2f}  "
                f"{ours['trace'] / tsit5['trace']:5.2f}x {total / t_total:5.2f}x"
                f"            {grads[0]:5.2f}x {grads[1]:5.2f}x"
            )
    print(
        "targets: a variational solve's trace + compile <= 1.5x Tsit5's on the same "
        "term (constrained <= 2x); a gradient's <= 2.5x its forward solve's "
        "(Tsit5's row: its own checkpointed gradient, for reference)"
    )


if __name__ == "__main__":
    main()
