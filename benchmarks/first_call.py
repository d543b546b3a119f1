"""The first call of a solve: tracing and compiling, each against Tsit5's on the same
term, and each gradient against its forward solve.

Every case runs in a fresh process (as a user's first call does, with no trace
cached by an earlier case), the fastest of `--processes` (3) by its total, as a
single process's compile time moves by up to half from one to the next; a scene's
cases take turns, one process each per round, so that its ratios compare runs made
in the same minutes:
`jax.jit(solve).trace(y0)` is timed as the tracing,
`.lower()` and `.compile()` of the traced program as the compilation. A solve is a
`diffeqsolve` over 100 steps saving only `t1`; a gradient is `jax.grad` of the sum
of its final state with respect to `y0`, under `RecursiveCheckpointAdjoint` and
`ReversibleAdjoint`; Tsit5's gradient (under `RecursiveCheckpointAdjoint`) is the
reference for what diffrax's adjoint costs any solver, and the first calls of diffrax's
own implicit solvers on the same term (`ImplicitEuler`, `Kvaerno5`; forward solves,
and `ImplicitEuler`'s checkpointed gradient) the reference for what an implicit step
costs in diffrax. On Kepler, `MidpointVI` also
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


# (scene, its variational solvers); Tsit5 and diffrax's own implicit solvers
# (`IMPLICIT`) run on the same term for each scene.
SCENES = [
    ("kepler", ["MidpointVI", "MidpointVI/FixedPoint"]),
    ("double_pendulum", ["TrapezoidalVI"]),
    ("free_rigid_body", ["MidpointVI", "LGVI"]),
    ("heavy_top", ["LGVI"]),
    ("four_bar", ["MidpointVI"]),
    ("rigid_double_pendulum", ["TrapezoidalVI"]),
]
# diffrax's implicit solvers: its one-stage method and the one
# its documentation recommends for stiff problems. Their first calls are what
# diffrax's own implicit steps cost, the reference for ours beside Tsit5's.
IMPLICIT = ["ImplicitEuler", "Kvaerno5"]
# The one of them whose checkpointed gradient is measured too: what diffrax's adjoint
# costs an implicit step, beside Tsit5's.
IMPLICIT_GRADIENT = "ImplicitEuler"

CASE = """
import json, re, sys, time
import diffrax as dfx
import jax
import jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi
from diffrax_vi.diagnostics._loops import kernels_outside_loops
from diffrax_vi.study import make_solver

scene_name, solver_name, adjoint = sys.argv[1:]
scene = dvi.scenes.SCENES[scene_name]()
if solver_name == "MidpointVI/FixedPoint":
    solver = dvi.MidpointVI(root_finder=dvi.FixedPoint())
elif solver_name in ("ImplicitEuler", "Kvaerno5"):
    # diffrax's default root finder, with the tolerances a constant step needs
    # (Newton's in this package: sqrt(eps), about 1.5e-8, relative).
    solver = getattr(dfx, solver_name)(root_finder=dfx.VeryChord(rtol=1e-8, atol=1e-8))
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
compiled = lowered.compile()
end = time.perf_counter()
# The optimised program's size, and the fused kernels outside every loop.
text = compiled.as_text()
print(json.dumps(dict(trace=lowered_at - start, lower=compiled_at - lowered_at,
                      compile=end - compiled_at,
                      instructions=len(re.findall(r"^\\s+\\S+ = ", text, re.M)),
                      kernels=kernels_outside_loops(text))))
"""

TIMES = ("trace", "lower", "compile")


def total(run: dict) -> float:
    """A first call's seconds: tracing, lowering and compiling."""
    return sum(run[k] for k in TIMES)


def run_once(case: str, argv: list[str]) -> dict:
    """The times `case` prints last (a JSON object), run as a script with `argv` in
    a fresh process."""
    done = subprocess.run(
        [sys.executable, "-c", case, *argv], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def fastest(case: str, argv: list[str], processes: int, key) -> dict:
    """`run_once` of `case` in `processes` fresh processes: the fastest run by
    `key`."""
    return min((run_once(case, argv) for _ in range(processes)), key=key)


def measure_scene(scene: str, cases: list[tuple[str, str]], processes: int) -> dict:
    """Each `(solver, adjoint)` of `cases` on `scene`, the fastest of `processes`
    fresh processes (by its total). The cases take turns, one process each per
    round, so that the ratios between them compare runs made in the same minutes,
    on a machine whose speed drifts from one minute to the next."""
    runs = {case: [] for case in cases}
    for _ in range(processes):
        for solver, adjoint in cases:
            runs[solver, adjoint].append(run_once(CASE, [scene, solver, adjoint]))
    return {case: min(found, key=total) for case, found in runs.items()}


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
        f"{processes} fresh processes, a scene's cases taking turns"
    )
    print(
        f"{'scene':<21} {'solver':<22} {'trace':>6} {'lower':>6} {'compile':>7} "
        f"{'total':>6}  vs Tsit5 (trace, total)  grad/forward (checkpoint, reversible)"
        "  optimised instructions, kernels outside loops"
    )
    for scene, solvers in [
        (name, solvers) for name, solvers in SCENES if name in chosen
    ]:
        adjoints = ("none", "checkpoint", "reversible")
        cases = [("Tsit5", "none"), ("Tsit5", "checkpoint")]
        cases += [(solver, a) for solver in solvers for a in adjoints]
        cases += [(solver, "none") for solver in IMPLICIT]
        cases += [(IMPLICIT_GRADIENT, "checkpoint")]
        runs = measure_scene(scene, cases, processes)
        tsit5 = runs["Tsit5", "none"]
        t_total = total(tsit5)
        t_grad = total(runs["Tsit5", "checkpoint"])
        print(
            f"{scene:<21} {'Tsit5':<22} {tsit5['trace']:6.2f} {tsit5['lower']:6.2f} "
            f"{tsit5['compile']:7.2f} {t_total:6.2f}"
            f"{'':27}{t_grad / t_total:5.2f}x"
            f"{'':18}{tsit5['instructions']:6d} {tsit5['kernels']:3d}"
        )
        for solver in IMPLICIT:
            theirs = runs[solver, "none"]
            grad = ""
            if solver == IMPLICIT_GRADIENT:
                grad = f"{total(runs[solver, 'checkpoint']) / total(theirs):5.2f}x"
            print(
                f"{scene:<21} {solver:<22} {theirs['trace']:6.2f} "
                f"{theirs['lower']:6.2f} {theirs['compile']:7.2f} "
                f"{total(theirs):6.2f}  {theirs['trace'] / tsit5['trace']:5.2f}x "
                f"{total(theirs) / t_total:5.2f}x{'':12}{grad:>6}{'':18}"
                f"{theirs['instructions']:6d} {theirs['kernels']:3d}"
            )
        for solver in solvers:
            ours = runs[solver, "none"]
            ours_total = total(ours)
            grads = [total(runs[solver, a]) / ours_total for a in adjoints[1:]]
            print(
                f"{scene:<21} {solver:<22} {ours['trace']:6.2f} {ours['lower']:6.2f} "
                f"{ours['compile']:7.2f} {ours_total:6.2f}  "
                f"{ours['trace'] / tsit5['trace']:5.2f}x {ours_total / t_total:5.2f}x"
                f"            {grads[0]:5.2f}x {grads[1]:5.2f}x"
                f"  {ours['instructions']:6d} {ours['kernels']:3d}"
            )
    print(
        "targets: a variational solve's trace + compile <= 1.5x Tsit5's on the same "
        "term (constrained <= 2x); a gradient's <= 2.5x its forward solve's "
        "(Tsit5's and ImplicitEuler's rows: their own checkpointed gradients, for "
        "reference); "
        f"{' and '.join(IMPLICIT)}: diffrax's implicit solvers on the same term "
        "(VeryChord, rtol = atol = 1e-8), for reference"
    )


if __name__ == "__main__":
    main()
