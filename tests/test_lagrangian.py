import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from .helpers import (
    DoublePendulum,
    max_abs_diff,
    Pendulum,
    reference,
    solve,
    stiffening,
    stiffening_velocity,
)


def _dp_mass_matrix(q):
    c = jnp.cos(q[0] - q[1])
    return jnp.array([[2.0, c], [c, 1.0]])


def test_momentum_separable_pytree_mass():
    lagrangian = dvi.SeparableLagrangian(
        lambda t, q, args: jnp.sum(q["a"] ** 2) + jnp.sum(q["b"]),
        mass={"a": jnp.array([[2.0], [3.0]]), "b": 5.0},
    )
    q = {"a": jnp.ones((2, 3)), "b": jnp.ones(4)}
    v = {"a": jnp.arange(6.0).reshape(2, 3), "b": jnp.arange(4.0)}
    p = dvi.momentum(lagrangian, 0.0, q, v)
    assert jnp.array_equal(p["a"], jnp.array([[2.0], [3.0]]) * v["a"])
    assert jnp.array_equal(p["b"], 5.0 * v["b"])
    v_back, result = dvi.velocity(lagrangian, 0.0, (q, p))
    assert result == dfx.RESULTS.successful
    assert jnp.allclose(v_back["a"], v["a"]) and jnp.allclose(v_back["b"], v["b"])


def test_velocity_quadratic_is_exact_single_solve():
    # The double pendulum's momentum is M(q) v with M known in closed form.
    q = jnp.array([0.3, -1.1])
    v = jnp.array([0.7, 0.2])
    p = dvi.momentum(DoublePendulum(), 0.0, q, v)
    assert jnp.allclose(p, _dp_mass_matrix(q) @ v, rtol=1e-14)
    v_back, result = dvi.velocity(DoublePendulum(), 0.0, (q, p))
    assert result == dfx.RESULTS.successful
    assert jnp.allclose(v_back, v, rtol=1e-14)


def test_the_start_of_a_quadratic_lagrangian_is_one_eigendecomposition():
    """A solve's start for a Lagrangian marked quadratic in `v` takes the velocity
    and the extremes of d2L/dv2 it checks from one matrix and one
    eigendecomposition (`explicit_start`): the double pendulum's start velocity is
    M(q)^-1 p to round-off, its extremes are those of M in units of its diagonal
    (NumPy's), and the start's program holds one `eigh` and no elimination (the
    unrolled LU writes its rows by index: scatters)."""
    from diffrax_vi._lagrangian import explicit_start

    q, v = jnp.array([0.3, -1.1]), jnp.array([0.7, 0.2])
    mass = _dp_mass_matrix(q)
    y0 = (q, mass @ v)
    v0, result, extremes = jax.jit(
        lambda y: explicit_start(DoublePendulum(), 0.0, y, None)
    )(y0)
    assert result == dfx.RESULTS.successful
    assert jnp.allclose(v0, v, rtol=1e-14, atol=0)
    d = 1 / np.sqrt(np.diag(mass))
    eigs = np.linalg.eigvalsh(d[:, None] * np.asarray(mass) * d[None, :])
    np.testing.assert_allclose(extremes, (eigs[0], eigs[-1], eigs[0]), rtol=1e-14)

    term = dvi.LagrangianTerm(DoublePendulum())
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI()):
        start = str(jax.make_jaxpr(lambda y: solver.init(term, 0.0, 0.1, y, None))(y0))
        assert start.count("eigh[") == 1 and "scatter" not in start


def test_velocity_general_newton():
    q = jnp.array([0.1, 0.2])
    p = jnp.array([1.5, -0.7])
    v, result = dvi.velocity(stiffening, 0.0, (q, p))
    assert result == dfx.RESULTS.successful
    assert jnp.allclose(v, stiffening_velocity(p), rtol=1e-13, atol=1e-15)
    assert jnp.allclose(dvi.momentum(stiffening, 0.0, q, v), p, rtol=1e-14)


def test_energy_matches_closed_forms():
    q, p = jnp.array(0.4), jnp.array(0.9)
    assert jnp.allclose(
        dvi.energy(Pendulum(g=2.0), 0.0, (q, p)), 0.5 * p**2 - 2 * jnp.cos(q)
    )
    q2, p2 = jnp.array([0.1, 0.2]), jnp.array([1.5, -0.7])
    v2 = jnp.sum(stiffening_velocity(p2) ** 2)
    expected = 0.5 * v2 + 0.25 * v2**2 + 0.5 * jnp.sum(q2**2) + 0.1 * q2[0] ** 2 * q2[1]
    assert jnp.allclose(dvi.energy(stiffening, 0.0, (q2, p2)), expected, rtol=1e-13)
    qd, vd = jnp.array([0.3, -1.1]), jnp.array([0.7, 0.2])
    pd = _dp_mass_matrix(qd) @ vd
    expected = 0.5 * vd @ _dp_mass_matrix(qd) @ vd - 2 * jnp.cos(qd[0]) - jnp.cos(qd[1])
    assert jnp.allclose(
        dvi.energy(DoublePendulum(), 0.0, (qd, pd)), expected, rtol=1e-13
    )


def test_user_equinox_module_as_lagrangian():
    class Spring(dvi.AbstractLagrangian):
        k: jax.Array

        def __call__(self, t, q, v, args):
            return 0.5 * v**2 - 0.5 * self.k * q**2

    term = dvi.LagrangianTerm(Spring(jnp.array(4.0)))
    dq, dp = term.vf(0.0, (jnp.array(1.0), jnp.array(2.0)), None)
    assert jnp.allclose(dq, 2.0) and jnp.allclose(dp, -4.0)


def test_degenerate_lagrangian_is_singular():
    degenerate = lambda t, q, v, args: 0.5 * jnp.sum(v) ** 2 - jnp.sum(q**4)
    q, p = jnp.array([0.1, 0.2]), jnp.array([1.0, 1.0])
    _, result = dvi.velocity(degenerate, 0.0, (q, p))
    assert result != dfx.RESULTS.successful
    zero_mass = dvi.SeparableLagrangian(lambda t, q, args: jnp.sum(q**2), mass=0.0)
    _, result = dvi.velocity(zero_mass, 0.0, (q, p))
    assert result == dfx.RESULTS.singular
    # The partitioned terms check a known mass when built.
    with pytest.raises(ValueError, match="Every degree of freedom needs a positive"):
        dvi.separable_terms(zero_mass)


def test_a_general_lagrangian_starts_at_rest():
    # The double pendulum as a plain function, from rest with both rods level:
    # its momentum is recognised as affine in v, and the Jacobi probe's estimate
    # of its coupled mass M = [[2, 1], [1, 1]] there, z * M z = (1, 0), has a zero.
    # At zero momentum the Jacobi step solves any system, so that zero must not
    # read as a singular diagonal mass: the map is v = 0, and the solves from rest
    # match scipy's.
    plain = lambda t, q, v, args: DoublePendulum()(t, q, v, args)
    y0 = (jnp.full(2, jnp.pi / 2), jnp.zeros(2))
    v, result = dvi.velocity(plain, 0.0, y0)
    assert result == dfx.RESULTS.successful
    assert jnp.array_equal(v, jnp.zeros(2))
    q1, p1 = reference(DoublePendulum(), y0, 1.0)
    for solver, tol in [(dvi.MidpointVI(), 1e-5), (dfx.Tsit5(), 1e-12)]:
        sol = solve(plain, solver, y0, 1.0, 100, throw=False)
        assert sol.result == dfx.RESULTS.successful
        assert max_abs_diff((sol.ys[0][-1], sol.ys[1][-1]), (q1, p1)) < tol
    # A mass singular at rest is still told, by Newton's pivots (up to 16
    # coordinates; beyond, by the start check of an implicit solve).
    degenerate = lambda t, q, v, args: 0.5 * jnp.sum(v[:-1] ** 2) - jnp.sum(q**2)
    _, result = dvi.velocity(degenerate, 0.0, (jnp.zeros(4), jnp.zeros(4)))
    assert result == dfx.RESULTS.singular


def test_non_scalar_lagrangian_raises():
    vector_valued = lambda t, q, v, args: 0.5 * v**2 - 0.5 * q**2
    with pytest.raises(ValueError, match="must return a scalar"):
        dvi.momentum(vector_valued, 0.0, jnp.ones(3), jnp.ones(3))


def test_bad_mass_structure_raises():
    lagrangian = dvi.SeparableLagrangian(lambda t, q, args: 0.0, mass=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="mass"):
        dvi.momentum(
            lagrangian, 0.0, (jnp.ones(2), jnp.ones(2)), (jnp.ones(2), jnp.ones(2))
        )


def test_quadratic_in_velocity_is_structural_and_sound():
    from diffrax_vi._lagrangian import as_lagrangian, quadratic_in_velocity

    q = jnp.linspace(0.1, 0.5, 3)
    quadratic = [
        DoublePendulum(),
        lambda t, q, v, args: 0.5 * jnp.sum(v**2) + jnp.dot(jnp.sin(q), v) - q @ q,
        dvi.scenes.bead_wire(3).lagrangian,
    ]
    not_quadratic = [
        lambda t, q, v, args: -jnp.sqrt(1 - jnp.sum(v**2)),
        lambda t, q, v, args: 0.5 * jnp.sum(v**2) + 0.0 * jnp.sum(v**4),
        lambda t, q, v, args: jnp.sum(jnp.exp(v)),
    ]
    for lagrangian in quadratic:
        qq = q[:2] if isinstance(lagrangian, DoublePendulum) else q
        assert quadratic_in_velocity(as_lagrangian(lagrangian), 0.0, qq, None)
    for lagrangian in not_quadratic:
        assert not quadratic_in_velocity(as_lagrangian(lagrangian), 0.0, q, None)


def test_momentum_reads_position_is_structural_and_sound():
    # dL/dv free of q (constant mass, a relativistic particle) makes the Jacobians
    # of the midpoint and linearized steps symmetric: conjugate gradients. A mass
    # that depends on q (the bead wire, the double pendulum) or a magnetic term
    # A(q).v does not.
    from diffrax_vi._lagrangian import as_lagrangian, momentum_reads_position

    q = jnp.linspace(0.1, 0.5, 3)
    v = jnp.linspace(-0.2, 0.3, 3)
    constant_mass = [
        lambda t, q, v, args: 0.5 * jnp.sum(jnp.arange(1.0, 4.0) * v**2) - q @ q,
        lambda t, q, v, args: -jnp.sqrt(1 - jnp.sum(v**2)) - jnp.sum(jnp.cos(q)),
        # Reads q, but not in dL/dv: still free of q.
        lambda t, q, v, args: (
            jnp.sum(jnp.sin(q)) * jnp.sum(jnp.exp(0.0 * q)) + 0.5 * v @ v
        ),
    ]
    reads_q = [
        DoublePendulum(),
        lambda t, q, v, args: 0.5 * jnp.sum(v**2) + jnp.dot(jnp.sin(q), v),
        dvi.scenes.bead_wire(3).lagrangian,
    ]
    for lagrangian in constant_mass:
        L = as_lagrangian(lagrangian)
        assert not momentum_reads_position(L, 0.0, q, v, None)
    for lagrangian in reads_q:
        qq, vv = (q[:2], v[:2]) if isinstance(lagrangian, DoublePendulum) else (q, v)
        assert momentum_reads_position(as_lagrangian(lagrangian), 0.0, qq, vv, None)


def _wire_velocity(x, p, amplitude=0.2):
    # The bead wire's Legendre map in closed form: p = m (1 + y'(x)^2) v.
    slope = amplitude * 2 * jnp.pi * jnp.sin(2 * jnp.pi * x)
    return p / (1 + slope**2)


def test_large_affine_legendre_map_is_one_krylov_solve():
    # 100 beads, beyond the dense solves: a Lagrangian quadratic in v by its trace is
    # inverted by one conjugate-gradient solve, to round-off against the closed
    # form; the same Lagrangian with a term that hides it (0 * v^4) takes Newton's
    # path and agrees.
    scene = dvi.scenes.bead_wire(100)
    x = scene.y0[0] + 0.07 * jnp.sin(jnp.arange(100.0))
    p = jnp.cos(0.3 * jnp.arange(100.0))
    exact = _wire_velocity(x, p)
    v, result = jax.jit(dvi.velocity)(scene.lagrangian, 0.0, (x, p))
    assert result == dfx.RESULTS.successful
    assert jnp.max(jnp.abs(v - exact)) < 1e-14
    hidden = lambda t, q, v, args: scene.lagrangian(t, q, v, args) + 0.0 * jnp.sum(v**4)
    v_newton, result = jax.jit(lambda y: dvi.velocity(hidden, 0.0, y))((x, p))
    assert result == dfx.RESULTS.successful
    assert jnp.max(jnp.abs(v_newton - exact)) < 1e-14
    # Through the vector field under jit, as diffrax's solvers call it.
    term = dvi.LagrangianTerm(scene.lagrangian)
    dq, _ = jax.jit(lambda y: term.vf(0.0, y, None))((x, p))
    assert jnp.max(jnp.abs(dq - exact)) < 1e-14


def _coupled_mass(q, coupling):
    # A tridiagonal mass matrix, positive definite (diagonally dominant), whose
    # off-diagonal entries vanish where neighbours are level.
    off = coupling * jnp.sin(q[1:] - q[:-1])
    return jnp.diag(2.0 + jnp.sin(q) ** 2) + jnp.diag(off, 1) + jnp.diag(off, -1)


def _coupled_lagrangian(coupling):
    return lambda t, q, v, args: (
        0.5 * v @ _coupled_mass(q, coupling) @ v + 0.3 * jnp.sum(v) - q @ q
    )


def test_large_coupled_mass_legendre_map_equals_dense_solve():
    # 80 coordinates, a mass matrix that is not diagonal: the Jacobi step cannot
    # solve it, conjugate gradients do, to round-off against a dense solve.
    n = 80
    q = 0.9 * jnp.sin(1.7 * jnp.arange(n, dtype=float))
    p = jnp.cos(0.3 * jnp.arange(n, dtype=float))
    lagrangian = _coupled_lagrangian(0.4)
    v, result = dvi.velocity(lagrangian, 0.0, (q, p))
    exact = jnp.linalg.solve(_coupled_mass(q, 0.4), p - 0.3)
    assert result == dfx.RESULTS.successful
    assert jnp.max(jnp.abs(v - exact)) < 1e-13 * jnp.max(jnp.abs(exact))


def test_large_affine_velocity_derivative_where_the_mass_is_diagonal_by_accident():
    # At level neighbours the mass is diagonal, so the Jacobi step alone solves the
    # Legendre map, but its derivative along q is not diagonal: the velocity's
    # Jacobian (forward and reverse) must still be the implicit one,
    # -M^{-1} (dM/dq) v + M^{-1} dp/dq, as the dense solve's.
    n = 80
    q = jnp.full(n, 0.4)
    p = jnp.cos(0.3 * jnp.arange(n, dtype=float))
    lagrangian = _coupled_lagrangian(0.4)
    velocity = lambda q: dvi.velocity(lagrangian, 0.0, (q, p))[0]
    dense = lambda q: jnp.linalg.solve(_coupled_mass(q, 0.4), p - 0.3)
    direction = jnp.sin(2.3 * jnp.arange(n, dtype=float))
    _, exact = jax.jvp(dense, (q,), (direction,))
    # The off-diagonal part of dM/dq matters: without it the derivative differs.
    diagonal = jax.jvp(
        lambda q: (p - 0.3) / jnp.diag(_coupled_mass(q, 0.4)), (q,), (direction,)
    )[1]
    assert jnp.max(jnp.abs(exact - diagonal)) > 1e-2
    _, forward = jax.jit(lambda q, d: jax.jvp(velocity, (q,), (d,)))(q, direction)
    assert jnp.max(jnp.abs(forward - exact)) < 1e-12
    reverse = jax.jit(lambda q, d: jax.vjp(velocity, q)[1](d)[0])(q, direction)
    assert jnp.max(jnp.abs(reverse - jax.vjp(dense, q)[1](direction)[0])) < 1e-12


def test_large_degenerate_affine_lagrangian_is_not_successful():
    # No kinetic energy in the last coordinate (of 4, 20, 100): the Jacobi step
    # and (beyond 16) the conjugate-gradient solve cannot converge, Newton's method
    # takes over and reports failure. With no momentum there either, the system is
    # consistent and a solve would succeed: the zero diagonal entry is reported as
    # singular, also in a batch beside the inconsistent case.
    degenerate = lambda t, q, v, args: 0.5 * jnp.sum(v[:-1] ** 2) - jnp.sum(q**2)
    result_of = lambda q, p: dvi.velocity(degenerate, 0.0, (q, p))[1]._value
    single, batch = jax.jit(result_of), jax.jit(jax.vmap(result_of, (None, 0)))
    for n in (4, 20, 100):
        q, p = jnp.zeros(n), jnp.ones(n)
        consistent = p.at[-1].set(0.0)
        assert single(q, p) != dfx.RESULTS.successful._value
        assert single(q, consistent) == dfx.RESULTS.singular._value
        results = batch(q, jnp.stack([consistent, p, 0.5 * p]))
        assert results[0] == dfx.RESULTS.singular._value
        assert results[1] != dfx.RESULTS.successful._value
        assert results[2] != dfx.RESULTS.successful._value


@pytest.mark.parametrize("n", [8, 100])
def test_large_affine_legendre_map_does_not_see_the_units(n):
    # Mass in units 1e8 times smaller: L and p scale by 1e8, the velocity does not;
    # the Jacobi check, the CG tolerance, the diagonal estimate's floor and the
    # Newton fallback's test are all relative, so the same path gives the same
    # answer (at 8 coordinates the Jacobi step alone, at 100 with CG behind it).
    scene = dvi.scenes.bead_wire(n)
    x = scene.y0[0] + 0.07 * jnp.sin(jnp.arange(float(n)))
    p = jnp.cos(0.3 * jnp.arange(float(n)))
    plain = lambda t, q, v, args: scene.lagrangian(t, q, v, args)
    scaled = lambda t, q, v, args: 1e8 * scene.lagrangian(t, q, v, args)
    v, result = dvi.velocity(plain, 0.0, (x, p))
    v_scaled, result_scaled = dvi.velocity(scaled, 0.0, (x, 1e8 * p))
    assert result == result_scaled == dfx.RESULTS.successful
    assert jnp.max(jnp.abs(v - v_scaled)) < 1e-14 * jnp.max(jnp.abs(v))


def test_user_functions_are_traced_once_per_signature():
    """A general Lagrangian's implicit step differentiates the Lagrangian and the
    constraint dozens of times; each is traced once per signature and JAX transforms
    that trace (a reversible gradient of a constrained double pendulum called the
    Lagrangian's Python 69 times and the constraint's 39 without it, against 3 and
    4). A first call's tracing depends on it (`benchmarks/first_call.py`)."""
    calls = {"lagrangian": 0, "constraint": 0}
    scene = dvi.scenes.double_pendulum()

    class CountedLagrangian(dvi.AbstractLagrangian):
        def __call__(self, t, q, v, args):
            calls["lagrangian"] += 1
            return scene.lagrangian(t, q, v, args)

    def constraint(t, q, args):
        # Holds the angles on a circle through the start.
        calls["constraint"] += 1
        return jnp.sum(q**2) - jnp.sum(scene.y0[0] ** 2)

    term = dvi.LagrangianTerm(CountedLagrangian(), constraint=constraint)

    def loss(y0):
        sol = dfx.diffeqsolve(
            term,
            dvi.TrapezoidalVI(),
            0.0,
            0.1,
            0.01,
            y0,
            saveat=dfx.SaveAt(t1=True),
            adjoint=dvi.ReversibleAdjoint(),
        )
        return sum(jnp.sum(x) for x in sol.ys)

    jax.jit(jax.grad(loss)).trace(scene.y0)
    # One trace for each of a few signatures (a time known or traced, a state or a
    # point on a tangent line).
    assert 1 <= calls["lagrangian"] <= 4 and 1 <= calls["constraint"] <= 4, calls


def test_functions_called_on_saved_states_are_one_program_each():
    """`energy`, `velocity` and `project_onto_constraints` are called outside `jit`,
    on a solve's saved states or its start: each is one compiled program, as
    `diffeqsolve` is, not dozens of operations compiled and dispatched one by one
    (2 to 9 times slower first calls, `benchmarks/helpers_first_call.py`)."""
    lagrangian, y0 = DoublePendulum(), (jnp.array([0.3, -0.2]), jnp.array([0.1, 0.4]))
    pendulum = dvi.scenes.cartesian_pendulum()
    calls = [
        (lambda y: dvi.energy(lagrangian, 0.0, y), y0),
        (lambda y: dvi.velocity(lagrangian, 0.0, y), y0),
        (lambda y: dvi.project_onto_constraints(pendulum.term(), 0.0, y), pendulum.y0),
    ]
    for call, y in calls:
        equations = jax.make_jaxpr(call)(y).eqns
        assert [e.primitive.name for e in equations] == ["jit"], equations
