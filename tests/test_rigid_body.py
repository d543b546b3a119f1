"""Rigid bodies with declared constant inertia: the Cayley Lie group variational
integrator of Lee, Leok & McClamroch (LGVI), the Cayley retraction of SO(3), and
Runge–Kutta steps whose velocity map is settled when the term is built. References:
scipy on Euler's equations written by hand (test_lie.py) and the LGVI's own discrete
equations in matrix form."""

import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from .test_lie import _errors, _final, _weightless_top


def _slope(steps, errors):
    return -np.polyfit(np.log(steps), np.log(errors), 1)[0]


# The free body as a top of zero weight: one Lagrangian class, one compilation.
_TOP, _FREE = dvi.scenes.heavy_top, _weightless_top


# Steps in the asymptotic range: the Cayley LGVI's error constant is larger than
# the exponential midpoint's (fast spins take a phase error), and a composition's
# long substeps need Newton's iteration to converge (yoshida4 at h = 0.5 on the free
# body does not).
@pytest.mark.parametrize(
    "make,t1,solver,order,steps",
    [
        (_TOP, 1.0, dvi.LGVI(), 2, (40, 80, 160)),
        (_FREE, 10.0, dvi.LGVI(), 2, (40, 80, 160)),
        (_TOP, 1.0, dvi.Composition(dvi.LGVI(), "yoshida4"), 4, (40, 80, 160)),
        (_FREE, 10.0, dvi.Composition(dvi.LGVI(), "yoshida4"), 4, (40, 80, 160)),
        (_FREE, 10.0, dvi.Composition(dvi.LGVI(), "kahan_li6"), 6, (20, 40, 80)),
        (_FREE, 10.0, dvi.Composition(dvi.LGVI(), "kahan_li8"), 8, (20, 40, 80)),
    ],
    ids=["top", "free", "top-yoshida4", "free-yoshida4", "kahan_li6", "kahan_li8"],
)
def test_lgvi_order_against_scipy(make, t1, solver, order, steps):
    errors = _errors(make(), solver, t1, steps)
    assert abs(_slope(steps, errors) - order) < 0.3, errors


def test_lgvi_solves_lees_discrete_equations():
    """One step of the 3D pendulum (torque from a centre of mass off every axis)
    against the equations of Lee, Leok & McClamroch in matrix form:
    h (Pi0 + h/2 M0)^ = F Jd - Jd F^T, Pi1 = F^T (Pi0 + h/2 M0) + h/2 M1, with
    F = R0^T R1, Jd = tr(J)/2 I - J and the torque M = -w chi x (R^T e3), written
    here with NumPy's matrix products."""
    scene = dvi.scenes.pendulum_3d()
    lag = scene.lagrangian
    J, chi, w = (np.asarray(x) for x in (lag.inertia, lag.centre, lag.weight))
    h = 0.05
    y1 = _final(scene, dvi.LGVI(), h, h).ys
    R0, pi0 = (np.asarray(x) for x in scene.y0)
    R1, pi1 = np.asarray(y1[0][-1]), np.asarray(y1[1][-1])
    torque = lambda R: -w * np.cross(chi, R[2])
    F = R0.T @ R1
    Jd = 0.5 * np.sum(J) * np.eye(3) - np.diag(J)
    g = h * (pi0 + 0.5 * h * torque(R0))
    skew = F @ Jd - Jd @ F.T
    np.testing.assert_allclose(
        [skew[2, 1], skew[0, 2], skew[1, 0]], g, rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(skew, -skew.T, rtol=0, atol=1e-15)
    expected = F.T @ (pi0 + 0.5 * h * torque(R0)) + 0.5 * h * torque(R1)
    np.testing.assert_allclose(pi1, expected, rtol=0, atol=1e-14)


def test_lgvi_keeps_a_free_bodys_energy_to_round_off():
    """10^5 steps at h = 0.1: the energy and the Casimir |Pi| to 1e-13, R on SO(3)
    to 1e-12 (the exponential-map midpoint's energy error is 5.6e-5 here)."""
    scene = dvi.scenes.free_rigid_body()
    n = 100_000
    ts = jnp.linspace(0.0, 0.1 * n, 201)
    ys = _final(scene, dvi.LGVI(), 0.1 * n, 0.1, dfx.SaveAt(ts=ts), n + 1).ys
    energy = jax.vmap(lambda y: scene.energy(0.0, y, None))(ys)
    casimir = jax.vmap(lambda y: scene.invariants["casimir"](0.0, y, None))(ys)
    orthogonality = jax.vmap(lambda y: scene.invariants["orthogonality"](0.0, y, None))
    assert jnp.max(jnp.abs(energy - energy[0])) < 1e-13
    assert jnp.max(jnp.abs(casimir - casimir[0])) < 1e-13
    assert jnp.max(orthogonality(ys)) < 1e-12


def test_lgvi_keeps_the_heavy_tops_noether_momenta():
    scene = dvi.scenes.heavy_top()
    y1 = _final(scene, dvi.LGVI(), 100.0, 0.01, max_steps=10_001).ys
    y1 = (y1[0][-1], y1[1][-1])
    for name in ("vertical_momentum", "spin"):
        fn = scene.invariants[name]
        assert abs(fn(0.0, y1, None) - fn(0.0, scene.y0, None)) < 1e-11, name


class _CayleyTop(dvi.AbstractRigidBodyLagrangian):
    inertia: jax.Array
    centre: jax.Array
    weight: jax.Array
    space = dvi.SO3(retraction="cayley")

    def potential(self, t, R, args):
        return self.weight * jnp.sum(R[2] * self.centre)


@pytest.mark.parametrize("solver", [dvi.MidpointVI(), dvi.TrapezoidalVI()])
def test_the_cayley_retraction_keeps_each_solvers_order(solver):
    top = dvi.scenes.heavy_top()
    cayley = dvi.scenes.Scene(
        name="cayley_top",
        lagrangian=_CayleyTop(
            top.lagrangian.inertia, top.lagrangian.centre, top.lagrangian.weight
        ),
        y0=top.y0,
        period=top.period,
    )
    steps = (40, 80, 160)
    errors = _errors(cayley, solver, 1.0, steps)
    assert abs(_slope(steps, errors) - 2) < 0.3, errors
    R = _final(cayley, solver, 1.0, 0.01, max_steps=101).ys[0][-1]
    assert jnp.max(jnp.abs(R.T @ R - jnp.eye(3))) < 1e-14


def test_cayley_maps_against_their_definitions():
    """tau(x) = (I - x^/2)^-1 (I + x^/2) by a dense solve; its inverse; pull as the
    transposed right derivative by automatic differentiation; transport as
    tau(x)^T w."""
    space = dvi.SO3(retraction="cayley")
    rng = np.random.default_rng(1)
    for scale in (0.0, 1e-6, 0.3, 3.0):
        x = jnp.asarray(rng.normal(size=3)) * scale
        w = jnp.asarray(rng.normal(size=3))
        hat = np.cross(np.eye(3), np.asarray(x))
        tau = np.linalg.solve(np.eye(3) - 0.5 * hat, np.eye(3) + 0.5 * hat)
        F = space.retract(jnp.eye(3), x)
        np.testing.assert_allclose(F, tau, rtol=0, atol=1e-14)
        np.testing.assert_allclose(space.difference(jnp.eye(3), F), x, atol=1e-14)
        np.testing.assert_allclose(space.transport(x, w), tau.T @ w, atol=1e-14)

        def right(y):
            r, dr = jax.jvp(lambda z: space.retract(jnp.eye(3), z), (x,), (y,))
            skew = dr @ r.T
            return jnp.stack([skew[2, 1], skew[0, 2], skew[1, 0]])

        definition = jax.linear_transpose(right, x)(w)[0]
        np.testing.assert_allclose(space.pull(x, w), definition, atol=1e-14)


def test_an_unknown_retraction_names_the_choices(as_a_user_runs_it):
    with pytest.raises(ValueError, match="'exp' or 'cayley'"):
        dvi.SO3(retraction="quaternion")


def test_what_lgvi_cannot_take_says_what_to_use():
    kepler = dvi.scenes.kepler()
    with pytest.raises(ValueError, match="AbstractRigidBodyLagrangian"):
        dfx.diffeqsolve(kepler.term(), dvi.LGVI(), 0.0, 1.0, 0.1, kepler.y0)
    top = dvi.scenes.heavy_top()
    damped = dvi.LagrangianTerm(top.lagrangian, force=lambda t, R, v, a: -v)
    with pytest.raises(ValueError, match="MidpointVI"):
        dfx.diffeqsolve(damped, dvi.LGVI(), 0.0, 1.0, 0.1, top.y0)


@pytest.mark.parametrize(
    "solver", [dvi.LGVI(), dvi.MidpointVI(), dvi.TrapezoidalVI(), dfx.Tsit5()]
)
def test_a_zero_moment_of_inertia_or_mass_is_singular_not_a_nan(solver):
    """As the errors page says: `singular` from the implicit solvers, and the
    degenerate-Lagrangian message (not a force's) from Runge-Kutta."""
    top = dvi.scenes.free_rigid_body()
    rigid = type(top.lagrangian)(jnp.array([1.0, 0.0, 1.0]))
    massless = dvi.Lagrangian(lambda t, q, v, args: 0.0 * jnp.sum(v**2) - q @ q)
    cases = [(rigid, top.y0), (massless, (jnp.ones(2), jnp.zeros(2)))]
    if isinstance(solver, dvi.LGVI):
        cases = cases[:1]
    for lagrangian, y0 in cases:
        solve = lambda: dfx.diffeqsolve(
            dvi.LagrangianTerm(lagrangian), solver, 0.0, 1.0, 0.1, y0, throw=False
        )
        if isinstance(solver, dfx.Tsit5):
            with pytest.raises(Exception, match="The Lagrangian is degenerate"):
                solve()
        else:
            assert solve().result == dfx.RESULTS.singular


@pytest.mark.parametrize(
    "solver",
    [
        dvi.LGVI(),
        dvi.Composition(dvi.LGVI(), "yoshida4"),
        dvi.MidpointVI(),
        dvi.TrapezoidalVI(),
    ],
    ids=["LGVI", "yoshida4(LGVI)", "MidpointVI", "TrapezoidalVI"],
)
def test_a_non_finite_start_on_the_group_is_nonfinite(solver):
    """A NaN attitude or an infinite momentum is `nonfinite` at the first step,
    whatever Newton's method makes of it, and before a singular inertia: the start
    of an implicit step takes its velocity p0 / I unchecked, and the first step's
    check of its start reports it."""
    scene = dvi.scenes.free_rigid_body()
    R0, pi0 = scene.y0
    lag = scene.lagrangian
    flat = type(lag)(jnp.array([1.0, 0.0, 1.0]))
    solve = lambda lagrangian, y0: dfx.diffeqsolve(
        dvi.LagrangianTerm(lagrangian), solver, 0.0, 1.0, 0.1, y0, throw=False
    )
    for lagrangian in (lag, flat):
        for y0 in ((R0.at[1, 2].set(jnp.nan), pi0), (R0, pi0.at[0].set(jnp.inf))):
            sol = solve(lagrangian, y0)
            assert sol.result == dfx.RESULTS.nonfinite
            assert sol.stats["num_steps"] == 1
    assert solve(lag, scene.y0).result == dfx.RESULTS.successful


def test_lgvi_moves_the_attitude_once_per_step(monkeypatch):
    """The step computes its new attitude R0 cay(f) for the torque at the end and
    hands it to the engine (`MethodStep.q1`), which moves the state with it instead
    of retracting again: a second 3 x 3 product per step, 4% of the heavy top's
    step. Retractions counted in one traced step (each call is one in the program;
    the engine's own would be a second); over 50 steps the states are those of the
    engine's own retraction, to round-off (bitwise here)."""
    import dataclasses

    from diffrax_vi._solver import base, lgvi

    class Retracting(dvi.LGVI):
        def method_step(self, step, state, made_jump):
            out = super().method_step(step, state, made_jump)
            return dataclasses.replace(out, q1=None)

    scene = _TOP()
    term = scene.term()
    ours, theirs = (_final(scene, s, 0.5, 0.01).ys for s in (dvi.LGVI(), Retracting()))
    assert max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(ours, theirs)) < 1e-13

    calls = []
    for module in (base, lgvi):
        monkeypatch.setattr(
            module,
            "retract",
            lambda *a, _retract=module.retract: calls.append(1) or _retract(*a),
        )
    solver = dvi.LGVI()

    def step(y0):
        state = solver.init(term, 0.0, 0.01, y0, scene.args)
        return solver.step(term, 0.0, 0.01, y0, scene.args, state, False)

    jax.make_jaxpr(step)(scene.y0)
    assert len(calls) == 1


def test_runge_kutta_on_a_rigid_body_runs_as_on_eulers_equations():
    """The velocity Pi / J is settled when the term is built: Tsit5 on the term
    takes the same steps as on Euler's equations written by hand, with no check in
    its vector field (the loop holds no host callback)."""
    scene = dvi.scenes.heavy_top()
    lag = scene.lagrangian
    assert scene.term().mass_checked

    def euler(t, y, args):
        R, pi = y
        omega = pi / lag.inertia
        torque = -lag.weight * jnp.cross(lag.centre, R[2])
        hat = jnp.array(
            [
                [0.0, -omega[2], omega[1]],
                [omega[2], 0.0, -omega[0]],
                [-omega[1], omega[0], 0.0],
            ]
        )
        return R @ hat, jnp.cross(pi, omega) + torque

    ours = _final(scene, dfx.Tsit5(), 1.0, 0.01, max_steps=101).ys
    theirs = dfx.diffeqsolve(
        dfx.ODETerm(euler), dfx.Tsit5(), 0.0, 1.0, 0.01, scene.y0
    ).ys
    for a, b in zip(ours, theirs):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    "solver", [dvi.MidpointVI(), dvi.LGVI()], ids=["MidpointVI", "LGVI"]
)
def test_a_start_attitude_off_the_group_is_refused(solver):
    """A start matrix off orthogonality by 1e-3, or a reflection, would run as a
    "successful" solve that stays off SO(3): refused, with how to project it. One
    off by round-off (1e-12) runs."""
    scene = dvi.scenes.free_rigid_body()
    R0, pi0 = scene.y0
    solve = jax.jit(
        lambda R: dfx.diffeqsolve(scene.term(), solver, 0.0, 0.5, 0.1, (R, pi0)).ys
    )
    nudge = jnp.zeros((3, 3)).at[0, 1].set(1.0)
    for R in (R0 + 1e-3 * nudge, jnp.diag(jnp.array([1.0, 1.0, -1.0]))):
        with pytest.raises(Exception, match="not on its group") as caught:
            jax.block_until_ready(solve(R))
        assert "jnp.linalg.svd" in str(caught.value)
    R, _ = solve(R0 + 1e-12 * nudge)
    assert np.max(np.abs(R[-1].T @ R[-1] - np.eye(3))) < 1e-11


def test_a_planar_angle_off_the_group_is_refused():
    L = dvi.Lagrangian(lambda t, q, v, args: 0.5 * v**2 + q[0, 0], space=dvi.SO2())
    R0 = jnp.array([[1.0, 0.0], [0.0, -1.0]])  # a reflection
    with pytest.raises(Exception, match="not on its group"):
        dfx.diffeqsolve(
            dvi.LagrangianTerm(L), dvi.MidpointVI(), 0.0, 0.3, 0.1, (R0, jnp.array(0.0))
        )


def test_a_torque_of_the_wrong_shape_names_the_angular_velocitys(as_a_user_runs_it):
    """A torque shaped like the matrix R is refused with the body angular
    velocity's shape, and the fix the message gives runs."""
    scene = dvi.scenes.free_rigid_body()

    def solve(force):
        term = dvi.LagrangianTerm(scene.lagrangian, force=force)
        return dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 0.2, 0.1, scene.y0)

    with pytest.raises(ValueError, match=r"velocity has shape \(3,\)") as caught:
        solve(lambda t, q, v, args: jnp.full_like(q, 0.1))
    assert "jnp.full_like(v, value)" in str(caught.value)
    sol = solve(lambda t, q, v, args: jnp.full_like(v, 0.1))
    assert sol.result == dfx.RESULTS.successful


def test_runge_kutta_with_a_nan_torque_fails_clearly_in_fixed_steps():
    """solve_fixed_steps with Tsit5 and a NaN torque: on a rigid body (its velocity
    map settled, no check in the loop) it returns RESULTS.nonfinite; on a general
    Lagrangian on SO(3) the term's own message is raised, as diffeqsolve raises it,
    not a failed host callback."""
    scene = dvi.scenes.free_rigid_body()
    nan_torque = lambda t, q, v, args: jnp.full_like(v, jnp.nan)
    rigid = dvi.LagrangianTerm(scene.lagrangian, force=nan_torque)
    sol = dvi.solve_fixed_steps(rigid, dfx.Tsit5(), 0.0, 1.0, 0.1, scene.y0)
    assert sol.result == dfx.RESULTS.nonfinite
    J = scene.lagrangian.inertia
    general = dvi.Lagrangian(
        lambda t, q, v, args: 0.5 * jnp.sum(J * v**2), space=dvi.SO3()
    )
    term = dvi.LagrangianTerm(general, force=nan_torque)
    with pytest.raises(Exception, match="NaN or inf at a finite state") as caught:
        dvi.solve_fixed_steps(term, dfx.Tsit5(), 0.0, 1.0, 0.1, scene.y0)
    assert "INTERNAL" not in str(caught.value)
