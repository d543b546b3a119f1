"""Per-step cost against the number of degrees of freedom N, from 16 to 4096, for every
solver on two large systems, as ratios from one run:

- `chain`: a fixed-end chain of N unit masses with springs V(r) = r^2/2 + r^4/4,
  written twice: as a plain `eqx.Module` Lagrangian (nothing known of it: the
  solvers and `LagrangianTerm.vf` find velocities by Newton's method) and as a
  `SeparableLagrangian` (the mass known, explicit methods possible);
- `wire`: the scene `diffrax_vi.scenes.bead_wire`, N beads on a corrugated wire joined
  by springs: a kinetic energy that depends on the configuration, non-separable.

For each solver it prints the time per step at each N, the growth exponent fitted
over N = 256 ... 4096 (least squares on log-log), and the targets:

- MidpointVI on the generic chain at N = 1024 <= 10x Tsit5 on the separable form;
- growth exponents of MidpointVI and GaussVPRK(2) from 256 to 4096 <= 1.2;
- Tsit5 on the generic LagrangianTerm <= 3x Tsit5 on the separable form at 1024;
- LinearizedVI <= 0.5x MidpointVI at every N >= 32.

Pin it to one core for stable figures. Minutes.

Run: `taskset -c 1 python benchmarks/scaling.py [--sizes 16,64,256,1024,4096]`.
`--figure PATH` also draws the tables (log-log); with `--from-output FILE` it draws
them from a previous run's printed output instead of measuring again.
"""

import argparse
import math

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import scenes  # noqa: E402
from step_cost import (  # noqa: E402
    add_xla_option,
    apply_xla_option,
    best_time,
    versions,
)


def springs(q):
    r = jnp.diff(jnp.concatenate([jnp.zeros(1, q.dtype), q, jnp.zeros(1, q.dtype)]))
    return jnp.sum(0.5 * r**2 + 0.25 * r**4)


class GenericChain(eqx.Module):
    """The chain as a user who knows nothing of the package's markers writes it."""

    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) - springs(q)


def chain_y0(n):
    i = jnp.arange(1.0, n + 1.0)
    return 0.3 * jnp.sin(2.1 * i), jnp.zeros(n)


SOLVERS = {
    # name -> (solver, which form of the system it runs on)
    "MidpointVI": (dvi.MidpointVI(), "generic"),
    "GaussVPRK(2)": (dvi.GaussVPRK(2), "generic"),
    "LinearizedVI(centered)": (dvi.LinearizedVI(velocity="centered"), "generic"),
    "Tsit5 (generic)": (dfx.Tsit5(), "generic"),
    "Tsit5 (separable)": (dfx.Tsit5(), "separable"),
    "TrapezoidalVI (separable)": (dvi.TrapezoidalVI(), "separable"),
}


def per_step(lagrangian, y0, solver, h, steps, repeats):
    terms = dvi.terms_for(solver, lagrangian)

    @jax.jit
    def solve(y0):
        sol = dfx.diffeqsolve(
            terms,
            solver,
            0.0,
            h * steps,
            h,
            y0,
            saveat=dfx.SaveAt(t1=True),
            max_steps=steps,
            throw=False,
        )
        return sol.ys, sol.result

    (_, result) = solve(y0)
    if result != dfx.RESULTS.successful:
        return math.nan
    return best_time(solve, y0, repeats=repeats) / steps


def exponent(sizes, times, lo=256):
    keep = [(n, t) for n, t in zip(sizes, times) if n >= lo and math.isfinite(t)]
    if len(keep) < 2:
        return math.nan
    n, t = np.log(np.array(keep)).T
    return float(np.polyfit(n, t, 1)[0])


def table(title, sizes, times):
    print(f"\n{title}: microseconds per step")
    print(f"{'solver':>26} " + " ".join(f"{n:>9}" for n in sizes) + "  exponent")
    for name, row in times.items():
        cells = " ".join(f"{1e6 * t:9.1f}" for t in row)
        print(f"{name:>26} {cells}  {exponent(sizes, row):8.2f}")


def parse_tables(text):
    """The tables a previous run printed: `{title: (sizes, {solver: times})}`, times
    in seconds."""
    tables, lines = {}, text.splitlines()
    for i, line in enumerate(lines):
        if line.endswith(": microseconds per step"):
            sizes = [int(n) for n in lines[i + 1].split()[1:-1]]
            rows = {}
            for row in lines[i + 2 :]:
                if not row.strip():
                    break
                cells = row.split()
                name = " ".join(cells[: -len(sizes) - 1])
                rows[name] = [1e-6 * float(c) for c in cells[-len(sizes) - 1 : -1]]
            tables[line.split(":")[0]] = (sizes, rows)
    return tables


def draw(tables, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(tables), figsize=(6 * len(tables), 4.5))
    for ax, (title, (sizes, rows)) in zip(np.atleast_1d(axes), tables.items()):
        for name, times in rows.items():
            ax.loglog(sizes, [1e6 * t for t in times], "o-", label=name, ms=3)
        n = np.array([sizes[0], sizes[-1]], float)
        ax.loglog(n, 10 * n / n[0], "k:", lw=1, label="slope 1")
        ax.set_xlabel("degrees of freedom N")
        ax.set_ylabel("microseconds per step")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="16,32,64,128,256,512,1024,2048,4096")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--solvers", default=",".join(SOLVERS))
    parser.add_argument("--figure", help="also draw the tables to this image file")
    parser.add_argument(
        "--from-output", help="draw --figure from this earlier run's printed output"
    )
    add_xla_option(parser)
    args = parser.parse_args()
    if args.from_output:
        with open(args.from_output) as f:
            draw(parse_tables(f.read()), args.figure or "scaling.png")
        return
    print(apply_xla_option(args))
    sizes = [int(n) for n in args.sizes.split(",")]
    names = args.solvers.split(",")
    print(f"{versions()}, device {jax.devices()[0]}, float64, best of {args.repeats}")

    chain = {n: {} for n in names}
    wire = {n: {} for n in names if SOLVERS[n][1] == "generic"}
    for size in sizes:
        forms = {
            "generic": GenericChain(),
            "separable": dvi.SeparableLagrangian(lambda t, q, args: springs(q)),
        }
        scene = scenes.bead_wire(size, displacement=0.05)
        for name in names:
            solver, form = SOLVERS[name]
            chain[name][size] = per_step(
                forms[form], chain_y0(size), solver, 0.05, args.steps, args.repeats
            )
            if name in wire:
                wire[name][size] = per_step(
                    scene.lagrangian,
                    scene.y0,
                    solver,
                    scene.period / 40,
                    args.steps,
                    args.repeats,
                )
            wire_us = f"{1e6 * wire[name][size]:.1f}" if name in wire else "-"
            print(
                f"  N = {size:5d} {name:>26}: chain {1e6 * chain[name][size]:.1f} us,"
                f" bead_wire {wire_us} us",
                flush=True,
            )
    chain = {k: [v[n] for n in sizes] for k, v in chain.items()}
    wire = {k: [v[n] for n in sizes] for k, v in wire.items()}
    table("chain, h = 0.05", sizes, chain)
    table("bead_wire (displacement 0.05), h = period / 40", sizes, wire)
    if args.figure:
        draw(
            {
                "chain, h = 0.05": (sizes, chain),
                "bead_wire (displacement 0.05), h = period / 40": (sizes, wire),
            },
            args.figure,
        )

    def at(name, n):
        return chain[name][sizes.index(n)] if name in chain and n in sizes else math.nan

    print("\nTargets:")
    ratio = at("MidpointVI", 1024) / at("Tsit5 (separable)", 1024)
    print(f"  MidpointVI / Tsit5 (separable), N = 1024     {ratio:7.2f}x  (<= 10)")
    for name in ("MidpointVI", "GaussVPRK(2)"):
        if name in chain:
            print(
                f"  exponent of {name:<12} 256 -> 4096          "
                f"{exponent(sizes, chain[name]):7.2f}   (<= 1.2)"
            )
    ratio = at("Tsit5 (generic)", 1024) / at("Tsit5 (separable)", 1024)
    print(f"  Tsit5 generic / separable, N = 1024          {ratio:7.2f}x  (<= 3)")
    ratios = [at("LinearizedVI(centered)", n) / at("MidpointVI", n) for n in sizes]
    worst = max((r for n, r in zip(sizes, ratios) if n >= 32), default=math.nan)
    print(f"  LinearizedVI / MidpointVI, worst N >= 32     {worst:7.2f}x  (<= 0.5)")


if __name__ == "__main__":
    main()
