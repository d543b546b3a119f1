"""Properties under random polynomial Lagrangians and states (hypothesis):
symplecticity, time-reversibility of the symmetric methods, vmap equals a loop."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings


def _polynomial(t, q, v, c):
    """A 2-DOF polynomial Lagrangian with coefficients `c` (passed as `args`, so one
    compilation serves every example): diagonal masses, a gyroscopic term linear in v
    (non-separable unless c[2] = 0), and a potential with quadratic, cubic and quartic
    terms (quartic ones positive, so the well is bounded)."""
    kinetic = 0.5 * (c[0] * v[0] ** 2 + c[1] * v[1] ** 2)
    gyroscopic = c[2] * (q[0] * v[1] - q[1] * v[0])
    potential = (
        0.5 * (c[3] * q[0] ** 2 + c[4] * q[1] ** 2)
        + c[5] * q[0] ** 2 * q[1]
        + c[6] * q[0] ** 4
        + c[7] * q[1] ** 4
    )
    return kinetic + gyroscopic - potential


GENERAL = dvi.Lagrangian(_polynomial)
SEPARABLE = dvi.SeparableLagrangian(
    lambda t, q, c: _polynomial(t, q, jnp.zeros(2, q.dtype), c), mass=1.0
)

SOLVERS = {
    "MidpointVI": (dvi.MidpointVI(), GENERAL),
    "TrapezoidalVI": (dvi.TrapezoidalVI(), GENERAL),
    "StormerVerlet": (dvi.StormerVerlet(), SEPARABLE),
    "GaussVPRK(2)": (dvi.GaussVPRK(2), GENERAL),
    "LobattoVPRK(3)": (dvi.LobattoVPRK(3), GENERAL),
    "yoshida4(MidpointVI)": (dvi.Composition(dvi.MidpointVI(), "yoshida4"), GENERAL),
}


# The default suite checks the one-stage and a two-stage method on the general
# Lagrangian, and the explicit method on the separable one; the others run with
# `-m slow` (their steps share the engine, and test_higher_order checks them).
FAST = ("MidpointVI", "GaussVPRK(2)", "StormerVerlet")
NAMES = [
    name if name in FAST else pytest.param(name, marks=pytest.mark.slow)
    for name in SOLVERS
]
VMAP_NAMES = [
    name if name == "MidpointVI" else pytest.param(name, marks=pytest.mark.slow)
    for name in SOLVERS
]


def _terms(solver, lagrangian):
    if isinstance(solver.term_structure, tuple):
        return dvi.separable_terms(lagrangian)
    return dvi.LagrangianTerm(lagrangian)


coefficients = st.tuples(
    st.floats(0.5, 2.0),  # masses
    st.floats(0.5, 2.0),
    st.floats(-0.5, 0.5),  # gyroscopic
    st.floats(0.5, 2.0),  # stiffnesses
    st.floats(0.5, 2.0),
    st.floats(-0.5, 0.5),  # cubic
    st.floats(0.0, 0.5),  # quartic
    st.floats(0.0, 0.5),
)
states = st.lists(st.floats(-0.5, 0.5), min_size=4, max_size=4)
SETTINGS = settings(max_examples=15, deadline=None, derandomize=True)


def _args(c, lagrangian):
    c = jnp.asarray(c)
    if lagrangian is SEPARABLE:
        c = c.at[0].set(1.0).at[1].set(1.0).at[2].set(0.0)  # unit masses, separable
    return c


def _state(x):
    return jnp.asarray(x[:2]), jnp.asarray(x[2:])


@pytest.mark.parametrize("name", NAMES)
@SETTINGS
@given(c=coefficients, x=states)
def test_symplectic(name, c, x):
    solver, lagrangian = SOLVERS[name]
    terms = _terms(solver, lagrangian)
    args = _args(c, lagrangian)
    assert (
        dvi.diagnostics.symplecticity_defect(solver, terms, _state(x), args, h=0.1)
        < 1e-10
    )


@eqx.filter_jit
def _there_and_back(solver, lagrangian, y0, c):
    terms = _terms(solver, lagrangian)
    there = dfx.diffeqsolve(terms, solver, 0.0, 1.0, 0.1, y0, c, max_steps=16)
    y1 = jax.tree.map(lambda x: x[-1], there.ys)
    back = dfx.diffeqsolve(terms, solver, 1.0, 0.0, -0.1, y1, c, max_steps=16)
    return jax.tree.map(lambda x: x[-1], back.ys), y1


@pytest.mark.parametrize("name", NAMES)
@SETTINGS
@given(c=coefficients, x=states)
def test_time_reversible(name, c, x):
    """Symmetric methods: ten steps forward, then ten back, return to the start."""
    solver, lagrangian = SOLVERS[name]
    y0 = _state(x)
    y_back, y1 = _there_and_back(solver, lagrangian, y0, _args(c, lagrangian))
    moved = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(y1, y0))
    error = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(y_back, y0))
    assert error < 1e-10 and (moved > 1e-3 or max(map(abs, x)) < 1e-3)


@eqx.filter_jit
def _final(solver, lagrangian, y0, c):
    terms = _terms(solver, lagrangian)
    sol = dfx.diffeqsolve(terms, solver, 0.0, 1.0, 0.1, y0, c, max_steps=16)
    return jax.tree.map(lambda x: x[-1], sol.ys)


@pytest.mark.parametrize("name", VMAP_NAMES)
@SETTINGS
@given(
    c=coefficients,
    xs=st.lists(states, min_size=3, max_size=3),
)
def test_vmap_equals_loop(name, c, xs):
    solver, lagrangian = SOLVERS[name]
    args = _args(c, lagrangian)
    batch = (jnp.asarray([x[:2] for x in xs]), jnp.asarray([x[2:] for x in xs]))
    vmapped = jax.vmap(lambda y: _final(solver, lagrangian, y, args))(batch)
    for i, x in enumerate(xs):
        single = _final(solver, lagrangian, _state(x), args)
        for a, b in zip(vmapped, single):
            assert np.allclose(a[i], b, rtol=1e-12, atol=1e-14)
