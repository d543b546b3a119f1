"""`ReversibleAdjoint`'s backward pass with and without the inverse step's root.

Each backward step rebuilds the state before a step by the inverse step, then
differentiates the forward step from it. A symmetric implicit method knows that
forward step's root from the inverse step's (`root_of_inverse`: the same
velocities, a Gauss method's stages in reverse order, `LGVI`'s velocity 2f/h, a
constrained step's multipliers from the inverse step's momentum projection), and
the adjoint takes it, differentiated by the implicit function theorem there (by
the forward solves' dense elimination, or beyond 16 unknowns matrix-free, as
Newton's method solves them), instead of solving the step's equations again. The
reference solves them again, as the adjoint did before (and still does with
`checkpoint_every`; beyond 16 unknowns, before the matrix-free derivative of a
known root): it is run here by patching the choice
(`_adjoint._takes_inverse_roots`) to "no".

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

import diffrax as dfx
import equinox as eqx
import jax


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import _adjoint  # noqa: E402
from diffrax_vi.study import make_solver  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from gradient_loops import (  # noqa: E402
    compare,
    compiled,
    generic_chain,
    solve_to_period,
    STEPS,
)


CASES = [
    ("kepler", "MidpointVI"),
    ("double_pendulum", "TrapezoidalVI"),
    ("double_pendulum", "GaussVPRK2"),
    ("free_rigid_body", "MidpointVI"),
    ("heavy_top", "LGVI"),
    ("four_bar", "MidpointVI"),
    ("rigid_double_pendulum", "TrapezoidalVI"),
    # Beyond 16 unknowns, unconstrained: Newton's solves and the root's derivative
    # are matrix-free (conjugate gradients; on the normal equations for the bead
    # wire, whose Jacobian is not symmetric).
    ("outer_solar_system", "MidpointVI"),
    ("bead_wire", "MidpointVI"),
    ("generic chain 256", "MidpointVI"),
]
SCENES = {"generic chain 256": lambda: generic_chain(256)}
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
        scene = SCENES.get(scene_name, dvi.scenes.SCENES.get(scene_name))()
        final, loss = solve_to_period(
            scene, make_solver(solver_name), dvi.ReversibleAdjoint()
        )
        programs, rows = [], []
        for choice in (TAKEN, solved_again):
            _adjoint._takes_inverse_roots = choice
            jax.clear_caches()
            eqx.clear_caches()
            gradient = jax.grad(loss)
            solves = str(jax.make_jaxpr(gradient)(scene.y0)).count("name=root_find")
            program, seconds = compiled(gradient, scene.y0)
            rows.append((solves, seconds))
            programs.append(program)
        _adjoint._takes_inverse_roots = TAKEN
        difference, (t_taken, t_again, t_forward) = compare(programs, final, scene.y0)
        print(
            f"  {scene_name:21s} {solver_name:14s} root solves {rows[0][0]} vs "
            f"{rows[1][0]}  compile {rows[0][1]:5.2f} vs {rows[1][1]:5.2f} s  "
            f"run {t_taken * 1e3:6.2f} vs {t_again * 1e3:6.2f} ms "
            f"({t_again / t_taken:4.2f}x faster; {t_taken / t_forward:4.1f}x forward)"
            f"  gradients differ by {difference:.0e}",
            flush=True,
        )


if __name__ == "__main__":
    main()
