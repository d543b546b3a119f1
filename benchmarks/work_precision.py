"""Work-precision: max energy error and final global error against wall time, for our
methods and diffrax's Runge-Kutta solvers (fixed steps and PIDController), on Kepler
(e = 0.6) and Henon-Heiles (q0 = (0.1, 0), p0 = (0, 0.5)), over 10^2 and 10^4 periods.

Writes `work_precision.csv`, `work_precision.md` and one PNG per problem and horizon
into `--out` (default `benchmarks/results`). The energy error is sampled at 1000 times
(on step boundaries for fixed steps; interpolated for PIDController). The global error
of Kepler is against its exact solution (Kepler's equation); Henon-Heiles is chaotic
at this energy, so its global error is reported at 10^2 periods only, against Dopri8
at rtol = atol = 1e-13.

Run: `python benchmarks/work_precision.py [--quick]` (minutes to tens of minutes).
"""

import argparse
import csv
import pathlib
import time

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np


jax.config.update("jax_enable_x64", True)
matplotlib.use("Agg")
import diffrax_vi as dvi  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402


class Kepler(dvi.AbstractSeparableLagrangian):
    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        return -1 / jnp.sqrt(jnp.sum(q**2))


class HenonHeiles(dvi.AbstractSeparableLagrangian):
    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        x, y = q[0], q[1]
        return 0.5 * (x**2 + y**2) + x**2 * y - y**3 / 3


E = 0.6
PROBLEMS = {
    "kepler": (
        Kepler(),
        (jnp.array([1 - E, 0.0]), jnp.array([0.0, np.sqrt((1 + E) / (1 - E))])),
    ),
    "henon_heiles": (HenonHeiles(), (jnp.array([0.1, 0.0]), jnp.array([0.0, 0.5]))),
}
PERIOD = 2 * np.pi


def kepler_exact(t):
    """Exact Kepler orbit from pericentre (a = 1, period 2 pi)."""
    mean = np.mod(t, 2 * np.pi)
    ecc = mean.copy()
    for _ in range(50):
        ecc = ecc - (ecc - E * np.sin(ecc) - mean) / (1 - E * np.cos(ecc))
    b = np.sqrt(1 - E**2)
    q = np.array([np.cos(ecc) - E, b * np.sin(ecc)])
    edot = 1 / (1 - E * np.cos(ecc))
    p = np.array([-np.sin(ecc) * edot, b * np.cos(ecc) * edot])
    return q, p


def ours(quick):
    sv = dvi.StormerVerlet()
    spp = [25, 50, 100, 200, 400] if not quick else [50, 200]
    return {
        "StormerVerlet": (sv, [100, 200, 400, 800, 1600] if not quick else [200, 800]),
        "MidpointVI": (dvi.MidpointVI(), [100, 200, 400, 800] if not quick else [400]),
        "yoshida4(SV)": (dvi.Composition(sv, "yoshida4"), spp),
        "kahan_li6(SV)": (dvi.Composition(sv, "kahan_li6"), spp),
        "kahan_li8(SV)": (dvi.Composition(sv, "kahan_li8"), spp),
        "GaussVPRK(2)": (dvi.GaussVPRK(2), spp),
        "GaussVPRK(3)": (dvi.GaussVPRK(3), [25, 50, 100, 200] if not quick else [50]),
    }


def runge_kutta(quick):
    fixed = [50, 100, 200, 400, 800] if not quick else [100, 400]
    tols = [1e-6, 1e-8, 1e-10, 1e-12] if not quick else [1e-8, 1e-11]
    runs = {}
    for name, solver in [
        ("Tsit5", dfx.Tsit5()),
        ("Dopri5", dfx.Dopri5()),
        ("Dopri8", dfx.Dopri8()),
    ]:
        runs[name] = (solver, fixed)
        runs[f"{name}+PID"] = (solver, tols)
    return runs


def run_one(lagrangian, y0, solver, periods, setting, adaptive):
    t1 = PERIOD * periods
    # Partitioned solvers (compositions of StormerVerlet too) take the pair of terms.
    if isinstance(solver.term_structure, tuple):
        terms = dvi.separable_terms(lagrangian)
    else:
        terms = dvi.LagrangianTerm(lagrangian)
    energy = lambda t, y, args: dvi.energy(lagrangian, t, y[0], y[1])
    if adaptive:
        controller = dfx.PIDController(rtol=setting, atol=setting)
        dt0, max_steps, n_steps = PERIOD / 100, 10_000_000, None
    else:
        n_steps = int(setting * periods)
        controller = dfx.ConstantStepSize()
        dt0, max_steps = t1 / n_steps, n_steps + 1
    ts = jnp.linspace(0.0, t1, 1001)
    saveat = dfx.SaveAt(subs=[dfx.SubSaveAt(ts=ts, fn=energy), dfx.SubSaveAt(t1=True)])

    @jax.jit
    def solve(y0):
        sol = dfx.diffeqsolve(
            terms,
            solver,
            0.0,
            t1,
            dt0,
            y0,
            saveat=saveat,
            max_steps=max_steps,
            stepsize_controller=controller,
            throw=False,
        )
        return sol.ys, sol.stats["num_steps"], sol.result

    jax.block_until_ready(solve(y0))
    start = time.perf_counter()
    (energies, final), steps, result = jax.block_until_ready(solve(y0))
    wall = time.perf_counter() - start
    energies = np.asarray(energies)
    final = (np.asarray(final[0][-1]), np.asarray(final[1][-1]))
    ok = result == dfx.RESULTS.successful
    return dict(
        wall_time=wall,
        steps=int(steps),
        energy_error=float(np.max(np.abs(energies - energies[0]))) if ok else np.nan,
        final=final if ok else None,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--quick", action="store_true", help="a small grid")
    parser.add_argument("--horizons", default="100,10000")
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    horizons = [int(h) for h in args.horizons.split(",")]
    rows = []
    for problem, (lagrangian, y0) in PROBLEMS.items():
        for periods in horizons:
            if problem == "kepler":
                exact = kepler_exact(PERIOD * periods)
            elif periods <= 100:
                ref = dfx.diffeqsolve(
                    dvi.LagrangianTerm(lagrangian),
                    dfx.Dopri8(),
                    0.0,
                    PERIOD * periods,
                    0.01,
                    y0,
                    stepsize_controller=dfx.PIDController(rtol=1e-13, atol=1e-13),
                    max_steps=10_000_000,
                )
                exact = (np.asarray(ref.ys[0][-1]), np.asarray(ref.ys[1][-1]))
            else:
                exact = None
            methods = [(n, s, x, False) for n, (s, x) in ours(args.quick).items()]
            methods += [
                (n, s, x, n.endswith("+PID"))
                for n, (s, x) in runge_kutta(args.quick).items()
            ]
            for name, solver, settings, adaptive in methods:
                for setting in settings:
                    r = run_one(lagrangian, y0, solver, periods, setting, adaptive)
                    global_error = (
                        float(
                            np.max(
                                np.abs(
                                    np.concatenate(r["final"]) - np.concatenate(exact)
                                )
                            )
                        )
                        if exact is not None and r["final"] is not None
                        else np.nan
                    )
                    row = dict(
                        problem=problem,
                        periods=periods,
                        method=name,
                        setting=setting,
                        steps=r["steps"],
                        wall_time_s=r["wall_time"],
                        max_energy_error=r["energy_error"],
                        global_error=global_error,
                    )
                    rows.append(row)
                    print(
                        f"{problem} {periods:>6} {name:>15} {setting:>8g} "
                        f"steps {r['steps']:>9} {r['wall_time']:8.3f}s "
                        f"dE {r['energy_error']:.2e} err {global_error:.2e}",
                        flush=True,
                    )
    with open(out / "work_precision.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    for problem in PROBLEMS:
        for periods in horizons:
            subset = [
                r for r in rows if r["problem"] == problem and r["periods"] == periods
            ]
            fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
            for key, ax in zip(("max_energy_error", "global_error"), axes):
                for method in dict.fromkeys(r["method"] for r in subset):
                    pts = [
                        (r["wall_time_s"], r[key])
                        for r in subset
                        if r["method"] == method and np.isfinite(r[key])
                    ]
                    if pts:
                        x, y = zip(*sorted(pts))
                        style = "--" if method.startswith(("Tsit5", "Dopri")) else "-"
                        ax.loglog(x, y, style + "o", ms=3, label=method)
                ax.set_xlabel("wall time (s)")
                ax.set_ylabel(key.replace("_", " "))
                ax.grid(True, which="both", alpha=0.3)
            axes[0].legend(fontsize=7)
            fig.suptitle(f"{problem}, {periods} periods")
            fig.savefig(out / f"work_precision_{problem}_{periods}.png", dpi=110)
            plt.close(fig)


if __name__ == "__main__":
    main()
