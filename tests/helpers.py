"""Shared test Lagrangians, independent references and comparisons."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jax.random as jr
import jax.tree_util as jtu
import numpy as np
import scipy.integrate


def untrained_learned_scene():
    """A context in which `scenes.learned()` builds its network untrained: training
    it compiles for half a minute per process, and the tests that take every scene
    read its structure (the compiled loop, the methods it gets, the checks a
    command makes), not its weights. Its training is tested in
    tests/test_scenes.py."""
    from unittest import mock

    from diffrax_vi.scenes import _learned

    untrained = lambda seed, max_steps: dvi.scenes.LearnedLagrangian(jr.key(seed))
    return mock.patch.object(_learned, "_trained", untrained)


def scene(name: str) -> dvi.scenes.Scene:
    """`scenes.SCENES[name]()`, the learned scene untrained
    (`untrained_learned_scene`)."""
    with untrained_learned_scene():
        return dvi.scenes.SCENES[name]()


class Pendulum(dvi.AbstractSeparableLagrangian):
    """L = v^2/2 + g cos q (unit length and mass)."""

    g: float | jax.Array = 1.0
    mass: float = 1.0

    def potential(self, t, q, args):
        return -self.g * jnp.cos(q)


class Duffing(dvi.AbstractSeparableLagrangian):
    """The seed's unforced undamped Duffing oscillator, L = v^2/2 + q^2/2 - q^4/4."""

    mass: float = 1.0

    def potential(self, t, q, args):
        return -0.5 * q**2 + 0.25 * q**4


class DoublePendulum(dvi.AbstractQuadraticLagrangian):
    """Unit masses and lengths: quadratic in v with a configuration-dependent mass."""

    g: float = 1.0

    def __call__(self, t, q, v, args):
        q1, q2 = q[0], q[1]
        v1, v2 = v[0], v[1]
        kinetic = v1**2 + 0.5 * v2**2 + v1 * v2 * jnp.cos(q1 - q2)
        potential = -2 * self.g * jnp.cos(q1) - self.g * jnp.cos(q2)
        return kinetic - potential


def stiffening(t, q, v, args):
    """A 2-DOF Lagrangian that is not quadratic in v (kinetic energy stiffening with
    speed, p = v (1 + |v|^2/3)) in an anharmonic coupled well. A plain function, to
    exercise `Lagrangian(fn)` and Newton's inverse Legendre map."""
    v2 = jnp.sum(v**2)
    return 0.5 * v2 + v2**2 / 12 - 0.5 * jnp.sum(q**2) - 0.1 * q[0] ** 2 * q[1]


def stiffening_velocity(p):
    """Closed-form inverse Legendre map of `stiffening`: |v| = s solves
    s^3 + 3 s - 3 |p| = 0 (Cardano)."""
    a = 1.5 * jnp.sqrt(jnp.sum(p**2))
    root = jnp.sqrt(a**2 + 1)
    s = jnp.cbrt(a + root) + jnp.cbrt(a - root)
    return p * s / (2 * a / 3)


def central(t, q, v, args):
    """A central-force Lagrangian (rotation invariant), written in general form."""
    r = jnp.sqrt(jnp.sum(q**2))
    return 0.5 * jnp.sum(v**2) + 1 / r - 0.05 / r**2


def kepler_state(e=0.6):
    q0 = jnp.array([1 - e, 0.0])
    p0 = jnp.array([0.0, np.sqrt((1 + e) / (1 - e))])
    return q0, p0


KEPLER = dvi.SeparableLagrangian(lambda t, q, args: -1 / jnp.sqrt(jnp.sum(q**2)))


def reference(lagrangian, y0, t1, t0=0.0, args=None):
    """The state at `t1` from scipy's DOP853 at rtol 1e-13 on Hamilton's equations
    of a Lagrangian, or of a `LagrangianTerm` with its force and constraint."""
    term = (
        lagrangian
        if isinstance(lagrangian, dvi.LagrangianTerm)
        else dvi.LagrangianTerm(lagrangian)
    )
    flat, unravel = jax.flatten_util.ravel_pytree(y0)
    rhs = jax.jit(
        lambda t, x: jax.flatten_util.ravel_pytree(term.vf(t, unravel(x), args))[0]
    )
    sol = scipy.integrate.solve_ivp(
        # t as one type: scipy passes a float first and np.float64 after, which
        # jit would compile for twice (a weak type and a strong one).
        lambda t, x: np.asarray(rhs(np.float64(t), jnp.asarray(x))),
        (t0, t1),
        np.asarray(flat),
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    assert sol.success
    return unravel(jnp.asarray(sol.y[:, -1]))


def solve(lagrangian, solver, y0, t1, n, t0=0.0, **kwargs):
    term = dvi.LagrangianTerm(lagrangian)
    kwargs.setdefault("max_steps", n + 1)
    return dfx.diffeqsolve(term, solver, t0, t1, (t1 - t0) / n, y0, **kwargs)


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    return eqx.tree_equal(x, y, typematch=True, rtol=rtol, atol=atol)


def max_abs_diff(x, y):
    return max(
        float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))
        for a, b in zip(jtu.tree_leaves(x), jtu.tree_leaves(y))
    )


def fitted_order(hs, errors):
    """Slope of the least-squares line through (log h, log error)."""
    return float(np.polyfit(np.log(np.asarray(hs)), np.log(np.asarray(errors)), 1)[0])


# Every solver of the package, for tests that must hold for all of them.
ALL_SOLVERS = [
    ("MidpointVI", dvi.MidpointVI()),
    ("TrapezoidalVI", dvi.TrapezoidalVI()),
    ("StormerVerlet", dvi.StormerVerlet()),
    ("GaussVPRK(2)", dvi.GaussVPRK(2)),
    ("LobattoVPRK(3)", dvi.LobattoVPRK(3)),
    ("yoshida4(StormerVerlet)", dvi.Composition(dvi.StormerVerlet(), "yoshida4")),
    ("yoshida4(MidpointVI)", dvi.Composition(dvi.MidpointVI(), "yoshida4")),
    ("LinearizedVI", dvi.LinearizedVI()),
    ("LinearizedVI(centered)", dvi.LinearizedVI(velocity="centered")),
]


@eqx.filter_jit
def final_state(lagrangian, solver, y0, t1, dt0):
    """The state at `t1` of a fixed-step solve from `t0 = 0` (one compilation per
    solver and Lagrangian)."""
    sol = dfx.diffeqsolve(
        dvi.terms_for(solver, lagrangian), solver, 0.0, t1, dt0, y0, max_steps=1024
    )
    return jax.tree.map(lambda x: x[-1], sol.ys)
