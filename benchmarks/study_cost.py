"""What a drift study adds to the cost of a step: per-step wall time on Kepler (e = 0.6,
200 steps per orbit) of

- a bare `diffeqsolve` saving only `t1` (the solver's own cost, as in `step_cost.py`);
- the drift study's own solve (`diffrax_vi.study.drift`), which takes every invariant's
  error after every step and keeps the largest per save interval (one per orbit) in
  the solver state (the study reports the wall time of a separate plain solve);
- the same maximum taken instead from every step's errors saved through
  `SaveAt(steps=True, fn=...)` (one solve, a buffer write per step);
- the study's solve tracking a constant instead of the invariants: the cost of the
  running maxima alone, without evaluating the invariants.

Prints the ratios of the last three to the first. Pin it to one core for stable figures.

Run: `taskset -c 1 python benchmarks/study_cost.py [--orbits 1000]`.
"""

import argparse

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)
from diffrax_vi import StormerVerlet  # noqa: E402
from diffrax_vi.scenes import kepler  # noqa: E402
from diffrax_vi.study import make_solver, Method  # noqa: E402
from diffrax_vi.study._track import max_error, TrackWorstError  # noqa: E402
from step_cost import add_xla_option, apply_xla_option, best_time  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--orbits", type=int, default=1000)
    parser.add_argument(
        "--solvers", default="StormerVerlet(plain),StormerVerlet,MidpointVI,Tsit5"
    )
    add_xla_option(parser)
    args = parser.parse_args()
    print(apply_xla_option(args))
    scene = kepler()
    steps = 200 * args.orbits
    h = scene.period / 200
    conserved = scene.conserved()
    start = {k: f(0.0, scene.y0, None) for k, f in conserved.items()}
    ts = jnp.linspace(0.0, steps * h, args.orbits + 1)  # one interval per orbit

    def errors(t, y, args):
        return {k: max_error(f(t, y, args), start[k]) for k, f in conserved.items()}

    per_step = 1e6 / steps
    print(f"Kepler e=0.6, {steps} steps, float64, us per step (best of 3)")
    print(
        f"{'solver':>20} {'t1 only':>9} {'study':>9} {'per-step save':>14}"
        f" {'track a constant':>16}"
    )
    for name in args.solvers.split(","):
        solver = (
            StormerVerlet(compensated=False)
            if name == "StormerVerlet(plain)"
            else make_solver(name)
        )
        method = Method(name, solver)
        terms = method.terms(scene)

        def solve_with(solver, y0, saveat, max_steps=steps):
            return dfx.diffeqsolve(
                terms, solver, 0.0, steps * h, h, y0, saveat=saveat, max_steps=max_steps
            )

        solve = lambda y0, saveat: solve_with(solver, y0, saveat)

        bare = per_step * best_time(
            jax.jit(lambda y0: solve(y0, dfx.SaveAt(t1=True)).ys), scene.y0, repeats=3
        )
        saved = per_step * best_time(
            jax.jit(
                lambda y0: jax.tree.map(
                    jnp.max, solve(y0, dfx.SaveAt(steps=True, fn=errors)).ys
                )
            ),
            scene.y0,
            repeats=3,
        )

        def tracking(conserved, start):
            tracked = TrackWorstError(
                solver, conserved, start, ts[1:], steps_per_interval=200
            )
            return per_step * best_time(
                jax.jit(
                    lambda y0: (
                        solve_with(
                            tracked, y0, dfx.SaveAt(t1=True, solver_state=True)
                        ).solver_state
                    )
                ),
                scene.y0,
                repeats=3,
            )

        # The study's own solve (its reported wall time is of the plain solve), and
        # the same tracking of a constant in place of the invariants: what the
        # running maxima cost without evaluating anything.
        study = tracking(conserved, start)
        constant = {"zero": lambda t, y, args: jnp.zeros(())}
        machinery = tracking(constant, {"zero": jnp.zeros(())})
        print(
            f"{name:>20} {bare:>9.3f} {study:>9.3f} {saved:>14.3f} {machinery:>16.3f}"
            f"   study/bare {study / bare:5.2f}x   save/bare {saved / bare:5.2f}x"
            f"   constant/bare {machinery / bare:5.2f}x"
        )


if __name__ == "__main__":
    main()
