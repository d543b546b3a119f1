import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from .helpers import (
    central,
    DoublePendulum,
    Duffing,
    fitted_order,
    KEPLER,
    kepler_state,
    max_abs_diff,
    Pendulum,
    reference,
    stiffening,
)


def _duffing_general(t, q, v, args):
    # The same Duffing Lagrangian, but not declared separable: TrapezoidalVI is then
    # implicit.
    return 0.5 * v**2 + 0.5 * q**2 - 0.25 * q**4


class HenonHeiles(dvi.AbstractSeparableLagrangian):
    mass: float = 1.0

    def potential(self, t, q, args):
        x, y = q[0], q[1]
        return 0.5 * (x**2 + y**2) + x**2 * y - y**3 / 3


def _forced(t, q, v, args):
    # A time-dependent Lagrangian: catches a solver that evaluates L at the wrong time.
    return 0.5 * v**2 - 0.5 * q**2 + q * jnp.sin(2 * t)


# Each entry: (name, lagrangian, solver, whether to hand StormerVerlet partitioned
# terms). Shared so that compiled solves are reused across tests.
@eqx.filter_jit
def _final(lagrangian, solver, y0, t0, t1, dt0, args=None):
    sol = dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian), solver, t0, t1, dt0, y0, args, max_steps=512
    )
    return jax.tree.map(lambda x: x[-1], sol.ys)


SECOND_ORDER = [
    ("MidpointVI", dvi.MidpointVI()),
    ("TrapezoidalVI", dvi.TrapezoidalVI()),
    ("StormerVerlet", dvi.StormerVerlet()),
]


@pytest.mark.parametrize(
    "name,solver", SECOND_ORDER + [("SemiImplicitEuler", dfx.SemiImplicitEuler())]
)
@pytest.mark.parametrize(
    "lagrangian,y0",
    [
        (Duffing(), (jnp.array(0.5), jnp.array(0.0))),
        (Pendulum(), (jnp.array(1.2), jnp.array(0.0))),
    ],
    ids=["duffing", "pendulum"],
)
def test_order(name, solver, lagrangian, y0):
    t1 = 4.0
    exact = reference(lagrangian, y0, t1)
    ns = [20, 40, 80, 160]
    errors = [
        max_abs_diff(_final(lagrangian, solver, y0, 0.0, t1, jnp.array(t1 / n)), exact)
        for n in ns
    ]
    order = fitted_order([t1 / n for n in ns], errors)
    expected = 1 if name == "SemiImplicitEuler" else 2
    assert abs(order - expected) < 0.3, (name, errors, order)


def test_order_implicit_trapezoidal():
    y0 = (jnp.array(0.5), jnp.array(0.0))
    t1 = 4.0
    exact = reference(_duffing_general, y0, t1)
    ns = [20, 40, 80, 160]
    solver = dvi.TrapezoidalVI()
    errors = [
        max_abs_diff(
            _final(
                dvi.Lagrangian(_duffing_general), solver, y0, 0.0, t1, jnp.array(t1 / n)
            ),
            exact,
        )
        for n in ns
    ]
    assert abs(fitted_order([t1 / n for n in ns], errors) - 2) < 0.3, errors


def test_trapezoidal_separable_is_stormer_verlet():
    y0 = (jnp.array([0.1, -0.2]), jnp.array([0.3, 0.25]))
    a = _final(HenonHeiles(), dvi.TrapezoidalVI(), y0, 0.0, 5.0, jnp.array(0.05))
    b = _final(HenonHeiles(), dvi.StormerVerlet(), y0, 0.0, 5.0, jnp.array(0.05))
    assert max_abs_diff(a, b) < 1e-15


@pytest.mark.parametrize(
    "lagrangian,solver",
    [
        (DoublePendulum(), dvi.MidpointVI()),
        (dvi.Lagrangian(stiffening), dvi.MidpointVI()),
        (dvi.Lagrangian(stiffening), dvi.TrapezoidalVI()),
        (DoublePendulum(), dvi.TrapezoidalVI()),
        (HenonHeiles(), dvi.TrapezoidalVI()),
        (HenonHeiles(), dvi.StormerVerlet()),
    ],
    ids=[
        "mid-quadratic",
        "mid-general",
        "trap-general",
        "trap-quadratic",
        "trap-separable",
        "sv",
    ],
)
def test_symplectic_step(lagrangian, solver):
    y0 = (jnp.array([0.4, -0.7]), jnp.array([0.3, 0.5]))
    defect = dvi.diagnostics.symplecticity_defect(
        solver, dvi.terms_for(solver, lagrangian), y0
    )
    assert defect < 1e-13


def test_runge_kutta_step_is_not_symplectic():
    # The check above can fail: Tsit5's step map on the same term is not symplectic.
    y0 = (jnp.array([0.4, -0.7]), jnp.array([0.3, 0.5]))
    terms = dvi.LagrangianTerm(DoublePendulum())
    assert dvi.diagnostics.symplecticity_defect(dfx.Tsit5(), terms, y0) > 1e-7


def _energy_deciles(solver, n_steps, n_save=1000):
    steps_per_orbit = 200
    t1 = 2 * np.pi * n_steps / steps_per_orbit
    ts = jnp.linspace(0.0, t1, n_save + 1)
    energy = lambda t, y, args: dvi.energy(KEPLER, t, y)
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(KEPLER),
        solver,
        0.0,
        t1,
        t1 / n_steps,
        kepler_state(),
        saveat=dfx.SaveAt(ts=ts, fn=energy),
        max_steps=n_steps + 1,
    )
    assert sol.result == dfx.RESULTS.successful
    error = np.abs(np.asarray(sol.ys) - float(sol.ys[0]))
    decile = n_save // 10
    return error[1 : decile + 1].max(), error[-decile:].max()


@pytest.mark.parametrize(
    "solver", [dvi.MidpointVI(), dvi.TrapezoidalVI()], ids=["mid", "trap"]
)
def test_energy_bounded_over_1e5_steps(solver):
    first, last = _energy_deciles(solver, 100_000)
    # Bounded: the last decile's worst error is that of the first (500 orbits, e = 0.6).
    assert last < 1.2 * first, (first, last)
    assert last < 0.05


def test_runge_kutta_energy_drifts_on_same_steps():
    first, last = _energy_deciles(dfx.Tsit5(), 100_000)
    assert last > 5 * first, (first, last)


@pytest.mark.parametrize(
    "lagrangian,solver",
    [
        (dvi.Lagrangian(central), dvi.MidpointVI()),
        (dvi.Lagrangian(central), dvi.TrapezoidalVI()),
        (
            dvi.SeparableLagrangian(
                lambda t, q, args: 0.05 / jnp.sum(q**2) - 1 / jnp.sqrt(jnp.sum(q**2))
            ),
            dvi.StormerVerlet(),
        ),
    ],
    ids=["mid", "trap", "sv"],
)
def test_noether_angular_momentum(lagrangian, solver):
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 0.8]))
    sol = dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian),
        solver,
        0.0,
        200.0,
        0.02,
        y0,
        saveat=dfx.SaveAt(steps=True),
        max_steps=10_000,
    )
    q, p = sol.ys
    angular = q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0]
    # 10^4 steps of a precessing orbit: conserved to round-off, not to truncation error.
    assert float(jnp.max(jnp.abs(angular - 0.8))) < 1e-13
    energy = jax.vmap(lambda a, b: dvi.energy(lagrangian, 0.0, (a, b)))(q, p)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) > 1e-8  # truncation is visible


@pytest.mark.parametrize("name,solver", SECOND_ORDER)
def test_backward_returns_to_start(name, solver):
    y0 = (jnp.array(1.2), jnp.array(0.3))
    y1 = _final(Pendulum(), solver, y0, 0.0, 3.0, jnp.array(0.05))
    back = _final(Pendulum(), solver, y1, 3.0, 0.0, jnp.array(-0.05))
    assert max_abs_diff(back, y0) < 1e-12


@pytest.mark.parametrize(
    "solver", [dvi.MidpointVI(), dvi.TrapezoidalVI()], ids=["mid", "trap"]
)
def test_time_dependent_forward_and_backward(solver):
    y0 = (jnp.array(0.3), jnp.array(-0.2))
    lagrangian = dvi.Lagrangian(_forced)
    forward = _final(lagrangian, solver, y0, 0.0, 3.0, jnp.array(0.01))
    assert max_abs_diff(forward, reference(_forced, y0, 3.0)) < 1e-4
    backward = _final(lagrangian, solver, y0, 3.0, 0.5, jnp.array(-0.01))
    assert max_abs_diff(backward, reference(_forced, y0, 0.5, t0=3.0)) < 1e-4


@pytest.mark.parametrize("name,solver", SECOND_ORDER)
def test_vmap_equals_loop(name, solver):
    q0s = jnp.array([0.1, 0.5, 1.0, 2.0])
    y0s = (q0s, jnp.zeros(4))
    batched = jax.vmap(
        lambda y0: _final(Pendulum(), solver, y0, 0.0, 2.0, jnp.array(0.1))
    )(y0s)
    for i in range(4):
        single = _final(
            Pendulum(), solver, (q0s[i], jnp.array(0.0)), 0.0, 2.0, jnp.array(0.1)
        )
        assert max_abs_diff((batched[0][i], batched[1][i]), single) < 1e-14


def _q_final(g, solver, adjoint):
    lagrangian = Pendulum(g=g)
    sol = dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian),
        solver,
        0.0,
        2.0,
        0.05,
        (jnp.array(1.0), jnp.array(0.0)),
        adjoint=adjoint,
    )
    return sol.ys[0][-1]


@pytest.mark.parametrize("name,solver", SECOND_ORDER)
def test_grad_matches_finite_difference(name, solver):
    g = jnp.array(1.3)
    grad = jax.grad(_q_final)(g, solver, dfx.RecursiveCheckpointAdjoint())
    eps = 1e-6
    adjoint = dfx.RecursiveCheckpointAdjoint()
    fd = (_q_final(g + eps, solver, adjoint) - _q_final(g - eps, solver, adjoint)) / (
        2 * eps
    )
    assert jnp.allclose(grad, fd, rtol=1e-6), (grad, fd)
    _, tangent = jax.jvp(
        lambda g: _q_final(g, solver, dfx.ForwardMode()), (g,), (jnp.array(1.0),)
    )
    assert jnp.allclose(tangent, fd, rtol=1e-6), (tangent, fd)


def test_grad_through_args_and_general_lagrangian():
    def q_final(k):
        sol = dfx.diffeqsolve(
            dvi.LagrangianTerm(lambda t, q, v, k: 0.5 * v**2 - 0.25 * k * q**4),
            dvi.MidpointVI(),
            0.0,
            2.0,
            0.05,
            (jnp.array(1.0), jnp.array(0.0)),
            args=k,
        )
        return sol.ys[0][-1]

    k = jnp.array(0.7)
    eps = 1e-6
    fd = (q_final(k + eps) - q_final(k - eps)) / (2 * eps)
    assert jnp.allclose(jax.grad(q_final)(k), fd, rtol=1e-6)


def test_saveat_modes_and_dense_output():
    y0 = (jnp.array(1.2), jnp.array(0.0))
    ts = jnp.array([0.123, 0.5, 1.777])
    solve = lambda saveat: dfx.diffeqsolve(
        dvi.LagrangianTerm(Pendulum()),
        dvi.MidpointVI(),
        0.0,
        2.0,
        0.01,
        y0,
        saveat=saveat,
        max_steps=256,
    )
    sol = solve(dfx.SaveAt(t0=True, t1=True, ts=ts, dense=True))
    steps = solve(dfx.SaveAt(steps=True))
    assert sol.result == dfx.RESULTS.successful
    assert jnp.array_equal(
        sol.ts, jnp.concatenate([jnp.array([0.0]), ts, jnp.array([2.0])])
    )
    n_steps = int(steps.stats["num_steps"])
    assert n_steps == 200
    assert (
        max_abs_diff(
            (sol.ys[0][-1], sol.ys[1][-1]), (steps.ys[0][199], steps.ys[1][199])
        )
        == 0
    )
    for i, t in enumerate(ts):
        exact = reference(Pendulum(), y0, float(t))
        interpolated = (sol.ys[0][1 + i], sol.ys[1][1 + i])
        assert max_abs_diff(interpolated, exact) < 1e-5  # O(h^2) of the method
        assert max_abs_diff(sol.evaluate(t), interpolated) < 1e-14
    # Dense output passes through the steps.
    dense = jax.vmap(sol.evaluate)(steps.ts[:n_steps])
    assert max_abs_diff(dense, (steps.ys[0][:n_steps], steps.ys[1][:n_steps])) < 1e-13


def test_progress_meter(capsys):
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(Pendulum()),
        dvi.MidpointVI(),
        0.0,
        1.0,
        0.1,
        (jnp.array(1.0), jnp.array(0.0)),
        progress_meter=dfx.TextProgressMeter(minimum_increase=0.5),
    )
    assert sol.result == dfx.RESULTS.successful
    assert "100.00%" in capsys.readouterr().out


def test_float32_preserves_dtype_and_is_accurate():
    f32 = lambda x: jnp.array(x, dtype=jnp.float32)
    y0 = (f32(1.2), f32(0.0))
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI()):
        # Times in float32 too: diffrax promotes the state to the dtype of the times.
        sol = dfx.diffeqsolve(
            dvi.LagrangianTerm(
                dvi.Lagrangian(lambda t, q, v, a: 0.5 * v**2 + jnp.cos(q))
            ),
            solver,
            f32(0.0),
            f32(4.0),
            f32(0.05),
            y0,
        )
        assert sol.result == dfx.RESULTS.successful
        assert sol.ys[0].dtype == jnp.float32 and sol.ys[1].dtype == jnp.float32
        exact = reference(Pendulum(), (jnp.array(1.2), jnp.array(0.0)), 4.0)
        assert max_abs_diff((sol.ys[0][-1], sol.ys[1][-1]), exact) < 2e-3


# --- Bad input ---


def _solve(lagrangian, solver, y0, **kwargs):
    return dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian), solver, 0.0, 1.0, 0.1, y0, **kwargs
    )


@pytest.mark.parametrize("solver", [dvi.MidpointVI(), dvi.TrapezoidalVI(), dfx.Tsit5()])
def test_non_scalar_lagrangian(solver):
    vector = dvi.Lagrangian(lambda t, q, v, args: 0.5 * v**2 - 0.5 * q**2)
    with pytest.raises(ValueError, match="must return a scalar"):
        _solve(vector, solver, (jnp.ones(2), jnp.ones(2)))


@pytest.mark.parametrize("solver", [dvi.MidpointVI(), dfx.Tsit5()])
def test_mismatched_state(solver):
    with pytest.raises(ValueError, match="same PyTree structure"):
        _solve(Pendulum(), solver, (jnp.ones(2), (jnp.ones(2),)))
    with pytest.raises(ValueError, match="matching shapes"):
        _solve(Pendulum(), solver, (jnp.ones(2), jnp.ones(3)))
    with pytest.raises(ValueError, match="pair"):
        _solve(Pendulum(), solver, [jnp.ones(2), jnp.ones(2), jnp.ones(2)])


def test_wrong_term():
    with pytest.raises(ValueError, match="LagrangianTerm"):
        dfx.diffeqsolve(
            dfx.ODETerm(lambda t, y, args: y), dvi.MidpointVI(), 0, 1, 0.1, (1.0, 1.0)
        )
    with pytest.raises(ValueError, match="not compatible"):
        dfx.diffeqsolve(
            dvi.LagrangianTerm(Pendulum()), dvi.StormerVerlet(), 0, 1, 0.1, (1.0, 1.0)
        )


def test_newton_failure_is_reported():
    # A huge step on a strongly nonlinear system: the implicit equation has no nearby
    # root. The failure is a RESULTS, never a NaN trajectory marked successful.
    strong = dvi.Lagrangian(lambda t, q, v, a: 0.5 * v**2 - q**4 - jnp.cosh(3 * q))
    y0 = (jnp.array(2.0), jnp.array(5.0))
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(strong), dvi.MidpointVI(), 0.0, 30.0, 3.0, y0, throw=False
    )
    assert sol.result != dfx.RESULTS.successful
    with pytest.raises(eqx.EquinoxRuntimeError):
        dfx.diffeqsolve(
            dvi.LagrangianTerm(strong), dvi.MidpointVI(), 0.0, 30.0, 3.0, y0
        )


@pytest.mark.parametrize("name,solver", SECOND_ORDER)
def test_non_finite_initial_condition(name, solver):
    sol = _solve(Pendulum(), solver, (jnp.array(jnp.nan), jnp.array(0.0)), throw=False)
    assert sol.result == dfx.RESULTS.nonfinite


def test_non_finite_parameter():
    sol = _solve(
        Pendulum(g=jnp.array(jnp.inf)),
        dvi.MidpointVI(),
        (jnp.array(1.0), jnp.array(0.0)),
        throw=False,
    )
    assert sol.result != dfx.RESULTS.successful


def test_singular_hessian():
    degenerate = dvi.Lagrangian(
        lambda t, q, v, args: 0.5 * jnp.sum(v) ** 2 - jnp.sum(q**4)
    )
    y0 = (jnp.array([0.1, 0.2]), jnp.array([1.0, 1.0]))
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI()):
        sol = _solve(degenerate, solver, y0, throw=False)
        assert sol.result == dfx.RESULTS.singular
        with pytest.raises(eqx.EquinoxRuntimeError, match="linear solver"):
            _solve(degenerate, solver, y0)
    with pytest.raises(eqx.EquinoxRuntimeError, match="singular"):
        _solve(degenerate, dfx.Tsit5(), y0)


def test_adaptive_through_half_solver():
    # Works, but is no longer symplectic: documented in docs/errors.md.
    y0 = (jnp.array(1.2), jnp.array(0.0))
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(Pendulum()),
        dfx.HalfSolver(dvi.MidpointVI()),
        0.0,
        10.0,
        0.1,
        y0,
        stepsize_controller=dfx.PIDController(rtol=1e-8, atol=1e-8),
        max_steps=10_000,
    )
    assert sol.result == dfx.RESULTS.successful
    final = (sol.ys[0][-1], sol.ys[1][-1])
    assert max_abs_diff(final, reference(Pendulum(), y0, 10.0)) < 1e-5


@pytest.mark.parametrize("name,solver", SECOND_ORDER)
def test_non_finite_position_of_a_free_particle(name, solver):
    # The force does not depend on q, so a NaN position never reaches the momentum
    # through a kick: the start itself must be checked.
    free = dvi.SeparableLagrangian(lambda t, q, args: 0.0 * jnp.sum(q))
    sol = _solve(free, solver, (jnp.array([jnp.nan, 0.0]), jnp.ones(2)), throw=False)
    assert sol.result == dfx.RESULTS.nonfinite


def test_newton_takes_any_lineax_solver():
    """Newton's method with a lineax solver in place of its own elimination (here
    lineax's LAPACK LU, an independent solve) takes the same steps on the double
    pendulum under MidpointVI over 150 steps, to round-off, and reports success
    as diffrax's result."""
    scene = dvi.scenes.double_pendulum()
    h = scene.period / 100

    def solve(linear_solver):
        solver = dvi.MidpointVI(root_finder=dvi.Newton(linear_solver=linear_solver))
        return dfx.diffeqsolve(scene.term(), solver, 0.0, 150 * h, h, scene.y0)

    ours, reference = solve(lx.LU()), solve("dense")
    assert ours.result == dfx.RESULTS.successful
    size = max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(reference.ys))
    assert max_abs_diff(ours.ys, reference.ys) < 1e-12 * size
    assert max_abs_diff(ours.ys, jax.tree.map(lambda x: x[None], scene.y0)) > 0.1


def test_simplified_newton_takes_newtons_steps_without_lapack_lu():
    """The chord method keeps one factorisation across iterations and steps, and
    converges to the same roots as Newton's method: on the double pendulum (a
    general Lagrangian) under MidpointVI and the Cartesian pendulum's RATTLE step,
    within what each step's tolerance (sqrt(eps) of the state's size) allows over
    150 steps (a period and a half); the chord method converges linearly, so it
    stops short of the round-off that Newton's quadratic last iteration reaches
    (1e-8 apart on the double pendulum). On these small systems it factorises
    without LAPACK's LU, whose call would keep XLA from compiling the time-stepping
    loop whole (a MidpointVI step on the double pendulum took 16x Newton's with
    it)."""
    chord, newton = dvi.SimplifiedNewton(), dvi.Newton()
    for scene, make in [
        (dvi.scenes.double_pendulum(), dvi.MidpointVI),
        (dvi.scenes.cartesian_pendulum(), dvi.TrapezoidalVI),
    ]:
        h = scene.period / 100

        def solve(root_finder, scene=scene, make=make, h=h):
            return dfx.diffeqsolve(
                scene.term(), make(root_finder=root_finder), 0.0, 150 * h, h, scene.y0
            ).ys

        compiled = jax.jit(lambda: solve(chord)).lower().compile()
        ours, reference = compiled(), solve(newton)
        size = max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(reference))
        tolerance = float(jnp.finfo(jnp.float64).eps) ** 0.5
        assert max_abs_diff(ours, reference) < 150 * tolerance * size
        assert max_abs_diff(ours, jax.tree.map(lambda x: x[None], scene.y0)) > 0.1
        # No LAPACK LU (getrf); the start's checks keep theirs, outside the loop.
        assert "getrf" not in compiled.as_text()


def test_rolled_elimination_is_the_unrolled_one():
    """Newton's dense solves beyond 16 unknowns (constrained steps) factorise in a
    loop over the columns, which compiles in constant time: the same pivots and
    factors as the unrolled elimination, solutions to numpy's within round-off,
    including a matrix that needs row swaps, and the singular case still shows as a
    zero pivot ratio (the step's singular-Jacobian test)."""
    from diffrax_vi._linear import (
        dense_lu_solve,
        rolled_lu_factor,
        unrolled_lu_factor,
    )

    rng = np.random.default_rng(0)
    a = rng.normal(size=(20, 20))
    a[0, 0] = 0.0  # The first column's pivot is in another row.
    b = rng.normal(size=20)
    lu_rolled, perm_rolled = jax.jit(rolled_lu_factor)(a)
    lu_unrolled, perm_unrolled = jax.jit(unrolled_lu_factor)(a)
    np.testing.assert_array_equal(perm_rolled, perm_unrolled)
    np.testing.assert_allclose(lu_rolled, lu_unrolled, rtol=0, atol=1e-12)
    assert not np.array_equal(perm_rolled, np.arange(20))
    x, ratio = jax.jit(lambda a, b: dense_lu_solve(a, b, 16))(a, b)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10)
    assert 0 < ratio <= 1
    singular = a.copy()
    singular[:, 5] = singular[:, 3]
    _, ratio = jax.jit(lambda a, b: dense_lu_solve(a, b, 16))(singular, b)
    assert ratio < 1e-12


@pytest.mark.parametrize("n", [2, 3])
def test_closed_form_solves_in_any_units(n):
    """`cofactor_solve`, Newton's and the Legendre map's 2 x 2 and 3 x 3 solves:
    the solution is NumPy's, also for a matrix whose first pivot is zero (which an
    elimination without pivoting could not take), in units 1e12 apart too (`C A C`,
    the units of a step's coordinates); the singular measure is at most one, the
    same in both units where the diagonal, which it takes the units from, has no
    zero, and below the singular threshold for a singular matrix in either."""
    from diffrax_vi._linear import cofactor_solve
    from diffrax_vi._tolerance import singular_threshold

    rng = np.random.default_rng(n)
    b = rng.normal(size=n)
    c = np.where(np.arange(n) % 2 == 0, 1e-6, 1e6)
    solve = jax.jit(cofactor_solve)
    zero_pivot = np.roll(np.eye(n), 1, axis=0) + 0.1 * rng.normal(size=(n, n))
    zero_pivot[0, 0] = 0.0
    for a in (rng.normal(size=(n, n)), zero_pivot):
        x, measure = solve(a, b)
        np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10)
        assert 0 < measure <= 1
        x, scaled = solve(c[:, None] * a * c[None, :], c * b)
        np.testing.assert_allclose(c * x, np.linalg.solve(a, b), rtol=1e-10)
        if np.all(np.diagonal(a) != 0):  # The diagonal carries the units.
            np.testing.assert_allclose(scaled, measure, rtol=1e-10)
    singular = rng.normal(size=(n, n))
    singular[-1] = singular[0]
    for units in (np.ones(n), c):
        _, measure = solve(units[:, None] * singular * units[None, :], b)
        assert measure <= singular_threshold(n, jnp.float64), (units, measure)


def test_unpivoted_elimination_of_a_definite_matrix_in_any_units():
    """`unpivoted_solve`: a definite, non-symmetric 6 x 6 matrix (the fixed-point
    iteration's Schur complement G(q1) M^-1 G(q0)^T) and a symmetric positive
    definite one (a step's momentum projection, G M^-1 G^T), each also in units
    1e12 apart (`C A C`), solve as NumPy does, with the ratio of the smallest to
    the largest pivot that the leading principal minors give (pivot k is
    det A_k / det A_(k-1)). A projection onto constraints that repeat one another
    is singular to working precision in any units; a zero leading pivot, which
    partial pivoting would have avoided, gives a ratio of zero and a non-finite
    answer (the fixed-point iteration then falls back to Newton's method), not a
    wrong finite one."""
    from diffrax_vi._constraint import _reduced_solve
    from diffrax_vi._linear import unpivoted_solve
    from diffrax_vi._tolerance import singular_threshold

    def minors_ratio(a):
        dets = [np.linalg.det(a[:k, :k]) for k in range(1, len(a) + 1)]
        pivots = np.abs(np.array(dets) / np.array([1.0, *dets[:-1]]))
        return pivots.min() / pivots.max()

    rng = np.random.default_rng(1)
    g0 = rng.normal(size=(6, 12))
    g1 = g0 + 0.05 * rng.normal(size=(6, 12))
    w = np.diag(rng.uniform(0.5, 2.0, size=12))
    b = rng.normal(size=6)
    c = np.where(np.arange(6) % 2 == 0, 1e-6, 1e6)
    solve = jax.jit(unpivoted_solve)
    for a in (g1 @ w @ g0.T, g0 @ w @ g0.T):
        x, ratio = solve(a, b)
        np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10)
        np.testing.assert_allclose(ratio, minors_ratio(a), rtol=1e-10)
        x, _ = solve(c[:, None] * a * c[None, :], c * b)
        np.testing.assert_allclose(c * x, np.linalg.solve(a, b), rtol=1e-10)
    # A joint's three rows given twice: G W G^T is singular.
    repeated = np.concatenate([g0[:3], g0[:3]])
    reduced = jax.jit(lambda a, b: _reduced_solve(a, b, unpivoted_solve))
    for units in (np.ones(6), c):
        g = units[:, None] * repeated
        _, ratio = reduced(g @ w @ g.T, b)
        assert ratio <= singular_threshold(6, jnp.float64), (units, ratio)
    swapped = np.array([[0.0, 1.0], [1.0, 0.0]])
    x, ratio = solve(swapped, np.ones(2))
    assert not np.all(np.isfinite(x)) and ratio == 0
