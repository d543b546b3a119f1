import diffrax as dfx
import diffrax_vi as dvi
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
