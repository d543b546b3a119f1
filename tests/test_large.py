"""Large systems: the bead-wire scene against hand-derived equations of motion, and the
matrix-free (Krylov) solves against the dense ones they replace beyond 16 unknowns."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
import scipy.integrate
from diffrax_vi import scenes
from diffrax_vi._tolerance import NEWTON_DENSE_MAX

from .helpers import final_state, max_abs_diff, reference


def _bead_wire_rhs(n, m=1.0, a=0.2, ell=1.0, kappa=1.0, g=1.0):
    """Hand-derived Euler-Lagrange equations of the bead wire in (x, v):
    m (1 + y'^2) x'' + m y' y'' x'^2 = -dV/dx, for y = -a cos(k x)."""
    k = 2 * np.pi / ell

    def rhs(t, state):
        x, v = state[:n], state[n:]
        xs = np.concatenate([[0.0], x, [(n + 1) * ell]])
        ys = -a * np.cos(k * xs)
        slope = a * k * np.sin(k * xs)
        curvature = a * k**2 * np.cos(k * xs)
        dx, dy = np.diff(xs), np.diff(ys)
        d = np.hypot(dx, dy)
        tension = kappa * (d - ell) / d  # per unit of (dx + dy y')
        # Spring j joins beads j and j + 1 (0 and n + 1 are fixed).
        grad = m * g * slope[1:-1]
        grad += tension[:-1] * (dx[:-1] + dy[:-1] * slope[1:-1])
        grad -= tension[1:] * (dx[1:] + dy[1:] * slope[1:-1])
        mass = m * (1 + slope[1:-1] ** 2)
        accel = (-grad - m * slope[1:-1] * curvature[1:-1] * v**2) / mass
        return np.concatenate([v, accel])

    return rhs


def test_bead_wire_matches_hand_derived_equations():
    n = 5
    scene = scenes.bead_wire(n)
    t1 = 3 * scene.period
    # The scene's coordinates are displacements from the troughs x_i = i.
    troughs = np.arange(1.0, n + 1.0)
    x0 = troughs + np.asarray(scene.y0[0])
    sol = scipy.integrate.solve_ivp(
        _bead_wire_rhs(n),
        (0, t1),
        np.concatenate([x0, np.zeros(n)]),
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    x, v = sol.y[:n, -1], sol.y[n:, -1]
    p = (1 + (0.2 * 2 * np.pi * np.sin(2 * np.pi * x)) ** 2) * v
    theirs = reference(scene.lagrangian, scene.y0, t1)
    assert max_abs_diff(theirs, (x - troughs, p)) < 1e-9
    assert max_abs_diff(theirs, scene.y0) > 0.05  # it moved


def test_bead_wire_forces_do_not_see_how_many_beads_precede():
    # The coordinates are displacements from the troughs, so a bead's force is the
    # same arithmetic on its and its neighbours' displacements at the end of 65 536
    # beads as at the end of 7. In the abscissae themselves (x_i ~ i) the rounding
    # of x_i and cos(2 pi x_i) grew with i: at 65 536 beads MidpointVI's Newton
    # residual stalled at 1.2e-7 of its terms, above sqrt(eps), and the first step
    # failed.
    n, tail = 2**16, 7
    big = scenes.bead_wire(n)
    v = 0.3 * jnp.cos(jnp.arange(float(n)))
    force = jax.grad(big.lagrangian, argnums=1)
    far = force(0.0, big.y0[0], v, None)[-(tail - 1) :]
    near = force(0.0, big.y0[0][-tail:], v[-tail:], None)[1:]
    assert float(jnp.max(jnp.abs(far - near))) <= 4e-16 * float(jnp.max(jnp.abs(near)))


def test_bead_wire_rejects_bad_parameters():
    with pytest.raises(ValueError, match="leaves its trough"):
        scenes.bead_wire(8, displacement=0.6)
    with pytest.raises(ValueError, match="at least 1"):
        scenes.bead_wire(0)


def _solve(lagrangian, solver, y0, h, steps):
    # `final_state` solves with diffrax's default `throw=True`: a failed step raises.
    return final_state(lagrangian, solver, y0, h * steps, h)


@pytest.mark.parametrize(
    "make",
    [
        lambda rf: dvi.MidpointVI(root_finder=rf),
        pytest.param(
            lambda rf: dvi.GaussVPRK(2, root_finder=rf), marks=pytest.mark.slow
        ),
        pytest.param(
            lambda rf: dvi.TrapezoidalVI(root_finder=rf), marks=pytest.mark.slow
        ),
    ],
    ids=["MidpointVI", "GaussVPRK2", "TrapezoidalVI"],
)
def test_krylov_newton_equals_dense_newton(make):
    # 20 beads: above the 16 unknowns where Newton goes matrix-free by default. The
    # Newton matrix is not symmetric (BiCGStab). Newton's last Krylov solve goes to
    # round-off, as the dense solve does, so they agree to round-off amplified by 10
    # steps (2.6e-12 apart when the last solve stopped at half the Newton tolerance).
    scene = scenes.bead_wire(20)
    h = scene.period / 40
    dense = _solve(
        scene.lagrangian, make(dvi.Newton(linear_solver="dense")), scene.y0, h, 10
    )
    auto = _solve(scene.lagrangian, make(None), scene.y0, h, 10)
    assert max_abs_diff(dense, auto) < 1e-13
    assert max_abs_diff(dense, scene.y0) > 1e-2


@pytest.mark.parametrize("system", ["bead_wire", "chain"])
def test_krylov_newton_gradient_equals_dense_newtons(system):
    """Beyond 16 unknowns a step's root is differentiated matrix-free, as Newton's
    method solves for it: by conjugate gradients on the normal equations of the
    bead wire's Jacobian (its mass reads q), on a chain's own (symmetric). The
    gradient of 10 `MidpointVI` steps equals the one through dense eliminations
    (`Newton(linear_solver="dense")`) to 1e-10, and its backward loop holds no
    LAPACK call and no host callback (optimistix's `ImplicitAdjoint` solves there by
    lineax's LU and checks the solve).

    So does the bead wire's gradient under `ReversibleAdjoint`, whose backward
    steps take the roots of the inverse steps that have just undone them,
    differentiated matrix-free there (`known_root`): its program holds 5 root
    solves, not the 6 of solving those steps again (as with `checkpoint_every`,
    whose steps from an anchor must). The matrix-free derivative's tolerance is
    relative: the bead wire's gradient is the same, to 1e-12, for its Lagrangian in
    units of energy 1e6 times smaller (its mass and stiffness times 1e-6, an
    argument of the same compiled gradient)."""
    from diffrax_vi.diagnostics import loop_breakers

    if system == "bead_wire":
        scene = scenes.bead_wire(20)
        lagrangian, y0, h = scene.lagrangian, scene.y0, scene.period / 40

        def in_units(k):
            # The same motion with the Lagrangian in units of energy k: k L.
            return eqx.tree_at(
                lambda l: (l.mass, l.stiffness),
                lagrangian,
                (k * lagrangian.mass, k * lagrangian.stiffness),
            )
    else:
        n = 20
        lagrangian, h = _Chain(), 0.1
        y0 = (0.3 * jnp.sin(2.1 * jnp.arange(1.0, n + 1.0)), jnp.zeros(n))
        in_units = lambda k: lagrangian

    def gradient(root_finder=None, adjoint=dfx.RecursiveCheckpointAdjoint()):
        def fn(q0, k):
            sol = dfx.diffeqsolve(
                dvi.LagrangianTerm(in_units(k)),
                dvi.MidpointVI(root_finder=root_finder),
                0.0,
                10 * h,
                h,
                (q0, k * y0[1]),
                adjoint=adjoint,
            )
            q, p = (x[-1] for x in sol.ys)
            return jnp.sum(jnp.sin(q)) + jnp.sum(jnp.sin(p / k))

        return jax.grad(fn)

    one = jnp.asarray(1.0)

    def compiled(traced):
        program = traced.lower().compile()
        assert loop_breakers(program.as_text()) == []
        return program

    dense = jax.jit(gradient(dvi.Newton(linear_solver="dense")))(y0[0], one)
    assert jnp.max(jnp.abs(dense)) > 1e-2
    krylov = compiled(jax.jit(gradient()).trace(y0[0], one))
    gradients = [krylov(y0[0], one)]
    if system == "bead_wire":

        def traced(adjoint):
            return jax.jit(gradient(adjoint=adjoint)).trace(y0[0], one)

        def solves(traced):
            return str(traced.jaxpr).count("name=root_find")

        reversible = traced(dvi.ReversibleAdjoint())
        assert solves(reversible) == 5
        assert solves(traced(dvi.ReversibleAdjoint(checkpoint_every=4))) == 6
        gradients.append(compiled(reversible)(y0[0], one))
        scaled = krylov(y0[0], jnp.asarray(1e-6))
        assert max_abs_diff(scaled, gradients[0]) < 1e-12 * jnp.max(jnp.abs(dense))
    for value in gradients:
        assert max_abs_diff(value, dense) < 1e-10 * jnp.max(jnp.abs(dense))


class _Chain(eqx.Module):
    """A chain of unequal masses written as a plain module: dL/dv does not read q,
    so the midpoint and linearized steps' Jacobians are symmetric (CG)."""

    def __call__(self, t, q, v, args):
        mass = jnp.linspace(1.0, 3.0, q.shape[0])
        r = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return 0.5 * jnp.sum(mass * v**2) - jnp.sum(0.5 * r**2 + 0.25 * r**4)


def test_symmetric_krylov_equals_dense():
    # 24 unknowns of a Lagrangian whose momentum is free of q: Newton's Krylov
    # solves and LinearizedVI's one solve are conjugate gradients, and agree with
    # the dense solves to round-off.
    n = 24
    y0 = (0.3 * jnp.sin(2.1 * jnp.arange(1.0, n + 1.0)), jnp.zeros(n))
    pairs = [
        (
            dvi.MidpointVI(),
            dvi.MidpointVI(root_finder=dvi.Newton(linear_solver="dense")),
        ),
        (
            dvi.LinearizedVI(velocity="centered"),
            dvi.LinearizedVI(velocity="centered", linear_solver=lx.LU()),
        ),
    ]
    for krylov, dense in pairs:
        a = _solve(_Chain(), krylov, y0, 0.05, 20)
        b = _solve(_Chain(), dense, y0, 0.05, 20)
        assert max_abs_diff(a, b) < 1e-12
        assert max_abs_diff(a, y0) > 1e-2


def test_krylov_falls_back_where_bicgstab_breaks_down():
    # BiCGStab breaks down on this symmetric indefinite matrix (a swap of two
    # coordinates); the solve falls back to CG on the normal equations.
    from diffrax_vi._linear import krylov_solve

    a = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    b = jnp.array([1.0, 0.0, 1.0])
    direct = lx.linear_solve(
        lx.MatrixLinearOperator(a), b, lx.BiCGStab(rtol=1e-12, atol=1e-12), throw=False
    )
    assert direct.result != lx.RESULTS.successful
    x, result = krylov_solve(lambda w: a @ w, b, 1e-14, frozenset(), 30)
    assert result == lx.RESULTS.successful
    assert np.allclose(x, np.linalg.solve(a, b), rtol=0, atol=1e-14)


def test_large_separable_midpoint_equals_dense_newton():
    # A separable chain just past NEWTON_DENSE_MAX masses, so that Newton is
    # matrix-free: the fixed-point iteration, with Newton-Krylov (CG, preconditioned
    # by the inverse mass) as its fallback, against dense Newton (whose unrolled LU
    # costs most of the test's compile time, growing with n).
    n = NEWTON_DENSE_MAX + 4
    masses = jnp.linspace(1.0, 3.0, n)

    def potential(t, q, args):
        r = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return jnp.sum(0.5 * r**2 + 0.25 * r**4)

    lagrangian = dvi.SeparableLagrangian(potential, masses)
    y0 = (0.3 * jnp.sin(2.1 * jnp.arange(1.0, n + 1.0)), jnp.zeros(n))
    stiff = dvi.MidpointVI(root_finder=dvi.Newton())
    dense = dvi.MidpointVI(root_finder=dvi.Newton(linear_solver="dense"))
    for solver in (dvi.MidpointVI(), stiff):
        assert (
            max_abs_diff(
                _solve(lagrangian, solver, y0, 0.05, 20),
                _solve(lagrangian, dense, y0, 0.05, 20),
            )
            < 1e-12
        )


@pytest.mark.slow  # 30 s, mostly compiling the dense path it compares with
def test_linearized_krylov_equals_lu():
    scene = scenes.bead_wire(17, displacement=0.05)
    h = scene.period / 40
    krylov = dvi.LinearizedVI(velocity="centered")
    lu = dvi.LinearizedVI(velocity="centered", linear_solver=lx.LU())
    a = _solve(scene.lagrangian, krylov, scene.y0, h, 10)
    b = _solve(scene.lagrangian, lu, scene.y0, h, 10)
    assert max_abs_diff(a, b) < 1e-11
    assert max_abs_diff(a, scene.y0) > 1e-3


@pytest.mark.slow  # 17 s; test_lagrangian differentiates the same map in 9 s
def test_gradient_through_a_large_generic_term_equals_hamiltons_equations():
    # 80 beads, beyond the dense Legendre solves: Tsit5 on the scene's
    # LagrangianTerm (velocities from the matrix-free inverse Legendre map, a mass
    # that depends on q) and on Hamilton's equations written by hand,
    # H = p^2 / (2 m(q)) - L(q, 0) with m(q) = d2L/dv2, are one ODE, so the
    # derivatives of the final state with respect to the initial positions agree.
    # Differentiating the matrix-free map used to raise (lineax does not
    # differentiate a solve's options, here the q-dependent preconditioner).
    scene = scenes.bead_wire(80, displacement=0.05)
    lagrangian = scene.lagrangian
    ones = jnp.ones(80)

    def hamiltonian(q, p):
        grad_v = jax.grad(lambda v: lagrangian(0.0, q, v, None))
        mass = jax.jvp(grad_v, (0 * ones,), (ones,))[1]
        return 0.5 * jnp.sum(p**2 / mass) - lagrangian(0.0, q, 0 * ones, None)

    hamilton = dfx.ODETerm(
        lambda t, y, args: (jax.grad(hamiltonian, 1)(*y), -jax.grad(hamiltonian)(*y))
    )
    terms = {"lagrangian": dvi.LagrangianTerm(lagrangian), "hamilton": hamilton}

    def gradient(term):
        def f(q0):
            sol = dfx.diffeqsolve(
                term,
                dfx.Tsit5(),
                0.0,
                scene.period / 4,
                scene.period / 40,
                (q0, scene.y0[1]),
            )
            return sol.ys[0][-1, 40]

        return jax.jit(jax.grad(f))(scene.y0[0])

    generic, exact = gradient(terms["lagrangian"]), gradient(terms["hamilton"])
    assert jnp.max(jnp.abs(generic - exact)) < 1e-12 * jnp.max(jnp.abs(exact))
    assert jnp.max(jnp.abs(exact)) > 1e-2


@pytest.mark.slow  # 30 s of compilation; the guess's derivative is also dropped in
# the inverse Legendre map, which test_lagrangian differentiates.
def test_linearized_krylov_gradient_equals_finite_differences():
    # LinearizedVI's Krylov step is warm-started from the last velocity; the guess
    # must not be differentiated (lineax does not differentiate a solve's options:
    # differentiating it used to raise). Its gradient against central differences.
    n = 24
    y0 = (0.3 * jnp.sin(2.1 * jnp.arange(1.0, n + 1.0)), jnp.zeros(n))
    solver = dvi.LinearizedVI(velocity="centered")

    @jax.jit
    def f(q0):
        return final_state(_Chain(), solver, (q0, y0[1]), 0.5, 0.05)[0][n // 2]

    gradient = jax.jit(jax.grad(f))(y0[0])
    e = 1e-5 * jnp.eye(n)[n // 2]
    central = (f(y0[0] + e) - f(y0[0] - e)) / 2e-5
    assert abs(gradient[n // 2] - central) < 1e-8
    assert abs(central) > 1e-1
