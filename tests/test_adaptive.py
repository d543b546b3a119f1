"""Reversible adaptive steps (`ReversibleController`): reversibility, order, equality
with fixed steps, bounded energy, exact momentum maps and output times, jit/vmap/grad,
errors. References: Kepler's exact solution and its conserved quantities."""

import math

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from diffrax_vi import scenes

from .helpers import fitted_order


KEPLER = scenes.kepler(0.9)
TERMS = dvi.terms_for(dvi.StormerVerlet(), KEPLER.lagrangian)
MONITOR = dvi.PotentialMonitor(KEPLER.lagrangian)
TWO_PI = 2 * math.pi


def solve(
    t1,
    dt0,
    y0=KEPLER.y0,
    solver=dvi.StormerVerlet(),
    controller=None,
    terms=TERMS,
    t0=0.0,
    **kwargs,
):
    controller = dvi.ReversibleController(MONITOR) if controller is None else controller
    kwargs.setdefault("max_steps", 200_000)
    return dfx.diffeqsolve(
        terms, solver, t0, t1, dt0, y0, stepsize_controller=controller, **kwargs
    )


def last(sol):
    return jax.tree.map(lambda x: x[-1], sol.ys)


def test_forward_then_backward_returns_to_the_start():
    # Stop on a node: the times of the first run's steps.
    # (dt0 is the step at pericentre, where the motion is fastest: 281 steps per
    # orbit at e = 0.9.)
    steps = solve(TWO_PI, 0.001, saveat=dfx.SaveAt(steps=True))
    t_node = float(steps.ts[249])
    forward = solve(t_node, 0.001, saveat=dfx.SaveAt(t1=True, controller_state=True))
    assert forward.stats["num_steps"] == 250
    # 250 steps from pericentre past apocentre: the steps grew 50-fold.
    assert float(jnp.max(jnp.diff(steps.ts[:250]))) > 50 * float(steps.ts[0])
    back = solve(
        0.0,
        -0.001,
        y0=last(forward),
        t0=t_node,
        controller=dvi.ReversibleController(
            MONITOR, density=forward.controller_state.density
        ),
    )
    assert back.stats["num_steps"] == 250
    # Round-off: 250 steps of 1e-16 relative error, sheared by the pericentre
    # passage.
    for start, end in zip(KEPLER.y0, last(back)):
        np.testing.assert_allclose(end, start, rtol=0, atol=1e-12)
    # Without the final density (restarted at density 1 from the end) the return
    # misses by the method's error.
    fresh = solve(0.0, -0.001, y0=last(forward), t0=t_node)
    assert float(jnp.max(jnp.abs(last(fresh)[0] - KEPLER.y0[0]))) > 1e-6


@pytest.mark.parametrize(
    "solver, order, dt0",
    [
        (dvi.StormerVerlet(), 2, 1e-3),
        (dvi.Composition(dvi.StormerVerlet(), "yoshida4"), 4, 2e-3),
    ],
    ids=["StormerVerlet", "yoshida4"],
)
def test_order_in_the_fictive_step(solver, order, dt0):
    # 280 to 2200 steps per orbit (Stormer-Verlet), 135 to 1060 (yoshida4).
    dt0s = [dt0 / 2**k for k in range(4)]
    q_exact, _ = KEPLER.exact(TWO_PI)
    errors = [
        float(jnp.max(jnp.abs(last(solve(TWO_PI, h, solver=solver))[0] - q_exact)))
        for h in dt0s
    ]
    assert abs(fitted_order(dt0s, errors) - order) < 0.25
    # Adaptivity pays: at the same number of steps a fixed step is far worse.
    n = int(solve(TWO_PI, dt0s[-1], solver=solver).stats["num_steps"])
    fixed = solve(TWO_PI, TWO_PI / n, solver=solver, controller=dfx.ConstantStepSize())
    assert float(jnp.max(jnp.abs(last(fixed)[0] - q_exact))) > 30 * errors[-1]


def test_constant_monitor_takes_the_fixed_steps():
    n, dt0 = 300, TWO_PI / 300
    constant = dvi.ReversibleController(lambda t, y, args: jnp.array(2.5))
    adaptive = solve(TWO_PI, dt0, controller=constant, saveat=dfx.SaveAt(steps=True))
    fixed = solve(
        TWO_PI, dt0, controller=dfx.ConstantStepSize(), saveat=dfx.SaveAt(steps=True)
    )
    assert adaptive.stats["num_steps"] == fixed.stats["num_steps"] == n
    np.testing.assert_allclose(adaptive.ts[:n], fixed.ts[:n], rtol=1e-14, atol=0)
    for a, b in zip(adaptive.ys, fixed.ys):
        np.testing.assert_allclose(a[:n], b[:n], rtol=0, atol=1e-11)


def test_energy_bounded_over_a_hundred_thousand_steps():
    # e = 0.9, Stormer-Verlet about 180 steps per orbit: 600 orbits, 1e5 steps.
    sol = solve(600 * TWO_PI, 0.0015, saveat=dfx.SaveAt(steps=True))
    n = int(sol.stats["num_steps"])
    assert n >= 100_000
    ys = jax.tree.map(lambda x: x[:n], sol.ys)
    error = np.abs(
        np.asarray(jax.vmap(KEPLER.energy, (0, 0, None))(sol.ts[:n], ys, None)) + 0.5
    )
    first, final = error[: n // 10].max(), error[-n // 10 :].max()
    assert first < 1e-2
    # No drift: the last tenth's worst error is the first tenth's, within 1%.
    assert final < 1.01 * first
    # A fixed step with the same number of steps drifts off: 100x worse.
    fixed = solve(600 * TWO_PI, 600 * TWO_PI / n, controller=dfx.ConstantStepSize())
    assert abs(float(KEPLER.energy(0.0, last(fixed), None)) + 0.5) > 100 * first


def test_angular_momentum_to_round_off():
    solver = dvi.Composition(dvi.StormerVerlet(), "kahan_li8")
    sol = solve(10 * TWO_PI, 0.003, solver=solver, saveat=dfx.SaveAt(ts=[10 * TWO_PI]))
    momentum = scenes.kepler(0.9).invariants["angular_momentum"]
    drift = abs(float(momentum(0.0, last(sol), None) - momentum(0.0, KEPLER.y0, None)))
    assert drift < 50 * np.finfo(float).eps
    # And the energy (kahan_li8, order 8) to 1e-12 over 10 orbits at e = 0.9.
    assert abs(float(KEPLER.energy(0.0, last(sol), None)) + 0.5) < 1e-12


def test_output_at_physical_times():
    ts = jnp.linspace(0.0, TWO_PI, 13)
    solver = dvi.Composition(dvi.StormerVerlet(), "kahan_li8")
    sol = solve(TWO_PI, 0.001, solver=solver, saveat=dfx.SaveAt(ts=ts))
    np.testing.assert_array_equal(sol.ts, ts)
    q_exact, _ = jax.vmap(KEPLER.exact)(ts)
    # Cubic Hermite between steps of an eighth-order method (1.3e-8 measured).
    np.testing.assert_allclose(sol.ys[0], q_exact, rtol=0, atol=1e-7)
    dense = solve(TWO_PI, 0.001, solver=solver, saveat=dfx.SaveAt(dense=True))
    np.testing.assert_allclose(
        jax.vmap(dense.evaluate)(ts)[0], sol.ys[0], rtol=0, atol=1e-12
    )


@pytest.mark.parametrize("backward", [False, True])
def test_landing_on_output_times(backward):
    # Interpolated between steps, the output has the cubic interpolant's error;
    # with `step_ts` the steps land on the output times, and the saved states are the
    # method's own (kahan_li8, Kepler e = 0.9, 10 orbits).
    solver = dvi.Composition(dvi.StormerVerlet(), "kahan_li8")
    ts = jnp.linspace(0.0, 10 * TWO_PI, 41)
    t0, t1, y0, dt0 = 0.0, 10 * TWO_PI, KEPLER.y0, 0.002
    if backward:
        ts, t0, t1, dt0 = ts[::-1], t1, t0, -dt0
        y0 = KEPLER.exact(10 * TWO_PI)

    def energy_error(controller):
        sol = solve(
            t1,
            dt0,
            y0=y0,
            t0=t0,
            solver=solver,
            controller=controller,
            saveat=dfx.SaveAt(ts=ts),
        )
        np.testing.assert_array_equal(sol.ts, ts)
        energies = jax.vmap(KEPLER.energy, (0, 0, None))(sol.ts, sol.ys, None)
        return float(jnp.max(jnp.abs(energies + 0.5)))

    interpolated = energy_error(dvi.ReversibleController(MONITOR))
    landed = energy_error(dvi.ReversibleController(MONITOR, step_ts=ts))
    assert interpolated > 1e-7
    assert landed < 1e-11


def test_jit_vmap_grad():
    @eqx.filter_jit
    def final_q(p0y):
        y0 = (KEPLER.y0[0], KEPLER.y0[1].at[1].set(p0y))
        return last(solve(1.0, 0.01, y0=y0))[0]

    p = jnp.array([4.3, 4.35, 4.4])
    batched = jax.vmap(final_q)(p)
    for i in range(3):
        np.testing.assert_allclose(batched[i], final_q(p[i]), rtol=1e-13)
    # Reverse mode through the adaptive steps (their sizes depend on y0 too)
    # against central differences.
    grad = jax.grad(lambda p: final_q(p)[0])(p[0])
    step = 1e-6
    fd = (final_q(p[0] + step)[0] - final_q(p[0] - step)[0]) / (2 * step)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


@pytest.mark.parametrize(
    "monitor",
    [
        lambda t, y, args: jnp.sum(y[0] ** 2) - 0.5,  # vanishes on the way
        lambda t, y, args: jnp.where(t > 1.0, jnp.nan, 1.0),
        lambda t, y, args: -jnp.sum(y[0] ** 2),  # negative from the start
    ],
    ids=["vanishes", "nan", "negative"],
)
def test_a_bad_monitor_fails_the_solve(monitor):
    controller = dvi.ReversibleController(monitor)
    sol = solve(TWO_PI, 0.01, controller=controller, throw=False)
    assert sol.result == dfx.RESULTS.nonfinite
    assert float(sol.ts[-1]) < TWO_PI


def test_a_too_large_first_step_fails_the_solve():
    # Just after pericentre the density falls at the rate G = -1.5 (dr/dt) / r = -19;
    # with dt0 = 0.2, half a step of that takes it below zero.
    y0 = KEPLER.exact(0.02)
    controller = dvi.ReversibleController(MONITOR).wrap(1)
    func = dvi.StormerVerlet().func
    _, state = controller.init(TERMS, 0.0, 1.0, y0, 0.2, None, func, 2)
    assert not state.ok
    sol = solve(TWO_PI, 0.2, y0=y0, throw=False)
    assert sol.result == dfx.RESULTS.nonfinite
    assert sol.stats["num_steps"] == 1


def test_trace_time_errors():
    with pytest.raises(ValueError, match="needs `dt0`"):
        solve(1.0, None)
    vector = dvi.ReversibleController(lambda t, y, args: y[0])
    with pytest.raises(ValueError, match="must return a scalar"):
        solve(1.0, 0.01, controller=vector)


def test_potential_monitor_of_a_general_lagrangian():
    general = dvi.Lagrangian(KEPLER.lagrangian.__call__)
    separable = MONITOR(0.0, KEPLER.y0, None)
    assert float(separable) == pytest.approx(0.1**1.5, rel=1e-14)
    assert float(dvi.PotentialMonitor(general)(0.0, KEPLER.y0, None)) == pytest.approx(
        float(separable), rel=1e-14
    )


@pytest.mark.parametrize(
    "solver", [dvi.MidpointVI(), dvi.GaussVPRK(2)], ids=["MidpointVI", "GaussVPRK2"]
)
def test_implicit_solvers_adapt_too(solver):
    # On the LagrangianTerm, Newton's method in each step: 20 orbits at e = 0.9, the
    # energy error the same in the first and last tenth, momentum to round-off.
    sol = solve(
        20 * TWO_PI,
        0.001,
        solver=solver,
        terms=dvi.LagrangianTerm(KEPLER.lagrangian),
        saveat=dfx.SaveAt(steps=True),
    )
    n = int(sol.stats["num_steps"])
    ys = jax.tree.map(lambda x: x[:n], sol.ys)
    error = jnp.abs(jax.vmap(KEPLER.energy, (0, 0, None))(sol.ts[:n], ys, None) + 0.5)
    first, final = float(error[: n // 10].max()), float(error[-n // 10 :].max())
    assert first < 3e-3 and final < 1.001 * first
    momentum = KEPLER.invariants["angular_momentum"]
    along = jax.vmap(momentum, (0, 0, None))(sol.ts[:n], ys, None)
    drift = jnp.abs(along - momentum(0.0, KEPLER.y0, None))
    assert float(drift.max()) < 1e-14
