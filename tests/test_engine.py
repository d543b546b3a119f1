"""One engine, methods as data: user tableaus and schemes, nested compositions,
`terms_for`, capability markers, named solver states."""

import diffrax as dfx
import diffrax_vi as dvi
import jax.numpy as jnp
import numpy as np
import pytest
from diffrax_vi._solver.vprk import gauss_tableau, lobatto_tableau

from .helpers import (
    ALL_SOLVERS,
    DoublePendulum,
    final_state,
    fitted_order,
    KEPLER,
    kepler_state,
    max_abs_diff,
    Pendulum,
    reference,
)


# Published coefficients, typed by hand (Hairer, Lubich & Wanner, Tables II.1.1 and
# II.1.2): the 2-stage Gauss method and the 2-stage Lobatto IIIA-IIIB pair.
R3 = np.sqrt(3.0)
GAUSS2 = dvi.VPRKTableau(
    a=np.array([[1 / 4, 1 / 4 - R3 / 6], [1 / 4 + R3 / 6, 1 / 4]]),
    a_bar=np.array([[1 / 4, 1 / 4 - R3 / 6], [1 / 4 + R3 / 6, 1 / 4]]),
    b=np.array([1 / 2, 1 / 2]),
    c=np.array([1 / 2 - R3 / 6, 1 / 2 + R3 / 6]),
    order=4,
)
LOBATTO2 = dvi.VPRKTableau(
    a=np.array([[0.0, 0.0], [0.5, 0.5]]),
    a_bar=np.array([[0.5, 0.0], [0.5, 0.0]]),
    b=np.array([0.5, 0.5]),
    c=np.array([0.0, 1.0]),
    order=2,
)


@pytest.mark.parametrize(
    "typed,named", [(GAUSS2, dvi.GaussVPRK(2)), (LOBATTO2, dvi.LobattoVPRK(2))]
)
def test_user_typed_tableau_reproduces_the_library_method(typed, named):
    for field in ("a", "a_bar", "b", "c"):
        assert np.allclose(
            getattr(typed, field), getattr(named.tableau, field), 0, 1e-15
        )
    assert typed.symmetric and typed == typed
    solver = dvi.VPRK(typed)
    assert solver.order(None) == named.order(None)
    y0 = (jnp.array([0.4, -0.7]), jnp.array([0.3, 0.5]))
    a = final_state(DoublePendulum(), solver, y0, 2.0, jnp.array(0.05))
    b = final_state(DoublePendulum(), named, y0, 2.0, jnp.array(0.05))
    assert max_abs_diff(a, b) < 1e-13


def test_tableau_validation():
    with pytest.raises(ValueError, match="not symplectic"):
        dvi.VPRKTableau(
            a=LOBATTO2.a, a_bar=LOBATTO2.a, b=LOBATTO2.b, c=LOBATTO2.c, order=2
        )
    with pytest.raises(ValueError, match="shapes"):
        dvi.VPRKTableau(
            a=np.eye(3), a_bar=np.eye(2), b=np.ones(2) / 2, c=np.ones(2), order=1
        )
    for bad in (2.5, "3", jnp.array(2), True):
        with pytest.raises(ValueError, match="Python int"):
            dvi.GaussVPRK(bad)
    with pytest.raises(ValueError, match="stages"):
        dvi.LobattoVPRK(1)
    with pytest.raises(ValueError, match="stages"):
        dvi.GaussVPRK(25)


def test_tableau_order_is_an_integer_not_a_boolean(as_a_user_runs_it):
    fields = dict(a=LOBATTO2.a, a_bar=LOBATTO2.a_bar, b=LOBATTO2.b, c=LOBATTO2.c)
    with pytest.raises(ValueError, match="positive int"):
        dvi.VPRKTableau(**fields, order=True)
    tableau = dvi.VPRKTableau(**fields, order=np.int64(2))
    assert tableau.order == 2 and type(tableau.order) is int
    assert tableau == LOBATTO2


@pytest.mark.parametrize("s", [8, 12, 16, 24])
def test_many_stage_tableaus_are_exact_to_round_off(s):
    # Built by quadrature of the Lagrange basis: the collocation conditions C(s) hold
    # to round-off (a Vandermonde solve had lost 1e-10 at s = 12).
    for tableau in (gauss_tableau(s), lobatto_tableau(s)):
        c = tableau.c
        for k in range(1, s + 1):
            assert np.max(np.abs(tableau.a @ c ** (k - 1) - c**k / k)) < 1e-14
        assert tableau.symmetric


def test_non_symmetric_tableau_cannot_be_composed():
    # Radau IIA's positions with their symplectic momentum partner: a valid VPRK
    # tableau (order 3 for the pair), but not a symmetric method.
    a = np.array([[5 / 12, -1 / 12], [3 / 4, 1 / 4]])
    b = np.array([3 / 4, 1 / 4])
    a_bar = b[None, :] - (b[None, :] * a.T) / b[:, None]
    radau = dvi.VPRKTableau(a=a, a_bar=a_bar, b=b, c=np.array([1 / 3, 1.0]), order=3)
    assert not radau.symmetric
    # Symmetry is the tableau's, not the class's: the same VPRK class is symmetric
    # with a symmetric tableau.
    assert not dvi.VPRK(radau).symmetric
    assert dvi.VPRK(dvi.GaussVPRK(2).tableau).symmetric
    with pytest.raises(ValueError, match="not symmetric"):
        dvi.Composition(dvi.VPRK(radau), "yoshida4")


def test_nested_composition_has_order_six():
    # A triple jump over an order-4 triple jump of Stormer-Verlet (Yoshida 1990).
    inner = dvi.Composition(dvi.StormerVerlet(), "triple_jump")
    solver = dvi.Composition(inner, "triple_jump")
    assert inner.order(None) == 4 and solver.order(None) == 6
    # The same coefficients as the fixed scheme for a second-order base.
    assert inner.scheme == dvi.Composition(dvi.StormerVerlet(), "yoshida4").scheme
    y0, t1 = kepler_state(), 2 * np.pi
    exact = reference(KEPLER, y0, t1)
    ns = [200, 280, 400, 560]
    errors = [
        max_abs_diff(final_state(KEPLER, solver, y0, t1, jnp.array(t1 / n)), exact)
        for n in ns
    ]
    assert min(errors) > 1e-12, errors
    assert abs(fitted_order([t1 / n for n in ns], errors) - 6) < 0.3, errors
    # Without raising the inner order first, the outer triple jump (designed for an
    # order-4 base) only keeps order 2.
    assert dvi.Composition(dvi.StormerVerlet(), "triple_jump").order(None) == 4
    lone = dvi.CompositionScheme(solver.scheme.coefficients, order=6, base_order=4)
    assert lone.order_for(2) == 2


def test_composition_scheme_as_coefficients():
    g = 1 / (2 - 2 ** (1 / 3))
    solver = dvi.Composition(dvi.MidpointVI(), [g, 1 - 2 * g, g])
    assert solver.order(None) == 4  # inferred from sum g^3 = 0
    y0 = (jnp.array(1.2), jnp.array(0.3))
    a = final_state(Pendulum(), solver, y0, 2.0, jnp.array(0.1))
    b = final_state(
        Pendulum(), dvi.Composition(dvi.MidpointVI(), "yoshida4"), y0, 2.0, 0.1
    )
    assert max_abs_diff(a, b) < 1e-15
    # Symmetric and consistent but with sum g^3 != 0: order 2 only.
    assert dvi.Composition(dvi.MidpointVI(), [0.25, 0.5, 0.25]).order(None) == 2
    with pytest.raises(ValueError, match="symmetric"):
        dvi.Composition(dvi.MidpointVI(), [0.5, 0.3, 0.2])
    with pytest.raises(ValueError, match="sum to 1"):
        dvi.Composition(dvi.MidpointVI(), [0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="sum gamma"):
        dvi.CompositionScheme(np.array([0.25, 0.5, 0.25]), order=4)


def test_wrappers_are_neither_symplectic_nor_composable():
    half = dfx.HalfSolver(dvi.MidpointVI())
    # diffrax forwards isinstance through wrappers for its own classes ...
    assert isinstance(half, dfx.AbstractSolver)
    # ... but step doubling with adaptive steps is not symplectic.
    assert not isinstance(half, dvi.AbstractSymplecticSolver)
    assert not isinstance(half, dvi.AbstractComposableSolver)
    with pytest.raises(ValueError, match="not one"):
        dvi.Composition(half, "yoshida4")
    assert isinstance(dvi.MidpointVI(), dvi.AbstractSymplecticSolver)
    assert not isinstance(dvi.LinearizedVI(), dvi.AbstractSymplecticSolver)


@pytest.mark.parametrize(
    "name,solver",
    ALL_SOLVERS
    + [
        ("Tsit5", dfx.Tsit5()),
        ("SemiImplicitEuler", dfx.SemiImplicitEuler()),
        ("HalfSolver(MidpointVI)", dfx.HalfSolver(dvi.MidpointVI())),
        ("nested", dvi.Composition(dvi.Composition(dvi.StormerVerlet()), "yoshida4")),
    ],
)
def test_terms_for_every_solver(name, solver):
    terms = dvi.terms_for(solver, Pendulum())
    partitioned = name in ("StormerVerlet", "SemiImplicitEuler", "nested") or (
        name == "yoshida4(StormerVerlet)"
    )
    if partitioned:
        assert isinstance(terms, tuple) and len(terms) == 2
        with pytest.raises(ValueError, match="Partitioned terms exist only"):
            dvi.terms_for(solver, DoublePendulum())
    else:
        assert isinstance(terms, dvi.LagrangianTerm)
        assert dvi.terms_for(solver, DoublePendulum()).lagrangian == DoublePendulum()
    controller = (
        dfx.PIDController(rtol=1e-6, atol=1e-6)
        if name.startswith("HalfSolver")
        else dfx.ConstantStepSize()
    )
    sol = dfx.diffeqsolve(
        terms,
        solver,
        0.0,
        1.0,
        0.1,
        (jnp.array(1.0), jnp.array(0.0)),
        stepsize_controller=controller,
    )
    assert sol.result == dfx.RESULTS.successful
    final = (sol.ys[0][-1], sol.ys[1][-1])
    exact = reference(Pendulum(), (jnp.array(1.0), jnp.array(0.0)), 1.0)
    assert max_abs_diff(final, exact) < 5e-2


def test_terms_for_rejects_other_term_structures():
    class Odd(dfx.Euler):
        term_structure = (dfx.AbstractTerm, dfx.AbstractTerm, dfx.AbstractTerm)

    with pytest.raises(ValueError, match="structure"):
        dvi.terms_for(Odd(), Pendulum())


def test_solver_states_have_names():
    y0 = (jnp.array(1.0), jnp.array(0.0))

    def state(solver):
        terms = dvi.terms_for(solver, Pendulum())
        return solver.init(terms, 0.0, 0.1, y0, None)

    mid = state(dvi.MidpointVI())
    assert mid.method.last.shape == (1,) and mid.compensation is not None
    assert state(dvi.MidpointVI(compensated=False)).compensation is None
    assert jnp.shape(state(dvi.StormerVerlet()).force) == ()
    history = state(dvi.LinearizedVI(velocity="centered")).method
    assert len(history.positions) == 3 and len(history.steps) == 3


@pytest.mark.parametrize(
    "solver", [dvi.StormerVerlet(), dvi.LGVI()], ids=["StormerVerlet", "LGVI"]
)
def test_a_jump_known_when_traced_takes_no_branch(solver):
    """A step told at trace time that it follows a jump (ReversibleAdjoint's
    backward steps pass the Python True) recomputes its cached force without a
    conditional, and steps as a step told so at run time does."""
    import jax

    scene = (
        dvi.scenes.kepler()
        if isinstance(solver, dvi.StormerVerlet)
        else (dvi.scenes.free_rigid_body())
    )
    terms = dvi.terms_for(solver, scene.lagrangian)
    y0, h = scene.y0, scene.period / 100
    state = solver.init(terms, 0.0, h, y0, scene.args)

    def step(jump):
        return solver.step(terms, 0.0, h, y0, scene.args, state, jump)[0]

    def conds(jump):
        jaxpr = jax.make_jaxpr(lambda: step(jump))()
        return str(jaxpr).count("cond[")

    assert conds(True) < conds(jnp.array(True))
    known, traced = step(True), step(jnp.array(True))
    for a, b in zip(jax.tree.leaves(known), jax.tree.leaves(traced)):
        np.testing.assert_allclose(a, b, rtol=1e-15, atol=0)
