"""Linear stability on the harmonic oscillator, against characteristic roots derived
by hand (docs/stability.md), and behaviour past the limits."""

import math

import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.numpy as jnp
import numpy as np
import pytest


XS = [0.3, 1.0, 1.9, 2.5, 6.0]  # omega * h


def _verlet(x):
    # Kick-drift-kick on q'' = -q with step x, acting on (q, p).
    return np.array([[1 - x**2 / 2, x], [-x * (1 - x**2 / 4), 1 - x**2 / 2]])


def _prk(a, a_bar, b, x):
    # A partitioned RK method (a for q, a_bar for p) on q' = p, p' = -q, step x:
    # Q = q0 + x A P, P = p0 - x A_bar Q.
    s = len(b)
    one = np.ones(s)
    system = np.block([[np.eye(s), -x * a], [x * a_bar, np.eye(s)]])
    columns = []
    for q0, p0 in ((1.0, 0.0), (0.0, 1.0)):
        stages = np.linalg.solve(system, np.concatenate([q0 * one, p0 * one]))
        big_q, big_p = stages[:s], stages[s:]
        columns.append([q0 + x * b @ big_p, p0 - x * b @ big_q])
    return np.array(columns).T


def _pade(s, z):
    # The diagonal (s, s) Pade approximant of exp: Gauss methods' stability function.
    coefficients = [
        math.factorial(2 * s - j)
        * math.factorial(s)
        / (math.factorial(2 * s) * math.factorial(j) * math.factorial(s - j))
        for j in range(s + 1)
    ]
    numerator = sum(c * z**j for j, c in enumerate(coefficients))
    denominator = sum(c * (-z) ** j for j, c in enumerate(coefficients))
    return numerator / denominator


LOBATTO3 = (
    np.array([[0, 0, 0], [5 / 24, 1 / 3, -1 / 24], [1 / 6, 2 / 3, 1 / 6]]),  # IIIA
    np.array([[1 / 6, -1 / 6, 0], [1 / 6, 1 / 3, 0], [1 / 6, 5 / 6, 0]]),  # IIIB
    np.array([1 / 6, 2 / 3, 1 / 6]),
)
CUBE = 2 ** (1 / 3)
YOSHIDA4 = [1 / (2 - CUBE), -CUBE / (2 - CUBE), 1 / (2 - CUBE)]


def _roots_of(matrix):
    return np.linalg.eigvals(matrix)


def _linearized_roots(velocity, rule, x):
    # DEL of the oscillator: a q_{k-1} + b q_k + a q_{k+1} = 0; linearizing along
    # u_k multiplies its characteristic polynomial by (z - 1) (forward velocities)
    # or (z^2 - 1) (centered): the parasitic roots.
    if rule == "midpoint":
        a, b = -1 / x - x / 4, 2 / x - x / 2
    else:
        a, b = -1 / x, 2 / x - x
    parasitic = [1.0] if velocity == "forward" else [1.0, -1.0]
    return np.concatenate([np.roots([a, b, a]), parasitic])


# name -> (solver, analytic roots as a function of x, analytic stability limit)
CASES = {
    "MidpointVI": (
        dvi.MidpointVI(),
        lambda x: [_pade(1, 1j * x), _pade(1, -1j * x)],
        math.inf,
    ),
    "GaussVPRK(2)": (
        dvi.GaussVPRK(2),
        lambda x: [_pade(2, 1j * x), _pade(2, -1j * x)],
        math.inf,
    ),
    "StormerVerlet": (dvi.StormerVerlet(), lambda x: _roots_of(_verlet(x)), 2.0),
    "TrapezoidalVI": (dvi.TrapezoidalVI(), lambda x: _roots_of(_verlet(x)), 2.0),
    "LobattoVPRK(3)": (
        dvi.LobattoVPRK(3),
        lambda x: _roots_of(_prk(*LOBATTO3, x)),
        2 * math.sqrt(2),
    ),
    "yoshida4": (
        dvi.Composition(dvi.StormerVerlet(), "yoshida4"),
        lambda x: _roots_of(
            _verlet(YOSHIDA4[2] * x)
            @ _verlet(YOSHIDA4[1] * x)
            @ _verlet(YOSHIDA4[0] * x)
        ),
        None,  # the first root of |trace| = 2, found below from the closed form
    ),
    "LinearizedVI(forward)": (
        dvi.LinearizedVI(),
        lambda x: _linearized_roots("forward", "midpoint", x),
        math.inf,
    ),
    "LinearizedVI(centered)": (
        dvi.LinearizedVI(velocity="centered"),
        lambda x: _linearized_roots("centered", "midpoint", x),
        math.inf,
    ),
    "LinearizedVI(centered, trapezoidal)": (
        dvi.LinearizedVI(
            velocity="centered", discrete_lagrangian=dvi.TrapezoidalRule()
        ),
        lambda x: _linearized_roots("centered", "trapezoidal", x),
        2.0,
    ),
}


def _sorted(z):
    z = np.asarray(z, complex)
    return z[np.lexsort((np.round(z.imag, 9), np.round(z.real, 9)))]


@pytest.mark.parametrize("name", CASES)
def test_step_matrix_roots_match_the_characteristic_polynomial(name):
    solver, roots, _ = CASES[name]
    # One compilation for every step size, not an eager trace per step.
    matrices = jax.jit(
        jax.vmap(lambda x: dvi.diagnostics.oscillator_step_matrix(solver, x))
    )
    for x, m in zip(XS, np.asarray(matrices(jnp.asarray(XS)))):
        eig = np.linalg.eigvals(m)
        nonzero = eig[np.abs(eig) > 1e-9]
        assert np.allclose(_sorted(nonzero), _sorted(roots(x)), atol=1e-9), (x, eig)


def _closed_form_limit(roots):
    grid = np.linspace(1e-3, 10, 20000)
    radius = np.array([np.abs(roots(x)).max() for x in grid])
    first = np.argmax(radius > 1 + 1e-6)
    return grid[first - 1] if radius[first] > 1 + 1e-6 else math.inf


@pytest.mark.parametrize("name", CASES)
def test_stability_limit(name):
    solver, roots, limit = CASES[name]
    if limit is None:
        limit = _closed_form_limit(roots)
        assert 1.5 < limit < 1.6  # Yoshida's is famously short: 1.5734
    measured = dvi.diagnostics.stability_limit(solver)
    if math.isinf(limit):
        assert math.isinf(measured)
    else:
        assert measured == pytest.approx(limit, abs=1e-3)


def _oscillator(solver, x, n, **kwargs):
    lagrangian = dvi.SeparableLagrangian(lambda t, q, args: 0.5 * q**2)
    if isinstance(solver.term_structure, tuple):
        terms = dvi.separable_terms(lagrangian)
    else:
        terms = dvi.LagrangianTerm(lagrangian)
    return dfx.diffeqsolve(
        terms,
        solver,
        0.0,
        n * x,
        x,
        (jnp.array(1.0), jnp.array(0.0)),
        max_steps=n,
        throw=False,
        **kwargs,
    )


def test_explicit_past_the_limit_grows_at_the_predicted_rate_then_fails():
    x = 2.5
    rho = np.abs(_roots_of(_verlet(x))).max()  # 3.96
    sol = _oscillator(dvi.StormerVerlet(), x, 60, saveat=dfx.SaveAt(steps=True))
    q = np.abs(np.asarray(sol.ys[0]))
    rate = np.exp(np.polyfit(np.arange(20, 60), np.log(q[20:60]), 1)[0])
    assert rate == pytest.approx(rho, rel=1e-3)
    assert sol.result == dfx.RESULTS.successful  # still finite: 4^60 ~ 1e36
    # Until the values overflow, which is reported; the steps before it are kept.
    steps = int(math.log(np.finfo(np.float64).max) / math.log(rho)) + 20
    sol = _oscillator(dvi.StormerVerlet(), x, steps, saveat=dfx.SaveAt(steps=True))
    assert sol.result == dfx.RESULTS.nonfinite
    kept = np.asarray(sol.ys[0])
    finite = np.isfinite(kept)
    assert finite[:400].all() and np.abs(kept[400]) > 1e200


def test_implicit_far_past_any_limit_is_bounded_with_the_predicted_phase():
    # MidpointVI at omega h = 100: bounded, energy exact, but each step turns the
    # phase by 2 arctan(x / 2), not x.
    x, n = 100.0, 50
    sol = _oscillator(dvi.MidpointVI(), x, n, saveat=dfx.SaveAt(steps=True))
    assert sol.result == dfx.RESULTS.successful
    theta = 2 * math.atan(x / 2)
    k = np.arange(1, n + 1)
    assert np.allclose(sol.ys[0], np.cos(k * theta), atol=1e-10)
    assert np.allclose(sol.ys[0] ** 2 + sol.ys[1] ** 2, 1.0, atol=1e-10)


def test_centered_linearized_parasitic_root_is_marginal_on_the_oscillator():
    # The parasitic root -1 is on the unit circle: started on the DEL manifold the
    # mode is not excited, and 1e4 steps at omega h = 1 keep the energy.
    sol = _oscillator(dvi.LinearizedVI(velocity="centered"), 1.0, 10_000)
    assert sol.result == dfx.RESULTS.successful
    q, p = sol.ys[0][-1], sol.ys[1][-1]
    assert abs(float(q**2 + p**2) - 1) < 1e-9


# --- Tiny steps: the round-off floor ---


def _pendulum_error(solver, n):
    from .helpers import reference

    scene = dvi.scenes.pendulum() if hasattr(dvi, "scenes") else None
    del scene
    from diffrax_vi.scenes import pendulum

    scene = pendulum()
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(scene.lagrangian),
        solver,
        0.0,
        1.0,
        1.0 / n,
        scene.y0,
        max_steps=n,
    )
    exact = reference(scene.lagrangian, scene.y0, 1.0)
    return max(abs(float(sol.ys[i][-1] - exact[i])) for i in (0, 1))


@pytest.mark.slow
def test_linearized_round_off_floor():
    """The linearized method differences positions: its error falls like h^2 down to
    h ~ 1e-4 (pendulum, T = 1), then round-off, amplified like 1/h^2 by the nearly
    triple root at z = 1, takes over. MidpointVI keeps converging past that step."""
    centered = dvi.LinearizedVI(velocity="centered")
    errors = {n: _pendulum_error(centered, n) for n in (100, 1_000, 10_000, 100_000)}
    assert 80 < errors[100] / errors[1_000] < 120  # second order
    assert errors[100_000] > 10 * errors[10_000]  # past the floor, worse
    midpoint = {n: _pendulum_error(dvi.MidpointVI(), n) for n in (10_000, 100_000)}
    assert 80 < midpoint[10_000] / midpoint[100_000] < 120
    assert midpoint[100_000] < 1e-2 * errors[100_000]


# --- Long horizons ---


def _energy_deciles(scene, solver, periods, steps_per_period, saves=1000):
    from diffrax_vi.study import drift

    run = drift(
        scene,
        [solver],
        periods=periods,
        steps_per_period=steps_per_period,
        n_save=saves,
    ).runs[0]
    assert run.result == "successful"
    err = run.errors["energy"][1:]
    k = len(err) // 10
    return err[:k].max(), err[-k:].max()


@pytest.mark.parametrize(
    "solver",
    [dvi.StormerVerlet(), dvi.MidpointVI()],
    ids=["StormerVerlet", "MidpointVI"],
)
def test_a_million_steps_keep_the_energy_bounded(solver):
    from diffrax_vi.scenes import kepler

    first, last = _energy_deciles(kepler(), solver, 5_000, 200)  # 10^6 steps
    assert last < 1.05 * first < 5e-3


# --- float32 end to end ---


F32_SOLVERS = {
    "MidpointVI": dvi.MidpointVI(),
    "TrapezoidalVI": dvi.TrapezoidalVI(),
    "StormerVerlet": dvi.StormerVerlet(),
    "GaussVPRK(2)": dvi.GaussVPRK(2),
    "LobattoVPRK(3)": dvi.LobattoVPRK(3),
    "yoshida4": dvi.Composition(dvi.StormerVerlet(), "yoshida4"),
    "LinearizedVI": dvi.LinearizedVI(velocity="centered"),
}


@pytest.mark.parametrize("name", F32_SOLVERS)
def test_float32_end_to_end(name):
    from diffrax_vi.scenes import pendulum
    from diffrax_vi.study import drift

    solver = F32_SOLVERS[name]
    # Every step saved: a coarser sampling aliases with the period.
    kwargs = dict(periods=200, steps_per_period=50, n_save=10_000)
    study = drift(pendulum(), [solver], dtype=jnp.float32, **kwargs)
    run = study.runs[0]
    assert study.dtype == "float32" and run.result == "successful"
    err = run.errors["energy"][1:]
    # Bounded at float32 accuracy: the float64 run's truncation error plus float32
    # round-off, with no drift over 10^4 steps.
    err64 = drift(pendulum(), [solver], **kwargs).runs[0].errors["energy"][1:]
    # The linearized method amplifies round-off (see the floor test below): in
    # float32 its energy error is 7% above float64's here; the others agree to 1e-4.
    slack = 0.1 * err64.max() if isinstance(solver, dvi.LinearizedVI) else 1e-4
    assert abs(err.max() - err64.max()) < slack
    k = len(err) // 10
    assert err[-k:].max() < 1.5 * err[:k].max() + 1e-5
    # And the state stays float32 through a raw solve, solver state included.
    scene = pendulum()
    y0 = jax.tree.map(lambda x: x.astype(jnp.float32), scene.y0)
    terms = (
        dvi.separable_terms(scene.lagrangian)
        if isinstance(solver.term_structure, tuple)
        else dvi.LagrangianTerm(scene.lagrangian)
    )
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    sol = dfx.diffeqsolve(
        terms,
        solver,
        f32(0),
        f32(1),
        f32(0.1),
        y0,
        saveat=dfx.SaveAt(t1=True, solver_state=True),
    )
    floats = [
        x
        for x in jax.tree.leaves((sol.ys, sol.solver_state))
        if jnp.issubdtype(x.dtype, jnp.floating)
    ]
    assert floats and all(x.dtype == jnp.float32 for x in floats)


# --- Stiff: FPU with omega = 1000 ---


def _fpu_run(solver, omega_h, periods):
    from diffrax_vi.scenes import fpu
    from diffrax_vi.study import drift

    # The scene's period is the stiff one, 2 pi / omega.
    spp = int(round(2 * math.pi / omega_h))
    scene = fpu(omega=1000.0)
    run = drift(scene, [solver], periods=periods, steps_per_period=spp, n_save=periods)
    return run.runs[0], 2 * math.pi / spp


def test_stiff_fpu():
    """omega = 1000, stiff energy 1. Resolving the stiff springs (omega h ~ 0.5),
    StormerVerlet's energy error is that of its modified energy on the stiff
    oscillator, (omega h)^2 / 8, and MidpointVI, exact on quadratic energies, does
    better. Not resolving them (omega h = 2 pi, past StormerVerlet's limit 2),
    StormerVerlet blows up and says so, while MidpointVI, stable for every step,
    still keeps the energy bounded."""
    run, x = _fpu_run(dvi.StormerVerlet(), 0.5, 200)  # 2600 steps
    assert run.result == "successful"
    assert 0.5 * x**2 / 8 < run.max_error("energy") < 1.5 * x**2 / 8
    run, _ = _fpu_run(dvi.MidpointVI(), 0.5, 200)
    assert run.result == "successful" and run.max_error("energy") < 1e-3
    blown, _ = _fpu_run(dvi.StormerVerlet(), 2 * math.pi, 2000)
    assert blown.result != "successful"
    implicit, _ = _fpu_run(dvi.MidpointVI(), 2 * math.pi, 2000)
    assert implicit.result == "successful" and implicit.max_error("energy") < 5e-2


# --- Chaotic: the double pendulum ---


def test_double_pendulum_diverges_but_keeps_its_energy():
    from diffrax_vi.scenes import double_pendulum

    scene = double_pendulum()
    members = scene.perturbed(jax.random.key(0), 4, spread=1e-9)
    term = dvi.LagrangianTerm(scene.lagrangian)
    energy = jax.vmap(lambda q, p: dvi.energy(scene.lagrangian, 0.0, (q, p)))

    @jax.vmap
    def solve(y0):
        return dfx.diffeqsolve(
            term,
            dvi.MidpointVI(),
            0.0,
            200.0,
            0.02,
            y0,
            saveat=dfx.SaveAt(steps=True),
            max_steps=10_000,
        ).ys

    q, p = solve(members)
    separation = np.abs(np.asarray(q[1:, -1]) - np.asarray(q[0, -1])[None]).max()
    assert separation > 1e-2  # chaotic: 1e-9 grew past 1e-2
    e = np.stack([np.asarray(energy(q[i], p[i])) for i in range(4)])
    drift = np.abs(e - e[:, :1])
    half = drift.shape[1] // 2
    assert drift.max() < 5e-3
    assert drift[:, half:].max() < 2 * drift[:, :half].max()


def test_the_study_flags_blow_ups_that_solvers_report_as_success():
    """Past its limit (omega h = 2.5 > 2) StormerVerlet's values grow like 3.96^n but
    stay finite for 500 steps, and the solve is successful: the study's growth column
    shows it. Tsit5 past its limit overflows to NaN without diffrax noticing (fixed
    steps are not checked); the study reports it as non-finite."""
    from diffrax_vi.scenes import oscillator
    from diffrax_vi.study import drift

    study = drift(
        oscillator(),
        ["StormerVerlet", "MidpointVI"],
        periods=20,
        steps_per_period=3,
        n_save=20,  # omega h = 2.09
    )
    unstable, implicit = study.runs
    assert unstable.result == "successful" and unstable.growth() > 1e6
    assert implicit.result == "successful" and implicit.max_error("energy") < 1e-13
    stable = drift(
        oscillator(), ["StormerVerlet"], periods=20, steps_per_period=20, n_save=400
    )
    assert stable.runs[0].growth() < 1.5
    rk = drift(oscillator(), ["Tsit5"], periods=1000, steps_per_period=2, n_save=20)
    assert rk.runs[0].result.startswith("Nonfinite")
