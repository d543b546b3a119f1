import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.extend.core as jex
import jax.numpy as jnp
import pytest

from .helpers import DoublePendulum, max_abs_diff, reference, stiffening


def test_vf_is_hamiltons_equations():
    # Double pendulum: qdot = M(q)^{-1} p, pdot = dL/dq at that velocity.
    q, p = jnp.array([0.3, -1.1]), jnp.array([0.4, 0.9])
    dq, dp = dvi.LagrangianTerm(DoublePendulum()).vf(0.0, (q, p), None)
    c, s = jnp.cos(q[0] - q[1]), jnp.sin(q[0] - q[1])
    mass = jnp.array([[2.0, c], [c, 1.0]])
    v = jnp.linalg.solve(mass, p)
    expected_dp = jnp.array(
        [-v[0] * v[1] * s - 2 * jnp.sin(q[0]), v[0] * v[1] * s - jnp.sin(q[1])]
    )
    assert jnp.allclose(dq, v, rtol=1e-14)
    assert jnp.allclose(dp, expected_dp, rtol=1e-13)


@pytest.mark.parametrize(
    "solver",
    [dfx.Tsit5(), dfx.Dopri8(), dfx.Kvaerno5()],
    ids=["tsit5", "dopri8", "kvaerno5"],
)
@pytest.mark.parametrize(
    "lagrangian",
    [DoublePendulum(), dvi.Lagrangian(stiffening)],
    ids=["quadratic", "general"],
)
def test_runge_kutta_solvers_integrate_the_same_term(solver, lagrangian):
    y0 = (jnp.array([0.5, -0.3]), jnp.array([0.2, 0.1]))
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(lagrangian),
        solver,
        0.0,
        3.0,
        0.01,
        y0,
        stepsize_controller=dfx.PIDController(rtol=1e-10, atol=1e-10),
    )
    assert sol.result == dfx.RESULTS.successful
    final = (sol.ys[0][-1], sol.ys[1][-1])
    assert max_abs_diff(final, reference(lagrangian, y0, 3.0)) < 1e-7


def _loop_callbacks(jaxpr) -> int:
    """How many host callbacks sit inside the while loops of a traced program."""

    def count(jaxpr, in_loop):
        found = 0
        for eqn in jaxpr.eqns:
            if in_loop and "callback" in eqn.primitive.name:
                found += 1
            inner = in_loop or eqn.primitive.name == "while"
            for sub in jex.jaxprs_in_params(eqn.params):
                found += count(sub, inner)
        return found

    return count(jaxpr.jaxpr, False)


def _rk_program(term, y0):
    solve = lambda y0: dfx.diffeqsolve(term, dfx.Tsit5(), 0.0, 1.0, 0.1, y0).ys
    return jax.make_jaxpr(solve)(y0)


def test_separable_term_checks_its_mass_once_not_in_the_loop():
    """A host callback in the time-stepping loop keeps XLA from compiling it as one
    function (Runge-Kutta steps several times slower on small systems): a separable
    Lagrangian's Legendre map is settled by one check of its mass, made when the
    term is built, and its vector field has no callback. Where the map can fail
    during the solve, or the mass could not be checked, the check stays."""
    potential = lambda t, q, args: 0.5 * jnp.sum(q**2)
    y0 = (jnp.array([0.3, 0.5]), jnp.zeros(2))
    regular = dvi.LagrangianTerm(dvi.SeparableLagrangian(potential, jnp.ones(2)))
    assert _loop_callbacks(_rk_program(regular, y0)) == 0
    # The loop of a plain ODETerm has none either: the comparison is like for like.
    ode = dfx.ODETerm(lambda t, y, args: regular.vf(t, y, args))
    assert _loop_callbacks(_rk_program(ode, y0)) == 0
    singular = dvi.SeparableLagrangian(potential, jnp.array([1.0, 0.0]))
    with pytest.raises(eqx.EquinoxRuntimeError, match="degenerate"):
        dfx.diffeqsolve(dvi.LagrangianTerm(singular), dfx.Tsit5(), 0.0, 1.0, 0.1, y0)
    general = dvi.LagrangianTerm(DoublePendulum())
    assert _loop_callbacks(_rk_program(general, y0)) > 0

    # A mass traced where the term is built (being fitted) is checked every step.
    @eqx.filter_jit
    def final(mass):
        term = dvi.LagrangianTerm(dvi.SeparableLagrangian(potential, mass))
        assert _loop_callbacks(_rk_program(term, y0)) > 0
        return dfx.diffeqsolve(term, dfx.Tsit5(), 0.0, 1.0, 0.1, y0).ys

    with pytest.raises(eqx.EquinoxRuntimeError, match="degenerate"):
        final(jnp.array([1.0, 0.0]))
    assert jnp.all(jnp.isfinite(final(jnp.ones(2))[0]))
