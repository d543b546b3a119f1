"""Variational integrators on Lie groups: rigid bodies on SO(3), SO(2) and products,
against scipy on Euler's equations with dR/dt = R hat(Omega) (torque written by hand,
not by our derivatives)."""

import math
from fractions import Fraction

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
import scipy.integrate


def _euler_reference(scene, t1):
    """Euler's equations of the rigid body in gravity, Pi' = Pi x Omega + w Gamma x
    chi (Gamma = R^T e3), R' = R hat(Omega), by scipy at rtol 1e-13."""
    lagrangian = scene.lagrangian
    J = np.asarray(lagrangian.inertia)
    chi = np.asarray(lagrangian.centre)
    w = float(lagrangian.weight)

    def rhs(t, y):
        R, pi = y[:9].reshape(3, 3), y[9:]
        omega = pi / J
        torque = w * np.cross(R[2], chi)
        hat = np.array(
            [
                [0.0, -omega[2], omega[1]],
                [omega[2], 0.0, -omega[0]],
                [-omega[1], omega[0], 0.0],
            ]
        )
        return np.concatenate([(R @ hat).ravel(), np.cross(pi, omega) + torque])

    y0 = np.concatenate([np.asarray(scene.y0[0]).ravel(), np.asarray(scene.y0[1])])
    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, t1), y0, method="DOP853", rtol=1e-13, atol=1e-13
    )
    return sol.y[:9, -1].reshape(3, 3), sol.y[9:, -1]


def _final(scene, solver, t1, dt, saveat=None, max_steps=4096):
    # Times as arrays: one compilation serves every step size.
    sol = dfx.diffeqsolve(
        scene.term(),
        solver,
        0.0,
        jnp.asarray(t1),
        jnp.asarray(dt),
        scene.y0,
        saveat=saveat or dfx.SaveAt(t1=True),
        max_steps=max_steps,
    )
    assert sol.result == dfx.RESULTS.successful
    return sol


def _errors(scene, solver, t1, steps):
    """The largest error in `(R, Pi)` at `t1` against scipy, for each number of
    steps."""
    R_ref, pi_ref = _euler_reference(scene, t1)
    errors = []
    for n in steps:
        sol = _final(scene, solver, t1, t1 / n)
        R, pi = np.asarray(sol.ys[0][-1]), np.asarray(sol.ys[1][-1])
        errors.append(max(np.max(np.abs(R - R_ref)), np.max(np.abs(pi - pi_ref))))
    return errors


def _weightless_top():
    """The free rigid body as a heavy top of zero weight."""
    scene = dvi.scenes.free_rigid_body()
    top = dvi.scenes.RigidBodyLagrangian(
        scene.lagrangian.inertia, jnp.zeros(3), jnp.asarray(0.0)
    )
    return eqx.tree_at(lambda s: s.lagrangian, scene, top)


def _sines(fn, *args) -> int:
    """How many sines a traced program computes (at any depth)."""

    def count(jaxpr):
        return sum(
            (eqn.primitive.name == "sin")
            + sum(count(sub) for sub in jax.extend.core.jaxprs_in_params(eqn.params))
            for eqn in jaxpr.eqns
        )

    return count(jax.make_jaxpr(fn)(*args).jaxpr)


@pytest.mark.parametrize(
    "solver", [dvi.MidpointVI(), dvi.TrapezoidalVI()], ids=["Midpoint", "Trapezoidal"]
)
def test_a_lagrangian_that_reads_no_attitude_moves_none(solver):
    """The free body's Lagrangian does not read the attitude, so its steps build
    no moved attitude for it (an exponential map, with sines, that every Newton
    matrix and gradient would differentiate) where a heavy top of zero weight, whose
    potential reads it, does; and they take the same steps (MidpointVI, 20 steps:
    to round-off)."""
    free, top = dvi.scenes.free_rigid_body(), _weightless_top()

    def solve(scene):
        def run(y0):
            sol = dfx.diffeqsolve(
                scene.term(), solver, 0.0, 2.0, 0.1, y0, saveat=dfx.SaveAt(t1=True)
            )
            return sol.ys

        return run

    assert _sines(solve(free), free.y0) < _sines(solve(top), top.y0)
    if isinstance(solver, dvi.MidpointVI):
        ours = jax.jit(solve(free))(free.y0)
        theirs = jax.jit(solve(top))(top.y0)
        for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs)):
            assert float(jnp.max(jnp.abs(a - b))) < 1e-14 * float(jnp.max(jnp.abs(b)))


@pytest.mark.parametrize(
    "solver,order,steps",
    [
        (dvi.MidpointVI(), 2, (40, 80, 160)),
        (dvi.TrapezoidalVI(), 2, (40, 80, 160)),
        (dvi.Composition(dvi.MidpointVI(), "yoshida4"), 4, (20, 40, 80)),
        (dvi.Composition(dvi.TrapezoidalVI(), "kahan_li6"), 6, (10, 20, 40)),
        (dvi.Composition(dvi.MidpointVI(), "kahan_li8"), 8, (10, 15, 20)),
    ],
    ids=["midpoint", "trapezoidal", "yoshida4", "kahan_li6", "kahan_li8"],
)
@pytest.mark.parametrize(
    "make,t1",
    [
        (dvi.scenes.heavy_top, 1.0),
        pytest.param(_weightless_top, 10.0, id="free_rigid_body-10.0"),
    ],
)
def test_order_on_the_heavy_top_and_the_free_body(make, t1, solver, order, steps):
    # One RigidBodyLagrangian class with array parameters (the free body as a top
    # of zero weight), and times as arrays: the free body reuses the heavy top's
    # compiled solves. Its slower motion takes a longer horizon to keep the eighth
    # order's errors above round-off.
    errors = _errors(make(), solver, t1, steps)
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.3, (slope, errors)


def test_free_rigid_body_keeps_the_group_the_casimir_and_bounded_energy():
    """10^5 steps at h = 0.1: R orthogonal and |Pi| constant to round-off, the
    energy error oscillating without drift (last tenth within 2x the first)."""
    scene = dvi.scenes.free_rigid_body()
    n = 100_000
    ts = jnp.linspace(0.0, 0.1 * n, 201)
    sol = _final(scene, dvi.MidpointVI(), 0.1 * n, 0.1, dfx.SaveAt(ts=ts), n + 1)
    ys = sol.ys
    energy = jax.vmap(lambda y: scene.energy(0.0, y, None))(ys)
    error = jnp.abs(energy - scene.energy(0.0, scene.y0, None))
    casimir = jax.vmap(lambda y: scene.invariants["casimir"](0.0, y, None))(ys)
    orthogonality = jax.vmap(lambda y: scene.invariants["orthogonality"](0.0, y, None))(
        ys
    )
    assert jnp.max(orthogonality) < 1e-12
    assert jnp.max(jnp.abs(casimir - casimir[0])) < 1e-12
    first, last = jnp.max(error[1:21]), jnp.max(error[-20:])
    assert 0 < last < 2 * first, (first, last)


def test_heavy_top_keeps_its_noether_momenta():
    """Rotations about the vertical and about the symmetric body's axis are
    symmetries: the discrete Noether theorem keeps both momenta to round-off."""
    scene = dvi.scenes.heavy_top()
    y1 = _final(scene, dvi.TrapezoidalVI(), 100.0, 0.01, max_steps=10_001).ys
    y1 = (y1[0][-1], y1[1][-1])
    for name in ("vertical_momentum", "spin"):
        fn = scene.invariants[name]
        assert abs(fn(0.0, y1, None) - fn(0.0, scene.y0, None)) < 1e-11, name


def test_pendulum_3d_converges_and_keeps_its_vertical_momentum():
    """The 3D pendulum (centre of mass off every principal axis): second order
    against scipy, and the vertical momentum, its one Noether momentum, kept to
    round-off over 2000 steps while Tsit5 lets it move."""
    scene = dvi.scenes.pendulum_3d()
    t1 = 1.0
    R_ref, pi_ref = _euler_reference(scene, t1)
    steps = (40, 80, 160)
    errors = []
    for n in steps:
        sol = _final(scene, dvi.TrapezoidalVI(), t1, t1 / n)
        R, pi = np.asarray(sol.ys[0][-1]), np.asarray(sol.ys[1][-1])
        errors.append(max(np.max(np.abs(R - R_ref)), np.max(np.abs(pi - pi_ref))))
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - 2) < 0.3, (slope, errors)
    momentum = scene.invariants["vertical_momentum"]
    start = momentum(0.0, scene.y0, None)
    h = scene.period / 100
    for solver, bound in ((dvi.TrapezoidalVI(), 1e-12), (dfx.Tsit5(), None)):
        y1 = _final(scene, solver, 2000 * h, h).ys
        moved = abs(momentum(0.0, (y1[0][-1], y1[1][-1]), None) - start)
        if bound is None:
            assert moved > 1e-9, moved
        else:
            assert moved < bound, moved


def test_runge_kutta_on_the_same_term_drifts_off_the_group():
    scene = dvi.scenes.free_rigid_body()
    orthogonality = scene.invariants["orthogonality"]
    for solver, bound in ((dfx.Tsit5(), None), (dvi.MidpointVI(), 1e-13)):
        y = _final(scene, solver, 100.0, 0.1).ys
        off = orthogonality(0.0, (y[0][-1], y[1][-1]), None)
        if bound is None:
            assert off > 1e-9
        else:
            assert off < bound


def test_so2_pendulum_equals_the_angle_form():
    """SO(2) is abelian: the pendulum as a rotation matrix steps exactly as the angle
    form of the same Lagrangian, to round-off."""
    angle = lambda R: jnp.arctan2(R[1, 0], R[0, 0])
    as_rotation = dvi.Lagrangian(
        lambda t, R, w, args: 0.5 * w**2 + jnp.cos(angle(R)), space=dvi.SO2()
    )
    as_angle = dvi.Lagrangian(lambda t, q, v, args: 0.5 * v**2 + jnp.cos(q))
    q0, p0 = jnp.array(1.0), jnp.array(0.3)
    R0 = jnp.array([[jnp.cos(q0), -jnp.sin(q0)], [jnp.sin(q0), jnp.cos(q0)]])
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI()):
        a = dfx.diffeqsolve(
            dvi.LagrangianTerm(as_rotation), solver, 0.0, 10.0, 0.05, (R0, p0)
        ).ys
        b = dfx.diffeqsolve(
            dvi.LagrangianTerm(as_angle), solver, 0.0, 10.0, 0.05, (q0, p0)
        ).ys
        assert abs(angle(a[0][-1]) - b[0][-1]) < 1e-12
        assert abs(a[1][-1] - b[1][-1]) < 1e-12


@pytest.mark.slow  # the coupled product is tested on the satellite below
def test_product_space_steps_each_factor():
    """On R^3 x SO(3), q = (x, R): an uncoupled particle and free body step as each
    would alone."""
    J = jnp.array([2.0, 1.0, 2.0 / 3.0])
    body = lambda W: 0.5 * jnp.sum(J * W**2)
    particle = lambda x, v: 0.5 * jnp.sum(v**2) - 0.5 * jnp.sum(x**2)
    both = dvi.Lagrangian(
        lambda t, q, v, args: particle(q[0], v[0]) + body(v[1]),
        space=(dvi.Euclidean(), dvi.SO3()),
    )
    x0, px0 = jnp.array([1.0, 0.0, 0.5]), jnp.array([0.0, 1.0, 0.0])
    R0, pi0 = jnp.eye(3), jnp.array([jnp.cos(1.1), 0.0, jnp.sin(1.1)])
    solve = lambda L, y0: (
        dfx.diffeqsolve(dvi.LagrangianTerm(L), dvi.MidpointVI(), 0.0, 5.0, 0.05, y0).ys
    )
    (x, R), (px, pi) = solve(both, ((x0, R0), (px0, pi0)))
    alone_x = solve(dvi.Lagrangian(lambda t, x, v, a: particle(x, v)), (x0, px0))
    alone_R = solve(
        dvi.Lagrangian(lambda t, R, W, a: body(W), space=dvi.SO3()), (R0, pi0)
    )
    assert jnp.max(jnp.abs(x - alone_x[0])) < 1e-13
    assert jnp.max(jnp.abs(px - alone_x[1])) < 1e-13
    assert jnp.max(jnp.abs(R - alone_R[0])) < 1e-13
    assert jnp.max(jnp.abs(pi - alone_R[1])) < 1e-13


def test_gradients_wrt_inertia_and_initial_attitude_equal_finite_differences():
    scene = dvi.scenes.heavy_top()

    @eqx.filter_jit
    def loss(inertia, tilt):
        lagrangian = eqx.tree_at(lambda L: L.inertia, scene.lagrangian, inertia)
        c, s = jnp.cos(tilt), jnp.sin(tilt)
        R0 = jnp.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
        sol = dfx.diffeqsolve(
            dvi.LagrangianTerm(lagrangian),
            dvi.MidpointVI(),
            0.0,
            1.0,
            0.02,
            (R0, scene.y0[1]),
        )
        return jnp.sum(sol.ys[0][-1][:, 2] * jnp.array([1.0, 2.0, 3.0]))

    inertia, tilt = scene.lagrangian.inertia, jnp.asarray(0.3)
    g_inertia, g_tilt = jax.grad(loss, argnums=(0, 1))(inertia, tilt)
    eps = 1e-6
    for i in range(3):
        e = jnp.zeros(3).at[i].set(eps)
        fd = (loss(inertia + e, tilt) - loss(inertia - e, tilt)) / (2 * eps)
        assert abs(g_inertia[i] - fd) < 1e-6 * (1 + abs(fd))
    fd = (loss(inertia, tilt + eps) - loss(inertia, tilt - eps)) / (2 * eps)
    assert abs(g_tilt - fd) < 1e-6 * (1 + abs(fd))


def test_what_a_group_cannot_take_says_what_to_use():
    scene = dvi.scenes.free_rigid_body()
    term = scene.term()
    for solver, match in (
        (dvi.GaussVPRK(2), "Composition"),
        (dvi.LinearizedVI(), "MidpointVI"),
    ):
        with pytest.raises(ValueError, match=match):
            dfx.diffeqsolve(term, solver, 0.0, 1.0, 0.1, scene.y0)
    with pytest.raises(ValueError, match="group"):
        dvi.terms_for(dvi.StormerVerlet(), scene.lagrangian)
    with pytest.raises(ValueError, match="group"):
        dvi.TangentLift(scene.lagrangian)
    with pytest.raises(ValueError, match=r"\(3,\)"):
        dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 1.0, 0.1, (jnp.eye(3), jnp.eye(3)))


def test_so3_pull_is_the_transposed_right_derivative_of_exp():
    """The closed form (the left Jacobian of SO(3), transposed) against its
    definition, (d exp^R_x)^T with d exp^R_x(y) = vee(D exp(x)[y] exp(x)^T), by
    automatic differentiation of jaxlie's exp, across the series threshold."""
    space = dvi.SO3()
    exp = lambda x: jaxlie.SO3.exp(x).as_matrix()

    def definition(x, w):
        def right(y):
            r, dr = jax.jvp(exp, (x,), (y,))
            skew = dr @ r.T
            return 0.5 * jnp.stack(
                [
                    skew[2, 1] - skew[1, 2],
                    skew[0, 2] - skew[2, 0],
                    skew[1, 0] - skew[0, 1],
                ]
            )

        return jax.linear_transpose(right, x)(w)[0]

    rng = np.random.default_rng(0)
    for scale in (0.0, 1e-9, 1e-3, 9e-3, 1.1e-2, 0.3, 3.0):
        x = jnp.asarray(rng.normal(size=3)) * scale
        w = jnp.asarray(rng.normal(size=3))
        assert jnp.max(jnp.abs(space.pull(x, w) - definition(x, w))) < 1e-14, scale


def test_so3_exp_coefficients_derivatives_equal_their_exact_series():
    """The derivatives of the exponential's coefficients c_m(s) = sum_k (-1)^k s^k /
    (2k + m)! (m = 1, 2, 3; s = |x|^2), which a step's Newton matrix takes, against
    their series summed exactly in rationals, across both thresholds (the values'
    series below |x| = 1e-2, the derivatives' below 1/2)."""
    from diffrax_vi._so3 import _exp_coefficients

    rng = np.random.default_rng(2)
    direction = rng.normal(size=3)
    for scale in (1e-5, 9e-3, 1.01e-2, 2e-2, 0.1, 0.49, 0.51, 1.0, 3.0):
        x = direction / np.linalg.norm(direction) * scale
        dx = rng.normal(size=3)
        _, tangents = jax.jvp(_exp_coefficients, (jnp.asarray(x),), (jnp.asarray(dx),))
        s = sum(Fraction(float(v)) ** 2 for v in x)
        ds = 2 * sum(Fraction(float(a)) * Fraction(float(b)) for a, b in zip(x, dx))
        for m, tangent in zip((1, 2, 3), tangents):
            slope = sum(
                Fraction((-1) ** k * k, math.factorial(2 * k + m)) * s ** (k - 1)
                for k in range(1, 40)
            )
            exact = float(slope * ds)
            assert abs(float(tangent) - exact) <= 1e-12 * abs(exact), (scale, m)


def test_so3_cross_products_equal_numpys():
    """SO(3)'s cross product (`hat(a) b` for one pair, `jnp.cross` for a stack)
    against NumPy's, with its reverse-mode derivative against the product rule:
    d(a x b) = da x b + a x db."""
    from diffrax_vi._so3 import cross

    rng = np.random.default_rng(0)
    for shape in [(3,), (4, 3)]:
        a, b, c = (jnp.asarray(rng.normal(size=shape)) for _ in range(3))
        assert np.max(np.abs(cross(a, b) - np.cross(a, b))) < 1e-15
        da, db = jax.grad(lambda a, b: jnp.sum(c * cross(a, b)), argnums=(0, 1))(a, b)
        # c . (a x b) = a . (b x c) = b . (c x a).
        assert np.max(np.abs(da - np.cross(b, c))) < 1e-15
        assert np.max(np.abs(db - np.cross(c, a))) < 1e-15


def test_so3_exp_and_its_derivatives_equal_jaxlies():
    """The exponential map and its closed-form derivative, D exp(x)[y] = exp(x)
    hat(J(x)^T y), against jaxlie's exp and automatic differentiation through its
    quaternion: values, first and second derivatives (a step's Newton matrix takes
    the second), one attitude and a stack, across the series threshold."""
    space = dvi.SO3()
    ours = lambda x: space.retract(jnp.eye(3), x)
    reference = lambda x: jaxlie.SO3.exp(x).as_matrix()
    rng = np.random.default_rng(1)
    # Compiled once for every scale: run op by op, the Hessians took 11 s.
    pairs = [
        (jax.jit(derivative(ours)), jax.jit(derivative(reference)))
        for derivative in (lambda f: f, jax.jacfwd, jax.hessian)
    ]
    for scale in (0.0, 1e-9, 1e-3, 9e-3, 1.1e-2, 0.3, 3.0):
        x = jnp.asarray(rng.normal(size=3)) * scale
        for a, b in pairs:
            assert jnp.max(jnp.abs(a(x) - b(x))) < 1e-12, scale
    xs = jnp.asarray(rng.normal(size=(4, 3)))
    stack = lambda x: space.retract(jnp.broadcast_to(jnp.eye(3), (4, 3, 3)), x)
    jac = jax.jacfwd(stack)(xs)
    assert jnp.max(jnp.abs(jac - jax.jacfwd(jax.vmap(reference))(xs))) < 1e-14


def _height_monitor(t, y, args):
    # The height of the top's centre of mass, shifted positive: a function of the
    # position alone, so the step sequence is reversible.
    return 1.5 + y[0][2, 2]


def test_reversible_steps_on_the_group_return_to_the_start():
    scene = dvi.scenes.heavy_top(tilt=1.0, spin=3.0)
    term, solver = scene.term(), dvi.MidpointVI()

    def solve(t0, t1, dt0, y0, density=1.0):
        # Times as arrays and one SaveAt: the three solves share one compilation.
        sol = dfx.diffeqsolve(
            term,
            solver,
            jnp.asarray(t0),
            jnp.asarray(t1),
            jnp.asarray(dt0),
            y0,
            stepsize_controller=dvi.ReversibleController(
                _height_monitor, density=jnp.asarray(density)
            ),
            saveat=dfx.SaveAt(steps=True, controller_state=True),
            max_steps=1000,
        )
        last = int(sol.stats["num_accepted_steps"]) - 1
        return sol, (sol.ys[0][last], sol.ys[1][last])

    steps, _ = solve(0.0, 5.0, 0.02, scene.y0)
    t_node = float(steps.ts[199])
    assert float(jnp.ptp(jnp.diff(steps.ts[:200]))) > 1e-3  # the steps varied
    forward, end = solve(0.0, t_node, 0.02, scene.y0)
    _, returned = solve(t_node, 0.0, -0.02, end, forward.controller_state.density)
    for start, back in zip(scene.y0, returned):
        assert jnp.max(jnp.abs(back - start)) < 1e-11
    vertical = scene.invariants["vertical_momentum"]
    assert abs(vertical(0.0, end, None) - vertical(0.0, scene.y0, None)) < 1e-12


def test_solve_fixed_steps_on_the_group_equals_diffeqsolve():
    scene = dvi.scenes.heavy_top()
    term, solver = scene.term(), dvi.TrapezoidalVI()
    fast = dvi.solve_fixed_steps(term, solver, 0.0, 2.0, 0.01, scene.y0)
    sol = dfx.diffeqsolve(term, solver, 0.0, 2.0, 0.01, scene.y0)
    for a, b in zip(fast.ys, sol.ys):
        assert jnp.max(jnp.abs(a[-1] - b[-1])) < 1e-12


def test_float32_on_the_group():
    scene = dvi.scenes.heavy_top()
    cast = lambda x: jnp.asarray(x, jnp.float32)
    lagrangian = jax.tree.map(cast, scene.lagrangian)
    y0 = jax.tree.map(cast, scene.y0)
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(lagrangian),
        dvi.MidpointVI(),
        cast(0.0),
        cast(10.0),
        cast(0.01),
        y0,
        max_steps=1001,
    )
    assert sol.result == dfx.RESULTS.successful
    R, pi = sol.ys[0][-1], sol.ys[1][-1]
    assert R.dtype == jnp.float32 and pi.dtype == jnp.float32
    eps = float(jnp.finfo(jnp.float32).eps)
    # Round-off of 1000 steps in float32, not the method's error.
    assert float(jnp.max(jnp.abs(R.T @ R - jnp.eye(3, dtype=R.dtype)))) < 100 * eps
    vertical = scene.invariants["vertical_momentum"]
    assert abs(vertical(0.0, (R, pi), None) - vertical(0.0, y0, None)) < 1e3 * eps


@pytest.mark.parametrize("solver", [dvi.MidpointVI(), dvi.TrapezoidalVI()])
def test_a_damping_torque_on_a_sphere_decays_the_momentum_exactly(solver):
    """A spherical body (J = j I) under the body torque -c Omega: Pi x Omega = 0, so
    Pi(t) = Pi0 exp(-c t / j) exactly; the discrete Lagrange-d'Alembert principle on
    the group converges to it at order 2."""
    j, c = 2.0, 0.5
    sphere = dvi.Lagrangian(
        lambda t, R, W, args: 0.5 * j * jnp.sum(W**2), space=dvi.SO3()
    )
    term = dvi.LagrangianTerm(sphere, force=lambda t, R, W, args: -c * W)
    pi0 = jnp.array([0.3, -0.4, 1.2])
    t1 = 2.0
    exact = pi0 * jnp.exp(-c * t1 / j)
    errors = []
    steps = (20, 40, 80)
    for n in steps:
        sol = dfx.diffeqsolve(
            term, solver, 0.0, t1, jnp.asarray(t1 / n), (jnp.eye(3), pi0)
        )
        errors.append(float(jnp.max(jnp.abs(sol.ys[1][-1] - exact))))
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - 2) < 0.3, (slope, errors)


def test_satellite_on_a_product_space_converges_and_keeps_its_angular_momentum():
    """R^3 x SO(3), coupled by the gravity-gradient torque: order 2 against scipy on
    the term's Euler-Poincare equations, and the total angular momentum x x p + R Pi
    (the Noether momentum of rotating orbit and attitude together) to round-off."""
    from .helpers import reference

    scene = dvi.scenes.satellite()
    t1 = 1.0
    ref = reference(scene.term(), scene.y0, t1)
    steps = (20, 40, 80)
    errors = []
    for n in steps:
        y = _final(scene, dvi.MidpointVI(), t1, t1 / n, max_steps=1001).ys
        errors.append(
            max(
                float(jnp.max(jnp.abs(a[-1] - b)))
                for a, b in zip(jax.tree.leaves(y), jax.tree.leaves(ref))
            )
        )
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - 2) < 0.3, (slope, errors)
    momentum = scene.invariants["angular_momentum"]
    y = _final(scene, dvi.MidpointVI(), 20.0, 0.02, max_steps=1001).ys
    end = jax.tree.map(lambda x: x[-1], y)
    assert (
        jnp.max(jnp.abs(momentum(0.0, end, None) - momentum(0.0, scene.y0, None)))
        < 1e-12
    )
    # The torque did move momentum between the orbit and the attitude.
    assert jnp.max(jnp.abs(end[1][1] - scene.y0[1][1])) > 1e-4


def test_perturbed_states_stay_on_the_group():
    """`Scene.perturbed` on SO(3) moves each attitude along the group: orthogonal to
    round-off, the first member the scene's own start, the others moved."""
    scene = dvi.scenes.free_rigid_body()
    q, p = scene.perturbed(jax.random.key(0), 8, spread=1e-2)
    gram = jnp.einsum("nji,njk->nik", q, q) - jnp.eye(3)[None]
    assert jnp.max(jnp.abs(gram)) < 1e-14
    assert jnp.array_equal(q[0], scene.y0[0]) and jnp.array_equal(p[0], scene.y0[1])
    assert jnp.min(jnp.max(jnp.abs(q[1:] - q[:1]), axis=(1, 2))) > 1e-4


@pytest.mark.slow  # 35 s compiling; perturbed states are checked above, ensembles in
# test_study, the group's invariants under MidpointVI in the tests above
def test_drift_study_of_an_ensemble_on_the_group():
    """The study's ensemble (vmap over states that `Scene.perturbed` moves along
    SO(3)): every member keeps the group and its Casimir."""
    from diffrax_vi.study import drift

    (midpoint,) = drift(
        dvi.scenes.free_rigid_body(),
        [dvi.MidpointVI()],
        periods=5,
        steps_per_period=50,
        n_save=10,
        ensemble=4,
    ).runs
    assert midpoint.result == "successful"
    assert midpoint.max_error("orthogonality") < 1e-13
    assert midpoint.max_error("casimir") < 1e-13
