"""What a drift study adds to the cost of a step: per-step wall time on Kepler
(e = 0.6, 200 steps per orbit) of

- a plain `diffeqsolve` saving only `t1` (what a user's solve costs, as in
  `step_cost.py`);
- the study's own two solves, compiled by `diffrax_vi.study`'s `prepare` as the drift
  study compiles them: the `plain` one, whose wall time the study reports (a
  `diffeqsolve`, as a user's), and the `tracked` one, which takes every invariant's
  error after every step and keeps the largest per save interval (one per orbit) in
  the solver state (fixed steps in `solve_fixed_steps`'s scan, which skips
  `diffeqsolve`'s general loop);
- the same maxima taken instead from every step's errors saved through
  `SaveAt(steps=True, fn=...)` (one `diffeqsolve`, a buffer write per step).

Prints the ratios of the tracked solve to the study's plain one, and of the study's
plain solve to the plain `diffeqsolve`. Pin it to one core for stable figures.

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
from diffrax_vi.study._run import prepare  # noqa: E402
from diffrax_vi.study._track import max_error  # noqa: E402
from step_cost import add_xla_option, apply_xla_option, best_times  # noqa: E402


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

    def errors(t, y, args):
        return {k: max_error(f(t, y, args), start[k]) for k, f in conserved.items()}

    per_step = 1e6 / steps
    print(f"Kepler e=0.6, {steps} steps, float64, us per step (best of 3, in turns)")
    print(
        f"{'solver':>20} {'diffeqsolve':>11} {'study plain':>11} {'tracked':>9}"
        f" {'per-step save':>14}"
    )
    for name in args.solvers.split(","):
        solver = (
            StormerVerlet(compensated=False)
            if name == "StormerVerlet(plain)"
            else make_solver(name)
        )
        method = Method(name, solver)
        terms = method.terms(scene)

        def solve(y0, saveat):
            return dfx.diffeqsolve(
                terms, solver, 0.0, steps * h, h, y0, saveat=saveat, max_steps=steps
            )

        bare = jax.jit(lambda y0: solve(y0, dfx.SaveAt(t1=True)).ys)
        saved = jax.jit(
            lambda y0: jax.tree.map(
                jnp.max, solve(y0, dfx.SaveAt(steps=True, fn=errors)).ys
            )
        )
        study = prepare(
            scene,
            method,
            t1=steps * h,
            n_steps=steps,
            n_save=args.orbits,
            dtype=jnp.float64,
            y0=scene.y0,
        )
        times = best_times(
            [bare, study.plain, study.tracked, saved], scene.y0, repeats=3
        )
        bare, plain, tracked, saved = (per_step * t for t in times)
        print(
            f"{name:>20} {bare:>11.3f} {plain:>11.3f} {tracked:>9.3f} {saved:>14.3f}"
            f"   tracked/plain {tracked / plain:5.2f}x"
            f"   plain/diffeqsolve {plain / bare:5.2f}x"
        )


if __name__ == "__main__":
    main()
