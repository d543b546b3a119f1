"""Forces and constraints, measured: fitted orders on the damped oscillator (exact
solution), and on the Cartesian pendulum and the four-bar linkage the largest
constraint residuals |g(q)| and |G v| and the energy error over the first and the
last tenth of a long run, for the variational solvers and Tsit5 on the same
`LagrangianTerm` at the same step (the index-reduced ODE). The cost per step of a
constrained step is in `benchmarks/step_cost.py` (these runs save every step).

Run: `python benchmarks/forces_constraints.py [--steps 100000]`; the recorded output
is `benchmarks/results/forces_constraints_cpu.txt`.
"""

import argparse

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import scenes  # noqa: E402


def damped_orders():
    c = 0.2
    term = dvi.LagrangianTerm(
        scenes.OscillatorLagrangian(), force=lambda t, q, v, args: -c * v
    )
    gamma, w, t1 = c / 2, np.sqrt(1 - c**2 / 4), 5.0
    exact = np.exp(-gamma * t1) * (np.cos(w * t1) + gamma / w * np.sin(w * t1))
    y0 = (jnp.array(1.0), jnp.array(0.0))
    print("damped oscillator (c = 0.2), error in q(5) at h = 0.25, 0.125, 0.0625")
    for name, solver in [
        ("MidpointVI", dvi.MidpointVI()),
        ("TrapezoidalVI", dvi.TrapezoidalVI()),
        ("GaussVPRK(2)", dvi.GaussVPRK(2)),
        ("GaussVPRK(3)", dvi.GaussVPRK(3)),
        ("yoshida4(MidpointVI)", dvi.Composition(dvi.MidpointVI(), "yoshida4")),
        ("Tsit5", dfx.Tsit5()),
    ]:
        hs = np.array([0.25, 0.125, 0.0625])
        errors = []
        for h in hs:
            sol = dfx.diffeqsolve(term, solver, 0.0, t1, float(h), y0)
            errors.append(abs(float(sol.ys[0][-1]) - exact))
        slope = np.polyfit(np.log(hs), np.log(errors), 1)[0]
        print(
            f"  {name:<22} order {slope:5.2f}   errors "
            + " ".join(f"{e:.2e}" for e in errors)
        )


def long_run(scene, solver, steps, h):
    energy = scene.conserved()["energy"]
    residuals = scene.invariants

    def record(t, y, args):
        return (
            energy(t, y, args),
            residuals["constraint"](t, y, args),
            residuals["hidden_constraint"](t, y, args),
        )

    @jax.jit
    def run(y0):
        return dfx.diffeqsolve(
            scene.term(),
            solver,
            0.0,
            steps * h,
            h,
            y0,
            saveat=dfx.SaveAt(steps=True, fn=record),
            max_steps=steps,
        )

    sol = run(scene.y0)
    e, g, hidden = (np.abs(np.asarray(x)) for x in sol.ys)
    e = np.abs(np.asarray(sol.ys[0]) - float(sol.ys[0][0]))
    tenth = steps // 10
    return g.max(), hidden.max(), e[:tenth].max(), e[-tenth:].max()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100_000)
    args = parser.parse_args()
    damped_orders()
    for scene, solvers in [
        (
            scenes.cartesian_pendulum(),
            [
                ("TrapezoidalVI (RATTLE)", dvi.TrapezoidalVI()),
                ("MidpointVI", dvi.MidpointVI()),
                (
                    "yoshida4(TrapezoidalVI)",
                    dvi.Composition(dvi.TrapezoidalVI(), "yoshida4"),
                ),
                ("Tsit5", dfx.Tsit5()),
            ],
        ),
        (
            scenes.four_bar(),
            [("MidpointVI", dvi.MidpointVI()), ("Tsit5", dfx.Tsit5())],
        ),
    ]:
        h = scene.period / 50
        print(
            f"\n{scene.name}: {args.steps} steps of period/50; max |g|, max |G v|, "
            "energy error in the first and last tenth"
        )
        for name, solver in solvers:
            try:
                g, hidden, first, last = long_run(scene, solver, args.steps, h)
            except Exception as e:  # the vector field's own error, e.g. after drift
                said = [line for line in str(e).splitlines() if "singular" in line]
                print(f"  {name:<24} failed: {(said or [repr(e)])[0][:150]}")
                continue
            print(
                f"  {name:<24} |g| {g:8.1e}  |Gv| {hidden:8.1e}  energy {first:8.1e} "
                f"-> {last:8.1e}"
            )


if __name__ == "__main__":
    main()
