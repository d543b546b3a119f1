"""The seed thesis's lemmas and theorems as tests, at random points and along random
curves, for several Lagrangians including a nonlinear 2-DOF one."""

import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import pytest

from .helpers import (
    DoublePendulum,
    Duffing,
    fitted_order,
    max_abs_diff,
    reference,
    stiffening,
)


LAGRANGIANS = [
    ("oscillator", dvi.SeparableLagrangian(lambda t, q, a: 0.5 * jnp.sum(q**2)), 1),
    ("duffing", Duffing(), 1),
    ("double-pendulum", DoublePendulum(), 2),
    ("stiffening", dvi.Lagrangian(stiffening), 2),
]
IDS = [name for name, _, _ in LAGRANGIANS]


def _shape(n):
    return () if n == 1 else (n,)


def _curve(key, n):
    """A random polynomial curve q(t) of degree 5."""
    coeffs = 0.3 * jax.random.normal(key, (6, *_shape(n)))
    return lambda t: sum(c * t**i for i, c in enumerate(coeffs))


def _d(f):
    """Time derivative of a function of t along the curve."""
    return lambda t: jax.jvp(f, (t,), (jnp.ones_like(t),))[1]


def _euler_lagrange(lagrangian, q, v):
    """EL(L) along the curve (q(t), v(t) = dq/dt): dL/dq - d/dt dL/dv."""
    dl_dq = lambda t: jax.grad(lambda x: lagrangian(t, x, v(t), None))(q(t))
    dl_dv = lambda t: jax.grad(lambda x: lagrangian(t, q(t), x, None))(v(t))
    return lambda t: jtu.tree_map(jnp.subtract, dl_dq(t), _d(dl_dv)(t))


@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS, ids=IDS)
def test_lemma_2_acceleration_lift_is_null(name, lagrangian, n, getkey):
    # L~(q, qdot, qddot) = dL/dq qdot + dL/dv qddot, the lift along the acceleration,
    # has Euler-Lagrange equations dL~/dq - d/dt dL~/dqdot + d2/dt2 dL~/dqddot = 0.
    lift = dvi.TangentLift(lagrangian)
    q = _curve(getkey(), n)
    qd, qdd = _d(q), _d(_d(q))
    ltilde = lambda x, xd, xdd: lift(0.0, (x, xd), (xd, xdd), None)
    part = lambda i: lambda t: jax.grad(ltilde, argnums=i)(q(t), qd(t), qdd(t))
    el = lambda t: part(0)(t) - _d(part(1))(t) + _d(_d(part(2)))(t)
    ts = jnp.linspace(-1.0, 1.0, 5)
    values = jax.vmap(el)(ts)
    scale = float(jnp.max(jnp.abs(jax.vmap(part(0))(ts))))
    assert float(jnp.max(jnp.abs(values))) < 1e-12 * (1 + scale)
    # Not a trivial identity: the same expression for L itself does not vanish.
    assert (
        float(jnp.max(jnp.abs(jax.vmap(_euler_lagrange(lagrangian, q, qd))(ts)))) > 1e-3
    )


@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS, ids=IDS)
def test_lemma_3_tangent_lift_euler_lagrange(name, lagrangian, n, getkey):
    # EL(L2) on the curve (q, u) with u = qdot: its u-part is EL(L), its q-part is
    # d/dt EL(L).
    lift = dvi.TangentLift(lagrangian)
    q = _curve(getkey(), n)
    qd = _d(q)
    z = lambda t: (q(t), qd(t))  # configuration (q, u = qdot)
    zd = _d(z)
    el2 = _euler_lagrange(lift, z, zd)
    el = _euler_lagrange(lagrangian, q, qd)
    ts = jnp.linspace(-1.0, 1.0, 5)
    el2_q, el2_u = jax.vmap(el2)(ts)
    assert jnp.allclose(el2_u, jax.vmap(el)(ts), rtol=1e-11, atol=1e-11)
    assert jnp.allclose(el2_q, jax.vmap(_d(el))(ts), rtol=1e-11, atol=1e-11)


def _random_triple(key, n, scale=0.4):
    k1, k2, k3 = jax.random.split(key, 3)
    return tuple(scale * jax.random.normal(k, _shape(n)) for k in (k1, k2, k3))


@pytest.mark.parametrize("rule", [dvi.MidpointRule(), dvi.TrapezoidalRule()])
@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS, ids=IDS)
def test_lemma_5_midpoint_of_lift_is_lift_of_midpoint(
    name, lagrangian, n, rule, getkey
):
    # The discrete Lagrangian of L2 equals dLd . (u0, u1): (4.34) and Lemma 5 (which
    # holds for the trapezoidal rule too).
    q0, q1, _ = _random_triple(getkey(), n)
    u0, u1, _ = _random_triple(getkey(), n)
    lifted = dvi.discrete_lagrangian(
        rule, dvi.TangentLift(lagrangian), 0.1, 0.15, (q0, u0), (q1, u1), None
    )
    linearized = dvi.diagnostics.tangent_discrete_lagrangian(
        rule, lagrangian, 0.1, 0.15, (q0, u0), (q1, u1)
    )
    assert jnp.allclose(lifted, linearized, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS, ids=IDS)
def test_lemma_4_discrete_lift_is_discrete_derivative(name, lagrangian, n, getkey):
    # DEL(Ld2) at ((q_k, u_k)) with forward u_k: its u-part is DEL(Ld), its q-part is
    # the JVP of DEL(Ld) along the u's, the seed's (4.63).
    rule = dvi.MidpointRule()
    h = 0.05
    ts = (0.0, h, 2 * h, 3 * h)
    qs = _random_triple(getkey(), n) + (0.4 * jax.random.normal(getkey(), _shape(n)),)
    us = [jtu.tree_map(lambda a, b: (b - a) / h, qs[i], qs[i + 1]) for i in range(3)]
    zs = [(qs[i], us[i]) for i in range(3)]
    lifted = dvi.diagnostics.del_residual(
        rule, dvi.TangentLift(lagrangian), ts[:3], tuple(zs), None
    )
    residual = lambda a, b, c: dvi.diagnostics.del_residual(
        rule, lagrangian, ts[:3], (a, b, c), None
    )
    _, derivative = jax.jvp(residual, tuple(qs[:3]), tuple(us))
    q_part, u_part = lifted
    assert jnp.allclose(u_part, residual(*qs[:3]), rtol=1e-12, atol=1e-12)
    assert jnp.allclose(q_part, derivative, rtol=1e-11, atol=1e-11)
    if name == "oscillator":
        # For a linear DEL the JVP is exactly the difference quotient of F.
        later = dvi.diagnostics.del_residual(
            rule, lagrangian, ts[1:], tuple(qs[1:]), None
        )
        quotient = (later - residual(*qs[:3])) / h
        assert jnp.allclose(q_part, quotient, rtol=1e-10, atol=1e-10)


def _state(lagrangian, q0, v0):
    return q0, dvi.momentum(lagrangian, 0.0, q0, v0)


@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS[2:], ids=IDS[2:])
def test_theorem_1_midpoint_on_lift_is_tangent_of_flow(name, lagrangian, n, getkey):
    q0, v0, u0 = _random_triple(getkey(), n)
    _, pq0, _ = _random_triple(getkey(), n)
    y0 = _state(lagrangian, q0, v0)
    solve = lambda L, y: (
        dfx.diffeqsolve(
            dvi.LagrangianTerm(L),
            dvi.MidpointVI(),
            0.0,
            1.0,
            0.05,
            y,
            adjoint=dfx.ForwardMode(),
        ).ys
    )
    flow = lambda y: jax.tree.map(lambda x: x[-1], solve(lagrangian, y))
    (q1, p1), (u1, pq1) = jax.jvp(flow, (y0,), ((u0, pq0),))
    lifted = solve(dvi.TangentLift(lagrangian), ((y0[0], u0), (pq0, y0[1])))
    (lq, lu), (lpq, lpu) = jax.tree.map(lambda x: x[-1], lifted)
    # The q-part is MidpointVI on L; the u-part is its tangent map.
    assert max_abs_diff((lq, lpu), (q1, p1)) < 1e-12
    assert max_abs_diff((lu, lpq), (u1, pq1)) < 1e-10


def _on_S(lagrangian, q0, q1, h):
    """Complete (q0, q1) to a triple on S by one DEL step."""
    rule = dvi.MidpointRule()
    p1 = jax.grad(
        lambda b: dvi.discrete_lagrangian(rule, lagrangian, 0.0, h, q0, b, None)
    )(q1)
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(lagrangian),
        dvi.MidpointVI(),
        h,
        2 * h,
        h,
        (q1, p1),
        adjoint=dfx.ForwardMode(),
    )
    return sol.ys[0][-1]


def _triple_map(lagrangian, h):
    """The linearized algorithm Psi on triples, (q0, q1, q2) -> (q1, q2, q3)."""
    solver = dvi.LinearizedVI()
    term = dvi.LagrangianTerm(lagrangian)
    rule = dvi.MidpointRule()

    def psi(triple):
        q0, q1, q2 = triple
        p2 = jax.grad(
            lambda b: dvi.discrete_lagrangian(rule, lagrangian, h, 2 * h, q1, b, None)
        )(q2)
        state = solver.init_from_history((q1, q0), (h, h), (q2, p2))
        (q3, _), *_ = solver.step(term, 2 * h, 3 * h, (q2, p2), None, state, False)
        return q1, q2, q3

    return psi


@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS, ids=IDS)
def test_theorem_2_presymplectic_on_S(name, lagrangian, n, getkey):
    h = 0.1
    q0, q1, _ = _random_triple(getkey(), n)
    q2 = _on_S(lagrangian, q0, q1, h)
    rule = dvi.MidpointRule()
    residual = dvi.diagnostics.del_residual(
        rule, lagrangian, (0.0, h, 2 * h), (q0, q1, q2), None
    )
    assert float(jnp.max(jnp.abs(residual))) < 1e-12

    # Tangent vectors of S: S is the graph of (q0, q1) -> q2 (Proposition 4).
    def chart(a, b):
        return a, b, _on_S(lagrangian, a, b, h)

    # Each map is compiled once and applied to several tangent vectors.
    chart_jvp = jax.jit(lambda da, db: jax.jvp(chart, (q0, q1), (da, db))[1])

    def tangent(key):
        da, db, _ = _random_triple(key, n, scale=1.0)
        return chart_jvp(da, db)

    xi, eta = tangent(getkey()), tangent(getkey())
    psi = _triple_map(lagrangian, h)
    psi_jvp = jax.jit(lambda v: jax.jvp(psi, ((q0, q1, q2),), (v,)))
    ts = (0.0, h, 2 * h)
    omega = lambda x, a, b, t: dvi.diagnostics.presymplectic_form(
        rule, lagrangian, t, x, a, b
    )
    image, dxi = psi_jvp(xi)
    _, deta = psi_jvp(eta)
    before = omega((q0, q1, q2), xi, eta, ts)
    after = omega(image, dxi, deta, (h, 2 * h, 3 * h))
    assert abs(float(before)) > 1e-3  # a non-trivial pairing
    assert abs(float(after - before)) < 1e-10 * (1 + abs(float(before)))

    # Off S: vectors that are not tangent to S are not preserved.
    off_xi, off_eta = _random_triple(getkey(), n, 1.0), _random_triple(getkey(), n, 1.0)
    _, off_dxi = psi_jvp(off_xi)
    _, off_deta = psi_jvp(off_eta)
    off_before = omega((q0, q1, q2), off_xi, off_eta, ts)
    off_after = omega(image, off_dxi, off_deta, (h, 2 * h, 3 * h))
    assert abs(float(off_after - off_before)) > 1e-6


@pytest.mark.parametrize("velocity", ["forward", "centered"])
def test_linearized_starts_on_S_and_its_residual_drifts(velocity):
    # Along a Duffing solution the midpoint VI keeps F = 0 to round-off; the
    # linearized method starts on S and drifts off it slowly.
    y0 = (jnp.array(0.5), jnp.array(0.0))
    residual_max = {}
    for solver in (dvi.MidpointVI(), dvi.LinearizedVI(velocity=velocity)):
        sol = dfx.diffeqsolve(
            dvi.LagrangianTerm(Duffing()),
            solver,
            0.0,
            20.0,
            0.02,
            y0,
            saveat=dfx.SaveAt(t0=True, steps=True),
            max_steps=1000,
        )
        ts, qs = sol.ts[:1001], sol.ys[0][:1001]
        res = jnp.abs(dvi.diagnostics.del_residuals(Duffing(), ts, qs))
        residual_max[type(solver).__name__] = (float(res[0]), float(res.max()))
    # Round-off of differencing positions: about eps |q| / h.
    assert residual_max["MidpointVI"][1] < 1e-13
    first, worst = residual_max["LinearizedVI"]
    # Each term of F is of size |q|/h = 25; the drift stays far below that.
    assert first < 1e-8 and 10 * first < worst < 1e-2


@pytest.mark.parametrize("velocity", ["forward", "centered"])
@pytest.mark.parametrize("name,lagrangian,n", LAGRANGIANS, ids=IDS)
def test_linearized_history_lies_on_S(velocity, name, lagrangian, n, getkey):
    # init builds the past by backward variational steps: every triple it forms with
    # the start satisfies the DEL equations.
    q0, v0, _ = _random_triple(getkey(), n)
    y0 = _state(lagrangian, q0, v0)
    h = 0.05
    qs = (
        dvi.LinearizedVI(velocity=velocity)
        .init(dvi.LagrangianTerm(lagrangian), 0.0, h, y0, None)
        .method.positions
    )
    points = (q0,) + qs
    rule = dvi.MidpointRule()
    for k in range(len(qs) - 1):
        triple = (points[k + 2], points[k + 1], points[k])
        ts = (-(k + 2) * h, -(k + 1) * h, -k * h)
        residual = dvi.diagnostics.del_residual(rule, lagrangian, ts, triple, None)
        assert float(jnp.max(jnp.abs(residual))) < 1e-12
    # And p0 is the discrete Legendre transform D2 Ld(q_{-1}, q0).
    p0 = jax.grad(
        lambda b: dvi.discrete_lagrangian(rule, lagrangian, -h, 0.0, qs[0], b, None)
    )(q0)
    assert max_abs_diff(p0, y0[1]) < 1e-12


@pytest.mark.parametrize("velocity", ["forward", "centered"])
def test_linearized_exact_for_linear_del_invariant_residual(velocity):
    # For the oscillator (linear DEL) the residual is kept constant, here zero.
    osc = dvi.SeparableLagrangian(lambda t, q, a: 0.5 * q**2)
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(osc),
        dvi.LinearizedVI(velocity=velocity),
        0.0,
        20.0,
        0.02,
        (jnp.array(1.0), jnp.array(0.0)),
        saveat=dfx.SaveAt(t0=True, steps=True),
        max_steps=1000,
    )
    res = dvi.diagnostics.del_residuals(osc, sol.ts[:1001], sol.ys[0][:1001])
    assert float(jnp.max(jnp.abs(res))) < 1e-12


@pytest.mark.parametrize("velocity,duffing_order", [("forward", 1), ("centered", 2)])
def test_linearized_orders(velocity, duffing_order):
    # Global order 2 on the oscillator (Tables 5.1/5.2). On Duffing the forward
    # variant drops to order 1 (the seed's O(h) local error, Section 5.5) and the
    # centered one (Section 5.6) keeps order 2.
    solver = dvi.LinearizedVI(velocity=velocity)
    ns = [100, 200, 400, 800]
    hs = [5.0 / n for n in ns]
    osc = dvi.SeparableLagrangian(lambda t, q, a: 0.5 * q**2)
    # An array step and one max_steps: one compilation per Lagrangian, not per n.
    final = lambda L, y0, n: dfx.diffeqsolve(
        dvi.LagrangianTerm(L), solver, 0.0, 5.0, jnp.asarray(5.0 / n), y0
    ).ys[0][-1]
    y0 = (jnp.array(1.0), jnp.array(0.0))
    errors = [abs(float(final(osc, y0, n)) - np.cos(5.0)) for n in ns]
    assert abs(fitted_order(hs, errors) - 2) < 0.3, errors
    y0 = (jnp.array(0.5), jnp.array(0.0))
    exact = float(reference(Duffing(), y0, 5.0)[0])
    errors = [abs(float(final(Duffing(), y0, n)) - exact) for n in ns]
    assert abs(fitted_order(hs, errors) - duffing_order) < 0.3, errors
    # The order the solver reports (as diffrax's PIDController reads it) is the
    # fitted one.
    assert dvi.LinearizedVI(velocity=velocity).order(None) == duffing_order


def test_linearized_backward_vmap_grad():
    y0 = (jnp.array(0.5), jnp.array(0.1))
    solve = lambda y, t0, t1, dt: (
        dfx.diffeqsolve(
            dvi.LagrangianTerm(Duffing()),
            dvi.LinearizedVI(velocity="centered"),
            t0,
            t1,
            dt,
            y,
        ).ys
    )
    back = jax.tree.map(lambda x: x[-1], solve(y0, 2.0, 0.0, -0.01))
    exact = reference(Duffing(), y0, 0.0, t0=2.0)
    assert max_abs_diff(back, exact) < 1e-4  # O(h^2) = 2.3e-5 here, backwards in time
    batched = jax.vmap(lambda q: solve((q, jnp.array(0.0)), 0.0, 1.0, 0.05)[0][-1])(
        jnp.array([0.3, 0.5])
    )
    assert jnp.allclose(
        batched[1], solve((jnp.array(0.5), jnp.array(0.0)), 0.0, 1.0, 0.05)[0][-1]
    )
    f = lambda q: solve((q, jnp.array(0.0)), 0.0, 1.0, 0.05)[0][-1]
    eps = 1e-6
    assert jnp.allclose(
        jax.grad(f)(jnp.array(0.5)),
        (f(jnp.array(0.5 + eps)) - f(jnp.array(0.5 - eps))) / (2 * eps),
        rtol=1e-6,
    )


def test_linearized_bad_velocity(as_a_user_runs_it):
    with pytest.raises(ValueError, match="'forward' or 'centered'"):
        dvi.LinearizedVI(velocity="backward")


def test_linearized_with_trapezoidal_discrete_lagrangian():
    # The discrete Lagrangian is a parameter: the history lies on the trapezoidal S,
    # and the method is second order on the oscillator.
    rule = dvi.TrapezoidalRule()
    solver = dvi.LinearizedVI(discrete_lagrangian=rule)
    osc = dvi.SeparableLagrangian(lambda t, q, a: 0.5 * q**2)
    term = dvi.LagrangianTerm(osc)
    y0 = (jnp.array(1.0), jnp.array(0.0))
    qs = solver.init(term, 0.0, 0.05, y0, None).method.positions
    residual = dvi.diagnostics.del_residual(
        rule, osc, (-0.1, -0.05, 0.0), (qs[1], qs[0], y0[0]), None
    )
    assert abs(float(residual)) < 1e-13
    midpoint_residual = dvi.diagnostics.del_residual(
        dvi.MidpointRule(), osc, (-0.1, -0.05, 0.0), (qs[1], qs[0], y0[0]), None
    )
    assert abs(float(midpoint_residual)) > 1e-6  # a different S
    ns = [100, 200, 400, 800]
    errors = [
        abs(
            float(
                dfx.diffeqsolve(term, solver, 0.0, 5.0, jnp.asarray(5.0 / n), y0).ys[0][
                    -1
                ]
            )
            - np.cos(5.0)
        )
        for n in ns
    ]
    assert abs(fitted_order([5.0 / n for n in ns], errors) - 2) < 0.3, errors
