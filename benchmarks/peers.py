"""Our symplectic steps against blackjax's integrators, side by side in one process.

Kepler (e = 0.6, 200 steps per orbit, 1000 orbits), float64, one core: per-step wall
time saving only the final state, and the largest energy error over the run (from a
separate run that saves 1000 states), for

- Störmer–Verlet: `StormerVerlet` in `diffrax.diffeqsolve` against blackjax's
  `velocity_verlet` in a `jax.lax.scan`;
- the fourth-order composition: `Composition(StormerVerlet(), "yoshida4")`, plain and
  compensated (our default), against blackjax's `yoshida`;
- the implicit midpoint step: `MidpointVI` against blackjax's `implicit_midpoint`
  (fixed-point iteration) at its default tolerance and at one tight enough to match
  our energy error; and `MidpointVI(root_finder=FixedPoint(rtol=tol))`, the same
  iteration stopped at the same tolerance (ours relative to the step's terms).

blackjax is in the `bench` extra. Run: `python benchmarks/peers.py [--xla-default]`
(both settings are recorded: `results/peers_cpu.txt`, `results/peers_default_cpu.txt`).
"""

import argparse
import importlib.metadata
import pathlib
import sys

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parent))
from step_cost import (  # noqa: E402
    add_xla_option,
    apply_xla_option,
    best_time,
    Kepler,
)


E = 0.6
ORBITS = 1000
PER_ORBIT = 200
SAVES = 1000


def _potential(q):
    return -1 / jnp.sqrt(jnp.sum(q**2))


def _energy(q, p):
    return 0.5 * jnp.sum(p**2, axis=-1) + jax.vmap(_potential)(q)


def ours(terms, solver, y0, h, n):
    """(final state, states at `SAVES` equally spaced times) of a plain diffeqsolve."""

    def solve(saveat):
        @jax.jit
        def run(y0):
            return dfx.diffeqsolve(
                terms, solver, 0.0, h * n, h, y0, saveat=saveat, max_steps=n
            ).ys

        return run

    ts = jnp.linspace(0.0, h * n, SAVES + 1)[1:]
    return solve(dfx.SaveAt(t1=True)), solve(dfx.SaveAt(ts=ts))


def theirs(one_step, y0, h, n):
    """The same for a blackjax integrator stepped in a `jax.lax.scan`."""
    from blackjax.mcmc.integrators import new_integrator_state

    def logdensity(q):
        return -_potential(q)

    def steps(state, k):
        return jax.lax.fori_loop(0, k, lambda _, s: one_step(s, h), state)

    @jax.jit
    def final(y0):
        state = new_integrator_state(logdensity, *y0)
        state = jax.lax.scan(lambda s, _: (one_step(s, h), None), state, None, n)[0]
        return state.position, state.momentum

    @jax.jit
    def saved(y0):
        state = new_integrator_state(logdensity, *y0)

        def interval(s, _):
            s = steps(s, n // SAVES)
            return s, (s.position, s.momentum)

        return jax.lax.scan(interval, state, None, SAVES)[1]

    return final, saved


def measure(final, saved, y0, n, e0, repeats):
    ns = 1e9 * best_time(final, y0, repeats=repeats) / n
    q, p = saved(y0)
    return ns, float(jnp.max(jnp.abs(_energy(q, p) - e0)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    add_xla_option(parser)
    args = parser.parse_args()
    setting = apply_xla_option(args)
    from blackjax.mcmc import integrators, metrics

    print(
        f"jax {jax.__version__}, diffrax {importlib.metadata.version('diffrax')}, "
        f"blackjax {importlib.metadata.version('blackjax')}, {setting}"
    )
    h = 2 * np.pi / PER_ORBIT
    n = ORBITS * PER_ORBIT
    y0 = dvi.scenes.kepler(eccentricity=E).y0
    e0 = float(_energy(y0[0][None], y0[1][None])[0])
    pair = dvi.separable_terms(Kepler())
    term = dvi.LagrangianTerm(Kepler())
    kinetic = metrics.default_metric(jnp.ones(2)).kinetic_energy
    logdensity = lambda q: -_potential(q)

    measured = {}

    def once(run):
        # A run that appears in two rows is measured once: one number each.
        if id(run) not in measured:
            measured[id(run)] = measure(*run, y0, n, e0, args.repeats)
        return measured[id(run)]

    def row(name, ours_run, their_run):
        ns_ours, err_ours = once(ours_run)
        ns_theirs, err_theirs = once(their_run)
        print(
            f"  {name:<44} {ns_ours:7.1f} ns  {err_ours:8.1e}  |  {ns_theirs:7.1f} ns"
            f"  {err_theirs:8.1e}  |  {ns_ours / ns_theirs:5.2f}x"
        )

    print(
        f"Kepler e = {E}, {PER_ORBIT} steps per orbit, {ORBITS} orbits ({n} steps): "
        "ns per step, max energy error"
    )
    print(f"  {'ours | blackjax':<44} {'ours':>21}  |  {'blackjax':>19}  |  ratio")
    plain = dvi.StormerVerlet(compensated=False)
    row(
        "StormerVerlet(plain) | velocity_verlet",
        ours(pair, plain, y0, h, n),
        theirs(integrators.velocity_verlet(logdensity, kinetic), y0, h, n),
    )
    yoshida = theirs(integrators.yoshida(logdensity, kinetic), y0, h, n)
    row(
        "yoshida4(StormerVerlet(plain)) | yoshida",
        ours(pair, dvi.Composition(plain, "yoshida4"), y0, h, n),
        yoshida,
    )
    row(
        "yoshida4(StormerVerlet()) (default) | yoshida",
        ours(pair, dvi.Composition(dvi.StormerVerlet(), "yoshida4"), y0, h, n),
        yoshida,
    )
    midpoint = ours(term, dvi.MidpointVI(), y0, h, n)
    for tol in (1e-6, 1e-10):
        implicit_midpoint = theirs(
            integrators.implicit_midpoint(
                logdensity,
                lambda p, position=None: kinetic(p),
                convergence_tol=tol,
            ),
            y0,
            h,
            n,
        )
        name = f"implicit_midpoint(tol {tol:.0e})"
        row(f"MidpointVI | {name}", midpoint, implicit_midpoint)
        # Like for like: fixed-point iteration alone (no Newton fallback) stopped at
        # the same tolerance, relative to the size of the step's terms.
        row(
            f"MidpointVI(FixedPoint(rtol={tol:.0e})) | same",
            ours(term, dvi.MidpointVI(root_finder=dvi.FixedPoint(rtol=tol)), y0, h, n),
            implicit_midpoint,
        )


if __name__ == "__main__":
    main()
