import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lagrangian import AbstractQuadraticLagrangian, AbstractSeparableLagrangian
from ._one_dof import parameter
from ._scene import entries, GENERAL_SOLVERS, Scene


class DoublePendulumLagrangian(AbstractQuadraticLagrangian):
    r"""The planar double pendulum (point masses $m_1, m_2$ on massless rods of
    lengths $\ell_1, \ell_2$, gravity $g$; all 1 by default) in the absolute angles
    $q = (\theta_1, \theta_2)$:

    $$L = \tfrac12 (m_1 + m_2)\ell_1^2 v_1^2 + \tfrac12 m_2 \ell_2^2 v_2^2
    + m_2 \ell_1 \ell_2 v_1 v_2 \cos(\theta_1 - \theta_2)
    + (m_1 + m_2) g \ell_1 \cos\theta_1 + m_2 g \ell_2 \cos\theta_2.$$

    Not separable: its mass matrix depends on $q$."""

    m1: Float[Array, ""] = parameter(1.0)
    m2: Float[Array, ""] = parameter(1.0)
    l1: Float[Array, ""] = parameter(1.0)
    l2: Float[Array, ""] = parameter(1.0)
    g: Float[Array, ""] = parameter(1.0)

    def __call__(self, t, q, v, args):
        # In whole vectors where the terms allow (see `scenes._scene.entries`).
        (q1, q2), (v1, v2) = entries(q), entries(v)
        m12 = self.m1 + self.m2
        inertia = jnp.stack([m12 * self.l1**2, self.m2 * self.l2**2])
        coupling = self.m2 * self.l1 * self.l2 * v1 * v2 * jnp.cos(q1 - q2)
        moments = jnp.stack([m12 * self.l1, self.m2 * self.l2])
        potential = -self.g * jnp.sum(moments * jnp.cos(q))
        return 0.5 * jnp.sum(inertia * v**2) + coupling - potential


class HenonHeilesLagrangian(AbstractSeparableLagrangian):
    r"""The Hénon–Heiles potential,
    $V = \tfrac12(x^2 + y^2) + \lambda(x^2 y - y^3/3)$, with coupling $\lambda = 1$
    and unit mass by default."""

    coupling: Float[Array, ""] = parameter(1.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        x, y = q[0], q[1]
        return 0.5 * (x**2 + y**2) + self.coupling * (x**2 * y - y**3 / 3)


def double_pendulum(angle: float = math.pi / 2) -> Scene:
    r"""The double pendulum released from rest with both arms horizontal
    (`angle` = $\pi/2$): chaotic, so nearby trajectories separate exponentially while
    the energy stays bounded. Time scale $2\pi$ (the linear period is about 7.6)."""
    return Scene(
        name="double_pendulum",
        solvers=GENERAL_SOLVERS,
        lagrangian=DoublePendulumLagrangian(),
        y0=(jnp.array([angle, angle]), jnp.zeros(2)),
        period=2 * math.pi,
    )


def henon_heiles() -> Scene:
    r"""Hénon–Heiles from $q_0 = (0.1, 0)$, $p_0 = (0, 0.5)$, energy 0.13: bounded
    (below the escape energy 1/6) and chaotic. Time scale $2\pi$."""
    return Scene(
        name="henon_heiles",
        lagrangian=HenonHeilesLagrangian(),
        y0=(jnp.array([0.1, 0.0]), jnp.array([0.0, 0.5])),
        period=2 * math.pi,
    )
