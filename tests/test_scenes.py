import math

import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from diffrax_vi import scenes
from diffrax_vi.scenes._learned import _trajectories
from diffrax_vi.study import reference_state

from .helpers import max_abs_diff, reference, solve


# Every scene but the learned one (which trains, and is tested on its own below) and
# the Pythagorean three-body problem, whose close encounter at t = 15.8 costs even
# DOP853 at rtol 1e-13 its energy to 4e-8 (tested on its own below).
NAMES = [n for n in scenes.SCENES if n not in ("learned", "pythagorean_three_body")]


def _conserved_along(scene, y):
    return {k: np.asarray(f(0.0, y, None)) for k, f in scene.conserved().items()}


@pytest.mark.parametrize("name", ["falling_particle", "oscillator", "kepler"])
def test_exact_solutions_match_solve_ivp(name):
    scene = scenes.SCENES[name]()
    for t in (0.7 * scene.period, 3.3 * scene.period):
        assert max_abs_diff(scene.exact(t), reference(scene.term(), scene.y0, t)) < 1e-9


@pytest.mark.parametrize(
    "scene", [scenes.pendulum(), scenes.duffing(), scenes.duffing(1.2)]
)
def test_closed_form_periods(scene):
    # After one period (an elliptic integral, by the AGM) the orbit is back at y0;
    # after half a period it is not.
    assert (
        max_abs_diff(reference(scene.term(), scene.y0, scene.period), scene.y0) < 1e-9
    )
    half = reference(scene.term(), scene.y0, scene.period / 2)
    assert max_abs_diff(half, scene.y0) > 0.1


@pytest.mark.parametrize("name", NAMES)
def test_conserved_quantities_are_conserved_by_solve_ivp(name):
    scene = scenes.SCENES[name]()
    y1 = reference(scene.term(), scene.y0, 2.5 * scene.period)
    before, after = _conserved_along(scene, scene.y0), _conserved_along(scene, y1)
    for k in before:
        scale = 1 + np.max(np.abs(before[k]))
        assert np.max(np.abs(after[k] - before[k])) < 1e-10 * scale, k
    # And the state has moved, so this was no empty check.
    assert max_abs_diff(y1, scene.y0) > 1e-3


@pytest.mark.parametrize(
    "name", ["double_pendulum", "henon_heiles", "fpu", "outer_solar_system"]
)
def test_numerical_reference_matches_solve_ivp(name):
    scene = scenes.SCENES[name]()
    t1 = 2 * scene.period
    ours = reference_state(scene, t1)
    theirs = reference(scene.term(), scene.y0, t1)
    scale = max(1.0, max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(theirs)))
    assert max_abs_diff(ours, theirs) < 1e-9 * scale


def test_fpu_initial_data_and_stiff_frequency():
    omega = 1e3
    scene = scenes.fpu(omega)
    q0, p0 = scene.y0
    s = 1 / math.sqrt(2)
    # HLW I.5: x_{0,1} = 1, x_{1,1} = 1/omega, y_{0,1} = y_{1,1} = 1.
    assert np.allclose(s * (q0[1] + q0[0]), 1) and np.allclose(
        s * (q0[1] - q0[0]), 1 / omega
    )
    assert np.allclose(s * (p0[1] + p0[0]), 1) and np.allclose(s * (p0[1] - p0[0]), 1)
    # The stiff springs: Hessian eigenvalues omega^2 (three of them) at q = 0.
    hessian = jax.hessian(lambda q: scene.lagrangian.potential(0.0, q, None))(
        jnp.zeros(6)
    )
    eig = np.sort(np.linalg.eigvalsh(np.asarray(hessian)))
    assert np.allclose(eig[-3:], omega**2) and np.allclose(eig[:3], 0)


def test_solar_system_data():
    scene = scenes.outer_solar_system()
    q0, p0 = scene.y0
    assert q0.shape == p0.shape == (6, 3)
    # Jupiter's period from its initial state (two-body with the Sun): 4332.6 days.
    g = 2.95912208286e-4
    m = scene.lagrangian.mass[:, 0]
    r = float(jnp.linalg.norm(q0[1]))
    v2 = float(jnp.sum((p0[1] / m[1]) ** 2))
    a = 1 / (2 / r - v2 / (g * (m[0] + m[1])))
    period = 2 * np.pi * np.sqrt(a**3 / (g * (m[0] + m[1])))
    assert abs(period - scene.period) / scene.period < 0.01


def test_scene_parameter_errors():
    with pytest.raises(ValueError, match="eccentricity"):
        scenes.kepler(1.0)
    with pytest.raises(ValueError, match="amplitude"):
        scenes.pendulum(4.0)
    with pytest.raises(ValueError, match="q0"):
        scenes.duffing(2.0)
    with pytest.raises(ValueError, match="omega"):
        scenes.fpu(omega=-1.0)


def test_perturbed(getkey):
    scene = scenes.kepler()
    q, p = scene.perturbed(getkey(), 64, spread=1e-2)
    assert q.shape == p.shape == (64, 2)
    assert np.array_equal(q[0], scene.y0[0]) and np.array_equal(p[0], scene.y0[1])
    deviation = np.std(np.asarray(q[1:, 0] - scene.y0[0][0]))
    assert 0.5e-2 < deviation / (1 + 0.4) < 2e-2


def test_perturbed_states_of_a_constrained_scene_keep_its_constraint(getkey):
    """An ensemble of the Cartesian pendulum starts on its circle and its hidden
    constraint (a constrained solve refuses any other start), spread around y0 and
    with y0 itself first."""
    scene = scenes.cartesian_pendulum()
    q, p = scene.perturbed(getkey(), 8, spread=1e-2)
    assert np.max(np.abs(np.sum(np.asarray(q) ** 2, axis=-1) - 1)) < 1e-14
    assert np.max(np.abs(np.sum(np.asarray(q) * np.asarray(p), axis=-1))) < 1e-14
    assert np.allclose(q[0], scene.y0[0], rtol=0, atol=1e-15)
    assert 1e-3 < np.std(np.asarray(q[1:, 0])) < 1e-1


def test_learned_training_data_in_float32():
    """The learned scene's training data (Dopri8 trajectories of the pendulum) are
    computed in JAX's default float32 too: the reference tolerance follows the
    dtype, since an adaptive solve never meets 1e-12 in float32 (it ran out of
    steps, and `scenes.learned()` failed without 64-bit mode)."""
    amplitude = jnp.asarray([2.0], jnp.float32)
    ts = jnp.linspace(0.0, 6.0, 61, dtype=jnp.float32)
    qs = _trajectories(
        scenes.PendulumLagrangian(),
        dfx.Dopri8(),
        (amplitude, jnp.zeros_like(amplitude)),
        ts,
    )
    assert qs.dtype == jnp.float32
    exact = reference(scenes.PendulumLagrangian(), (2.0, 0.0), 6.0)
    # Float32 round-off over 6 time units, not the tolerance of a float64 solve.
    assert abs(float(qs[0, -1]) - float(exact[0])) < 1e-4


def test_fit_potential_lowers_the_misfit_through_the_solver():
    """`fit_potential`, the learned scene's training (BFGS through the differentiated
    MidpointVI solves), on a small network and two pendulum trajectories from scipy:
    within 30 steps the misfit falls at least a thousandfold (about 1e5 on this
    machine). The default suite's one run of the training; the trained scene's
    accuracy is test_learned_lagrangian's (slow)."""
    import scipy.integrate

    amplitudes = jnp.array([0.5, 1.5])
    ts = jnp.linspace(0.0, 3.0, 31)
    qs = jnp.stack(
        [
            scipy.integrate.solve_ivp(
                lambda t, y: [y[1], -np.sin(y[0])],
                (0.0, 3.0),
                [float(a), 0.0],
                t_eval=np.asarray(ts),
                rtol=1e-12,
                atol=1e-12,
            ).y[0]
            for a in amplitudes
        ]
    )
    y0s = (amplitudes, jnp.zeros_like(amplitudes))
    model = scenes.LearnedLagrangian(jr.key(0), width=8, depth=1)
    before = jnp.mean((_trajectories(model, dvi.MidpointVI(), y0s, ts) - qs) ** 2)
    fitted, after = scenes.fit_potential(model, y0s, ts, qs, max_steps=30)
    assert after < 1e-3 * before, (before, after)
    assert isinstance(fitted, scenes.LearnedLagrangian)


@pytest.mark.slow
def test_learned_lagrangian():
    """A small MLP potential trained through MidpointVI reproduces the pendulum on an
    amplitude it never saw, and, being a Lagrangian, keeps its own energy bounded."""
    scene = scenes.learned()
    truth = scenes.pendulum(1.2)
    y0 = truth.y0
    t1 = 2 * truth.period
    learned = solve(scene.lagrangian, dvi.MidpointVI(), y0, t1, 300)
    exact = reference(truth.lagrangian, y0, t1)
    untrained = scenes.LearnedLagrangian(jr.key(0))
    before = solve(untrained, dvi.MidpointVI(), y0, t1, 300)
    error = max_abs_diff(jax.tree.map(lambda x: x[-1], learned.ys), exact)
    assert error < 1e-2 < max_abs_diff(jax.tree.map(lambda x: x[-1], before.ys), exact)
    energy = jax.vmap(lambda q, p: dvi.energy(scene.lagrangian, 0.0, (q, p)))
    long = dfx.diffeqsolve(
        dvi.LagrangianTerm(scene.lagrangian),
        dvi.MidpointVI(),
        0.0,
        100 * truth.period,
        truth.period / 50,
        y0,
        saveat=dfx.SaveAt(steps=True),
        max_steps=5000,
    )
    e = np.asarray(energy(*long.ys))
    e0 = float(dvi.energy(scene.lagrangian, 0.0, y0))
    assert np.max(np.abs(e - e0)) < 1e-3


def test_pythagorean_three_body():
    scene = scenes.pythagorean_three_body()
    assert float(scene.energy(0.0, scene.y0, None)) == pytest.approx(-769 / 60, 1e-15)
    # Through two close encounters a high-accuracy reference keeps every invariant,
    # and reversible adaptive kahan_li8 agrees with it.
    y1 = reference(scene.term(), scene.y0, 10.0)
    before, after = _conserved_along(scene, scene.y0), _conserved_along(scene, y1)
    for k in before:
        assert np.max(np.abs(after[k] - before[k])) < 1e-9, k
    solver = dvi.Composition(dvi.StormerVerlet(), "kahan_li8")
    sol = dfx.diffeqsolve(
        dvi.terms_for(solver, scene.lagrangian),
        solver,
        0.0,
        10.0,
        1e-3,
        scene.y0,
        stepsize_controller=dvi.ReversibleController(scene.monitor),
        max_steps=100_000,
    )
    ours = jax.tree.map(lambda x: x[-1], sol.ys)
    assert max_abs_diff(ours, y1) < 1e-7
    # The closest approach (Szebehely & Peters 1967): 4.1e-4 near t = 15.83.
    q = reference(scene.term(), scene.y0, 15.82992)[0]
    i, j = np.triu_indices(3, 1)
    assert float(jnp.min(jnp.linalg.norm(q[i] - q[j], axis=-1))) < 1e-3


def test_monitored_lists_the_scenes_with_a_monitor():
    # (learned trains, and has none.)
    with_monitor = {n for n in NAMES if scenes.SCENES[n]().monitor is not None}
    with_monitor |= {"pythagorean_three_body"}
    assert set(scenes.MONITORED) == with_monitor
    assert scenes.pythagorean_three_body().monitor is not None
