"""Gradients of implicit solves: their backward loops compiled whole, against
optimistix's `ImplicitAdjoint` as the reference.

Each implicit step that Newton's method factorises densely (up to 16 unknowns, and a
constrained step's up to 128) is differentiated by the implicit function theorem with
the forward solves' elimination, unrolled up to 16 unknowns and rolled into a loop
beyond (`_root_finders._implicit_solve`): the rigid double pendulum's steps have 18
unknowns, the 4-link chain's 36. Beyond 16 unknowns an unconstrained step's Newton
solves are matrix-free, and so is its derivative: conjugate gradients on
Jacobian-vector products (the outer solar system's 18 unknowns and a generic chain's
256), on the normal equations where the Jacobian is not symmetric (the bead wire's
32 and 128).
The reference differentiates the same root find with optimistix's default
`ImplicitAdjoint`, whose lineax LU is a LAPACK call and whose solve check is a host
callback: both break the backward loop into kernels dispatched one by one. The
reference is run here by calling the root find without the package's derivative
(what the package did before).

For each scene's default solver: `jax.grad` of the sum of the final state over 400
steps of `diffeqsolve` (RecursiveCheckpointAdjoint), compiled once per variant; the
loop breakers `diffrax_vi.diagnostics.loop_breakers` finds in each; the compile
time; the run time of each (best of 5, taken in turns) and of the forward solve; and
the largest relative difference between the two gradients.

`LinearizedVI` solves one linear system a step, which its gradient differentiates
as a linear solve (`_linear.implicit_lu_solve`, `_linear.krylov_solve`): a
derivative is one more solve of the same system. Its reference differentiates the
same solves through lineax's derivative of its conjugate gradients (whose tangent
and transposed solves check themselves by a host callback) and through the
elimination itself (whose row permutation transposes into a scatter): what the
package did before.

Run: `taskset -c 1 python benchmarks/gradient_loops.py` (recorded:
`results/gradient_loops_cpu.txt`).
"""

import contextlib
import pathlib
import sys
import time

import diffrax as dfx
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import _linear, _root_finders  # noqa: E402
from diffrax_vi._solver import linearized  # noqa: E402
from diffrax_vi.study import make_solver  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from step_cost import best_times  # noqa: E402


CASES = [
    ("kepler", "MidpointVI"),
    ("double_pendulum", "TrapezoidalVI"),
    ("free_rigid_body", "MidpointVI"),
    ("heavy_top", "LGVI"),
    ("four_bar", "MidpointVI"),
    ("rigid_double_pendulum", "TrapezoidalVI"),
    ("rigid_chain", "TrapezoidalVI"),
]
MATRIX_FREE = [
    ("outer_solar_system", lambda: dvi.scenes.outer_solar_system()),
    ("bead_wire", lambda: dvi.scenes.bead_wire()),
    ("bead_wire(128)", lambda: dvi.scenes.bead_wire(128)),
    ("generic chain 256", lambda: generic_chain(256)),
]
LINEARIZED = ["kepler", "henon_heiles", "fpu", "double_pendulum"]
STEPS = 400


class GenericChain(dvi.AbstractLagrangian):
    """A chain with quartic springs written as a plain function of (t, q, v, args),
    fixed at both ends: Newton's method, matrix-free beyond 16 masses."""

    def __call__(self, t, q, v, args):
        r = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return 0.5 * jnp.sum(v**2) - jnp.sum(0.5 * r**2 + 0.25 * r**4)


def generic_chain(n: int) -> dvi.scenes.Scene:
    """`GenericChain` of `n` masses released from rest in three half waves, over a
    period of 20 (time units of its unit springs)."""
    i = jnp.arange(1.0, n + 1.0)
    y0 = (0.1 * jnp.sin(3 * jnp.pi * i / (n + 1)), jnp.zeros(n))
    return dvi.scenes.Scene(
        name=f"generic_chain_{n}", lagrangian=GenericChain(), y0=y0, period=20.0
    )


def reference(find, residual, guess, preconditioner, carry, krylov_tags=None):
    """The root find with optimistix's own `ImplicitAdjoint`."""
    return find(residual, guess, preconditioner, carry)


def lineax_krylov(matvec, rhs, rtol, tags, max_steps, preconditioner=None, guess=None):
    """`_linear.krylov_solve`'s iteration, differentiated by lineax's derivative of
    its own solve."""
    guess = lax.stop_gradient(guess)
    residual = jtu.tree_map(lambda b, a: b - a, rhs, matvec(guess))
    value, result = _linear.krylov_iterate(
        matvec, residual, rtol, tags, max_steps, preconditioner
    )
    return jtu.tree_map(lambda x, g: x + g, value, guess), result


def differentiated_elimination(matvec, matrix, b, unrolled_max):
    """`_linear.implicit_lu_solve`'s elimination, differentiated through."""
    return _linear.dense_lu_solve(matrix, b, unrolled_max)[0]


@contextlib.contextmanager
def patched(module, **values):
    """`module`'s attributes set to `values` for the span of the block (none: the
    package as it is); caches cleared on the way in and out, so that each variant
    is traced afresh."""
    saved = {name: getattr(module, name) for name in values}
    for name, value in values.items():
        setattr(module, name, value)
    jax.clear_caches()
    eqx.clear_caches()
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(module, name, value)
        jax.clear_caches()
        eqx.clear_caches()


def compiled(fn, y0):
    start = time.perf_counter()
    program = jax.jit(fn).lower(y0).compile()
    return program, time.perf_counter() - start


def solve_to_period(scene, solver, adjoint=dfx.RecursiveCheckpointAdjoint()):
    """`final(y0)`, the state after `STEPS` steps of `solver` over the scene's
    period (saving only `t1`), and `loss(y0)`, the sum of that state under
    `adjoint`."""
    term = scene.term()

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

    return final, lambda y0: sum(
        jnp.sum(x) for x in jax.tree.leaves(final(y0, adjoint))
    )


def compare(programs, final, y0):
    """The largest relative difference between the gradients of the two compiled
    `programs`, and their run times and the forward solve's (best of 5, in
    turns)."""
    forward, _ = compiled(final, y0)
    first, second = (program(y0) for program in programs)
    difference = max(
        float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))
        for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second))
    )
    return difference, best_times([*programs, forward], y0, repeats=5)


def measure(scene_name, solver_name, solver, reference_variant, scene=None) -> None:
    """Print one row: the gradient of the scene's solve by `solver` as the package
    takes it and under `reference_variant` (a context manager), compiled and run in
    turns (`scene`: the scene, if not `scene_name`'s default)."""
    scene = dvi.scenes.SCENES[scene_name]() if scene is None else scene
    final, loss = solve_to_period(scene, solver)
    programs, rows = [], []
    for variant in (patched(_root_finders), reference_variant):
        with variant:
            program, seconds = compiled(jax.grad(loss), scene.y0)
        programs.append(program)
        breakers = dvi.diagnostics.loop_breakers(program.as_text())
        rows.append((len(breakers), seconds))
    difference, (t_ours, t_ref, t_forward) = compare(programs, final, scene.y0)
    print(
        f"  {scene_name:16s} {solver_name:14s} breakers {rows[0][0]:2d} vs "
        f"{rows[1][0]:2d}  compile {rows[0][1]:5.1f} vs {rows[1][1]:5.1f} s  "
        f"run {t_ours * 1e3:6.2f} vs {t_ref * 1e3:6.2f} ms "
        f"({t_ref / t_ours:4.1f}x faster; {t_ours / t_forward:4.1f}x forward)  "
        f"gradients differ by {difference:.0e}",
        flush=True,
    )


def main() -> None:
    print(f"jax {jax.__version__}, diffrax {dfx.__version__}, {jax.devices()[0]}")
    print(
        f"gradient of a {STEPS}-step solve (RecursiveCheckpointAdjoint): ours "
        "against optimistix's ImplicitAdjoint; loop breakers, compile s, run ms"
    )
    for scene_name, solver_name in CASES:
        reference_variant = patched(_root_finders, _implicit_solve=reference)
        measure(scene_name, solver_name, make_solver(solver_name), reference_variant)
    print(
        "matrix-free Newton steps (beyond 16 unknowns): ours differentiated by the "
        "Krylov method of the forward solves, against optimistix's ImplicitAdjoint"
    )
    for label, make_scene in MATRIX_FREE:
        reference_variant = patched(_root_finders, _implicit_solve=reference)
        measure(label, "MidpointVI", dvi.MidpointVI(), reference_variant, make_scene())
    print(
        "LinearizedVI (forward velocities): its linear solve differentiated as one, "
        "against lineax's derivative of its conjugate gradients and the elimination "
        "differentiated through"
    )
    for scene_name in LINEARIZED:
        reference_variant = patched(
            linearized,
            krylov_solve=lineax_krylov,
            implicit_lu_solve=differentiated_elimination,
        )
        measure(scene_name, "LinearizedVI", dvi.LinearizedVI(), reference_variant)


if __name__ == "__main__":
    main()
