import math

import equinox as eqx
import jax.numpy as jnp

from .._lagrangian import AbstractQuadraticLagrangian, AbstractSeparableLagrangian
from ._scene import Scene


class DoublePendulumLagrangian(AbstractQuadraticLagrangian):
    r"""The planar double pendulum with unit masses, lengths and gravity, in the
    absolute angles $q = (\theta_1, \theta_2)$:
    $L = v_1^2 + \tfrac12 v_2^2 + v_1 v_2 \cos(\theta_1 - \theta_2)
    + 2\cos\theta_1 + \cos\theta_2$. Not separable: its mass matrix depends on $q$."""

    def __call__(self, t, q, v, args):
        kinetic = v[0] ** 2 + 0.5 * v[1] ** 2 + v[0] * v[1] * jnp.cos(q[0] - q[1])
        return kinetic + 2 * jnp.cos(q[0]) + jnp.cos(q[1])


class HenonHeilesLagrangian(AbstractSeparableLagrangian):
    r"""The Hénon–Heiles potential,
    $V = \tfrac12(x^2 + y^2) + x^2 y - y^3/3$, unit mass."""

    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        x, y = q[0], q[1]
        return 0.5 * (x**2 + y**2) + x**2 * y - y**3 / 3


def double_pendulum(angle: float = math.pi / 2) -> Scene:
    r"""The double pendulum released from rest with both arms horizontal
    (`angle` = $\pi/2$): chaotic, so nearby trajectories separate exponentially while
    the energy stays bounded. Time scale $2\pi$ (the linear period is about 7.6)."""
    return Scene(
        name="double_pendulum",
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
