"""Per-step cost on SO(3), as ratios from one run: the heavy top (Lagrange top) and
the free rigid body.

Each solver in `diffrax.diffeqsolve` (saving only t1) over a bare `jax.lax.scan` of
the same update written here by hand, at its floor: small products as sums, 3 x 3
solves in closed form (by cross products), the exponential and its derivative in
closed form (the package's), no LAPACK call and no custom fusion in
the loop (checked with `diffrax_vi.diagnostics.compiled_loop_breakers`), Newton
iterated until the residual relative to its terms is below sqrt(eps) and then once
more, as the solvers' Newton does; each pair checked to agree:

- LGVI, the Cayley Lie group variational integrator of Lee, Leok & McClamroch
  (target <= 1.3x): by default, its momentum's increment added with Kahan's
  compensated sum in both, and with plain sums in both (`compensated=False`);
- TrapezoidalVI and MidpointVI with the exponential map: Newton on the three
  unknowns of $\\partial_\\xi\\Lambda = J_l(-h\\xi)(\\Pi_0 +
  h\\partial_g\\Lambda)$, then $R_1 = R_0\\exp(h\\xi)$, $\\Pi_1 =
  \\exp(h\\xi)^\\top(\\Pi_0 + h\\partial_g\\Lambda)$ (target <= 1.3x);
- Tsit5 on the `LagrangianTerm` over Tsit5 on a hand-written `ODETerm` of the same
  equations, $\\dot R = R\\hat\\Omega$, $\\dot\\Pi = \\Pi\\times\\Omega + M$
  (target <= 1.2x);
- the free rigid body against jax-md's rigid-body integrator (the symplectic
  quaternion splitting of Miller et al. 2002, `jax_md.simulate.nve`; the `bench`
  extra): each method's largest energy error over 10^4 steps at three step sizes
  (from a run that saves every step, not timed), and its time per unit of simulated
  time against jax-md's at h = 0.1, at the same step and at equal or lower energy
  error;
- the free rigid body over 10^6 steps at h = 0.1 (`--skip-long` skips it):
  orthogonality, the Casimir's change and the energy error in the first and last
  tenth, for LGVI, TrapezoidalVI, MidpointVI and jax-md (its quaternion's norm).

By default the script runs at the small-loop threshold `import diffrax_vi` sets;
`--xla-default` keeps XLA's default threshold.

Run: `taskset -c 1 python benchmarks/lie_groups.py [--repeats 5] [--xla-default]`.
"""

import argparse

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402

# The exponential and the transpose of its derivative (J_l(-x) w) are the package's
# closed forms, Rodrigues' formula sharing one sine and cosine with its derivative:
# the fastest written yet (the MidpointVI update took 1.53 us through jaxlie's
# quaternion, 1.08 us with these).
from diffrax_vi._so3 import _exp as exp, _exp_pull as pull  # noqa: E402
from step_cost import (  # noqa: E402
    add_xla_option,
    apply_xla_option,
    best_time,
    best_times,
    final_state,
    kahan_add,
    versions,
)


def hat(w):
    """The skew matrix of `w` (of each vector of a stack)."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], -1),
            jnp.stack([z, zero, -x], -1),
            jnp.stack([-y, x, zero], -1),
        ],
        -2,
    )


# hat(e_i), the generators of so(3).
GENERATORS = np.array(
    [
        [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
        [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
    ]
)


def hat_linear(w):
    """`hat(w)` as its contraction with the generators, for a vector that reverse
    mode differentiates: `hat`'s transpose is made of pads, and the exponential-map
    updates took 1.18 against 1.08 us with it; where nothing is transposed,
    `hat` is the faster (LGVI 0.104 against 0.107 us, Tsit5's field 0.299 against
    0.320 us)."""
    return jnp.sum(w[:, None, None] * GENERATORS, axis=0)


def matmul(a, b):
    """`a @ b` for 3 x 3 matrices (of each pair of a stack), as a sum (a small `dot`
    can become a custom fusion that breaks the loop into kernels)."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def rmatvec(a, x):
    """`a.T @ x`, as a sum."""
    return jnp.sum(a * x[:, None], axis=0)


def cayley(x):
    """(I - x^/2)^{-1} (I + x^/2)."""
    x_hat = hat(x)
    c = 4 / (4 + jnp.sum(x**2))
    return jnp.eye(3) + c * (x_hat + 0.5 * matmul(x_hat, x_hat))


def cross_rows(a):
    """The rows of the cofactor matrix of `a` (3 x 3), by cross products."""
    return jnp.stack(
        [jnp.cross(a[1], a[2]), jnp.cross(a[2], a[0]), jnp.cross(a[0], a[1])]
    )


def solve3(a, b):
    """`a^{-1} b` for a 3 x 3 `a`, in closed form: the cofactors' rows are the
    columns of `det(a) a^{-1}`."""
    cof = cross_rows(a)
    return jnp.sum(cof * b[:, None], axis=0) / jnp.sum(a[0] * cof[0])


def newton(residual, jacobian, x, max_steps=16):
    """Newton's method until the residual relative to its terms (`residual`
    returns both) is below sqrt(eps), then one more update, as the solvers'."""
    tol = float(jnp.finfo(x.dtype).eps) ** 0.5

    def body(s):
        x, _, k = s
        r, size = residual(x)
        rho = jnp.max(jnp.abs(r) / jnp.where(size > 0, size, 1))
        return x - solve3(jacobian(x), r), rho, k + 1

    def going(s):
        _, rho, k = s
        return (rho > tol) & (k < max_steps)

    return jax.lax.while_loop(going, body, (x, jnp.inf, 0))[0]


def rigid_body(scene):
    """The heavy top's inertia and torque M(R) = -weight * chi x (R^T e3)."""
    lag = scene.lagrangian
    J, chi, weight = lag.inertia, lag.centre, lag.weight
    return J, lambda R: -weight * jnp.cross(chi, R[2])


def bare_lgvi(scene, h, n, compensated=False):
    """Lee, Leok & McClamroch's Cayley LGVI as a bare scan: Newton on f in
    2 J f = g + g x f + (f.g) f, g = h (Pi + h/2 M), Jacobian 2J - g^ - (f.g) I
    - f g^T in closed form. With `compensated`, the momentum's increment is added
    with Kahan's compensated sum, as `LGVI()` (the default) adds it."""
    J, torque = rigid_body(scene)

    def update(carry, _):
        R0, pi0, m0, f, f_before, c = carry
        kicked = pi0 + 0.5 * h * m0
        g = h * kicked

        def residual(f):
            gf, fg = jnp.cross(g, f), jnp.sum(f * g)
            r = 2 * J * f - g - gf - fg * f
            return r, 2 * J * jnp.abs(f) + jnp.abs(g) + jnp.abs(gf) + jnp.abs(fg * f)

        def jacobian(f):
            fg = jnp.sum(f * g)
            return jnp.diag(2 * J - fg) - hat(g) - f[:, None] * g[None, :]

        # From the extrapolation of the last two steps, as the solvers guess.
        f_new = newton(residual, jacobian, 2 * f - f_before)
        F = cayley(2 * f_new)
        R1 = matmul(R0, F)
        m1 = torque(R1)
        dp = rmatvec(F, kicked) + 0.5 * h * m1 - pi0
        if compensated:
            pi1, c = kahan_add(pi0, dp, c)
        else:
            pi1 = pi0 + dp
        return (R1, pi1, m1, f_new, f, c), None

    @jax.jit
    def run(y0):
        R0, pi0 = y0
        f0 = 0.5 * h * pi0 / J
        (R, pi, *_), _ = jax.lax.scan(
            update, (R0, pi0, torque(R0), f0, f0, jnp.zeros_like(pi0)), None, length=n
        )
        return R, pi

    return run


def bare_exp_vi(scene, h, n, rule):
    """TrapezoidalVI (`rule="trapezoidal"`) or MidpointVI (`"midpoint"`) on SO(3)
    with the exponential map, as a bare scan: Newton on the step velocity xi of
    d_xi Lambda = J_l(-h xi)(Pi0 + h d_g Lambda), its Jacobian by forward-mode
    differentiation, written with sums and a closed-form 3 x 3 solve."""
    J, torque = rigid_body(scene)
    lag = scene.lagrangian
    potential = lambda R: lag.potential(0.0, R, None)

    def average(eta, xi, R0):
        # Differentiated at eta = 0 only: R0 (I + hat(eta)) has the same first
        # derivative as R0 exp(eta) and costs less.
        R = R0 + matmul(R0, hat_linear(eta))
        kinetic = 0.5 * jnp.sum(J * xi**2)
        if rule == "midpoint":
            return kinetic - potential(matmul(R, exp(0.5 * h * xi)))
        return kinetic - 0.5 * (potential(R) + potential(matmul(R, exp(h * xi))))

    zeros = jnp.zeros(3)

    def update(carry, _):
        R0, pi0, xi, xi_before = carry

        def residual(xi):
            d_eta, d_xi = jax.grad(average, argnums=(0, 1))(zeros, xi, R0)
            kicked = pi0 + h * d_eta
            r = d_xi - pull(h * xi, kicked)
            return r, jnp.abs(d_xi) + jnp.abs(pi0) + jnp.abs(h * d_eta)

        jacobian = jax.jacfwd(lambda x: residual(x)[0])
        # From the extrapolation of the last two steps, as the solvers guess.
        xi_new = newton(residual, jacobian, 2 * xi - xi_before)
        d_eta, _ = jax.grad(average, argnums=(0, 1))(zeros, xi_new, R0)
        F = exp(h * xi_new)
        return (matmul(R0, F), rmatvec(F, pi0 + h * d_eta), xi_new, xi), None

    @jax.jit
    def run(y0):
        R0, pi0 = y0
        xi0 = pi0 / J
        (R, pi, *_), _ = jax.lax.scan(update, (R0, pi0, xi0, xi0), None, length=n)
        return R, pi

    return run


def euler_ode_term(scene):
    """Euler's equations of the rigid body written by hand: R' = R Omega^,
    Pi' = Pi x Omega + M(R), Omega = Pi / J."""
    J, torque = rigid_body(scene)

    def field(t, y, args):
        R, pi = y
        omega = pi / J
        return matmul(R, hat(omega)), jnp.cross(pi, omega) + torque(R)

    return dfx.ODETerm(field)


def agreement(ours, theirs):
    return max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(ours, theirs))


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
    steps = (0.4, 0.2, 0.1, 0.05)
    methods = {
        "LGVI": dvi.LGVI(),
        "TrapezoidalVI": dvi.TrapezoidalVI(),
        "MidpointVI": dvi.MidpointVI(),
        "jax-md nve": "jax-md",
    }
    print(
        f"\nfree rigid body: largest energy error over {n} steps at h = {steps}; "
        f"us per step at h = 0.1 (best of {repeats}); time per unit of simulated "
        "time over jax-md's at h = 0.1, at the same h and at the largest h whose "
        "energy error is at most jax-md's"
    )
    rows = {}
    for name, solver in methods.items():
        errors = [free_body_energy_error(scene, solver, h, n) for h in steps]
        if solver == "jax-md":
            run, state = jaxmd_free_body(scene, 0.1, n, energies=False)
            cost = best_time(run, state, repeats=repeats) / n
        else:
            run = final_state(scene.term(), solver, 0.1, n)
            cost = best_time(run, scene.y0, repeats=repeats) / n
        rows[name] = (errors, cost)
    target = rows["jax-md nve"][0][steps.index(0.1)]
    base = rows["jax-md nve"][1] / 0.1
    for name, (errors, cost) in rows.items():
        # Per-step cost hardly depends on h (Newton's iterations grow slowly).
        h_equal = max(h for h, e in zip(steps, errors) if e <= target * (1 + 1e-9))
        print(
            f"  {name:14s} errors {', '.join(f'{e:.2e}' for e in errors)}; "
            f"{1e6 * cost:7.3f} us per step; {cost / 0.1 / base:5.2f}x jax-md at "
            f"h = 0.1, {cost / h_equal / base:5.2f}x at h = {h_equal}"
        )


def long_run(scene):
    n, h = 1_000_000, 0.1
    print(f"\nfree rigid body, {n} steps at h = {h}:")
    e0 = scene.energy(0.0, scene.y0, None)
    casimir = scene.invariants["casimir"]
    orthogonality = scene.invariants["orthogonality"]
    ts = jnp.linspace(0.0, n * h, 1001)
    for name, solver in (
        ("LGVI", dvi.LGVI()),
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
    print(f"{versions()}, device {jax.devices()[0]}, {setting}")
    scene = dvi.scenes.heavy_top()
    term = scene.term()
    n = 20_000
    h = scene.period / 100
    print(
        f"\nheavy top: {n} steps at h = period/100, us per step "
        f"(best of {args.repeats}), each pair timed in turns"
    )
    us = lambda t: 1e6 * t / n
    pairs = (
        ("LGVI", dvi.LGVI(), bare_lgvi(scene, h, n, compensated=True), 1.3),
        (
            "LGVI, plain sums",
            dvi.LGVI(compensated=False),
            bare_lgvi(scene, h, n),
            1.3,
        ),
        (
            "TrapezoidalVI",
            dvi.TrapezoidalVI(),
            bare_exp_vi(scene, h, n, "trapezoidal"),
            1.3,
        ),
        ("MidpointVI", dvi.MidpointVI(), bare_exp_vi(scene, h, n, "midpoint"), 1.3),
        ("Tsit5", dfx.Tsit5(), None, 1.2),
    )
    for name, solver, bare, target in pairs:
        ours = final_state(term, solver, h, n)
        if bare is None:
            bare = final_state(euler_ode_term(scene), solver, h, n)
            what = "Tsit5 on a hand-written ODETerm"
        else:
            what = f"bare lax.scan of {name}"
        for fn in (ours, bare):
            breakers = dvi.diagnostics.compiled_loop_breakers(fn, scene.y0)
            assert not breakers, f"{name}: a loop is broken into kernels: {breakers}"
        gap = agreement(ours(scene.y0), bare(scene.y0))
        assert gap < 1e-9, f"{name} and the {what} differ by {gap}"
        t_ours, t_bare = best_times([ours, bare], scene.y0, repeats=args.repeats)
        print(
            f"  {name:16s} {us(t_ours):7.3f} us, {what} {us(t_bare):7.3f} us: "
            f"{t_ours / t_bare:5.2f}x (target <= {target}; states agree to "
            f"{gap:.1e})"
        )
    free_body = dvi.scenes.free_rigid_body()
    equal_error(free_body, args.repeats)
    if not args.skip_long:
        long_run(free_body)


if __name__ == "__main__":
    main()
