"""Stability at the extremes: the figures and tables of docs/stability.md.

1. Linear stability on the harmonic oscillator: the spectral radius of every solver's
   step matrix against omega * h, and each stability limit.
2. The round-off floor: global error of the pendulum at T = 1 against the step, down
   to h = 1e-6.

Writes PNGs into `--out` (default `docs/images`) and prints Markdown tables.
Run: `python examples/stability.py` (about two minutes).
"""

import argparse
import math
import pathlib

import diffrax as dfx
import jax
import matplotlib
import numpy as np


jax.config.update("jax_enable_x64", True)
matplotlib.use("Agg")
import diffrax_vi as dvi  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
from diffrax_vi.scenes import pendulum  # noqa: E402
from diffrax_vi.study import reference_state  # noqa: E402


SV = dvi.StormerVerlet()
SOLVERS = {
    "MidpointVI": dvi.MidpointVI(),
    "GaussVPRK(2)": dvi.GaussVPRK(2),
    "StormerVerlet / TrapezoidalVI": SV,
    "LobattoVPRK(3)": dvi.LobattoVPRK(3),
    "yoshida4(SV)": dvi.Composition(SV, "yoshida4"),
    "suzuki4(SV)": dvi.Composition(SV, "suzuki4"),
    "kahan_li6(SV)": dvi.Composition(SV, "kahan_li6"),
    "kahan_li8(SV)": dvi.Composition(SV, "kahan_li8"),
    "LinearizedVI (midpoint rule)": dvi.LinearizedVI(velocity="centered"),
    "LinearizedVI (trapezoidal rule)": dvi.LinearizedVI(
        velocity="centered", discrete_lagrangian=dvi.TrapezoidalRule()
    ),
    "Tsit5": dfx.Tsit5(),
    "Dopri8": dfx.Dopri8(),
}


def linear_stability(out):
    grid = np.linspace(0.01, 6, 600)
    fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
    lines = [
        "| solver | stability limit (ωh) | spectral radius at ωh = 1 | at ωh = 4 |",
        "|---|---|---|---|",
    ]
    for name, solver in SOLVERS.items():
        radius = dvi.diagnostics.spectral_radius(solver, grid)
        limit = dvi.diagnostics.stability_limit(solver)
        at = dvi.diagnostics.spectral_radius(solver, [1.0, 4.0])
        style = "--" if name in ("Tsit5", "Dopri8") else "-"
        ax.semilogy(grid, radius, style, label=name)
        lines.append(
            f"| {name} | {'∞' if math.isinf(limit) else f'{limit:.4f}'} | "
            f"{at[0]:.6f} | {at[1]:.3g} |"
        )
    ax.set_xlabel("ω h")
    ax.set_ylabel("spectral radius of one step")
    ax.set_ylim(0.5, 20)
    ax.axhline(1, color="k", lw=0.5)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("Linear stability on the harmonic oscillator")
    fig.savefig(out / "stability_radius.png", dpi=110)
    plt.close(fig)
    return lines


def round_off_floor(out):
    scene = pendulum()
    exact = reference_state(scene, 1.0)  # Dopri8 at rtol = atol = 1e-13
    methods = {
        "MidpointVI": dvi.MidpointVI(),
        "MidpointVI (plain sum)": dvi.MidpointVI(compensated=False),
        "LinearizedVI centered": dvi.LinearizedVI(velocity="centered"),
        "LinearizedVI centered (plain sum)": dvi.LinearizedVI(
            velocity="centered", compensated=False
        ),
        "LinearizedVI forward": dvi.LinearizedVI(),
    }
    ns = [10, 100, 1_000, 10_000, 100_000, 1_000_000]
    lines = [
        "| method | " + " | ".join(f"h = 1e-{round(math.log10(n))}" for n in ns) + " |",
        "|---|" + "---|" * len(ns),
    ]
    fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
    for name, solver in methods.items():
        term = dvi.LagrangianTerm(scene.lagrangian)
        solve = jax.jit(
            lambda h, n, solver=solver: (
                dfx.diffeqsolve(
                    term, solver, 0.0, 1.0, h, scene.y0, max_steps=n, throw=False
                ).ys
            ),
            static_argnums=1,
        )
        errors = []
        for n in ns:
            q, p = solve(1.0 / n, n)
            errors.append(
                max(abs(float(q[-1] - exact[0])), abs(float(p[-1] - exact[1])))
            )
        ax.loglog([1 / n for n in ns], errors, "o-", label=name)
        lines.append(f"| {name} | " + " | ".join(f"{e:.1e}" for e in errors) + " |")
    ax.set_xlabel("step h")
    ax.set_ylabel("global error at T = 1")
    ax.set_title("Pendulum: the round-off floor")
    ax.legend(fontsize=8)
    fig.savefig(out / "stability_floor.png", dpi=110)
    plt.close(fig)
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/images")
    out = pathlib.Path(parser.parse_args().out)
    out.mkdir(parents=True, exist_ok=True)
    print("\n".join(linear_stability(out)))
    print()
    print("\n".join(round_off_floor(out)))


if __name__ == "__main__":
    main()
