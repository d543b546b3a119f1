"""No silent wrong answers: every guard fires on the case it exists for, at two unit
scalings, and stays quiet on the same healthy physics in either units."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


# Mass scalings: the same physics with every momentum and energy multiplied by c.
UNITS = [1.0, 1e-6]
ONE_STEP = [
    ("MidpointVI", dvi.MidpointVI()),
    ("TrapezoidalVI", dvi.TrapezoidalVI()),
    ("GaussVPRK(2)", dvi.GaussVPRK(2)),
]
ALL = ONE_STEP + [("LinearizedVI", dvi.LinearizedVI(velocity="centered"))]


def _solve(lagrangian, solver, y0, *, t1=1.0, dt=0.1, **kwargs):
    return dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian), solver, 0.0, t1, dt, y0, **kwargs
    )


# The scales below are array fields, not Python floats, so that both unit scalings of
# a test run one compiled program (a float field would be static to the jit).


class Kepler(dvi.AbstractLagrangian):
    """Kepler's problem for a body of mass `m` (`mu = 1`)."""

    m: jax.Array

    def __call__(self, t, q, v, args):
        return self.m * (0.5 * jnp.sum(v**2) + 1 / jnp.sqrt(jnp.sum(q**2)))


class Pendulum(dvi.AbstractLagrangian):
    """A pendulum of unit mass and length under gravity `g`: `g -> g / s^2` with
    `h -> s h` is the same motion in other units of time."""

    g: jax.Array

    def __call__(self, t, q, v, args):
        return 0.5 * v**2 + self.g * jnp.cos(q)


class SeparablePendulum(dvi.AbstractSeparableLagrangian):
    """`Pendulum` as a separable Lagrangian, whose midpoint step the default policy
    solves by the fixed-point iteration first."""

    g: jax.Array
    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        return -self.g * jnp.cos(q)


class Relativistic(dvi.AbstractLagrangian):
    """A relativistic particle in a harmonic well: |v| < 1, not quadratic in v."""

    def __call__(self, t, q, v, args):
        return -jnp.sqrt(1 - v**2) - 0.5 * q**2


class FalselyQuadratic(dvi.AbstractQuadraticLagrangian):
    def __call__(self, t, q, v, args):
        return -jnp.sqrt(1 - v**2) - 0.5 * q**2


# Degenerate: L = c (q v - q^2 / 2), and a second velocity entering linearly beside a
# regular oscillator (the scale c passed as `args`: one compilation for both units).
LINEAR_IN_V = dvi.Lagrangian(lambda t, q, v, c: c * (q * v - 0.5 * q**2))
ONE_LINEAR_VELOCITY = dvi.Lagrangian(
    lambda t, q, v, c: c * (0.5 * v[0] ** 2 + q[1] * v[1] - 0.5 * jnp.sum(q**2))
)


@pytest.mark.parametrize("name,solver", ALL)
def test_velocity_entering_linearly_is_singular(name, solver):
    """L = q v - q^2 / 2 has dL/dv = q: no velocity is determined. From p0 on the
    constraint p = q the equations are consistent, and still the step is not
    determined: reported as singular, not stepped."""
    for c in UNITS:
        y0 = (jnp.array(0.5), jnp.array(0.5 * c))
        sol = _solve(LINEAR_IN_V, solver, y0, args=jnp.asarray(c), throw=False)
        assert sol.result == dfx.RESULTS.singular, c


def test_one_degenerate_direction_of_two_is_singular():
    for c in UNITS:
        y0 = (jnp.array([0.3, 0.5]), c * jnp.array([0.0, 0.5]))
        args = jnp.asarray(c)
        for name, solver in ALL:
            sol = _solve(ONE_LINEAR_VELOCITY, solver, y0, args=args, throw=False)
            assert sol.result == dfx.RESULTS.singular, (name, c)
        with pytest.raises(eqx.EquinoxRuntimeError, match="degenerate"):
            term = dvi.LagrangianTerm(ONE_LINEAR_VELOCITY)
            dfx.diffeqsolve(term, dfx.Tsit5(), 0.0, 1.0, 0.1, y0, args)


def test_zero_mass_is_singular_and_a_small_one_is_not():
    potential = lambda t, q, c: 0.5 * c * jnp.sum(q**2)
    y0 = (jnp.array([0.3, 0.5]), jnp.zeros(2))
    for c in UNITS:
        args = jnp.asarray(c)
        zero = dvi.SeparableLagrangian(potential, mass=c * jnp.array([1.0, 0.0]))
        for solver in (dvi.TrapezoidalVI(), dvi.MidpointVI()):
            sol = _solve(zero, solver, y0, args=args, throw=False)
            assert sol.result == dfx.RESULTS.singular, (solver, c)
        # The partitioned terms check a known mass when they are built.
        with pytest.raises(ValueError, match="mass"):
            _solve(zero, dvi.StormerVerlet(), y0, args=args)
        # Every mass small (the same physics in units of c): nothing is singular.
        small = dvi.SeparableLagrangian(potential, mass=c * jnp.ones(2))
        for solver in (dvi.TrapezoidalVI(), dvi.StormerVerlet(), dvi.MidpointVI()):
            sol = _solve(small, solver, y0, t1=np.pi, dt=np.pi / 200, args=args)
            # Unit frequency: half a period later q = -q0.
            assert np.allclose(sol.ys[0][-1], -y0[0], atol=1e-4), (solver, c)


def test_masses_far_apart_are_regular_in_float32():
    """A diagonal mass is singular only where an entry is zero: masses 1e-9 apart
    (the outer solar system's Pluto is 7.7e-9 of the Sun) are regular in float32
    too, whichever coordinate is the light one. A ratio test between the entries
    called them singular, and would change with each coordinate's units. Each
    coordinate is a unit-frequency oscillator: half a period later q = -q0."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    y0 = (f32([0.3, 0.5]), f32([0.0, 0.0]))
    t1, dt = f32(np.pi), f32(np.pi / 200)
    # One potential function for both masses: one compiled program per solver.
    potential = lambda t, q, m: 0.5 * jnp.sum(m * q**2)
    for masses in ([1.0, 1e-9], [1e-9, 1.0]):
        mass = f32(masses)
        lagrangian = dvi.SeparableLagrangian(potential, mass=mass)
        for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI(), dvi.StormerVerlet()):
            sol = _solve(lagrangian, solver, y0, t1=t1, dt=dt, args=mass)
            assert sol.ys[0].dtype == jnp.float32
            assert np.allclose(sol.ys[0][-1], -y0[0], atol=1e-4), (solver, masses)
        sol = dfx.diffeqsolve(
            dvi.LagrangianTerm(lagrangian), dfx.Tsit5(), f32(0), t1, dt, y0, mass
        )
        assert np.allclose(sol.ys[0][-1], -y0[0], atol=1e-4), masses


class _InUnits(dvi.AbstractLagrangian):
    """`inner` with each coordinate measured in its own unit `c` (an array field:
    one compiled program for every choice of units)."""

    inner: dvi.AbstractLagrangian
    c: jax.Array

    def __call__(self, t, q, v, args):
        return self.inner(t, self.c * q, self.c * v, args)


@pytest.mark.parametrize("dtype,unit", [(jnp.float64, 1e9), (jnp.float32, 1e4)])
def test_a_coupled_mass_is_regular_in_any_units(dtype, unit):
    """The double pendulum with its second angle in a unit `1/unit` of a radian:
    d2L/dv2 = C M C, whose eigenvalues are `unit**2` apart (1e18 in float64, 1e8
    in float32, beyond `n eps`) although the motion is the same. The start check
    judges the matrix in units of its diagonal, so the solve runs, and its states,
    converted back, are those of the solve in radians."""
    scene = dvi.scenes.double_pendulum()
    cast = lambda x: jnp.asarray(x, dtype)
    q0, p0 = cast(scene.y0[0]), cast(scene.y0[1] + jnp.array([0.3, -0.2]))
    states = []
    for c in (jnp.ones(2, dtype), jnp.array([1.0, unit], dtype)):
        lagrangian = _InUnits(scene.lagrangian, c)
        y0 = (q0 / c, p0 * c)
        sol = _solve(lagrangian, dvi.MidpointVI(), y0, t1=cast(1.0), dt=cast(0.05))
        states.append(np.concatenate([sol.ys[0][-1] * c, sol.ys[1][-1] / c]))
    assert np.max(np.abs(states[1] - states[0])) < 100 * jnp.finfo(dtype).eps


class _ConstraintInUnits(eqx.Module):
    """`inner(t, c q)` (`inner(t, q)` for `c = None`) with each value in its own
    unit `k`."""

    inner: eqx.Module
    c: jax.Array | None
    k: jax.Array

    def __call__(self, t, q, args):
        return self.k * self.inner(t, q if self.c is None else self.c * q, args)


def test_a_mechanism_runs_in_any_units_in_float32():
    """The four-bar in float32 with its coupler's angle in centiradians and one
    closure constraint in units 1e8 times smaller than the other: the same motion.
    Each coordinate's unit scales a row and a column of d2L/dv2 and of the Newton
    matrices, each constraint's a row of dg/dq; the singular tests (the Legendre
    map's 3 x 3 solve, the constraints' rank) judge them in their own units, so the
    solve runs and its states, converted back, are those of the solve in radians.
    (Judged as given, both fell below n eps of float32: singular and redundant.)"""
    scene = dvi.scenes.four_bar()
    f32 = lambda tree: jax.tree.map(
        lambda x: jnp.asarray(x, jnp.float32) if eqx.is_inexact_array(x) else x, tree
    )
    lagrangian, closure = f32(scene.lagrangian), f32(scene.constraint)
    q0, p0 = f32(scene.y0)
    h = jnp.float32(scene.period / 50)
    states = []
    for c, k in [([1.0, 1.0, 1.0], [1.0, 1.0]), ([1.0, 100.0, 1.0], [1.0, 1e8])]:
        c, k = jnp.asarray(c, jnp.float32), jnp.asarray(k, jnp.float32)
        term = dvi.LagrangianTerm(
            _InUnits(lagrangian, c), constraint=_ConstraintInUnits(closure, c, k)
        )
        y0 = (q0 / c, p0 * c)
        sol = _solve(term, dvi.MidpointVI(), y0, t1=10 * h, dt=h)
        states.append(np.concatenate([sol.ys[0][-1] * c, sol.ys[1][-1] / c]))
    assert np.max(np.abs(states[1] - states[0])) < 1e-5


def test_constraint_forces_in_any_units_in_float32():
    """The rigid double pendulum's joint constraints, every other one in units 1e4
    times smaller, in float32: the index-reduced vector field that Runge-Kutta
    solvers step solves G W G^T for the constraint forces, whose entries then span
    1e8; judged in its own units it is regular, and the vector field is the same
    as in the constraints' own units. (Judged as given: "The constraint forces
    cannot be solved".)"""
    scene = dvi.scenes.rigid_double_pendulum()
    f32 = lambda tree: jax.tree.map(
        lambda x: jnp.asarray(x, jnp.float32) if eqx.is_inexact_array(x) else x, tree
    )
    lagrangian, joints, y0 = f32(scene.lagrangian), f32(scene.constraint), f32(scene.y0)
    m = joints(0.0, y0[0], None).shape[0]
    fields = []
    for k in (jnp.ones(m), jnp.where(jnp.arange(m) % 2 == 0, 1.0, 1e4)):
        constraint = _ConstraintInUnits(joints, None, k.astype(jnp.float32))
        term = dvi.LagrangianTerm(lagrangian, constraint=constraint)
        fields.append(jax.jit(lambda y: term.vf(0.0, y, None))(y0))
    for a, b in zip(jax.tree.leaves(fields[0]), jax.tree.leaves(fields[1])):
        assert np.max(np.abs(a - b)) < 1e-5 * np.max(np.abs(a))


@pytest.mark.parametrize("n", [5, 80])
def test_the_start_checks_spectrum_does_not_see_the_units(n):
    """`symmetric_extremes`, dense (5) and by Lanczos (80): a positive definite
    matrix and the same in other units of each coordinate, `C A C` with `C`
    alternating 1e-6 and 1e6 (its eigenvalues 1e24 apart), give the same extremes;
    a singular one (dense) stays singular in either units. The dense solve by the
    same eigendecomposition (`symmetric_solve`) equals NumPy's in either units."""
    from diffrax_vi._spectrum import symmetric_extremes, symmetric_solve

    i = jnp.arange(n, dtype=float)
    off = 0.3 * jnp.cos(i[:-1])
    a = jnp.diag(2.0 + jnp.sin(i)) + jnp.diag(off, 1) + jnp.diag(off, -1)
    c = jnp.where(i % 2 == 0, 1e-6, 1e6)
    u = jnp.cos(1.3 * i) / jnp.linalg.norm(jnp.cos(1.3 * i))
    projector = jnp.eye(n) - jnp.outer(u, u)
    cases = [(a, True)] + ([(projector @ a @ projector, False)] if n <= 64 else [])
    for matrix, regular in cases:
        natural = symmetric_extremes(lambda x: matrix @ x, n, float)
        scaled = symmetric_extremes(lambda x: c * (matrix @ (c * x)), n, float)
        np.testing.assert_allclose(scaled, natural, rtol=1e-12, atol=1e-14)
        smallest, largest, least = (float(x) for x in scaled)
        assert (least > n * 2.2e-16 * max(-smallest, largest)) == regular
        assert (smallest > 0) == regular
    if n <= 64:
        # The solve by the same eigendecomposition: (C A C)^-1 C b = C^-1 A^-1 b.
        b = jnp.sin(2.1 * i)
        x, extremes = symmetric_solve(c[:, None] * a * c[None, :], c * b)
        np.testing.assert_allclose(c * x, np.linalg.solve(a, b), rtol=1e-12)
        natural = symmetric_extremes(lambda x: a @ x, n, float)
        np.testing.assert_allclose(extremes, natural, rtol=1e-12, atol=1e-14)


def test_linearized_guard_is_unit_free():
    """Centered LinearizedVI on Kepler (e = 0.6, 200 steps per period) follows a
    parasitic mode and explodes: unguarded it reports success; guarded it fails near
    step 328 in any units of mass. A healthy run passes in either units."""
    for c in (1.0, 1e-3):
        e = 0.6
        y0 = (jnp.array([1 - e, 0.0]), c * jnp.array([0.0, np.sqrt((1 + e) / (1 - e))]))
        kwargs = dict(t1=6 * np.pi, dt=2 * np.pi / 200, throw=False)
        silent = _solve(
            Kepler(jnp.asarray(c)),
            dvi.LinearizedVI(velocity="centered", max_del_residual=None),
            y0,
            max_steps=None,
            **kwargs,
        )
        assert silent.result == dfx.RESULTS.successful
        assert np.max(np.abs(silent.ys[0])) > 10  # far off the unit ellipse
        guarded = _solve(
            Kepler(jnp.asarray(c)), dvi.LinearizedVI(velocity="centered"), y0, **kwargs
        )
        assert guarded.result == dfx.RESULTS.nonlinear_divergence
        assert 250 < int(guarded.stats["num_accepted_steps"]) < 450
        # e = 0: the circular orbit is healthy, in either units.
        circle = (jnp.array([1.0, 0.0]), c * jnp.array([0.0, 1.0]))
        healthy = _solve(
            Kepler(jnp.asarray(c)),
            dvi.LinearizedVI(velocity="centered"),
            circle,
            **kwargs,
        )
        assert healthy.result == dfx.RESULTS.successful
        assert abs(float(jnp.linalg.norm(healthy.ys[0][-1])) - 1) < 1e-3


@pytest.mark.parametrize(
    "pendulum", [SeparablePendulum, Pendulum], ids=["fixed point then Newton", "Newton"]
)
def test_huge_step_does_not_land_on_a_spurious_root(pendulum):
    """The bound pendulum (energy -0.54) at h = 5: Newton can converge to a root
    that puts it at energy 82. The root is reported as divergence, in any units of
    time; the same method at h = 1 is fine. Newton's dense Jacobian at its last
    iterate measures the curvature, whether it is the fallback of the fixed-point
    iteration (the default policy on a separable Lagrangian; the iteration alone
    fails at both steps) or the only root finder (on a general one). (Times and
    scales are arrays: one compiled solve for every step and both units.)"""
    for s in (1.0, 1e3):
        lagrangian = pendulum(jnp.asarray(1.0 / s**2))
        y0 = (jnp.array(1.0), jnp.array(0.5 / s))
        energy = lambda y: float(dvi.energy(lagrangian, 0.0, y)) * s**2
        for h, expected in (
            (5.0, dfx.RESULTS.nonlinear_divergence),
            (10.0, dfx.RESULTS.nonlinear_divergence),
            (1.0, dfx.RESULTS.successful),
        ):
            t1, dt = jnp.asarray(40 * s), jnp.asarray(h * s)
            sol = _solve(lagrangian, dvi.MidpointVI(), y0, t1=t1, dt=dt, throw=False)
            assert sol.result == expected, (h, s)
            if expected == dfx.RESULTS.successful:
                y1 = (sol.ys[0][-1], sol.ys[1][-1])
                assert abs(energy(y1) - energy(y0)) < 0.05


@pytest.mark.parametrize("stages", [2, 3])
def test_multi_stage_steps_pass_the_fold_test_on_the_oscillator_at_any_step(stages):
    """A multi-stage step's fold test measures the midpoint matrix at the stages'
    mean velocity, positive wherever the potential curves upwards: the oscillator's
    steps pass at every size, though the curvature of the Gauss stage equations'
    own Jacobian (weighted by b) is negative at their one root from h omega = 3.5
    (three stages) or 4 (two): a test on it fails them.
    Gauss steps keep the oscillator's energy, a quadratic invariant, to round-off.
    (tests/test_failures.py: the test fails a step across a blow-up.)"""
    oscillator = dvi.SeparableLagrangian(lambda t, q, args: 0.5 * q**2)
    y0 = (jnp.array(1.0), jnp.array(0.0))
    for h in (0.5, 3.5, 6.0, 20.0):
        t1, dt = jnp.asarray(20 * h), jnp.asarray(h)
        sol = _solve(oscillator, dvi.GaussVPRK(stages), y0, t1=t1, dt=dt, throw=False)
        assert sol.result == dfx.RESULTS.successful, h
        q, p = sol.ys[0][-1], sol.ys[1][-1]
        assert abs(float(0.5 * (q**2 + p**2)) - 0.5) < 1e-13, h


def test_multi_stage_fold_test_is_unit_free():
    """LobattoVPRK(3) stepping across the blow-up of V = -q^4 (t = 0.927) from rest
    at q = 1 at h = 0.1 stops at the step whose root lies across the fold, the
    ninth (tests/test_failures.py), in any units of time and length: with
    q -> l q, t -> s t (V = -g q^4, g = 1 / (s l)^2) it keeps the same states, q
    times l and p times l / s, and fails the same step. (Scales and times are
    arrays: one compiled solve for every unit.)"""
    blowup = dvi.SeparableLagrangian(lambda t, q, g: -g * q**4)
    kept = []
    for s, length in ((1.0, 1.0), (1e3, 1.0), (1.0, 1e-3), (1e-2, 1e2)):
        sol = _solve(
            blowup,
            dvi.LobattoVPRK(3),
            (jnp.asarray(length), jnp.asarray(0.0)),
            t1=jnp.asarray(3.0 * s),
            dt=jnp.asarray(0.1 * s),
            args=jnp.asarray(1 / (s * length) ** 2),
            throw=False,
            saveat=dfx.SaveAt(steps=True),
        )
        assert sol.result == dfx.RESULTS.nonlinear_divergence, (s, length)
        assert int(sol.stats["num_accepted_steps"]) == 9, (s, length)
        q, p = (np.asarray(x[:8]) for x in sol.ys)
        kept.append((q / length, p * s / length))
        assert np.isnan(sol.ys[0][8])
    for q, p in kept[1:]:
        np.testing.assert_allclose(q, kept[0][0], rtol=1e-10)
        np.testing.assert_allclose(p, kept[0][1], rtol=1e-10)


@pytest.mark.parametrize("bad", ["t1", "dt0"])
@pytest.mark.parametrize("name,solver", ALL + [("StormerVerlet", dvi.StormerVerlet())])
def test_nan_times_are_an_error(name, solver, bad):
    """diffeqsolve would take no step and report success. From Python floats the
    times are known when traced, and the error comes then; from arrays, at run time
    (one solver: the check is the same for all)."""
    lagrangian = dvi.SeparableLagrangian(lambda t, q, args: 0.5 * q**2)
    times = dict(t1=1.0, dt0=0.1)
    times[bad] = float("nan")
    solve = lambda t1, dt0: dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian),
        solver,
        0.0,
        t1,
        dt0,
        (jnp.array(1.0), jnp.array(0.0)),
    )
    with pytest.raises(ValueError, match="NaN or infinite"):
        solve(**times)
    if name == "MidpointVI":
        with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or infinite"):
            solve(**{k: jnp.asarray(t) for k, t in times.items()})


@pytest.mark.parametrize(
    "solver",
    [dvi.MidpointVI(), dvi.LinearizedVI(velocity="centered"), dfx.Tsit5()],
    ids=["MidpointVI", "LinearizedVI", "Tsit5"],
)
def test_relativistic_lagrangian_runs_in_every_solver(solver):
    """p0 = 3 is a velocity of 3 / sqrt(10) ~ 0.95, beyond what an undamped Newton
    step from v = 0 reaches without leaving |v| < 1. The one-step and multistep
    solvers, and the Legendre inversion under Tsit5, keep |v| < 1 and the energy."""
    y0 = (jnp.array(0.0), jnp.array(3.0))
    lagrangian = Relativistic()
    energy = jax.vmap(lambda q, p: dvi.energy(lagrangian, 0.0, (q, p)))
    velocity = jax.vmap(lambda q, p: dvi.velocity(lagrangian, 0.0, (q, p))[0])
    e0 = float(energy(*(x[None] for x in y0))[0])
    sol = _solve(
        lagrangian,
        solver,
        y0,
        t1=10.0,
        dt=0.01,
        saveat=dfx.SaveAt(ts=jnp.linspace(0.0, 10.0, 101)),
    )
    assert sol.result == dfx.RESULTS.successful
    qs, ps = sol.ys
    assert float(jnp.max(jnp.abs(velocity(qs, ps)))) < 1
    assert float(jnp.max(jnp.abs(energy(qs, ps) - e0))) < 1e-3 * abs(e0)


def test_false_quadratic_marker_is_caught():
    y0 = (jnp.array(0.0), jnp.array(0.5))
    for solver in (dvi.MidpointVI(), dfx.Tsit5()):
        with pytest.raises(eqx.EquinoxRuntimeError, match="not quadratic"):
            _solve(FalselyQuadratic(), solver, y0)
    # The true quadratic passes the same check.
    honest = dvi.SeparableLagrangian(lambda t, q, args: 0.5 * q**2)
    assert _solve(honest, dvi.MidpointVI(), y0).result == dfx.RESULTS.successful


def test_a_false_quadratic_marker_in_a_loop_is_nan_not_a_callback():
    """Where a Lagrangian marked quadratic in `v` is not, `diffrax_vi.energy` raises
    (a host callback); a scene's energy, which a study traces into every step of a
    solve that checked its own start, is NaN there (the study then reports the run
    non-finite) and its program holds no callback, which would break the loop into
    kernels. Where the marker holds (`p = 0` here) both give the energy."""
    zero = jnp.array(0.0)
    scene = dvi.scenes.Scene("false", FalselyQuadratic(), (zero, zero), 1.0)
    energy = jax.jit(scene.energy)
    held, broken = (jnp.array(0.3), jnp.array(0.0)), (jnp.array(0.3), jnp.array(0.5))
    assert float(energy(0.0, held, None)) == pytest.approx(1 + 0.5 * 0.3**2)
    assert float(dvi.energy(FalselyQuadratic(), 0.0, held)) == pytest.approx(1.045)
    assert np.isnan(float(energy(0.0, broken, None)))
    with pytest.raises(eqx.EquinoxRuntimeError, match="not quadratic"):
        dvi.energy(FalselyQuadratic(), 0.0, broken)
    assert "callback" not in str(jax.make_jaxpr(scene.energy)(0.0, broken, None))
    raising = jax.make_jaxpr(dvi.energy)(FalselyQuadratic(), 0.0, broken)
    assert "callback" in str(raising)


def test_bad_states_are_value_errors():
    lagrangian = dvi.SeparableLagrangian(lambda t, q, args: 0.5 * q**2)
    half = lambda x: jnp.asarray(x, "float16")
    with pytest.raises(ValueError, match="float16"):
        # (With float64 times diffrax promotes the state, and the solve is fine.)
        dfx.diffeqsolve(
            dvi.LagrangianTerm(lagrangian),
            dvi.MidpointVI(),
            half(0.0),
            half(1.0),
            half(0.1),
            (half(1.0), half(0.0)),
        )
    with pytest.raises(ValueError, match="tuple, not a list"):
        _solve(lagrangian, dvi.MidpointVI(), [jnp.ones(()), jnp.ones(())])
    with pytest.raises(ValueError, match="mass"):
        dvi.velocity(
            dvi.SeparableLagrangian(lambda t, q, args: 0.0, mass=jnp.ones(3)),
            0.0,
            (jnp.ones(2), jnp.ones(2)),
        )
