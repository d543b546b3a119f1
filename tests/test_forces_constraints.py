"""Forces (the discrete Lagrange–d'Alembert principle) and holonomic constraints
(the constrained discrete Euler–Lagrange equations with RATTLE's projection), against
exact solutions, scipy references and the discrete Noether theorem with forcing."""

import functools

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from diffrax_vi import scenes
from diffrax_vi.study import drift

from .helpers import fitted_order, max_abs_diff, reference


DAMPING = 0.2
DRIVE = (0.3, 1.7)  # amplitude and frequency of a harmonic drive


def _damping(t, q, v, args):
    return -DAMPING * v


def _drive(t, q, v, args):
    return DRIVE[0] * jnp.cos(DRIVE[1] * t) * jnp.ones_like(q)


def _damped_exact(t):
    """The unit oscillator with damping 2 gamma from q = 1, p = 0."""
    gamma = DAMPING / 2
    w = np.sqrt(1 - gamma**2)
    decay = np.exp(-gamma * t)
    return decay * (np.cos(w * t) + gamma / w * np.sin(w * t)), -decay * np.sin(
        w * t
    ) / w


def _driven_exact(t):
    """The unit oscillator driven by A cos(W t) from q = 1, p = 0."""
    a, w = DRIVE
    c = a / (1 - w**2)
    return (1 - c) * np.cos(t) + c * np.cos(w * t), -(1 - c) * np.sin(
        t
    ) - c * w * np.sin(w * t)


@eqx.filter_jit
def _final(terms, solver, y0, t1, dt0, args=None):
    sol = dfx.diffeqsolve(terms, solver, 0.0, t1, dt0, y0, args, max_steps=2048)
    return jax.tree.map(lambda x: x[-1], sol.ys), sol.result


OSCILLATOR = scenes.OscillatorLagrangian()
Y0 = (jnp.array(1.0), jnp.array(0.0))


@pytest.mark.parametrize(
    "name,solver,order,force,exact",
    [
        ("MidpointVI", dvi.MidpointVI(), 2, _damping, _damped_exact),
        ("TrapezoidalVI(implicit)", dvi.TrapezoidalVI(), 2, _damping, _damped_exact),
        ("GaussVPRK(2)", dvi.GaussVPRK(2), 4, _damping, _damped_exact),
        ("GaussVPRK(3)", dvi.GaussVPRK(3), 6, _damping, _damped_exact),
        (
            "yoshida4(MidpointVI)",
            dvi.Composition(dvi.MidpointVI(), "yoshida4"),
            4,
            _damping,
            _damped_exact,
        ),
        ("TrapezoidalVI(explicit)", dvi.TrapezoidalVI(), 2, _drive, _driven_exact),
        ("StormerVerlet", dvi.StormerVerlet(), 2, _drive, _driven_exact),
        (
            "kahan_li6(StormerVerlet)",
            dvi.Composition(dvi.StormerVerlet(), "kahan_li6"),
            6,
            _drive,
            _driven_exact,
        ),
    ],
)
def test_forced_oscillator_order(name, solver, order, force, exact):
    """Fitted orders on the damped (velocity-dependent force) and the driven
    (time-dependent force) oscillator against their exact solutions: 2 for the
    second-order methods, 2s for Gauss, and compositions of forced symmetric methods
    keep the composition's order."""
    terms = dvi.terms_for(solver, dvi.LagrangianTerm(OSCILLATOR, force=force))
    t1 = 5.0
    hs = [0.25, 0.125, 0.0625] if order < 6 else [0.5, 0.25, 0.125]
    errors = []
    for h in hs:
        (q, p), result = _final(terms, solver, Y0, t1, jnp.asarray(h))
        assert result == dfx.RESULTS.successful
        q_exact, p_exact = exact(t1)
        errors.append(max(abs(float(q) - q_exact), abs(float(p) - p_exact)))
    assert abs(fitted_order(hs, errors) - order) < 0.3, errors


def test_runge_kutta_integrates_the_same_forced_term():
    term = dvi.LagrangianTerm(OSCILLATOR, force=_damping)
    sol = dfx.diffeqsolve(
        term,
        dfx.Dopri8(),
        0.0,
        5.0,
        0.01,
        Y0,
        stepsize_controller=dfx.PIDController(rtol=1e-12, atol=1e-12),
    )
    assert max_abs_diff((sol.ys[0][-1], sol.ys[1][-1]), _damped_exact(5.0)) < 1e-10


class Radial(dvi.AbstractSeparableLagrangian):
    """A rotation-invariant anharmonic well in the plane."""

    mass: float = 1.0

    def potential(self, t, q, args):
        r2 = jnp.sum(q**2)
        return 0.5 * r2 + 0.1 * r2**2


def _torque(t, q, v, args):
    """An applied torque tau(t) about the origin: F = tau xi(q) / |q|^2, with
    xi(q) = (-y, x) the generator of rotations, so F . xi(q) = tau(t)."""
    tau = 0.3 * jnp.sin(t)
    return tau * jnp.stack([-q[1], q[0]]) / jnp.sum(q**2)


@pytest.mark.parametrize(
    "name,solver,impulse",
    [
        # Midpoint: f+- = h/2 F(q_mid): xi is linear, so the impulse is h tau(t_mid).
        ("MidpointVI", dvi.MidpointVI(), lambda t, h: h * 0.3 * np.sin(t + h / 2)),
        # Trapezoidal: h/2 (tau(t0) + tau(t1)).
        (
            "TrapezoidalVI",
            dvi.TrapezoidalVI(),
            lambda t, h: h / 2 * 0.3 * (np.sin(t) + np.sin(t + h)),
        ),
        # Gauss: h sum_i b_i tau(t0 + c_i h).
        (
            "GaussVPRK(2)",
            dvi.GaussVPRK(2),
            lambda t, h: (
                h
                / 2
                * 0.3
                * (
                    np.sin(t + (0.5 - np.sqrt(3) / 6) * h)
                    + np.sin(t + (0.5 + np.sqrt(3) / 6) * h)
                )
            ),
        ),
    ],
)
def test_forced_noether_balance(name, solver, impulse):
    """Discrete Noether theorem with forcing (Marsden & West (2001), §3.2): the change
    of angular momentum over each step equals the discrete impulse of the torque,
    f- . xi(q_k) + f+ . xi(q_k+1), to round-off."""
    term = dvi.LagrangianTerm(Radial(), force=_torque)
    h = 0.05
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.1, 0.9]))
    sol = dfx.diffeqsolve(
        term, solver, 0.0, 20.0, h, y0, saveat=dfx.SaveAt(steps=True), max_steps=400
    )
    ok = np.isfinite(np.asarray(sol.ts))
    q, p = (np.asarray(x)[ok] for x in sol.ys)
    ts = np.concatenate([[0.0], np.asarray(sol.ts)[ok]])
    qs = np.concatenate([np.asarray(y0[0])[None], q])
    ps = np.concatenate([np.asarray(y0[1])[None], p])
    angular = qs[:, 0] * ps[:, 1] - qs[:, 1] * ps[:, 0]
    expected = np.array([impulse(t, h) for t in ts[:-1]])
    assert np.max(np.abs(np.diff(angular) - expected)) < 1e-14
    # The torque does change it, by far more than round-off.
    assert np.ptp(angular) > 0.1


def test_velocity_dependent_force_is_refused_by_partitioned_solvers():
    terms = dvi.terms_for(
        dvi.StormerVerlet(), dvi.LagrangianTerm(OSCILLATOR, force=_damping)
    )
    with pytest.raises(ValueError, match="reads its velocity"):
        dfx.diffeqsolve(terms, dvi.StormerVerlet(), 0.0, 1.0, 0.1, Y0)


def test_force_with_the_wrong_structure():
    term = dvi.LagrangianTerm(
        scenes.KeplerLagrangian(), force=lambda t, q, v, args: jnp.zeros(3)
    )
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0]))
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI(), dfx.Tsit5()):
        with pytest.raises(ValueError, match="one component per degree"):
            dfx.diffeqsolve(term, solver, 0.0, 1.0, 0.1, y0)
    term = dvi.LagrangianTerm(
        scenes.KeplerLagrangian(), force=lambda t, q, v, args: (q, q)
    )
    with pytest.raises(ValueError, match="structure of q"):
        dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 1.0, 0.1, y0)


def test_linearized_vi_refuses_forces_and_constraints():
    for term in (
        dvi.LagrangianTerm(OSCILLATOR, force=_damping),
        scenes.cartesian_pendulum().term(),
    ):
        y0 = Y0 if term.constraint is None else scenes.cartesian_pendulum().y0
        with pytest.raises(ValueError, match="MidpointVI or TrapezoidalVI"):
            dfx.diffeqsolve(term, dvi.LinearizedVI(), 0.0, 1.0, 0.1, y0)


# Constraints.


def _pendulum_angle(q):
    return np.arctan2(q[..., 0], -q[..., 1])


@pytest.mark.parametrize(
    "name,solver,order",
    [
        ("MidpointVI", dvi.MidpointVI(), 2),
        ("TrapezoidalVI(RATTLE)", dvi.TrapezoidalVI(), 2),
        (
            "yoshida4(TrapezoidalVI)",
            dvi.Composition(dvi.TrapezoidalVI(), "yoshida4"),
            4,
        ),
    ],
)
def test_cartesian_pendulum_against_angle_pendulum(name, solver, order):
    """The constrained solvers on the Cartesian pendulum converge, at their order, to
    the angle-coordinate pendulum integrated by scipy's DOP853."""
    scene = scenes.cartesian_pendulum(amplitude=2.0)
    t1 = 3.0
    theta, omega = reference(scenes.PendulumLagrangian(), (jnp.array(2.0), 0.0), t1)
    hs = [0.1, 0.05, 0.025]
    errors = []
    for h in hs:
        (q, p), result = _final(scene.term(), solver, scene.y0, t1, jnp.asarray(h))
        assert result == dfx.RESULTS.successful
        q, p = np.asarray(q), np.asarray(p)
        # The angular momentum about the pivot is the angle's momentum.
        errors.append(
            max(
                abs(_pendulum_angle(q) - float(theta)),
                abs(q[0] * p[1] - q[1] * p[0] - float(omega)),
            )
        )
    assert abs(fitted_order(hs, errors) - order) < 0.3, errors


def _constraint_history(scene, solver, h, n):
    """The energy, the constraint values and the hidden constraint G v (the scene's
    invariants) after every step."""
    energy = scene.conserved()["energy"]
    residuals = scene.invariants

    def record(t, y, args):
        return (
            energy(t, y, args),
            residuals["constraint"](t, y, args),
            residuals["hidden_constraint"](t, y, args),
            y[0],
        )

    return dfx.diffeqsolve(
        scene.term(),
        solver,
        0.0,
        n * h,
        h,
        scene.y0,
        saveat=dfx.SaveAt(steps=True, fn=record),
        max_steps=n,
    )


@pytest.mark.parametrize(
    "name,scene,solver",
    [
        ("pendulum", scenes.cartesian_pendulum(), dvi.TrapezoidalVI()),
        ("four_bar", scenes.four_bar(), dvi.MidpointVI()),
    ],
)
def test_constraints_hold_at_every_step_of_1e5(name, scene, solver):
    """10^5 steps: |g(q)| and the hidden constraint |G v| stay at round-off at every
    step, relative to the size of q (and of v), and the energy error stays bounded
    without drift."""
    n = 100_000
    h = scene.period / 50
    sol = _constraint_history(scene, solver, h, n)
    assert sol.result == dfx.RESULTS.successful
    energy, values, hidden, q = (np.asarray(x) for x in sol.ys)
    eps = np.finfo(float).eps
    if name == "pendulum":
        assert np.max(np.abs(values)) < 1e-12
        assert np.max(np.abs(hidden)) < 1e-12
    else:
        # The crank has turned some 2000 times: its angle, ~1.3e4, carries a
        # round-off of 1.3e4 eps, and g(q) is at round-off relative to that.
        assert q[-1, 0] - q[0, 0] > 2000 * 2 * np.pi
        assert np.max(np.abs(values)) < 4 * eps * np.max(np.abs(q))
        # G(q) has the same round-off, times speeds of a few radians per unit time.
        assert np.max(np.abs(hidden)) < 16 * eps * np.max(np.abs(q))
    error = np.abs(energy - energy[0])
    decile = n // 10
    assert error[-decile:].max() < 1.5 * error[:decile].max()
    assert error.max() < 0.05 * abs(energy[0]) + 0.05


def test_runge_kutta_drifts_off_the_constraint():
    """The index-reduced ODE under Tsit5 keeps the constraint only to its local
    error, and drifts; the variational solver at the same step keeps it to
    round-off."""
    scene = scenes.cartesian_pendulum()
    n, h = 5000, scene.period / 50
    rk = _constraint_history(scene, dfx.Tsit5(), h, n)
    vi = _constraint_history(scene, dvi.TrapezoidalVI(), h, n)
    rk_values, vi_values = np.asarray(rk.ys[1]), np.asarray(vi.ys[1])
    assert np.max(np.abs(vi_values)) < 1e-13
    assert np.max(np.abs(rk_values)) > 1e-7
    assert np.abs(rk_values[-100:]).max() > 5 * np.abs(rk_values[:100]).max()


@pytest.mark.parametrize(
    "scene,solver",
    [
        (scenes.cartesian_pendulum(), dvi.MidpointVI()),
        (scenes.cartesian_pendulum(), dvi.TrapezoidalVI()),
        (scenes.cartesian_pendulum(), dvi.Composition(dvi.MidpointVI(), "yoshida4")),
        (scenes.four_bar(), dvi.MidpointVI()),
    ],
    ids=["pendulum-mid", "pendulum-trap", "pendulum-yoshida4(mid)", "four_bar-mid"],
)
def test_symplectic_on_the_constrained_phase_space(scene, solver):
    defect = dvi.diagnostics.symplecticity_defect(solver, scene.term(), scene.y0, h=0.1)
    assert defect < 1e-12


def test_runge_kutta_is_not_symplectic_on_the_constrained_phase_space():
    scene = scenes.cartesian_pendulum()
    defect = dvi.diagnostics.symplecticity_defect(
        dfx.Tsit5(), scene.term(), scene.y0, h=0.5
    )
    assert defect > 1e-6


def test_project_onto_constraints():
    scene = scenes.four_bar()
    q0, p0 = scene.y0
    (q, p), result = dvi.project_onto_constraints(
        scene.term(), 0.0, (q0 + jnp.array([0.05, -0.03, 0.02]), p0 + 0.1)
    )
    assert result == dfx.RESULTS.successful
    assert float(jnp.max(jnp.abs(scene.constraint(0.0, q, None)))) < 1e-14
    v, _ = dvi.velocity(scene.lagrangian, 0.0, (q, p))
    jacobian = jax.jacfwd(lambda x: scene.constraint(0.0, x, None))(q)
    assert float(jnp.max(jnp.abs(jacobian @ v))) < 1e-13
    # a consistent state is left where it is
    (q1, p1), _ = dvi.project_onto_constraints(scene.term(), 0.0, scene.y0)
    assert max_abs_diff((q1, p1), scene.y0) < 1e-14
    with pytest.raises(ValueError, match="needs a LagrangianTerm with a constraint"):
        dvi.project_onto_constraints(dvi.LagrangianTerm(OSCILLATOR), 0.0, Y0)


def _four_bar_projection(q, p):
    """The four-bar's momentum projected onto its hidden constraint, written out in
    numpy from the scene's formulas: M(q) from its kinetic energy, G(q) from its
    loop closure (the same lengths), mu from (G M^-1 G^T) mu = G M^-1 p."""
    lagrangian = scenes.FourBarLagrangian()
    l1, l2, l3, m1, m2, m3 = (
        float(getattr(lagrangian, k)) for k in ("l1", "l2", "l3", "m1", "m2", "m3")
    )
    mass = np.diag([(m1 / 3 + m2) * l1**2, m2 * l2**2 / 3, m3 * l3**2 / 3])
    mass[0, 1] = mass[1, 0] = 0.5 * m2 * l1 * l2 * np.cos(q[0] - q[1])
    arms = np.array([l1, l2, -l3])
    G = np.stack([-arms * np.sin(q), arms * np.cos(q)])
    inverse_mass = np.linalg.inv(mass)
    mu = np.linalg.solve(G @ inverse_mass @ G.T, G @ inverse_mass @ p)
    return p - G.T @ mu, G, inverse_mass


def test_quadratic_momentum_projection_is_one_linear_solve():
    """Projecting the four-bar's momentum (its mass depends on its angles) onto the
    hidden constraint, as every constrained step ends, is one solve of G M^-1 G^T:
    no Newton loop in the step's program. Its value is numpy's solve of the same
    equation, and its derivatives, in the momentum (exact: I - G^T S^-1 G M^-1) and
    in the angles (central differences of numpy's), are those of the projection."""
    from diffrax_vi._constraint import project_momentum
    from diffrax_vi._misc import has_loop

    term = scenes.four_bar().term()
    rng = np.random.default_rng(3)
    q = np.asarray(scenes.four_bar().y0[0]) + rng.normal(scale=0.1, size=3)
    p = rng.normal(size=3)
    project = lambda q_, p_: project_momentum(term, 0.0, q_, p_, None)
    assert not has_loop(jax.make_jaxpr(project)(q, p).jaxpr)
    projected = jax.jit(project)(q, p)
    assert projected.result == dfx.RESULTS.successful
    expected, G, inverse_mass = _four_bar_projection(q, p)
    assert np.max(np.abs(projected.p - expected)) < 1e-14 * np.max(np.abs(p))
    assert np.max(np.abs(G @ inverse_mass @ projected.p)) < 1e-14 * np.max(np.abs(p))

    along_p, along_q = jax.jit(jax.jacfwd(lambda q_, p_: project(q_, p_).p, (1, 0)))(
        q, p
    )
    schur = G @ inverse_mass @ G.T
    exact = np.eye(3) - G.T @ np.linalg.solve(schur, G @ inverse_mass)
    assert np.max(np.abs(along_p - exact)) < 1e-14
    step = 1e-5
    differences = np.stack(
        [
            (
                _four_bar_projection(q + step * e, p)[0]
                - _four_bar_projection(q - step * e, p)[0]
            )
            / (2 * step)
            for e in np.eye(3)
        ],
        axis=1,
    )
    assert np.max(np.abs(along_q - differences)) < 1e-8 * np.max(np.abs(differences))


class _SignedMasses(dvi.AbstractSeparableLagrangian):
    """Free motion with the constant masses `mass`: an indefinite d2L/dv2 where an
    entry is negative (the start admits it)."""

    mass: jax.Array

    def potential(self, t, q, args):
        return 0.0 * jnp.sum(q)


def test_an_indefinite_mass_is_projected_with_pivoting():
    """The momentum projection solves G M^-1 G^T without pivoting only where the
    term knows its constant mass to be positive (`mass_definite`, where it is
    built). With masses (1, -1, 1, 1, 1) and the linear constraints q0 + q1 = 0,
    q0 = 0, q3 = 0, q4 = 0, G M^-1 G^T = diag([[0, 1], [1, 1]], 1, 1) is regular,
    with a zero leading minor: partial pivoting solves it, and the projected
    momentum keeps the hidden constraint, as numpy's solve says, whether the mass
    is known when the term is built or traced. A positive mass known when the term
    is built keeps the unpivoted solve (no `argmax`, a pivot search, in its
    program); the same mass traced when the term is built pivots. (Four
    constraints: a system of two or three is solved in closed form, which needs no
    pivot.)"""
    from diffrax_vi._constraint import project_momentum

    a = np.zeros((4, 5))
    a[0, :2] = 1.0
    a[1, 0] = a[2, 3] = a[3, 4] = 1.0
    constraint = lambda t, q, args: jnp.asarray(a) @ q
    q, p = jnp.zeros(5), jnp.array([0.3, -0.7, 1.1, 0.5, -0.2])
    signed = jnp.array([1.0, -1.0, 1.0, 1.0, 1.0])

    def project(mass):
        term = dvi.LagrangianTerm(_SignedMasses(mass), constraint=constraint)
        return term, lambda p_: project_momentum(term, 0.0, q, p_, None)

    weights = np.asarray(signed)
    mu = np.linalg.solve((a * weights) @ a.T, a @ (weights * np.asarray(p)))
    term, indefinite = project(signed)
    assert not term.mass_definite
    traced = jax.jit(lambda m: project(m)[1](p))
    for projected in (jax.jit(indefinite)(p), traced(signed)):
        assert projected.result == dfx.RESULTS.successful
        np.testing.assert_allclose(projected.p, p - a.T @ mu, rtol=0, atol=1e-15)
        assert np.max(np.abs(a @ (weights * projected.p))) < 1e-15

    positive = jnp.array([1.0, 2.0, 3.0, 4.0, 5.0])
    term, definite = project(positive)
    assert term.mass_definite
    assert "argmax" not in str(jax.make_jaxpr(definite)(p))
    assert "argmax" in str(jax.make_jaxpr(lambda m: project(m)[1](p))(positive))


@pytest.mark.parametrize("scale", [1.0, 1e-3], ids=["unit", "milli"])
def test_inconsistent_start_is_an_error(scale):
    """A start off the constraint manifold is refused, in any units: the check is
    relative to the terms each constraint balances."""
    lagrangian = scenes.CartesianPendulumLagrangian()
    term = dvi.LagrangianTerm(lagrangian, constraint=scenes.Circle(scale))
    q0 = scale * jnp.array([0.6, -0.8])
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI()):
        sol = dfx.diffeqsolve(term, solver, 0.0, 1.0, 0.01, (q0, jnp.zeros(2)))
        assert sol.result == dfx.RESULTS.successful
        with pytest.raises(Exception, match="not on the constraint manifold"):
            dfx.diffeqsolve(term, solver, 0.0, 1.0, 0.01, (1.001 * q0, jnp.zeros(2)))
        moving = scale * jnp.array([0.1, 0.1])  # not tangent to the circle
        with pytest.raises(Exception, match="not on the constraint manifold"):
            dfx.diffeqsolve(term, solver, 0.0, 1.0, 0.01, (q0, moving))


def test_rank_deficient_constraint_is_an_error():
    # The same circle twice: redundant constraints.
    term = dvi.LagrangianTerm(
        scenes.CartesianPendulumLagrangian(),
        constraint=lambda t, q, args: jnp.stack([jnp.sum(q**2) - 1] * 2),
    )
    y0 = (jnp.array([0.6, -0.8]), jnp.zeros(2))
    with pytest.raises(Exception, match="full row rank"):
        dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 1.0, 0.01, y0)


def test_constraints_need_a_one_stage_method():
    scene = scenes.cartesian_pendulum()
    for solver in (dvi.GaussVPRK(2), dvi.LobattoVPRK(3)):
        with pytest.raises(ValueError, match="compositions of them"):
            dfx.diffeqsolve(scene.term(), solver, 0.0, 1.0, 0.01, scene.y0)
    with pytest.raises(ValueError, match="cannot keep holonomic constraints"):
        dvi.terms_for(dvi.StormerVerlet(), scene.term())


def test_jit_vmap_grad_through_forced_and_constrained_solves():
    # grad of a constrained solve with respect to the pendulum's gravity, against
    # central finite differences
    def final_x(g):
        scene = scenes.cartesian_pendulum()
        term = dvi.LagrangianTerm(
            scenes.CartesianPendulumLagrangian(g=g), constraint=scene.constraint
        )
        sol = dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 2.0, 0.02, scene.y0)
        return sol.ys[0][-1, 0]

    grad = jax.jit(jax.grad(final_x))(1.0)
    # Gravity traced, so that the finite differences and the loop share one
    # compilation (a Python float would be a new static Lagrangian each time).
    single = jax.jit(final_x)
    eps = 1e-5
    # Entries of an array, as the loop's gravities below are: a Python float is
    # weakly typed, and `jax.jit` compiles for it apart.
    up, down = jnp.array([1.0 + eps, 1.0 - eps])
    fd = (single(up) - single(down)) / (2 * eps)
    assert abs(float(grad) - float(fd)) < 1e-7 * max(1.0, abs(float(fd)))
    # vmap over gravities equals a loop
    gs = jnp.array([0.5, 1.0, 2.0])
    batched = jax.jit(jax.vmap(final_x))(gs)
    assert max_abs_diff(batched, jnp.stack([single(g) for g in gs])) < 1e-13

    # vmap over damping coefficients equals a loop (one term, so that the loop's
    # solves share one compilation)
    damped = dvi.LagrangianTerm(OSCILLATOR, force=lambda t, q, v, args: -args * v)

    def final_q(c):
        sol = dfx.diffeqsolve(damped, dvi.MidpointVI(), 0.0, 2.0, 0.05, Y0, args=c)
        return sol.ys[0][-1]

    cs = jnp.array([0.0, 0.1, 0.4])
    batched = jax.jit(jax.vmap(final_q))(cs)
    assert max_abs_diff(batched, jnp.stack([final_q(c) for c in cs])) < 1e-14


def test_swing_up_control_through_the_forced_solver():
    """Optimal control by differentiating through MidpointVI on a forced term: the
    gradient of the swing-up loss with respect to the control sequence matches
    central finite differences, and BFGS on it finds controls, each torque bounded by
    half the pendulum's weight, that bring the pendulum upright at rest."""
    import optimistix as optx

    scene = scenes.swing_up(controls=20, horizon=10.0)

    def final(controls):
        sol = dfx.diffeqsolve(
            scene.term(), dvi.MidpointVI(), 0.0, 10.0, 0.05, scene.y0, controls
        )
        return sol.ys[0][-1], sol.ys[1][-1]

    def loss(controls, _):
        q, p = final(controls)
        return (1 + jnp.cos(q)) + 0.1 * p**2 + 1e-4 * jnp.sum(controls**2)

    guess = jnp.where(jnp.arange(20) % 6 < 3, 1.0, -1.0)
    grad = jax.jit(jax.grad(loss))(guess, None)
    direction = jnp.sin(jnp.arange(20.0))
    eps = 1e-6
    fd = (loss(guess + eps * direction, None) - loss(guess - eps * direction, None)) / (
        2 * eps
    )
    assert abs(float(grad @ direction) - float(fd)) < 1e-6 * max(1.0, abs(float(fd)))

    controls = optx.minimise(
        loss, optx.BFGS(rtol=1e-8, atol=1e-8), guess, max_steps=500
    ).value
    q, p = final(controls)
    assert 1 + float(jnp.cos(q)) < 1e-3  # within 2.6 degrees of upright
    assert abs(float(p)) < 0.1
    # It had to swing: the torque alone (at most 0.5 of the weight) cannot lift it.
    torques = scene.force.max_torque * jnp.tanh(controls)
    assert float(jnp.max(jnp.abs(torques))) <= 0.5


# The drift study on forced and constrained scenes.


@functools.cache
def _work_reference() -> tuple[float, float]:
    """The forced Duffing's first drive period, and W = int F . v dt over it along
    the motion from scipy's DOP853 at rtol 1e-13 on Hamilton's equations augmented by
    dW/dt = F . v (independent of any method's discrete forces)."""
    scene = scenes.forced_duffing()
    term = scene.term()

    @jax.jit
    def rhs(t, x):
        (dq, dp), _ = term.hamilton(t, (x[0], x[1]), None)
        return jnp.stack([dq, dp, scene.force(t, x[0], dq, None) * dq])

    q0, p0 = scene.y0
    sol = scipy.integrate.solve_ivp(
        # t as one type: scipy passes a float first and np.float64 after, which
        # jit would compile for twice (a weak type and a strong one).
        lambda t, x: np.asarray(rhs(np.float64(t), jnp.asarray(x))),
        (0.0, scene.period),
        [float(q0), float(p0), 0.0],
        "DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    assert sol.success
    return scene.period, float(sol.y[2, -1])


@eqx.filter_jit
def _final_work(solver, h):
    scene = scenes.forced_duffing()
    sol = dfx.diffeqsolve(
        scene.term(),
        solver,
        0.0,
        scene.period,
        h,
        scene.y0,
        saveat=dfx.SaveAt(t1=True, solver_state=True),
        max_steps=256,
    )
    return sol.solver_state.work


@pytest.mark.parametrize(
    "name,solver,order",
    [
        ("MidpointVI", dvi.MidpointVI(), 2),
        ("TrapezoidalVI", dvi.TrapezoidalVI(), 2),
        ("GaussVPRK(2)", dvi.GaussVPRK(2), 4),
        (
            "yoshida4(TrapezoidalVI)",
            dvi.Composition(dvi.TrapezoidalVI(), "yoshida4"),
            4,
        ),
    ],
)
def test_discrete_work_converges_at_the_methods_order(name, solver, order):
    """The work of a method's discrete forces, kept in its state for the energy
    balance, converges to the work of the force along the exact motion at the
    method's order (a composition's substeps add theirs)."""
    t1, reference = _work_reference()
    hs = [t1 / 16, t1 / 32, t1 / 64]
    errors = [abs(float(_final_work(solver, jnp.asarray(h))) - reference) for h in hs]
    assert abs(fitted_order(hs, errors) - order) < 0.3, errors


def test_drift_study_reports_the_energy_balance_of_a_forced_scene():
    scene = scenes.forced_duffing()
    methods = ["MidpointVI", "GaussVPRK2", "Tsit5"]
    coarse, fine = (
        drift(scene, methods, periods=2, steps_per_period=spp, n_save=2)
        for spp in (40, 80)
    )
    assert coarse.energy == "energy_balance" and "energy" not in coarse.invariants
    for a, b, order in zip(coarse.runs, fine.runs, (2, 4, 5)):
        assert a.result == b.result == "successful"
        ratio = a.max_error("energy_balance") / b.max_error("energy_balance")
        # The balance error falls at the method's order (within a factor of 2**0.6).
        assert 2 ** (order - 0.6) < ratio < 2 ** (order + 0.6), (a.solver, ratio)
    assert "energy-balance error" in coarse.verdict()
    with pytest.raises(ValueError, match="StormerVerlet integrate"):
        drift(scene, ["StormerVerlet"], periods=1, steps_per_period=20)


def test_drift_study_reports_constraint_residuals():
    study = drift(
        scenes.cartesian_pendulum(),
        ["TrapezoidalVI", "Tsit5"],
        periods=20,
        steps_per_period=40,
        n_save=10,
    )
    vi, rk = study.runs
    assert study.invariants == ["energy", "constraint", "hidden_constraint"]
    for name in ("constraint", "hidden_constraint"):
        assert vi.max_error(name) < 1e-13
        assert rk.max_error(name) > 1e-5
    assert rk.growth("constraint") > 5


def _double_pendulum_rods(t, q, args):
    """Two rods of lengths 1 and 0.7 (times the unit of length)."""
    length = args["length"]
    first, second = q[:2], q[2:] - q[:2]
    return jnp.stack([first @ first - length**2, second @ second - (0.7 * length) ** 2])


# The double pendulum's forces in units of `args["scale"]` (arguments, not values
# captured by a function made in each test: both units run the same compiled
# programs).
def _gravity(t, q, args):
    mass, scale = args["mass"], args["scale"]
    return 9.81 * scale * (mass[1] * q[1] + mass[3] * q[3])


def _anharmonic_potential(t, q, args):
    return _gravity(t, q, args) + 2.0 * args["scale"] * q[2] ** 4


def _drive(t, q, v, args):
    return jnp.array([0.3, 0.0, 0.0, 0.0]) * args["scale"] * jnp.cos(1.7 * t)


def _general_lagrangian(t, q, v, args):
    return 0.5 * v @ (args["mass"] * v) - _gravity(t, q, args)


@pytest.mark.parametrize("scale", [1.0, 1e-3], ids=["unit", "milli"])
def test_rattle_on_the_multipliers_is_the_constrained_trapezoidal_step(scale):
    """TrapezoidalVI on a separable Lagrangian with constraints solves RATTLE for the
    multipliers alone; the same Lagrangian written as a general one goes through the
    general constrained step, Newton on velocity and multipliers together. Both solve
    the same discrete equations: a Cartesian double pendulum (4 coordinates, 2
    constraints, unequal masses) with a positional drive agrees to round-off over 400
    steps, energy balance included, in any units."""
    mass = jnp.array([1.0, 1.0, 0.5, 0.5]) * scale
    separable = dvi.SeparableLagrangian(_gravity, mass)
    general = dvi.Lagrangian(_general_lagrangian)
    args = {"length": jnp.asarray(1.0), "mass": mass, "scale": jnp.asarray(scale)}
    q0 = jnp.array([np.sin(1.0), -np.cos(1.0), np.sin(1.0) + 0.7, -np.cos(1.0)])
    y0 = (q0, jnp.zeros(4))
    finals = []
    for lagrangian in (separable, general):
        term = dvi.LagrangianTerm(
            lagrangian, force=_drive, constraint=_double_pendulum_rods
        )
        sol = dfx.diffeqsolve(
            term,
            dvi.TrapezoidalVI(),
            0.0,
            4.0,
            0.01,
            y0,
            args=args,
            saveat=dfx.SaveAt(t1=True, solver_state=True),
            max_steps=500,
        )
        assert sol.result == dfx.RESULTS.successful
        finals.append((sol.ys, sol.solver_state.work))
    (rattle, rattle_work), (joint, joint_work) = finals
    assert max_abs_diff(rattle[0], joint[0]) < 1e-12
    assert max_abs_diff(rattle[1], joint[1]) < 1e-12 * scale
    assert abs(float(rattle_work - joint_work)) < 1e-12 * scale
    q1 = np.asarray(rattle[0][0])
    assert np.max(np.abs(np.asarray(_double_pendulum_rods(4.0, q1, args)))) < 1e-13


@pytest.mark.parametrize("scale", [1.0, 1e-3], ids=["unit", "milli"])
def test_constrained_midpoint_iterates_as_without_constraints(scale, monkeypatch):
    """MidpointVI with constraints on a separable Lagrangian takes the fixed-point
    iteration, solving for the multipliers exactly in each iteration (an m x m Schur
    complement of derivatives of the constraint alone), rather than Newton's method
    on velocity and multipliers together. Both solve the same equations: on a
    Cartesian double pendulum (2 constraints, unequal masses) with an anharmonic
    potential and a positional drive, `FixedPoint()` alone, the default policy and
    `Newton()` agree to round-off over 100 steps, in any units, and the ends stay on
    the constraints. Where the multipliers' elimination without pivoting meets a
    zero pivot (made to fail here in every iterate, in unit scale), the iteration
    falls back to Newton's method and the solve is Newton's. (Over 400 steps the
    chaotic pendulum amplifies the round-off of either solve about tenfold per
    second: up to 2e-12 relative in the momentum, which measures the chaos rather
    than the solvers.)"""
    mass = jnp.array([1.0, 1.0, 0.5, 0.5]) * scale
    term = dvi.LagrangianTerm(
        dvi.SeparableLagrangian(_anharmonic_potential, mass),
        force=_drive,
        constraint=_double_pendulum_rods,
    )
    args = {"length": jnp.asarray(1.0), "mass": mass, "scale": jnp.asarray(scale)}
    q0 = jnp.array([np.sin(1.0), -np.cos(1.0), np.sin(1.0) + 0.7, -np.cos(1.0)])

    def final(solver):
        sol = dfx.diffeqsolve(
            term, solver, 0.0, 1.0, 0.01, (q0, jnp.zeros(4)), args=args, max_steps=100
        )
        assert sol.result == dfx.RESULTS.successful
        return sol.ys

    fixed, default, newton = (
        final(dvi.MidpointVI(root_finder=root_finder))
        for root_finder in (dvi.FixedPoint(), None, dvi.Newton())
    )
    for other in (default, newton):
        assert max_abs_diff(fixed[0], other[0]) < 1e-14
        assert max_abs_diff(fixed[1], other[1]) < 5e-14 * scale
    if scale == 1.0:
        import diffrax_vi._root_finders

        nan = lambda matrix, b: (jnp.full_like(b, jnp.nan), jnp.zeros(()))
        monkeypatch.setattr(diffrax_vi._root_finders, "unpivoted_solve", nan)
        # Another `root_find_max_steps`: a program of its own, traced with the patch.
        fallback = final(dvi.MidpointVI(root_find_max_steps=17))
        assert max_abs_diff(fallback[0], newton[0]) < 1e-14
        assert max_abs_diff(fallback[1], newton[1]) < 5e-14 * scale
    q1 = np.asarray(fixed[0][0])
    assert np.max(np.abs(np.asarray(_double_pendulum_rods(1.0, q1, args)))) < 1e-13
    # The anharmonic spring and the rods moved the bob: not a trivial motion.
    assert abs(float(fixed[0][0][2] - q0[2])) > 0.1
