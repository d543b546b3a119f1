"""Per-step cost on SO(3), as ratios from one run: the heavy top (Lagrange top).

- TrapezoidalVI in diffeqsolve (saving only t1) over a bare `jax.lax.scan` of the
  same update, written here by hand: Newton on the three unknowns of
  $\\partial_\\xi\\Lambda = J_l(-h\\xi)(\\Pi_0 + h\\partial_g\\Lambda)$, iterated to
  1e-13, then $R_1 = R_0\\exp(h\\xi)$, $\\Pi_1 = \\exp(h\\xi)^\\top(\\Pi_0 +
  h\\partial_g\\Lambda)$ (target <= 1.3x), checked to agree;
- MidpointVI the same way (its own discrete Lagrangian, the Lie midpoint);
- Tsit5 on the same `LagrangianTerm` at the same step, which leaves SO(3);
- the free rigid body against jax-md's rigid-body integrator (the symplectic
  quaternion splitting of Miller et al. 2002, `jax_md.simulate.nve`; the `bench`
  extra) at equal energy error: each method's largest energy error over 10^4 steps
  at three step sizes (from a run that saves every step, not timed), a fitted
  `error = C h^k`, and the wall time of a plain run (final state only) that reaches
  jax-md's error at h = 0.1;
- the free rigid body over 10^6 steps at h = 0.1 (`--skip-long` skips it):
  orthogonality, the Casimir's change and the energy error in the first and last
  tenth, for TrapezoidalVI, MidpointVI and jax-md (its quaternion's norm).

By default the script runs at the small-loop threshold `import diffrax_vi` sets;
`--xla-default` keeps XLA's default threshold.

Run: `taskset -c 1 python benchmarks/lie_groups.py [--repeats 5] [--xla-default]`.
"""

import argparse
import importlib.metadata

import diffrax as dfx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402
from step_cost import (  # noqa: E402
    add_xla_option,
    apply_xla_option,
    best_time,
    final_state,
)


def exp(x):
    return jaxlie.SO3.exp(x).as_matrix()


def pull(x, w):
    """(d exp^R_x)^T w = J_l(-x) w, the left Jacobian of SO(3) transposed."""
    t2 = jnp.sum(x**2)
    small = t2 < 1e-4
    safe = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(safe)
    a = jnp.where(small, 0.5 - t2 / 24, 2 * jnp.sin(0.5 * t) ** 2 / safe)
    b = jnp.where(small, 1 / 6 - t2 / 120, (t - jnp.sin(t)) / (safe * t))
    xw = jnp.cross(x, w)
    return w - a * xw + b * jnp.cross(x, xw)


def bare_trapezoidal(scene, h, n):
    """The trapezoidal LGVI of the heavy top as a bare scan."""
    lag = scene.lagrangian
    J, chi, weight = lag.inertia, lag.centre, lag.weight
    potential = lambda R: weight * (R @ chi)[2]

    def average(eta, xi, R0):
        # Differentiated at eta = 0 only: R0 (I + hat(eta)) has the same first
        # derivative as R0 exp(eta) and costs less.
        R = R0 + R0 @ jnp.cross(jnp.eye(3), eta)
        return 0.5 * jnp.sum(J * xi**2) - 0.5 * (
            potential(R) + potential(R @ exp(h * xi))
        )

    def update(carry, _):
        R0, pi0, xi = carry
        zeros = jnp.zeros(3)

        def residual(xi):
            d_eta, d_xi = jax.grad(average, argnums=(0, 1))(zeros, xi, R0)
            return d_xi - pull(h * xi, pi0 + h * d_eta)

        def not_converged(s):
            xi, step, k = s
            return (jnp.max(jnp.abs(step)) > 1e-13 * jnp.max(jnp.abs(xi))) & (k < 20)

        def newton(s):
            xi, _, k = s
            step = jnp.linalg.solve(jax.jacfwd(residual)(xi), residual(xi))
            return xi - step, step, k + 1

        xi, _, _ = jax.lax.while_loop(not_converged, newton, (xi, jnp.ones(3), 0))
        d_eta, _ = jax.grad(average, argnums=(0, 1))(zeros, xi, R0)
        F = exp(h * xi)
        return (R0 @ F, F.T @ (pi0 + h * d_eta), xi), None

    @jax.jit
    def run(y0):
        R0, pi0 = y0
        (R, pi, _), _ = jax.lax.scan(update, (R0, pi0, pi0 / J), None, length=n)
        return R, pi

    return run


def jaxmd_free_body(scene, h, n, energies):
    """jax-md's NVE step for one rigid body without potential: its final state, or
    with `energies` its kinetic energy after every step."""
    from jax_md import rigid_body, simulate, space

    _, shift = space.free()
    init, apply = simulate.nve(lambda body, **_: 0.0 * jnp.sum(body.center), shift, h)
    orientation = rigid_body.Quaternion(jnp.array([[1.0, 0.0, 0.0, 0.0]]))
    mass = rigid_body.RigidBody(jnp.ones((1,)), scene.lagrangian.inertia[None])
    state = init(
        jax.random.PRNGKey(0),
        rigid_body.RigidBody(jnp.zeros((1, 3)), orientation),
        mass=mass,
        kT=0.0,
    )
    momentum = rigid_body.angular_momentum_to_conjugate_momentum(
        orientation, scene.y0[1][None]
    )
    state = state.set(momentum=rigid_body.RigidBody(jnp.zeros((1, 3)), momentum))
    energy = lambda s: rigid_body.kinetic_energy(s.position, s.momentum, s.mass)

    @jax.jit
    def run(state):
        def update(s, _):
            s = apply(s)
            return s, (energy(s) if energies else None)

        return jax.lax.scan(update, state, None, length=n)

    return run, state


def free_body_energy_error(scene, solver, h, n):
    """The largest energy error over n steps at h, from a run saving every step."""
    if solver == "jax-md":
        run, state = jaxmd_free_body(scene, h, n, energies=True)
        _, energies = run(state)
    else:
        sol = dfx.diffeqsolve(
            scene.term(),
            solver,
            0.0,
            h * n,
            h,
            scene.y0,
            saveat=dfx.SaveAt(steps=True),
            max_steps=n,
        )
        energies = jax.vmap(lambda y: scene.energy(0.0, y, None))(sol.ys)
    return float(jnp.max(jnp.abs(energies - scene.energy(0.0, scene.y0, None))))


def equal_error(scene, repeats):
    n = 10_000
    steps = (0.2, 0.1, 0.05)
    methods = {
        "TrapezoidalVI": dvi.TrapezoidalVI(),
        "MidpointVI": dvi.MidpointVI(),
        "jax-md nve": "jax-md",
    }
    print(
        f"\nfree rigid body: largest energy error over {n} steps, error = C h^k fitted "
        f"at h = {steps}, us per step at h = 0.1 (best of {repeats})"
    )
    fits = {}
    for name, solver in methods.items():
        errors = [free_body_energy_error(scene, solver, h, n) for h in steps]
        k, log_c = np.polyfit(np.log(steps), np.log(errors), 1)
        if solver == "jax-md":
            run, state = jaxmd_free_body(scene, 0.1, n, energies=False)
            cost = best_time(run, state, repeats=repeats) / n
        else:
            cost = (
                best_time(
                    final_state(scene.term(), solver, 0.1, n), scene.y0, repeats=repeats
                )
                / n
            )
        fits[name] = (k, log_c, cost)
        print(
            f"  {name:14s} errors {', '.join(f'{e:.2e}' for e in errors)}; "
            f"k = {k:.2f}; {1e6 * cost:7.3f} us per step"
        )
    target = float(np.exp(fits["jax-md nve"][1]) * 0.1 ** fits["jax-md nve"][0])

    def time_to(name):
        k, log_c, cost = fits[name]
        h = np.exp((np.log(target) - log_c) / k)
        return cost / h

    base = time_to("jax-md nve")
    for name in ("TrapezoidalVI", "MidpointVI"):
        print(
            f"  {name:14s} at jax-md's error at h = 0.1 ({target:.2e}): "
            f"{time_to(name) / base:5.2f}x jax-md's wall time per unit time"
        )


def long_run(scene):
    n, h = 1_000_000, 0.1
    print(f"\nfree rigid body, {n} steps at h = {h}:")
    e0 = scene.energy(0.0, scene.y0, None)
    casimir = scene.invariants["casimir"]
    orthogonality = scene.invariants["orthogonality"]
    ts = jnp.linspace(0.0, n * h, 1001)
    for name, solver in (
        ("TrapezoidalVI", dvi.TrapezoidalVI()),
        ("MidpointVI", dvi.MidpointVI()),
    ):
        sol = dfx.diffeqsolve(
            scene.term(),
            solver,
            0.0,
            n * h,
            h,
            scene.y0,
            saveat=dfx.SaveAt(ts=ts),
            max_steps=n + 1,
        )
        error = jnp.abs(jax.vmap(lambda y: scene.energy(0.0, y, None))(sol.ys) - e0)
        c = jax.vmap(lambda y: casimir(0.0, y, None))(sol.ys)
        o = jax.vmap(lambda y: orthogonality(0.0, y, None))(sol.ys)
        print(
            f"  {name:14s} max orthogonality error {float(jnp.max(o)):.1e}, "
            f"Casimir change {float(jnp.max(jnp.abs(c - c[0]))):.1e}, "
            f"energy error first tenth {float(jnp.max(error[1:101])):.2e}, "
            f"last tenth {float(jnp.max(error[-100:])):.2e}"
        )
    run, state = jaxmd_free_body(scene, h, n, energies=True)
    final, energies = run(state)
    error = jnp.abs(energies - e0)
    norm = jnp.linalg.norm(final.position.orientation.vec)
    print(
        f"  {'jax-md nve':14s} quaternion norm error {abs(float(norm) - 1):.1e}, "
        f"energy error first tenth {float(jnp.max(error[: n // 10])):.2e}, "
        f"last tenth {float(jnp.max(error[-n // 10 :])):.2e}"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-long", action="store_true")
    add_xla_option(parser)
    args = parser.parse_args()
    setting = apply_xla_option(args)
    print(
        f"jax {jax.__version__}, diffrax {importlib.metadata.version('diffrax')}, "
        f"device {jax.devices()[0]}, {setting}"
    )
    scene = dvi.scenes.heavy_top()
    term = scene.term()
    n = 20_000
    h = scene.period / 100
    us = lambda t: 1e6 * t / n
    print(
        f"\nheavy top: {n} steps at h = period/100, us per step "
        f"(best of {args.repeats})"
    )
    bare = bare_trapezoidal(scene, h, n)
    trapezoidal = final_state(term, dvi.TrapezoidalVI(), h, n)
    ours, theirs = trapezoidal(scene.y0), bare(scene.y0)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(ours, theirs))
    assert gap < 1e-9, f"TrapezoidalVI and the bare update differ by {gap}"
    t_bare = us(best_time(bare, scene.y0, repeats=args.repeats))
    t_trap = us(best_time(trapezoidal, scene.y0, repeats=args.repeats))
    t_mid = us(
        best_time(
            final_state(term, dvi.MidpointVI(), h, n), scene.y0, repeats=args.repeats
        )
    )
    t_tsit = us(
        best_time(final_state(term, dfx.Tsit5(), h, n), scene.y0, repeats=args.repeats)
    )
    print(f"  bare lax.scan, trapezoidal LGVI    {t_bare:9.3f} us")
    print(
        f"  TrapezoidalVI in diffeqsolve       {t_trap:9.3f} us = "
        f"{t_trap / t_bare:5.2f}x the bare update (target <= 1.3; states agree to "
        f"{gap:.1e})"
    )
    print(
        f"  MidpointVI in diffeqsolve          {t_mid:9.3f} us = "
        f"{t_mid / t_bare:5.2f}x the bare trapezoidal update"
    )
    print(f"  Tsit5 in diffeqsolve               {t_tsit:9.3f} us")
    free_body = dvi.scenes.free_rigid_body()
    equal_error(free_body, args.repeats)
    if not args.skip_long:
        long_run(free_body)


if __name__ == "__main__":
    main()
