"""Per-step cost of our solvers inside `diffrax.diffeqsolve`, as ratios from one run.

- StormerVerlet in diffeqsolve (saving only t1) over a bare `jax.lax.scan` of the same
  kick-drift-kick update (target <= 1.2x), both without compensated summation, as
  SemiImplicitEuler has none;
- StormerVerlet over `diffrax.SemiImplicitEuler` on the same terms (target <= 1.2x);
- the cost of compensated summation (on by default) over the plain update;
- MidpointVI over `diffrax.Tsit5` on the same `LagrangianTerm` at the same step;
- on Kepler, a composition over the sum of its substeps (Stormer-Verlet steps in
  diffeqsolve; target <= 1.3x), and MidpointVI over a bare fixed-point implicit
  midpoint in a `lax.scan` iterated to 1e-13 (target <= 1.5x), checked to agree;
- on the double pendulum (a general Lagrangian, whose implicit steps take Newton
  iterations with a dense Jacobian), MidpointVI, TrapezoidalVI and GaussVPRK(2)
  against Tsit5 on the same term;
- on Lagrangians given by MLPs (the learned potential, one degree of freedom, and
  a neural Lagrangian of q and v, two), MidpointVI, GaussVPRK(2), LobattoVPRK(3)
  and Tsit5, and the custom fusions that break each one's loops into kernels;
- on the Cartesian pendulum, TrapezoidalVI (RATTLE) and MidpointVI with the
  constraint over the same Lagrangian without it (target <= 3x);
- on Kepler, Tsit5 and Dopri8 on a `LagrangianTerm` over the same solver on a
  hand-written `ODETerm` of Hamilton's equations (target <= 1.2x at either XLA
  setting): the handicap a Runge-Kutta method would carry into every study.

By default the script runs at the setting `import diffrax_vi` chooses
(`diffrax_vi.compile_small_loops_whole()`), so that XLA compiles the small loops of
both sides as one function; `--xla-default` keeps XLA's default 1 kB threshold
instead (`diffrax_vi.keep_xla_default()`).

On Kepler (2 degrees of freedom) and Fermi-Pasta-Ulam-like chains of 64 and 4096
particles with quartic springs, whose force costs about as much as an axpy. As a
reference, it also prints diffrax's own loop overhead: SemiImplicitEuler in diffeqsolve
over a bare scan of the SemiImplicitEuler update. Where that is large, the update is too
cheap for any solver inside diffeqsolve to come near a bare scan.

Run: `taskset -c 1 python benchmarks/step_cost.py [--repeats 5] [--xla-default]`.
"""

import argparse
import importlib.metadata
import os
import time

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402


class Chain(dvi.AbstractSeparableLagrangian):
    """Fixed-end chain with springs V(r) = r^2/2 + r^4/4."""

    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        r = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return jnp.sum(0.5 * r**2 + 0.25 * r**4)


class Kepler(dvi.AbstractSeparableLagrangian):
    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        return -1 / jnp.sqrt(jnp.sum(q**2))


def versions() -> str:
    """The jax and diffrax versions, for a results file's first line."""
    return f"jax {jax.__version__}, diffrax {importlib.metadata.version('diffrax')}"


def add_xla_option(parser):
    """`--xla-default`: keep XLA's default small-loop threshold (see the docstring)."""
    parser.add_argument(
        "--xla-default",
        action="store_true",
        help="keep XLA's default small-loop threshold (1 kB) instead of the one "
        "`import diffrax_vi` sets",
    )


def apply_xla_option(args) -> str:
    """The raised small-loop threshold that `import diffrax_vi` sets (also when
    `DIFFRAX_VI_XLA_DEFAULT` kept it from doing so), or XLA's default with
    `--xla-default`; before JAX runs anything. Returns the setting, to print."""
    if args.xla_default:
        dvi.keep_xla_default()
    else:
        dvi.compile_small_loops_whole()
    return f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}"


def best_times(fns, *args, repeats):
    """The best of `repeats` wall times of each of `fns` on `args`, taken in turns
    (one run of each per round), so that the machine's slow spells, which come and
    go over seconds, fall on every side of a ratio alike."""
    for fn in fns:
        jax.block_until_ready(fn(*args))
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, spent in zip(fns, times):
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            spent.append(time.perf_counter() - start)
    return [min(spent) for spent in times]


def kahan_add(y, increment, compensation):
    """`y + increment` compensated (Kahan), for the bare scans: the sum and the new
    compensation."""
    corrected = increment - compensation
    y1 = y + corrected
    return y1, (y1 - y) - corrected


def best_time(fn, *args, repeats):
    return best_times([fn], *args, repeats=repeats)[0]


def run(name, lagrangian, y0, h, n, repeats, implicit=True):
    t1 = h * n
    terms_pair = dvi.separable_terms(lagrangian)
    term = dvi.LagrangianTerm(lagrangian)

    def solve(terms, solver):
        @jax.jit
        def f(y0):
            sol = dfx.diffeqsolve(
                terms, solver, 0.0, t1, h, y0, saveat=dfx.SaveAt(t1=True), max_steps=n
            )
            return sol.ys

        return f

    force = lambda q: dvi.separable_terms(lagrangian)[1].vector_field(0.0, q, None)

    @jax.jit
    def bare_scan(y0):
        def update(carry, _):
            q, p, g = carry
            p_half = p + 0.5 * h * g
            q = q + h * p_half / lagrangian.mass
            g = force(q)
            return (q, p_half + 0.5 * h * g, g), None

        (q, p, _), _ = jax.lax.scan(update, (*y0, force(y0[0])), None, length=n)
        return q, p

    # The bare scan computes the plain update; compare it with the plain solver.
    plain = dvi.StormerVerlet(compensated=False)
    sv_final = jax.tree.map(lambda x: x[-1], solve(terms_pair, plain)(y0))
    scan_final = bare_scan(y0)
    assert max(
        float(jnp.max(jnp.abs(a - b))) for a, b in zip(sv_final, scan_final)
    ) < 1e-9 * (1 + float(jnp.max(jnp.abs(scan_final[0])))), "bare scan differs"

    @jax.jit
    def bare_scan_sie(y0):
        def update(carry, _):
            q, p = carry
            q = q + h * p / lagrangian.mass
            return (q, p + h * force(q)), None

        return jax.lax.scan(update, y0, None, length=n)[0]

    t_sv, t_sv_kahan, t_scan, t_sie, t_scan_sie = best_times(
        [
            solve(terms_pair, plain),
            solve(terms_pair, dvi.StormerVerlet()),
            bare_scan,
            solve(terms_pair, dfx.SemiImplicitEuler()),
            bare_scan_sie,
        ],
        y0,
        repeats=repeats,
    )
    us = lambda t: 1e6 * t / n
    print(f"\n{name}: {n} steps, per-step wall time (best of {repeats})")
    print(f"  bare lax.scan, kick-drift-kick     {us(t_scan):9.3f} us")
    print(
        f"  StormerVerlet in diffeqsolve       {us(t_sv):9.3f} us  (compensated=False)"
    )
    print(
        f"  StormerVerlet, compensated         {us(t_sv_kahan):9.3f} us  (the default)"
    )
    print(f"  bare lax.scan, SemiImplicitEuler   {us(t_scan_sie):9.3f} us")
    print(f"  SemiImplicitEuler in diffeqsolve   {us(t_sie):9.3f} us")
    if implicit:
        t_mid = best_time(solve(term, dvi.MidpointVI()), y0, repeats=repeats)
        t_tsit = best_time(solve(term, dfx.Tsit5()), y0, repeats=repeats)
        print(f"  MidpointVI in diffeqsolve          {us(t_mid):9.3f} us")
        print(f"  Tsit5 in diffeqsolve               {us(t_tsit):9.3f} us")
    print(
        f"  StormerVerlet / bare scan          {t_sv / t_scan:9.2f}x  (target <= 1.2)"
    )
    print(f"  StormerVerlet / SemiImplicitEuler  {t_sv / t_sie:9.2f}x  (target <= 1.2)")
    print(f"  compensated / plain StormerVerlet  {t_sv_kahan / t_sv:9.2f}x")
    print(f"  reference: diffrax loop overhead   {t_sie / t_scan_sie:9.2f}x")
    print(f"  reference: bare update SV / SIE    {t_scan / t_scan_sie:9.2f}x")
    if implicit:
        print(f"  MidpointVI / Tsit5                 {t_mid / t_tsit:9.2f}x")


def small_system(lagrangian, y0, h, n, repeats):
    """Kepler: compositions against their substeps, MidpointVI against a bare
    fixed-point implicit midpoint."""
    pair = dvi.separable_terms(lagrangian)
    term = dvi.LagrangianTerm(lagrangian)
    us = lambda t: 1e6 * t / n

    def solve(terms, solver):
        @jax.jit
        def f(y0):
            sol = dfx.diffeqsolve(
                terms,
                solver,
                0.0,
                h * n,
                h,
                y0,
                saveat=dfx.SaveAt(t1=True),
                max_steps=n,
            )
            return jax.tree.map(lambda x: x[-1], sol.ys)

        return f

    force = lambda q: pair[1].vector_field(0.0, q, None)

    @jax.jit
    def bare_midpoint(y0):
        # v = M^-1 (p0 + h/2 F(q0 + h/2 v)), iterated until the update is 1e-13 of v.
        def update(carry, _):
            q, p = carry

            def not_converged(s):
                v, v_old, k = s
                big = jnp.max(jnp.abs(v - v_old)) > 1e-13 * jnp.max(jnp.abs(v))
                return big & (k < 100)

            def iterate(s):
                v, _, k = s
                return (
                    (p + 0.5 * h * force(q + 0.5 * h * v)) / lagrangian.mass,
                    v,
                    k + 1,
                )

            v, _, _ = jax.lax.while_loop(not_converged, iterate, (p, p + 1.0, 0))
            return (q + h * v, p + h * force(q + 0.5 * h * v)), None

        return jax.lax.scan(update, y0, None, length=n)[0]

    print(f"\nKepler (2 DOF), compositions and MidpointVI: {n} steps, us per step")
    t_sv = us(best_time(solve(pair, dvi.StormerVerlet()), y0, repeats=repeats))
    print(f"  StormerVerlet (compensated)        {t_sv:9.3f} us")
    for scheme in ("yoshida4", "kahan_li6", "kahan_li8"):
        solver = dvi.Composition(dvi.StormerVerlet(), scheme)
        m = len(solver.scheme.coefficients)
        t = us(best_time(solve(pair, solver), y0, repeats=repeats))
        print(
            f"  Composition {scheme:<10} {t:9.3f} us = {t / (m * t_sv):5.2f}x its "
            f"{m} substeps (target <= 1.3)"
        )
    midpoint = solve(term, dvi.MidpointVI())
    ours, bare = midpoint(y0), bare_midpoint(y0)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(ours, bare))
    assert gap < 1e-9, f"MidpointVI and the bare implicit midpoint differ by {gap}"
    t_mid, t_bare = map(us, best_times([midpoint, bare_midpoint], y0, repeats=repeats))
    print(f"  bare fixed-point implicit midpoint {t_bare:9.3f} us")
    print(
        f"  MidpointVI                         {t_mid:9.3f} us = "
        f"{t_mid / t_bare:5.2f}x the bare midpoint (target <= 1.5; states agree "
        f"to {gap:.1e})"
    )
    # The same Hamilton's equations written by hand as a diffrax ODETerm: what a
    # Runge-Kutta solver on a LagrangianTerm is compared with in every study.
    by_hand = dfx.ODETerm(lambda t, y, args: (y[1] / lagrangian.mass, force(y[0])))
    for solver in (dfx.Tsit5(), dfx.Dopri8()):
        name = type(solver).__name__
        t_term, t_hand = map(
            us,
            best_times(
                [solve(term, solver), solve(by_hand, solver)], y0, repeats=repeats
            ),
        )
        print(
            f"  {name:<6} on LagrangianTerm {t_term:9.3f} us = "
            f"{t_term / t_hand:5.2f}x on a hand-written ODETerm ({t_hand:.3f} us; "
            "target <= 1.2)"
        )
    # What the opt-in NaN check of every evaluation costs (a host callback).
    checked = dvi.LagrangianTerm(lagrangian, check_every_step=True)
    t_checked, t_term = map(
        us,
        best_times(
            [solve(checked, dfx.Tsit5()), solve(term, dfx.Tsit5())], y0, repeats=repeats
        ),
    )
    print(
        f"  Tsit5  on LagrangianTerm(check_every_step=True) {t_checked:9.3f} us = "
        f"{t_checked / t_term:5.2f}x unchecked ({t_term:.3f} us; the user's choice)"
    )


def final_state(term, solver, h, n):
    """A jitted plain `diffeqsolve` of `n` steps of `h` from `y0`, saving only t1:
    `y0 -> y(t1)`."""

    @jax.jit
    def f(y0):
        sol = dfx.diffeqsolve(
            term, solver, 0.0, h * n, h, y0, saveat=dfx.SaveAt(t1=True), max_steps=n
        )
        return jax.tree.map(lambda x: x[-1], sol.ys)

    return f


def general_lagrangian(repeats):
    """The double pendulum (a general Lagrangian: Newton with a dense Jacobian at
    each step) under the implicit solvers and Tsit5; "chord method" is MidpointVI
    with `SimplifiedNewton` (one factorisation kept across iterations and steps)."""
    scene = dvi.scenes.double_pendulum()
    term, n, h = scene.term(), 20_000, scene.period / 100
    solvers = [
        ("MidpointVI", dvi.MidpointVI()),
        ("  chord method", dvi.MidpointVI(root_finder=dvi.SimplifiedNewton())),
        ("TrapezoidalVI", dvi.TrapezoidalVI()),
        ("GaussVPRK(2)", dvi.GaussVPRK(2)),
        ("Tsit5", dfx.Tsit5()),
    ]
    # In turns: this machine's slow spells fall on every solver alike.
    fns = [final_state(term, solver, h, n) for _, solver in solvers]
    *times, t_tsit = (1e6 * t / n for t in best_times(fns, scene.y0, repeats=repeats))
    print(
        f"\nDouble pendulum (general Lagrangian, dense Newton): {n} steps, us per step"
    )
    for (name, _), t in zip(solvers, times):
        print(f"  {name:14s} {t:9.3f} us = {t / t_tsit:5.2f}x Tsit5 on the same term")
    print(f"  {'Tsit5':14s} {t_tsit:9.3f} us")


class NeuralLagrangian(dvi.AbstractLagrangian):
    """A Lagrangian neural network's kind of Lagrangian on two degrees of freedom: an
    MLP (`equinox.nn.Linear` layers) of the positions and velocities on top of a
    regular kinetic term and a harmonic well."""

    net: eqx.nn.MLP

    def __init__(self, width: int = 32):
        self.net = eqx.nn.MLP(4, "scalar", width, 2, jax.nn.tanh, key=jax.random.key(0))

    def __call__(self, t, q, v, args):
        well = 0.5 * jnp.sum(v**2) - 0.5 * jnp.sum(q**2)
        return well + 0.05 * self.net(jnp.concatenate([q, v]))


def learned_lagrangian(repeats):
    """Lagrangians given by MLPs, whose layers are matrix-vector products of the
    user's: the `learned` scene (a potential, one degree of freedom) and a
    `NeuralLagrangian` (of q and v, two), under the implicit solvers and Tsit5, and
    how many custom fusions break each solve's loops into kernels
    (`diagnostics.loop_breakers`): a matrix product XLA on CPU makes a YNNPACK
    fusion."""
    learned = dvi.scenes.learned()
    neural_y0 = (jnp.array([0.1, 0.5]), jnp.array([0.0, 0.2]))
    cases = [
        ("Learned potential (an MLP, 1 DOF)", learned.term(), learned.y0),
        (
            "Neural Lagrangian (an MLP of q and v, 2 DOF)",
            dvi.LagrangianTerm(NeuralLagrangian()),
            neural_y0,
        ),
    ]
    solvers = [
        ("MidpointVI", dvi.MidpointVI()),
        ("GaussVPRK(2)", dvi.GaussVPRK(2)),
        ("LobattoVPRK(3)", dvi.LobattoVPRK(3)),
        ("Tsit5", dfx.Tsit5()),
    ]
    n, h = 5_000, learned.period / 100
    for title, term, y0 in cases:
        print(f"\n{title}: {n} steps, us per step")
        # Compiled once: the programs timed are the programs whose HLO is read.
        programs = [
            final_state(term, solver, h, n).lower(y0).compile() for _, solver in solvers
        ]
        times = best_times(programs, y0, repeats=repeats)
        for (name, _), program, t in zip(solvers, programs, times):
            found = len(dvi.diagnostics.loop_breakers(program.as_text()))
            print(f"  {name:14s} {1e6 * t / n:9.3f} us, {found} fusions in its loops")


def bare_rattle(scene, h, n):
    """A bare `lax.scan` of RATTLE on the scene's Lagrangian and its one constraint
    (the Cartesian pendulum: scalar mass, one multiplier): the kick, Newton's method
    on the multiplier in a while loop from the last two steps' multipliers
    extrapolated, stopped after the update from a residual below sqrt(eps) of
    |G| |q|, as the library's, then the momentum's projection. No checks, no
    compensated sums: the floor of a RATTLE step inside XLA's compiled loop."""
    lagrangian, constraint = scene.lagrangian, scene.constraint
    mass = lagrangian.mass
    tol = float(jnp.finfo(jnp.float64).eps) ** 0.5
    force = jax.grad(lambda q: -lagrangian.potential(0.0, q, None))
    g = lambda q: jnp.atleast_1d(constraint(0.0, q, None))
    jacobian = jax.jacrev(g)

    def update(carry, _):
        q, p, f, G, lam, lam_prev = carry
        kicked = p + 0.5 * h * f

        def residual(x):
            q1 = q + h * (kicked + G.T @ x) / mass
            return g(q1), jnp.abs(G) @ jnp.abs(q1)

        def newton(c):
            x, _, k = c
            r, s = residual(x)
            slope = jax.jacfwd(lambda y: residual(y)[0])(x)[:, 0]
            return x - r / slope, jnp.max(jnp.abs(r) / s), k + 1

        x, _, _ = jax.lax.while_loop(
            lambda c: (c[1] > tol) & (c[2] < 16),
            newton,
            (2 * lam - lam_prev, jnp.array(jnp.inf), 0),
        )
        q1 = q + h * (kicked + G.T @ x) / mass
        f1, G1 = force(q1), jacobian(q1)
        p1 = kicked + G.T @ x + 0.5 * h * f1
        mu = (G1 @ p1) / (G1 @ G1.T)[0]
        return (q1, p1 - G1.T @ mu, f1, G1, x, lam), None

    @jax.jit
    def run(y0):
        q0, p0 = y0
        zero = jnp.zeros(1)
        start = (q0, p0, force(q0), jacobian(q0), zero, zero)
        return jax.lax.scan(update, start, None, length=n)[0][:2]

    return run


def constrained(repeats):
    """The Cartesian pendulum (a separable Lagrangian in the plane, one holonomic
    constraint) against the same Lagrangian without the constraint, per step, and
    RATTLE against a bare scan of RATTLE."""
    scene = dvi.scenes.cartesian_pendulum()
    n, h = 20_000, scene.period / 100
    free = dvi.LagrangianTerm(scene.lagrangian)
    bare = bare_rattle(scene, h, n)

    print(
        f"\nCartesian pendulum, constrained over unconstrained: {n} steps, us per step"
    )
    for name, solver in (
        ("TrapezoidalVI", dvi.TrapezoidalVI()),
        ("MidpointVI", dvi.MidpointVI()),
    ):
        runs = [final_state(term, solver, h, n) for term in (scene.term(), free)]
        if name == "TrapezoidalVI":
            runs.append(bare)
        times = best_times(runs, scene.y0, repeats=repeats)
        t_c, t_f = (1e6 * t / n for t in times[:2])
        print(
            f"  {name:14s} {t_c:9.3f} us = {t_c / t_f:5.2f}x unconstrained "
            f"({t_f:.3f} us; target <= 3)"
        )
        if name == "TrapezoidalVI":
            ours, reference = runs[0](scene.y0), bare(scene.y0)
            gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(ours, reference))
            assert gap < 1e-9, f"RATTLE and the bare RATTLE differ by {gap}"
            t_b = 1e6 * times[2] / n
            print(
                f"    bare lax.scan of RATTLE {t_b:6.3f} us = "
                f"{t_b / t_f:5.2f}x unconstrained; RATTLE = {t_c / t_b:4.2f}x "
                f"the bare scan (states agree to {gap:.1e})"
            )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    add_xla_option(parser)
    args = parser.parse_args()
    setting = apply_xla_option(args)
    print(f"{versions()}, device {jax.devices()[0]}, {setting}")
    kepler_y0 = dvi.scenes.kepler(eccentricity=0.6).y0
    run("Kepler (2 DOF)", Kepler(), kepler_y0, 2 * jnp.pi / 200, 100_000, args.repeats)
    small_system(Kepler(), kepler_y0, 2 * jnp.pi / 200, 100_000, args.repeats)
    for n, steps, implicit in [(64, 5_000, True), (4096, 2_000, False)]:
        chain_y0 = (jnp.sin(jnp.linspace(0, jnp.pi, n)), jnp.zeros(n))
        # MidpointVI's dense Newton matrix is too costly to time at 4096 DOF.
        run(f"Chain ({n} DOF)", Chain(), chain_y0, 0.02, steps, args.repeats, implicit)
    general_lagrangian(args.repeats)
    learned_lagrangian(args.repeats)
    constrained(args.repeats)


if __name__ == "__main__":
    main()
