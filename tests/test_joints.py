"""Rigid bodies joined by joints: holonomic constraints on (R^3 x SO(3))^n, against
the same mechanisms in minimal coordinates (the attitudes alone, the centres
following from the joints: no constraint, no multiplier) integrated by scipy."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from diffrax_vi.scenes import RigidBodiesLagrangian


def _hat(w):
    return jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _chain_reference(lagrangian, half, y0, t1):
    """A chain of links hung by ball joints (link i's top (0, 0, half_i) at link
    i-1's bottom, link 0's top at the origin) in minimal coordinates: the reduced
    Lagrangian l(R, Omega) of the attitudes, with x_i(R) from the joints, and its
    Euler-Poincare equations d/dt dl/dOmega = dl/dOmega x Omega + dl/dR (left
    derivative), R' = R hat(Omega), by scipy's DOP853 at rtol 1e-12. Returns the
    attitudes and body angular velocities at t1."""
    mass = np.asarray(lagrangian.mass)
    inertia = np.asarray(lagrangian.inertia)
    gravity = float(lagrangian.gravity)
    n = len(mass)
    tops = [jnp.array([0.0, 0.0, h]) for h in np.broadcast_to(half, (n,))]

    def centres(R):
        joint, x = jnp.zeros(3), []
        for i in range(n):
            x.append(joint - R[i] @ tops[i])
            joint = x[-1] - R[i] @ tops[i]
        return jnp.stack(x)

    def reduced(R, omega):
        moving = jnp.stack([R[i] @ _hat(omega[i]) for i in range(n)])
        x, xdot = jax.jvp(centres, (R,), (moving,))
        kinetic = jnp.sum(mass[:, None] * xdot**2) + jnp.sum(inertia * omega**2)
        return 0.5 * kinetic - gravity * jnp.sum(mass * x[:, 2])

    def left(R, eta):
        return jnp.stack([R[i] + R[i] @ _hat(eta[i]) for i in range(n)])

    @jax.jit
    def rhs(y):
        R, omega = y[: 9 * n].reshape(n, 3, 3), y[9 * n :].reshape(n, 3)
        mu = lambda R_, w: jax.grad(reduced, argnums=1)(R_, w)
        metric = jax.jacfwd(lambda w: mu(R, w).ravel())(omega.ravel().reshape(n, 3))
        metric = metric.reshape(3 * n, 3 * n)
        moving = jnp.stack([R[i] @ _hat(omega[i]) for i in range(n)])
        mixed = jax.jvp(lambda R_: mu(R_, omega), (R,), (moving,))[1]
        force = jax.grad(lambda eta: reduced(left(R, eta), omega))(jnp.zeros((n, 3)))
        m = mu(R, omega)
        rate = jnp.cross(m, omega) + force - mixed
        omega_dot = jnp.linalg.solve(metric, rate.ravel())
        return jnp.concatenate([moving.ravel(), omega_dot])

    R0 = np.asarray(y0[0][1])
    omega0 = np.asarray(y0[1][1]) / inertia
    sol = scipy.integrate.solve_ivp(
        lambda t, y: np.asarray(rhs(jnp.asarray(y))),
        (0.0, t1),
        np.concatenate([R0.ravel(), omega0.ravel()]),
        method="DOP853",
        rtol=1e-12,
        atol=1e-12,
    )
    y1 = sol.y[:, -1]
    return y1[: 9 * n].reshape(n, 3, 3), y1[9 * n :].reshape(n, 3)


def _solve(scene, solver, t1, dt, y0=None, saveat=None, max_steps=4096):
    # Times as arrays: one compilation serves every step size.
    return dfx.diffeqsolve(
        scene.term(),
        solver,
        0.0,
        jnp.asarray(t1),
        jnp.asarray(dt),
        scene.y0 if y0 is None else y0,
        saveat=saveat or dfx.SaveAt(t1=True),
        max_steps=max_steps,
    )


def _attitude_errors(scene, solver, t1, steps, half):
    R_ref, omega_ref = _chain_reference(scene.lagrangian, half, scene.y0, t1)
    inertia = np.asarray(scene.lagrangian.inertia)
    errors = []
    for n in steps:
        sol = _solve(scene, solver, t1, t1 / n)
        assert sol.result == dfx.RESULTS.successful
        R = np.asarray(sol.ys[0][1][-1])
        omega = np.asarray(sol.ys[1][1][-1]) / inertia
        errors.append(max(np.max(np.abs(R - R_ref)), np.max(np.abs(omega - omega_ref))))
    return np.array(errors)


@pytest.mark.parametrize(
    "solver,order,steps",
    [
        (dvi.MidpointVI(), 2, (20, 40, 80)),
        (dvi.TrapezoidalVI(), 2, (20, 40, 80)),
        (dvi.Composition(dvi.MidpointVI(), "yoshida4"), 4, (10, 20, 40)),
    ],
    ids=["midpoint", "trapezoidal", "yoshida4"],
)
def test_rigid_double_pendulum_converges_to_minimal_coordinates(solver, order, steps):
    """Two boxes joined by ball joints, in maximal coordinates with six multipliers,
    against the attitudes alone by scipy: the fitted order of the attitudes and
    angular velocities at t = 1."""
    scene = dvi.scenes.rigid_double_pendulum()
    errors = _attitude_errors(scene, solver, 1.0, steps, (0.5, 0.4))
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.3, (slope, errors)


def test_runge_kutta_on_the_joined_bodies_follows_the_index_reduced_equations():
    """Tsit5 on the same term integrates the index-reduced equations (multipliers
    from the second derivative of the joints, on the group): it converges to the
    minimal-coordinate reference, while leaving the joints by more than round-off,
    which the variational solvers keep."""
    scene = dvi.scenes.rigid_double_pendulum()
    t1 = 1.0
    R_ref, _ = _chain_reference(scene.lagrangian, (0.5, 0.4), scene.y0, t1)
    sol = dfx.diffeqsolve(
        scene.term(),
        dfx.Tsit5(),
        0.0,
        t1,
        None,
        scene.y0,
        stepsize_controller=dfx.PIDController(rtol=1e-10, atol=1e-10),
    )
    assert sol.result == dfx.RESULTS.successful
    y1 = jax.tree.map(lambda x: x[-1], sol.ys)
    assert np.max(np.abs(np.asarray(y1[0][1]) - R_ref)) < 1e-8
    residual = scene.invariants["constraint"](t1, y1, None)
    assert 1e-14 < residual < 1e-7, residual


def test_rigid_double_pendulum_keeps_its_joints_group_and_momentum():
    """10^5 steps of TrapezoidalVI at h = period/100: the joints and SO(3) kept to
    round-off, the vertical angular momentum about the pivot (a symmetry) kept by
    the discrete Noether theorem, and the energy error bounded without drift: its
    mean over the second half within 1.5x its mean over the first, where a drift
    growing linearly in time makes it 3x. The mechanism is chaotic, and the size of
    the error depends on the region the motion visits: a tenth of the run can sit
    in a quiet one (a round-off change in the step's program moved the first
    tenth's mean to 7e-5 against 1.5-2.4e-4 in each later tenth, and its largest
    error to a third of the last tenth's), while 10^6 steps hold the largest error
    of each tenth between 8e-4 and 1.2e-3. The states every 500 steps, from
    `solve_fixed_steps`: `diffeqsolve`'s steps (tests/test_lie.py), without the
    interpolation that `SaveAt(ts)` compiles (12-14 s against 6.5 s saving t1)."""
    scene = dvi.scenes.rigid_double_pendulum()
    n, h = 100_000, scene.period / 100
    sol = dvi.solve_fixed_steps(
        scene.term(), dvi.TrapezoidalVI(), 0.0, n * h, h, scene.y0, n_save=200
    )
    assert sol.result == dfx.RESULTS.successful
    values = jax.jit(
        lambda ys: {
            name: jax.vmap(lambda y: fn(0.0, y, None))(ys)
            for name, fn in scene.conserved().items()
        }
    )(sol.ys)
    assert jnp.max(values["constraint"]) < 1e-12
    assert jnp.max(values["orthogonality"]) < 1e-12
    momentum = values["vertical_momentum"]
    assert jnp.max(jnp.abs(momentum - momentum[0])) < 1e-11
    error = jnp.abs(values["energy"] - values["energy"][0])
    half = len(error) // 2
    first, last = jnp.mean(error[1:half]), jnp.mean(error[half:])
    assert 0 < last < 1.5 * first, (first, last)


def test_bodies_momentum_projection_is_one_linear_solve():
    """Projecting joined bodies' momentum onto the hidden constraint (every
    constrained step ends with it) is one solve of G M^-1 G^T: no Newton loop, no
    Jacobian of the Legendre map, and (the matrix being symmetric positive
    definite) no pivot search, in every step's program. Its result is numpy's
    solve of the same equation, G taken along q + q eta^."""
    from diffrax_vi._constraint import project_momentum
    from diffrax_vi._misc import has_loop

    scene = dvi.scenes.rigid_double_pendulum()
    term, (q, _) = scene.term(), scene.y0
    rng = np.random.default_rng(1)
    p = (jnp.asarray(rng.normal(size=(2, 3))), jnp.asarray(rng.normal(size=(2, 3))))
    project = lambda p_: project_momentum(term, 0.0, q, p_, None)
    program = jax.make_jaxpr(project)(p).jaxpr
    assert not has_loop(program)
    assert "argmax" not in str(program)
    projected = jax.jit(project)(p)
    assert projected.result == dfx.RESULTS.successful

    flat_p, unravel = jax.flatten_util.ravel_pytree(p)

    def g(eta_flat):
        eta_x, eta_r = unravel(eta_flat)
        moved = (q[0] + eta_x, q[1] + q[1] @ jax.vmap(_hat)(eta_r))
        return term.constraint(0.0, moved, None)

    G = np.asarray(jax.jacfwd(g)(jnp.zeros_like(flat_p)))
    lagrangian = term.lagrangian
    mass = np.concatenate(
        [np.repeat(np.asarray(lagrangian.mass), 3), np.ravel(lagrangian.inertia)]
    )
    W = np.diag(1 / mass)
    mu = np.linalg.solve(G @ W @ G.T, G @ W @ np.asarray(flat_p))
    expected = np.asarray(flat_p) - G.T @ mu
    got = np.asarray(jax.flatten_util.ravel_pytree(projected.p)[0])
    assert np.max(np.abs(got - expected)) < 1e-13 * np.max(np.abs(expected))
    # On the hidden constraint: G v = 0 for v = M^-1 p, to round-off of its terms.
    size = np.max(np.abs(G)) * np.max(np.abs(W @ np.asarray(flat_p)))
    assert np.max(np.abs(G @ W @ got)) < 1e-13 * size


def _hinged_box(angle=1.2, rate=0.0, dtype=jnp.float64):
    """A box (edges 0.3 x 0.5 x 1, mass 1) hinged to the ground about its first
    body axis at the centre of its top face: a compound pendulum in the y-z plane."""
    inertia = np.array([[(0.25 + 1) / 12, (0.09 + 1) / 12, (0.09 + 0.25) / 12]])
    lagrangian = RigidBodiesLagrangian(
        jnp.ones(1, dtype), jnp.asarray(inertia, dtype), jnp.asarray(1.0, dtype)
    )
    top = np.array([0.0, 0.0, 0.5])
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    # The rate may be traced (differentiated, vmapped): the velocities in jnp.
    omega = jnp.asarray(rate, dtype) * jnp.array([1.0, 0.0, 0.0], dtype)
    R_, top_ = jnp.asarray(R, dtype), jnp.asarray(top, dtype)
    y0 = (
        (-(R_ @ top_)[None], R_[None]),
        (
            (R_ @ jnp.cross(top_, omega))[None],
            (jnp.asarray(inertia[0], dtype) * omega)[None],
        ),
    )
    hinge = dvi.HingeJoint(0, top, (1.0, 0.0, 0.0))
    return dvi.LagrangianTerm(lagrangian, constraint=hinge), y0, inertia


def test_hinge_is_a_compound_pendulum():
    """One box on a hinge has one degree of freedom, the angle theta about the
    axis: theta'' = -(m g d / (J_1 + m d^2)) sin theta. Against scipy: second order,
    the body's rotation stays about the hinge axis, and the five joint values stay
    at zero."""
    term, y0, inertia = _hinged_box()
    d, t1 = 0.5, 2.0
    stiffness = d / (inertia[0, 0] + d**2)
    ref = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], -stiffness * np.sin(y[0])],
        (0.0, t1),
        [1.2, 0.0],
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    ).y[0, -1]
    steps = (20, 40, 80)
    errors = []
    for n in steps:
        sol = dfx.diffeqsolve(
            term, dvi.MidpointVI(), 0.0, jnp.asarray(t1), jnp.asarray(t1 / n), y0
        )
        assert sol.result == dfx.RESULTS.successful
        R = sol.ys[0][1][-1, 0]
        errors.append(abs(float(jnp.arctan2(R[2, 1], R[1, 1])) - ref))
        y1 = jax.tree.map(lambda x: x[-1], sol.ys)
        assert jnp.max(jnp.abs(term.constraint(t1, y1[0], None))) < 1e-13
        assert jnp.max(jnp.abs(y1[1][1][0, 1:])) < 1e-12
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - 2) < 0.3, (slope, errors)


def _door():
    """Two bodies: a door on a vertical hinge through the origin, and a small body
    hanging from its far lower corner by a ball joint (eight constraint values)."""
    bodies = RigidBodiesLagrangian(
        jnp.array([2.0, 0.5]),
        jnp.array([[0.2, 0.3, 0.1], [0.02, 0.02, 0.01]]),
        jnp.asarray(1.0),
    )
    constraint = dvi.joints(
        dvi.HingeJoint(0, (-0.5, 0.0, 0.5), (0.0, 0.0, 1.0)),
        dvi.BallJoint(1, (0.0, 0.0, 0.2), 0, (0.5, 0.0, -0.5)),
    )
    x = jnp.array([[0.5, 0.0, -0.5], [1.0, 0.0, -1.2]])
    R = jnp.stack([jnp.eye(3), jnp.eye(3)])
    p = (jnp.array([[0.0, 0.2, 0.0], [0.1, 0.0, 0.0]]), jnp.zeros((2, 3)))
    return dvi.LagrangianTerm(bodies, constraint=constraint), ((x, R), p)


def test_project_onto_joints_on_the_group():
    """A state moved off the joints (centres, attitudes along SO(3), momenta) is
    refused as a start; its projection lies on the joints and their hidden
    constraint to round-off, keeps R on SO(3), stays near it, and runs (a hinge
    and a ball joint: the start check that XLA miscompiled, `rank_ok`)."""
    term, ((x, R), (p, pi)) = _door()
    rng = np.random.default_rng(0)
    bump = lambda a: a + 1e-3 * jnp.asarray(rng.normal(size=a.shape))
    q_off = dvi.SO3().retract(R, jnp.asarray(1e-3 * rng.normal(size=(2, 3))))
    y_off = ((bump(x), q_off), (bump(p), bump(pi)))

    def solve(y0):
        return dfx.diffeqsolve(term, dvi.TrapezoidalVI(), 0.0, 0.1, 0.01, y0)

    with pytest.raises(eqx.EquinoxRuntimeError, match="project_onto_constraints"):
        solve(y_off)
    (q, p1), result = dvi.project_onto_constraints(term, 0.0, y_off)
    assert result == dfx.RESULTS.successful
    assert jnp.max(jnp.abs(term.constraint(0.0, q, None))) < 1e-14
    assert float(dvi.SO3().departure(q[1])) < 1e-14
    v, _ = dvi.velocity(term.lagrangian, 0.0, (q, p1))
    hidden = jax.jvp(
        lambda eta: term.constraint(
            0.0, (q[0] + eta[0], q[1] + q[1] @ jax.vmap(_hat)(eta[1])), None
        ),
        (jax.tree.map(jnp.zeros_like, v),),
        (v,),
    )[1]
    assert jnp.max(jnp.abs(hidden)) < 1e-13
    assert jnp.max(jnp.abs(q[0] - x)) < 1e-2 and jnp.max(jnp.abs(q[1] - R)) < 1e-2
    sol = solve((q, p1))
    assert sol.result == dfx.RESULTS.successful


def test_joint_misuse_names_the_fix():
    with pytest.raises(ValueError, match="body index"):
        dvi.BallJoint(-1, (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="as many indices"):
        dvi.BallJoint((1, 2), jnp.zeros((2, 3)), (0,))
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        dvi.BallJoint((1, 2), jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match="must not be zero"):
        dvi.HingeJoint(0, (0.0, 0.0, 0.5), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="BallJoint or HingeJoint"):
        dvi.joints()
    scene = dvi.scenes.rigid_double_pendulum()
    joint = dvi.BallJoint(2, (0.0, 0.0, 0.5))
    with pytest.raises(ValueError, match="has 2 bodies"):
        joint(0.0, scene.y0[0], None)
    with pytest.raises(ValueError, match=r"q = \(x, R\)"):
        joint(0.0, jnp.zeros((2, 3)), None)


def test_joints_over_index_sequences_are_scatter_free_and_exact():
    """Joints given sequences of bodies (a chain's range, indices in any order) hold
    the values of the same joints one by one, and the constraint forces `G^T lam`
    (the derivative of taking the joined bodies) in a loop leave it whole: indexing
    by an array would differentiate to a scatter, which XLA on CPU runs kernel by
    kernel (a 4-link chain's step took 20 times a 2-link one's)."""
    scene = dvi.scenes.rigid_chain(links=5)
    q = scene.y0[0]
    a, b = jnp.array([0.1, -0.2, 0.5]), jnp.array([0.0, 0.3, -0.4])
    axis = jnp.array([0.3, 0.4, 1.0])
    grouped = dvi.joints(
        dvi.BallJoint((1, 2, 3, 4), a, (0, 1, 2, 3), b),
        dvi.BallJoint((4, 0, 2), a, (1, 1, 3), b),
        dvi.HingeJoint((3, 1), a, axis, (0, 4), b),
    )
    single = dvi.joints(
        *(dvi.BallJoint(i, a, j, b) for i, j in zip((1, 2, 3, 4), (0, 1, 2, 3))),
        *(dvi.BallJoint(i, a, j, b) for i, j in zip((4, 0, 2), (1, 1, 3))),
    )
    hinges = [dvi.HingeJoint(i, a, axis, j, b) for i, j in ((3, 0), (1, 4))]
    values = grouped(0.0, q, None)
    balls = values[: 3 * 7]
    np.testing.assert_array_equal(balls, single(0.0, q, None))
    # A hinge's values: its ball's three, then its two alignments.
    aligned = values[3 * 7 + 6 :].reshape(2, 2)
    for k, hinge in enumerate(hinges):
        np.testing.assert_array_equal(
            values[3 * 7 + 3 * k : 3 * 7 + 3 * k + 3], hinge(0.0, q, None)[:3]
        )
        np.testing.assert_array_equal(aligned[k], hinge(0.0, q, None)[3:])

    def loop(q, lam):
        def body(q, _):
            _, pull = jax.vjp(lambda q_: grouped(0.0, q_, None), q)
            return jax.tree.map(lambda a, f: a + 1e-3 * f, q, pull(lam)[0]), None

        return jax.lax.scan(body, q, None, length=4)[0]

    lam = jnp.ones_like(values)
    assert dvi.diagnostics.compiled_loop_breakers(loop, q, lam) == []


def test_joined_bodies_run_under_jax_transformations():
    """The hinged box through the package's other entry points: a vmapped solve
    equals the solves one by one; `solve_fixed_steps` equals `diffeqsolve`; float32
    keeps the hinge to its round-off."""
    rates = jnp.array([0.0, 0.7])

    def final(rate, solve=None):
        term, y0, _ = _hinged_box(rate=rate)
        if solve is not None:
            return solve(term, y0)
        sol = dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 1.0, 0.05, y0)
        return jax.tree.map(lambda x: x[-1], sol.ys)

    batched = jax.vmap(final)(rates)
    for i, rate in enumerate(rates):
        one = final(rate)
        assert jnp.max(jnp.abs(batched[0][1][i] - one[0][1])) < 1e-14
    fixed = final(
        rates[1],
        lambda term, y0: (
            dvi.solve_fixed_steps(term, dvi.MidpointVI(), 0.0, 1.0, 0.05, y0).ys
        ),
    )
    fixed = jax.tree.map(lambda x: x[-1], fixed)
    assert jnp.max(jnp.abs(fixed[0][1] - final(rates[1])[0][1])) < 1e-13

    term, y0, _ = _hinged_box(rate=0.7, dtype=jnp.float32)
    sol = dfx.diffeqsolve(term, dvi.MidpointVI(), 0.0, 1.0, jnp.float32(0.05), y0)
    assert sol.result == dfx.RESULTS.successful
    y1 = jax.tree.map(lambda x: x[-1], sol.ys)
    assert y1[0][0].dtype == jnp.float32
    assert jnp.max(jnp.abs(term.constraint(1.0, y1[0], None))) < 1e-6


@pytest.mark.slow  # 3 minutes compiling both adjoints of a constrained group solve
def test_reversible_adjoint_through_a_hinge():
    """The reversible adjoint's gradient of the hinged box's final angle with
    respect to its initial rate equals checkpointing's."""

    def angle(rate, adjoint):
        term, y0, _ = _hinged_box(rate=rate)
        sol = dfx.diffeqsolve(
            term, dvi.TrapezoidalVI(), 0.0, 1.0, 0.05, y0, adjoint=adjoint
        )
        R = sol.ys[0][1][-1, 0]
        return jnp.arctan2(R[2, 1], R[1, 1])

    ours = jax.grad(angle)(0.7, dvi.ReversibleAdjoint())
    checkpoint = jax.grad(angle)(0.7, dfx.RecursiveCheckpointAdjoint())
    assert abs(ours - checkpoint) < 1e-10 * abs(checkpoint), (ours, checkpoint)
