"""Our symplectic steps against blackjax's integrators, side by side in one process.

Kepler (e = 0.6, 200 steps per orbit, 1000 orbits), float64, one core: per-step wall
time saving only the final state (every run timed in turns with the others), and the
largest energy error over the run (from a separate run that saves 1000 states), for

- Störmer–Verlet: `StormerVerlet` in `diffrax.diffeqsolve` against blackjax's
  `velocity_verlet` in a `jax.lax.scan`;
- the fourth-order composition: `Composition(StormerVerlet(), "yoshida4")`, plain and
  compensated (our default), against blackjax's `yoshida`;
- the implicit midpoint step: `MidpointVI` against blackjax's `implicit_midpoint`
  (fixed-point iteration) at its default tolerance and at one tight enough to match
  our energy error; and `MidpointVI(root_finder=FixedPoint(rtol=tol))`, the same
  iteration stopped at the same tolerance (ours relative to the step's terms);
- what compensated summation costs, and where: bare `jax.lax.scan`s of the yoshida4
  composition of kick-drift-kick steps with plain sums, with compensated (Kahan)
  sums in every substep (what `Composition` of a compensated `StormerVerlet` does),
  and with the substeps' increments summed in plain arithmetic and compensated once
  per composed step, beside ours compensated and plain, all timed in turns.

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
    best_times,
    kahan_add,
    Kepler,
    versions,
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


# The force as our partitioned terms and blackjax's integrators take it: the
# gradient of the potential, so that the bare scans step the same update.
_kepler_force = jax.grad(lambda q: -_potential(q))


def bare_yoshida4(h, n, compensation):
    """A bare scan of yoshida4 over kick-drift-kick steps on Kepler:
    `compensation` is `"none"` (plain sums), `"substep"` (each substep's
    increments added by Kahan's summation) or `"step"` (the substeps' increments
    summed in plain arithmetic from the step's start, the sum added to the state by
    Kahan's summation once per composed step)."""
    gammas = dvi.Composition(dvi.StormerVerlet(), "yoshida4").scheme.coefficients

    def increments(q, p, force, step):
        """(dq, dp, force at the end) of one kick-drift-kick step from (q, p)."""
        dq = step * (p + 0.5 * step * force)
        end = _kepler_force(q + dq)
        return dq, 0.5 * step * (force + end), end

    def update(carry, _):
        q, p, force, cq, cp = carry
        if compensation == "step":
            sq, sp = jnp.zeros_like(q), jnp.zeros_like(p)
            for gamma in gammas:
                dq, dp, force = increments(q + sq, p + sp, force, gamma * h)
                sq, sp = sq + dq, sp + dp
            (q, cq), (p, cp) = kahan_add(q, sq, cq), kahan_add(p, sp, cp)
            return (q, p, force, cq, cp), None
        for gamma in gammas:
            dq, dp, force = increments(q, p, force, gamma * h)
            if compensation == "substep":
                (q, cq), (p, cp) = kahan_add(q, dq, cq), kahan_add(p, dp, cp)
            else:
                q, p = q + dq, p + dp
        return (q, p, force, cq, cp), None

    @jax.jit
    def run(y0):
        q, p = y0
        zero = jnp.zeros_like(q)
        start = (q, p, _kepler_force(q), zero, zero)
        return jax.lax.scan(update, start, None, length=n)[0][:2]

    return run


def compensation_floor(plain_ours, compensated_ours, y0, h, n, repeats):
    """Compensated over plain yoshida4: ours (the table's compiled solves, as the
    same program compiled again can run at another speed), and the bare scans'."""
    bare = {c: bare_yoshida4(h, n, c) for c in ("none", "substep", "step")}
    reference = compensated_ours(y0)
    for compensation, run in bare.items():
        gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(run(y0), reference))
        assert gap < 1e-9, f"the bare yoshida4 ({compensation}) differs by {gap}"
    fns = [plain_ours, compensated_ours, *bare.values()]
    t = dict(
        zip(
            ["plain", "compensated", "none", "substep", "step"],
            best_times(fns, y0, repeats=repeats),
        )
    )
    ns = lambda key: 1e9 * t[key] / n
    print(
        f"\nyoshida4 on Kepler, compensated over plain sums, ns per step (timed in "
        f"turns): what compensation costs\n"
        f"  ours: Composition(StormerVerlet(), 'yoshida4') {ns('compensated'):6.1f} ns,"
        f" plain {ns('plain'):6.1f} ns: {t['compensated'] / t['plain']:.2f}x\n"
        f"  bare scan, plain sums                          {ns('none'):6.1f} ns"
        f" (ours plain: {t['plain'] / t['none']:.2f}x)\n"
        f"  bare scan, compensated in every substep        {ns('substep'):6.1f} ns:"
        f" {t['substep'] / t['none']:.2f}x plain\n"
        f"  bare scan, compensated once per composed step  {ns('step'):6.1f} ns:"
        f" {t['step'] / t['none']:.2f}x plain"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    add_xla_option(parser)
    args = parser.parse_args()
    setting = apply_xla_option(args)
    from blackjax.mcmc import integrators, metrics

    print(f"{versions()}, blackjax {importlib.metadata.version('blackjax')}, {setting}")
    h = 2 * np.pi / PER_ORBIT
    n = ORBITS * PER_ORBIT
    y0 = dvi.scenes.kepler(eccentricity=E).y0
    e0 = float(_energy(y0[0][None], y0[1][None])[0])
    pair = dvi.separable_terms(Kepler())
    term = dvi.LagrangianTerm(Kepler())
    kinetic = metrics.default_metric(jnp.ones(2)).kinetic_energy
    logdensity = lambda q: -_potential(q)

    rows = []

    def row(name, ours_run, their_run):
        rows.append((name, ours_run, their_run))

    plain = dvi.StormerVerlet(compensated=False)
    row(
        "StormerVerlet(plain) | velocity_verlet",
        ours(pair, plain, y0, h, n),
        theirs(integrators.velocity_verlet(logdensity, kinetic), y0, h, n),
    )
    yoshida = theirs(integrators.yoshida(logdensity, kinetic), y0, h, n)
    yoshida4_plain = ours(pair, dvi.Composition(plain, "yoshida4"), y0, h, n)
    yoshida4 = ours(pair, dvi.Composition(dvi.StormerVerlet(), "yoshida4"), y0, h, n)
    row("yoshida4(StormerVerlet(plain)) | yoshida", yoshida4_plain, yoshida)
    row("yoshida4(StormerVerlet()) (default) | yoshida", yoshida4, yoshida)
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
    # Every run timed in turns with all the others, one number each (a run in two
    # rows is timed once): the machine's slow spells fall on every ratio alike.
    runs = list({id(r): r for _, a, b in rows for r in (a, b)}.values())
    times = best_times([final for final, _ in runs], y0, repeats=args.repeats)
    ns = {id(r): 1e9 * t / n for r, t in zip(runs, times)}
    error = {}
    for run in runs:
        q, p = run[1](y0)
        error[id(run)] = float(jnp.max(jnp.abs(_energy(q, p) - e0)))
    print(
        f"Kepler e = {E}, {PER_ORBIT} steps per orbit, {ORBITS} orbits ({n} steps): "
        "ns per step (all runs timed in turns), max energy error"
    )
    print(f"  {'ours | blackjax':<44} {'ours':>21}  |  {'blackjax':>19}  |  ratio")
    for name, a, b in rows:
        a, b = id(a), id(b)
        print(
            f"  {name:<44} {ns[a]:7.1f} ns  {error[a]:8.1e}  |  {ns[b]:7.1f} ns"
            f"  {error[b]:8.1e}  |  {ns[a] / ns[b]:5.2f}x"
        )
    compensation_floor(yoshida4_plain[0], yoshida4[0], y0, h, n, args.repeats)


if __name__ == "__main__":
    main()
