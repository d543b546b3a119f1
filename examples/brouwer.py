"""Brouwer's law: round-off in the energy, with and without compensated summation.

An ensemble of nearby initial conditions, 10^5 steps at a step where truncation error
is below round-off:

- the 2-D harmonic oscillator under MidpointVI, which conserves its quadratic energy
  exactly, so that all error is round-off;
- Kepler (e = 0.6) under kahan_li8 (StormerVerlet composed to order 8) at 800 steps per
  orbit, where the truncation error in the energy is below 1e-16.

Plots the ensemble's RMS energy error against time and prints the fitted slopes. Writes
`brouwer.png` into `--out` (default `seed-results`). Run: `python examples/brouwer.py`.
"""

import argparse
import functools
import pathlib

import diffrax as dfx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np


jax.config.update("jax_enable_x64", True)
matplotlib.use("Agg")
import diffrax_vi as dvi  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402


def rms_energy_error(lagrangian, terms, solver, y0s, h, n, n_save=100):
    ts = jnp.linspace(0.0, n * h, n_save + 1)
    energy = functools.partial(dvi.energy, lagrangian)
    es = jax.jit(
        jax.vmap(
            lambda y0: (
                dfx.diffeqsolve(
                    terms,
                    solver,
                    0.0,
                    n * h,
                    h,
                    y0,
                    saveat=dfx.SaveAt(ts=ts, fn=energy),
                    max_steps=n + 1,
                ).ys
            )
        )
    )(y0s)
    err = np.asarray(es - es[:, :1])[:, 1:]
    return np.asarray(ts[1:]), np.sqrt(np.mean(err**2, axis=0))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="seed-results")
    parser.add_argument("--members", type=int, default=64)
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    key = jax.random.key(0)
    m, n = args.members, 100_000

    osc = dvi.SeparableLagrangian(lambda t, q, a: 0.5 * jnp.sum(q**2))
    q0 = jnp.array([[1.0, 0.5]]) + 1e-3 * jax.random.normal(key, (m, 2))
    osc_y0 = (q0, jnp.zeros((m, 2)))
    e = 0.6
    kepler = dvi.SeparableLagrangian(lambda t, q, a: -1 / jnp.sqrt(jnp.sum(q**2)))
    kq0 = jnp.array([[1 - e, 0.0]]) + 1e-4 * jax.random.normal(key, (m, 2))
    kp0 = jnp.broadcast_to(jnp.array([0.0, np.sqrt((1 + e) / (1 - e))]), (m, 2))
    cases = {
        "oscillator, MidpointVI, h = 0.01": (
            osc,
            lambda c: (dvi.LagrangianTerm(osc), dvi.MidpointVI(compensated=c)),
            osc_y0,
            0.01,
        ),
        "Kepler e = 0.6, kahan_li8, 800 steps/orbit": (
            kepler,
            lambda c: (
                dvi.terms_for(dvi.StormerVerlet(), kepler),
                dvi.Composition(dvi.StormerVerlet(compensated=c), "kahan_li8"),
            ),
            (kq0, kp0),
            2 * np.pi / 800,
        ),
    }
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
    for ax, (title, (lagrangian, make, y0s, h)) in zip(axes, cases.items()):
        for compensated in (False, True):
            terms, solver = make(compensated)
            ts, rms = rms_energy_error(lagrangian, terms, solver, y0s, h, n)
            late = ts >= ts[-1] / 10
            slope = np.polyfit(np.log(ts[late]), np.log(rms[late]), 1)[0]
            label = f"{'compensated' if compensated else 'plain'} (slope {slope:.2f})"
            print(f"{title}: {label}, RMS at the end {rms[-1]:.2e}")
            ax.loglog(ts, rms, label=label)
        t = np.asarray(ts)
        ax.loglog(t, 1e-16 * np.sqrt(t / t[0]), "k:", lw=1, label="∝ √t")
        ax.set_title(title)
        ax.set_xlabel("time")
        ax.set_ylabel("RMS energy error over the ensemble")
        ax.legend(fontsize=8)
    fig.savefig(out / "brouwer.png", dpi=110)


if __name__ == "__main__":
    main()
