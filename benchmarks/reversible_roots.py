"""`ReversibleAdjoint`'s backward pass with and without the inverse step's root.

Each backward step rebuilds the state before a step by the inverse step, then
differentiates the forward step from it. A symmetric implicit method knows that
forward step's root from the inverse step's (`root_of_inverse`: the same
velocities, a Gauss method's stages in reverse order, `LGVI`'s velocity 2f/h, a
constrained step's multipliers from the inverse step's momentum projection), and
the adjoint takes it, differentiated by the implicit function theorem there,
instead of solving the step's equations again. The reference solves them again, as
the adjoint did before (and still does with `checkpoint_every`): it is run here by
patching the choice (`_adjoint._takes_inverse_roots`) to "no".

For each case: `jax.grad` of the sum of the final state over 400 steps of
`diffeqsolve`, compiled once per variant in this process (caches cleared between);
the root solves in each program (`optimistix.root_find` calls); the trace and
compile time; the run time of each and of the forward solve (best of 5, in turns);
and the largest relative difference between the two gradients.

Run: `taskset -c 1 python benchmarks/reversible_roots.py` (recorded:
`results/reversible_roots_cpu.txt`).
"""

import pathlib
import sys
import time

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import _adjoint  # noqa: E402
from diffrax_vi.study import make_solver  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from step_cost import best_times  # noqa: E402


CASES = [
    ("kepler", "MidpointVI"),
    ("double_pendulum", "TrapezoidalVI"),
    ("double_pendulum", "GaussVPRK2"),
    ("free_rigid_body", "MidpointVI"),
    ("heavy_top", "LGVI"),
    ("four_bar", "MidpointVI"),
]
STEPS = 400

TAKEN = _adjoint._takes_inverse_roots


def solved_again(solver, terms, back_state, checkpoint_every):
    return False


def main() -> None:
    print(f"jax {jax.__version__}, diffrax {dfx.__version__}, {jax.devices()[0]}")
    print(
        f"gradient of a {STEPS}-step solve (ReversibleAdjoint): the forward steps "
        "taking the inverse step's root against solving again; root solves in the "
        "program, trace + compile s, run ms"
    )
    for scene_name, solver_name in CASES:
        scene = dvi.scenes.SCENES[scene_name]()
        solver, term = make_solver(solver_name), scene.term()

        def final(y0, adjoint=dfx.RecursiveCheckpointAdjoint()):
            return dfx.diffeqsolve(
                term,
                solver,
                0.0,
                scene.period,
                scene.period / STEPS,
                y0,
                args=scene.args,
                saveat=dfx.SaveAt(t1=True),
                adjoint=adjoint,
                max_steps=STEPS,
            ).ys

        def loss(y0):
            ys = final(y0, dvi.ReversibleAdjoint())
            return sum(jnp.sum(x) for x in jax.tree.leaves(ys))

        programs, rows = [], []
        for choice in (TAKEN, solved_again):
            _adjoint._takes_inverse_roots = choice
            jax.clear_caches()
            eqx.clear_caches()
            gradient = jax.grad(loss)
            solves = str(jax.make_jaxpr(gradient)(scene.y0)).count("name=root_find")
            start = time.perf_counter()
            program = jax.jit(gradient).lower(scene.y0).compile()
            rows.append((solves, time.perf_counter() - start))
            programs.append(program)
        _adjoint._takes_inverse_roots = TAKEN
        forward = jax.jit(final).lower(scene.y0).compile()
        taken, again = (program(scene.y0) for program in programs)
        difference = max(
            float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))
            for a, b in zip(jax.tree.leaves(taken), jax.tree.leaves(again))
        )
        t_taken, t_again, t_forward = best_times(
            [*programs, forward], scene.y0, repeats=5
        )
        print(
            f"  {scene_name:16s} {solver_name:14s} root solves {rows[0][0]} vs "
            f"{rows[1][0]}  compile {rows[0][1]:5.2f} vs {rows[1][1]:5.2f} s  "
            f"run {t_taken * 1e3:6.2f} vs {t_again * 1e3:6.2f} ms "
            f"({t_again / t_taken:4.2f}x faster; {t_taken / t_forward:4.1f}x forward)"
            f"  gradients differ by {difference:.0e}",
            flush=True,
        )


if __name__ == "__main__":
    main()
