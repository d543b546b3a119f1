"""Higher-order variational integrators: VPRK tableaus, compositions, compensated
summation."""

import dataclasses

import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.extend.core as jex
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from diffrax_vi._solver.composition import named_scheme
from diffrax_vi._solver.vprk import gauss_tableau, lobatto_tableau

from .helpers import (
    DoublePendulum,
    final_state,
    fitted_order,
    KEPLER,
    kepler_state,
    max_abs_diff,
    Pendulum,
    reference,
)


# (solver, claimed order, step counts for the pendulum and for Kepler): in the
# asymptotic range, with every error above the round-off floor.
METHODS = [
    (dvi.GaussVPRK(2), 4, [20, 40, 80, 160], [40, 80, 160, 320]),
    (dvi.GaussVPRK(3), 6, [15, 22, 30, 45], [30, 45, 60, 90]),
    (dvi.LobattoVPRK(3), 4, [20, 40, 80, 160], [40, 80, 160, 320]),
    (dvi.LobattoVPRK(4), 6, [15, 22, 30, 45], [60, 90, 120, 180]),
    (
        dvi.Composition(dvi.StormerVerlet(), "yoshida4"),
        4,
        [40, 80, 160, 320],
        [80, 160, 320, 640],
    ),
    (
        dvi.Composition(dvi.StormerVerlet(), "suzuki4"),
        4,
        [40, 80, 160, 320],
        [80, 160, 320, 640],
    ),
    (
        dvi.Composition(dvi.StormerVerlet(), "kahan_li6"),
        6,
        [10, 20, 40, 80],
        [40, 80, 160, 320],
    ),
    (
        dvi.Composition(dvi.StormerVerlet(), "kahan_li8"),
        8,
        [8, 10, 14, 20],
        [40, 56, 80, 112],
    ),
    (
        dvi.Composition(dvi.MidpointVI(), "yoshida4"),
        4,
        [40, 80, 160, 320],
        [80, 160, 320, 640],
    ),
]
IDS = [
    "gauss2",
    "gauss3",
    "lobatto3",
    "lobatto4",
    "yoshida4",
    "suzuki4",
    "kahan_li6",
    "kahan_li8",
    "midpoint-yoshida4",
]


@pytest.mark.parametrize("solver,order,ns_pendulum,ns_kepler", METHODS, ids=IDS)
@pytest.mark.parametrize("problem", ["pendulum", "kepler"])
def test_order(solver, order, ns_pendulum, ns_kepler, problem):
    if problem == "pendulum":
        lagrangian, y0, t1 = Pendulum(), (jnp.array(1.5), jnp.array(0.0)), 4.0
        ns = ns_pendulum
    else:
        lagrangian, y0, t1, ns = KEPLER, kepler_state(), 2 * np.pi, ns_kepler
    exact = reference(lagrangian, y0, t1)
    errors = [
        max_abs_diff(final_state(lagrangian, solver, y0, t1, jnp.array(t1 / n)), exact)
        for n in ns
    ]
    assert min(errors) > 1e-12, errors  # the fit is above the round-off floor
    assert abs(fitted_order([t1 / n for n in ns], errors) - order) < 0.3, errors


def test_gauss1_is_midpoint_and_lobatto2_is_stormer_verlet():
    y0 = (jnp.array(1.2), jnp.array(0.3))
    a = final_state(Pendulum(), dvi.GaussVPRK(1), y0, 3.0, jnp.array(0.05))
    b = final_state(Pendulum(), dvi.MidpointVI(), y0, 3.0, jnp.array(0.05))
    assert max_abs_diff(a, b) < 1e-15
    c = final_state(Pendulum(), dvi.LobattoVPRK(2), y0, 3.0, jnp.array(0.05))
    d = final_state(Pendulum(), dvi.StormerVerlet(), y0, 3.0, jnp.array(0.05))
    assert max_abs_diff(c, d) < 1e-14


@pytest.mark.parametrize("s", [1, 2, 3, 4, 5])
def test_tableaus_are_valid_and_exact(s):
    # Built tableaus pass validation; Gauss integrates polynomials of degree 2s - 1
    # exactly, Lobatto of degree 2s - 3.
    gauss = gauss_tableau(s)
    assert all(
        np.isclose(gauss.b @ gauss.c**k, 1 / (k + 1), atol=1e-14) for k in range(2 * s)
    )
    if s >= 2:
        lob = lobatto_tableau(s)
        assert lob.c[0] == 0 and np.isclose(lob.c[-1], 1)
        assert all(
            np.isclose(lob.b @ lob.c**k, 1 / (k + 1), atol=1e-14)
            for k in range(2 * s - 2)
        )
        # IIIA is explicit in its first stage, IIIB in its last column.
        assert np.allclose(lob.a[0], 0) and np.allclose(lob.a_bar[:, -1], 0)


def test_non_symplectic_tableau_is_rejected():
    good = gauss_tableau(2)
    with pytest.raises(ValueError, match="not symplectic"):
        dataclasses.replace(good, a_bar=good.a_bar + 0.01)
    with pytest.raises(ValueError, match="row sums"):
        dataclasses.replace(good, c=good.c + 0.01)
    with pytest.raises(ValueError, match="stages"):
        dvi.GaussVPRK(0)


# The fixed schemes for a second-order base ("triple_jump" and "suzuki_fractal" are
# "yoshida4" and "suzuki4" there).
SCHEMES = ["yoshida4", "suzuki4", "kahan_li6", "kahan_li8"]


@pytest.mark.parametrize("scheme", SCHEMES)
def test_composition_order_conditions(scheme):
    # For a symmetric second-order base, a symmetric composition of order p needs
    # sum g = 1 and sum g^k = 0 for odd 3 <= k < p (Hairer-Lubich-Wanner V.3); the
    # fitted orders above check the remaining conditions.
    gammas, order = named_scheme(scheme, 2).coefficients, named_scheme(scheme, 2).order
    assert np.allclose(gammas, gammas[::-1])
    assert np.isclose(gammas.sum(), 1, atol=1e-15)
    for k in range(3, order, 2):
        assert abs(np.sum(gammas**k)) < 1e-14, (k, np.sum(gammas**k))
    # The next odd power does not vanish: the order is not higher by accident.
    assert abs(np.sum(gammas ** (order + 1))) > 1e-6


def test_composition_rejects_non_symmetric_base():
    with pytest.raises(ValueError, match="symmetric"):
        dvi.Composition(dvi.LinearizedVI(), "yoshida4")
    with pytest.raises(ValueError, match="Unknown composition scheme"):
        dvi.Composition(dvi.MidpointVI(), "ruth3")


@pytest.mark.parametrize(
    "base",
    [
        dvi.StormerVerlet(),
        dvi.MidpointVI(),
        dvi.TrapezoidalVI(),
        pytest.param(dvi.GaussVPRK(2), marks=pytest.mark.slow),
        pytest.param(dvi.LobattoVPRK(3), marks=pytest.mark.slow),
    ],
    ids=lambda base: type(base).__name__,
)
def test_composition_substeps_do_not_round_with_t(base):
    # An autonomous problem, one step of h = 2^-5 from t0 = 0 and from t0 = 2^30, where
    # t0 + h is exact but t0 + c h is not (ulp 2.4e-7). The substeps must be sized from
    # h, not from differences of rounded sub-times: that cost kahan_li8 on Kepler a
    # factor 10^4 in energy error at t = 2^30 (and a slow drift from t = 2^18).
    solver = dvi.Composition(base, "kahan_li8")
    terms = dvi.terms_for(solver, KEPLER)
    y0 = kepler_state()

    @jax.jit
    def step(t0):
        state = solver.init(terms, t0, t0 + 2.0**-5, y0, None)
        return solver.step(terms, t0, t0 + 2.0**-5, y0, None, state, False)[0]

    assert max_abs_diff(step(jnp.array(2.0**30)), step(jnp.array(0.0))) < 1e-14


def _scans(jaxpr):
    """`(length, unroll)` of every `scan` in a traced program, at any depth."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            found.append((eqn.params["length"], eqn.params["unroll"]))
        for sub in jex.jaxprs_in_params(eqn.params):
            found += _scans(sub)
    return found


@pytest.mark.parametrize(
    "base,raised,unrolled",
    [
        (dvi.StormerVerlet(), True, True),
        (dvi.StormerVerlet(), False, False),
        (dvi.MidpointVI(), True, False),
    ],
    ids=["StormerVerlet", "StormerVerlet-xla-default", "MidpointVI"],
)
def test_explicit_substeps_are_unrolled_and_implicit_ones_loop(
    base, raised, unrolled, monkeypatch
):
    """At the small-loop threshold `import diffrax_vi` sets, a composition of an
    explicit step unrolls its substeps, so that XLA fuses across them and a
    compensated sum costs no copy of a carried state (Kepler's compensated
    yoshida4 of Stormer-Verlet 1.4x faster); at XLA's default it keeps them in a
    small loop, which XLA then compiles whole where the time-stepping loop runs
    kernel by kernel. A composition of an implicit step keeps them in a loop, so
    that its root find is compiled once, not once per substep (kahan_li8 of
    MidpointVI: 18.5 against 0.55 s of compilation). The same step either way as
    its substeps taken one by one."""
    from diffrax_vi._solver import composition

    monkeypatch.setattr(composition, "small_loops_compiled_whole", lambda: raised)
    solver = dvi.Composition(base, "yoshida4")
    terms = dvi.terms_for(solver, KEPLER)
    y0 = kepler_state()

    def step(y, state):
        return solver.step(terms, 0.0, 0.1, y, None, state, False)[0]

    state = solver.init(terms, 0.0, 0.1, y0, None)
    assert _scans(jax.make_jaxpr(step)(y0, state).jaxpr) == [(3, 3 if unrolled else 1)]

    @jax.jit
    def substeps(y):
        base_terms = dvi.terms_for(base, KEPLER)
        t = jnp.asarray(0.0)
        for gamma in named_scheme("yoshida4", 2).coefficients:
            h = 0.1 * float(gamma)
            base_state = base.init(base_terms, t, t + h, y, None)
            y = base.step(base_terms, t, t + h, y, None, base_state, False)[0]
            t = t + h
        return y

    assert max_abs_diff(jax.jit(step)(y0, state), substeps(y0)) < 1e-14


@pytest.mark.parametrize(
    "solver",
    [
        dvi.GaussVPRK(2),
        dvi.GaussVPRK(3),
        dvi.LobattoVPRK(3),
        dvi.Composition(dvi.MidpointVI(), "yoshida4"),
        pytest.param(
            dvi.Composition(dvi.TrapezoidalVI(), "kahan_li6"), marks=pytest.mark.slow
        ),
    ],
    ids=["gauss2", "gauss3", "lobatto3", "midpoint-yoshida4", "trapezoidal-kahan_li6"],
)
def test_symplectic_step(solver):
    y0 = (jnp.array([0.4, -0.7]), jnp.array([0.3, 0.5]))
    terms = dvi.LagrangianTerm(DoublePendulum())
    assert dvi.diagnostics.symplecticity_defect(solver, terms, y0) < 1e-12


@pytest.mark.parametrize("scheme", SCHEMES)
def test_composition_of_stormer_verlet_is_symplectic(scheme):
    sep = dvi.SeparableLagrangian(
        lambda t, q, a: 0.5 * jnp.sum(q**2) + q[0] ** 2 * q[1] - q[1] ** 3 / 3
    )
    y0 = (jnp.array([0.1, -0.2]), jnp.array([0.3, 0.25]))
    solver = dvi.Composition(dvi.StormerVerlet(), scheme)
    assert (
        dvi.diagnostics.symplecticity_defect(solver, dvi.separable_terms(sep), y0)
        < 1e-12
    )


@pytest.mark.parametrize(
    "solver",
    [
        dvi.GaussVPRK(2),
        dvi.LobattoVPRK(3),
        dvi.Composition(dvi.StormerVerlet(), "suzuki4"),
    ],
    ids=["gauss2", "lobatto3", "suzuki4"],
)
def test_jit_vmap_grad(solver):
    def q_final(g, q0):
        lagrangian = Pendulum(g=g)
        sol = dfx.diffeqsolve(
            dvi.terms_for(solver, lagrangian),
            solver,
            0.0,
            2.0,
            0.1,
            (q0, jnp.array(0.0)),
        )
        return sol.ys[0][-1]

    g, eps = jnp.array(1.3), 1e-6
    fd = (q_final(g + eps, 1.0) - q_final(g - eps, 1.0)) / (2 * eps)
    assert jnp.allclose(jax.jit(jax.grad(q_final))(g, 1.0), fd, rtol=1e-6)
    q0s = jnp.array([0.3, 1.0])
    batched = jax.vmap(lambda q: q_final(g, q))(q0s)
    assert jnp.allclose(batched[1], q_final(g, q0s[1]), rtol=1e-14)


def test_compensated_summation_brouwer():
    # A 2-D oscillator, whose quadratic energy the midpoint rule conserves exactly:
    # all energy error is round-off. Over 10^5 steps an ensemble's RMS error grows
    # like sqrt(t) without compensation and stays at a few eps with it.
    osc = dvi.SeparableLagrangian(lambda t, q, a: 0.5 * jnp.sum(q**2))
    n, h = 100_000, 0.01
    q0 = jnp.array([[1.0, 0.5]]) + 1e-3 * jax.random.normal(jax.random.key(0), (64, 2))
    ts = jnp.linspace(0, n * h, 101)
    energy = lambda q, p: 0.5 * jnp.sum(p**2 + q**2, axis=-1)

    def rms(compensated):
        solver = dvi.MidpointVI(compensated=compensated)
        qs, ps = jax.vmap(
            lambda q: (
                dfx.diffeqsolve(
                    dvi.LagrangianTerm(osc),
                    solver,
                    0.0,
                    n * h,
                    h,
                    (q, jnp.zeros(2)),
                    saveat=dfx.SaveAt(ts=ts),
                    max_steps=n + 1,
                ).ys
            )
        )(q0)
        err = energy(qs, ps) - energy(qs[:, :1], ps[:, :1])
        return np.sqrt(np.mean(np.asarray(err[:, 1:]) ** 2, axis=0))

    plain, kahan = rms(False), rms(True)
    t = np.asarray(ts[1:])
    late = t >= 100
    slope_plain = np.polyfit(np.log(t[late]), np.log(plain[late]), 1)[0]
    slope_kahan = np.polyfit(np.log(t[late]), np.log(kahan[late]), 1)[0]
    assert abs(slope_plain - 0.5) < 0.15, slope_plain  # random walk, Brouwer's law
    assert slope_kahan < 0.35, slope_kahan  # below the random walk
    assert plain[-1] > 10 * kahan[-1]
    assert kahan[-1] < 1e-15
