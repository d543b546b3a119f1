"""Every solver fails loudly: a ValueError at trace time, or a non-successful RESULTS
at run time that keeps the steps before the failure."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

from .helpers import ALL_SOLVERS, Pendulum


IMPLICIT = [
    (n, s)
    for n, s in ALL_SOLVERS
    if n in ("MidpointVI", "GaussVPRK(2)", "LobattoVPRK(3)", "yoshida4(MidpointVI)")
]


def _solve(lagrangian, solver, y0, t1=1.0, dt=0.1, **kwargs):
    return dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian), solver, 0.0, t1, dt, y0, **kwargs
    )


@pytest.mark.parametrize("name,solver", ALL_SOLVERS)
def test_non_finite_initial_condition(name, solver):
    for y0 in (
        (jnp.array(jnp.nan), jnp.array(0.0)),
        (jnp.array(1.0), jnp.array(jnp.inf)),
    ):
        sol = _solve(Pendulum(), solver, y0, throw=False)
        assert sol.result == dfx.RESULTS.nonfinite, name
        with pytest.raises(eqx.EquinoxRuntimeError, match="Nonfinite"):
            _solve(Pendulum(), solver, y0)


@pytest.mark.parametrize("name,solver", ALL_SOLVERS)
def test_non_finite_parameter(name, solver):
    sol = _solve(
        Pendulum(g=jnp.array(jnp.nan)),
        solver,
        (jnp.array(1.0), jnp.array(0.0)),
        throw=False,
    )
    assert sol.result != dfx.RESULTS.successful


@pytest.mark.parametrize("name,solver", ALL_SOLVERS)
def test_structural_misuse_is_a_value_error(name, solver):
    # Partitioned solvers take any pair of terms, as diffrax.SemiImplicitEuler does,
    # so only solvers of a LagrangianTerm know that q and p must match.
    if not isinstance(solver.term_structure, tuple):
        with pytest.raises(ValueError, match="same PyTree structure|pair"):
            _solve(Pendulum(), solver, (jnp.ones(2), (jnp.ones(2),)))
        with pytest.raises(ValueError, match="matching shapes"):
            _solve(Pendulum(), solver, (jnp.ones(2), jnp.ones(3)))
    with pytest.raises(ValueError, match="scalar"):
        _solve(
            dvi.SeparableLagrangian(lambda t, q, args: 0.5 * q**2),
            solver,
            (jnp.ones(2), jnp.ones(2)),
        )
    wrong = dfx.ODETerm(lambda t, y, args: y)
    with pytest.raises(ValueError):
        dfx.diffeqsolve(wrong, solver, 0.0, 1.0, 0.1, (jnp.ones(()), jnp.ones(())))


# When V = -q^4 from rest at q = 1 blows up: the integral of dq / sqrt(2 (q^4 - 1))
# from 1 to infinity, K(1/sqrt 2) / 2 with K the complete elliptic integral of the
# first kind.
BLOW_UP = 0.9270373386


@pytest.mark.parametrize("name,solver", IMPLICIT)
def test_newton_failure_keeps_the_steps_before_it(name, solver):
    """V = -q^4 from rest at q = 1 blows up at t = 0.927 (`BLOW_UP`): at a fixed
    step the implicit equation soon has no root that continues the motion. The
    failure is reported, the steps before it are kept and are states of the motion,
    and the failed step's output is NaN, never the unconverged Newton iterate, nor a
    root beyond the blow-up, dressed up as a state."""
    blowup = dvi.SeparableLagrangian(lambda t, q, args: -(q**4))
    y0 = (jnp.array(1.0), jnp.array(0.0))
    sol = _solve(
        blowup, solver, y0, t1=3.0, dt=0.1, throw=False, saveat=dfx.SaveAt(steps=True)
    )
    # Newton runs out of iterations, its residual overflows (a divergence), or its
    # root lies across the fold (a divergence too).
    assert sol.result in (
        dfx.RESULTS.nonlinear_max_steps_reached,
        dfx.RESULTS.nonlinear_divergence,
    )
    done = int(sol.stats["num_accepted_steps"])
    q = np.asarray(sol.ys[0])
    # diffrax saves the failing step too: it must not look like a state.
    assert 5 <= done < 15 and np.isfinite(q[: done - 1]).all()
    assert np.isnan(q[done - 1])
    # Near the start the motion is q = 1 + 2 t^2 + O(t^4).
    assert abs(q[0] - 1.02) < 1e-3
    # Every state kept is one of the motion, none past its blow-up, each within 10%
    # of scipy's (DOP853 at rtol 1e-12; the states near the blow-up are the methods'
    # least accurate: yoshida4(MidpointVI) 4% at t = 0.7). LobattoVPRK(3) once
    # reported q = -1235, p = -1.3e8 at t = 1.0 (an energy of 8e15), and went on.
    kept_t = np.asarray(sol.ts[: done - 1])
    assert kept_t[-1] < BLOW_UP, kept_t
    exact = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], 4 * y[0] ** 3],
        (0.0, kept_t[-1]),
        [1.0, 0.0],
        method="DOP853",
        t_eval=kept_t,
        rtol=1e-12,
        atol=1e-12,
    ).y[0]
    np.testing.assert_allclose(q[: done - 1], exact, rtol=0.1)
    with pytest.raises(eqx.EquinoxRuntimeError, match="(?i)nonlinear solve"):
        _solve(blowup, solver, y0, t1=3.0, dt=0.1)


@pytest.mark.parametrize(
    "name,solver", IMPLICIT + [("TrapezoidalVI", dvi.TrapezoidalVI())]
)
def test_degenerate_lagrangian_is_singular(name, solver):
    degenerate = dvi.Lagrangian(
        lambda t, q, v, args: 0.5 * jnp.sum(v) ** 2 - jnp.sum(q**4)
    )
    y0 = (jnp.array([0.1, 0.2]), jnp.array([1.0, 1.0]))
    sol = _solve(degenerate, solver, y0, throw=False)
    assert sol.result == dfx.RESULTS.singular


def test_linearized_on_a_degenerate_lagrangian_is_singular():
    # The starting history is built by backward variational steps, whose Newton
    # iteration cannot invert a singular d2L/dv2: reported, not linearized about.
    degenerate = dvi.Lagrangian(
        lambda t, q, v, args: 0.5 * jnp.sum(v) ** 2 - jnp.sum(q**4)
    )
    y0 = (jnp.array([0.1, 0.2]), jnp.array([1.0, 1.0]))
    sol = _solve(degenerate, dvi.LinearizedVI(), y0, throw=False)
    assert sol.result == dfx.RESULTS.singular


def test_linearized_divergence_is_reported_not_silent():
    """The linearized methods have no Newton iteration to fail: past a finite-time
    blow-up (V = -q^4 from rest at q = 1, singular at t ~ 1.31) the unguarded method
    returns finite garbage as success. The DEL-residual guard fails the solve instead,
    keeping the steps before it."""
    blowup = dvi.SeparableLagrangian(lambda t, q, args: -(q**4))
    y0 = (jnp.array(1.0), jnp.array(0.0))
    kwargs = dict(t1=3.0, dt=0.1, throw=False, saveat=dfx.SaveAt(steps=True))
    unguarded = _solve(blowup, dvi.LinearizedVI(max_del_residual=None), y0, **kwargs)
    assert unguarded.result == dfx.RESULTS.successful  # the silent failure
    assert int(unguarded.stats["num_accepted_steps"]) == 30
    assert np.isfinite(np.asarray(unguarded.ys[0])[:30]).all()
    guarded = _solve(blowup, dvi.LinearizedVI(), y0, **kwargs)
    assert guarded.result == dfx.RESULTS.nonlinear_divergence
    done = int(guarded.stats["num_accepted_steps"])
    q = np.asarray(guarded.ys[0])
    # diffrax saves the failing step too: it must not look like a state.
    assert 5 <= done < 15 and np.isfinite(q[: done - 1]).all()
    assert np.isnan(q[done - 1])
    assert np.allclose(q[: done - 1], np.asarray(unguarded.ys[0])[: done - 1])


def test_centered_linearized_on_kepler_fails_instead_of_exploding():
    from diffrax_vi.scenes import kepler
    from diffrax_vi.study import drift

    study = drift(
        kepler(),
        [
            dvi.LinearizedVI(velocity="centered", max_del_residual=None),
            dvi.LinearizedVI(velocity="centered"),
        ],
        periods=20,
        steps_per_period=200,
        n_save=20,
    )
    silent, guarded = study.runs
    assert silent.result == "successful" and silent.max_error("energy") > 1e3
    assert guarded.result == "Nonlinear solve diverged."
    assert guarded.steps < 1000


@pytest.mark.parametrize(
    "name, spp", [("duffing", 8), ("pendulum", 12), ("henon_heiles", 12)]
)
def test_healthy_linearized_runs_pass_the_guard(name, spp):
    from diffrax_vi.scenes import SCENES
    from diffrax_vi.study import drift

    linearized, midpoint = drift(
        SCENES[name](),
        [dvi.LinearizedVI(velocity="centered"), dvi.MidpointVI()],
        periods=50,
        steps_per_period=spp,
        n_save=10,
    ).runs
    assert linearized.result == "successful" and linearized.growth() < 1.5
    # Second order like the midpoint VI it linearizes, with a larger constant
    # (measured 3.5x, 3.4x and 4.7x at these coarse steps).
    ratio = linearized.max_error("energy") / midpoint.max_error("energy")
    assert 1 < ratio < 6
