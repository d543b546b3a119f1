"""Per-step cost on SO(3), as ratios from one run: the heavy top (Lagrange top).

- TrapezoidalVI in diffeqsolve (saving only t1) over a bare `jax.lax.scan` of the
  same update, written here by hand: Newton on the three unknowns of
  $\\partial_\\xi\\Lambda = J_l(-h\\xi)(\\Pi_0 + h\\partial_g\\Lambda)$, iterated to
  1e-13, then $R_1 = R_0\\exp(h\\xi)$, $\\Pi_1 = \\exp(h\\xi)^\\top(\\Pi_0 +
  h\\partial_g\\Lambda)$ (target <= 1.3x), checked to agree;
- MidpointVI the same way (its own discrete Lagrangian, the Lie midpoint);
- Tsit5 on the same `LagrangianTerm` at the same step, which leaves SO(3).

By default the script first calls `diffrax_vi.compile_small_loops_whole()`, as the
command line does; `--xla-default` keeps XLA's default threshold.

Run: `taskset -c 1 python benchmarks/lie_groups.py [--repeats 5] [--xla-default]`.
"""

import argparse
import importlib.metadata

import diffrax as dfx
import jax
import jax.numpy as jnp
import jaxlie


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402
from step_cost import add_xla_option, apply_xla_option, best_time  # noqa: E402


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
        R = R0 @ exp(eta)
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


def solve(term, solver, h, n):
    @jax.jit
    def run(y0):
        sol = dfx.diffeqsolve(
            term, solver, 0.0, h * n, h, y0, saveat=dfx.SaveAt(t1=True), max_steps=n
        )
        return jax.tree.map(lambda x: x[-1], sol.ys)

    return run


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
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
    trapezoidal = solve(term, dvi.TrapezoidalVI(), h, n)
    ours, theirs = trapezoidal(scene.y0), bare(scene.y0)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(ours, theirs))
    assert gap < 1e-9, f"TrapezoidalVI and the bare update differ by {gap}"
    t_bare = us(best_time(bare, scene.y0, repeats=args.repeats))
    t_trap = us(best_time(trapezoidal, scene.y0, repeats=args.repeats))
    t_mid = us(
        best_time(solve(term, dvi.MidpointVI(), h, n), scene.y0, repeats=args.repeats)
    )
    t_tsit = us(
        best_time(solve(term, dfx.Tsit5(), h, n), scene.y0, repeats=args.repeats)
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


if __name__ == "__main__":
    main()
