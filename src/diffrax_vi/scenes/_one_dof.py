import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lagrangian import AbstractSeparableLagrangian
from ._scene import agm, check_positive, Scene


def parameter(default: float):
    """A numeric parameter of a scene: an array leaf, so that `jax.grad` reaches it,
    `jax.vmap` can batch it and a dtype cast converts it."""
    return eqx.field(converter=jnp.asarray, default=default)


class FallingParticleLagrangian(AbstractSeparableLagrangian):
    r"""A particle of mass $m$ in uniform gravity, $L = \tfrac12 m v^2 - m g q$."""

    g: Float[Array, ""] = parameter(9.81)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        return self.mass * self.g * q


class OscillatorLagrangian(AbstractSeparableLagrangian):
    r"""The harmonic oscillator,
    $L = \tfrac12 m v^2 - \tfrac12 m \omega^2 q^2$."""

    omega: Float[Array, ""] = parameter(1.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        return 0.5 * self.mass * self.omega**2 * q**2


class DuffingLagrangian(AbstractSeparableLagrangian):
    r"""The unforced, undamped Duffing oscillator of Hirani (2000), §5.3,
    $L = \tfrac12 m v^2 + \tfrac12 \alpha q^2 - \tfrac14 \beta q^4$ (all 1 there): a
    double well with minima at $q = \pm\sqrt{\alpha/\beta}$."""

    alpha: Float[Array, ""] = parameter(1.0)
    beta: Float[Array, ""] = parameter(1.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        return -0.5 * self.alpha * q**2 + 0.25 * self.beta * q**4


class PendulumLagrangian(AbstractSeparableLagrangian):
    r"""The plane pendulum of unit length, $L = m(\tfrac12 v^2 + g\cos q)$ (unit
    mass and gravity by default)."""

    g: Float[Array, ""] = parameter(1.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        return -self.mass * self.g * jnp.cos(q)


def falling_particle(g: float = 9.81) -> Scene:
    r"""A particle thrown upwards in uniform gravity from $q_0 = 2$, $p_0 = 3$ (the
    example of Hirani (2000), §5.1). The exact solution $q_0 + p_0 t - g t^2/2$ is
    quadratic in $t$, so both the DEL equations and their linearization reproduce it
    up to round-off. Time scale 1."""
    q0, p0 = 2.0, 3.0

    def exact(t):
        return q0 + p0 * t - 0.5 * g * t**2, p0 - g * t

    return Scene(
        name="falling_particle",
        lagrangian=FallingParticleLagrangian(g),
        y0=(jnp.array(q0), jnp.array(p0)),
        period=1.0,
        exact=exact,
    )


def oscillator(omega: float = 1.0) -> Scene:
    r"""The harmonic oscillator from $q_0 = 1$, $p_0 = 0$: exact solution
    $q = \cos \omega t$, $p = -\omega \sin \omega t$; period $2\pi/\omega$."""
    check_positive("oscillator", omega=omega)

    def exact(t):
        return jnp.cos(omega * t), -omega * jnp.sin(omega * t)

    return Scene(
        name="oscillator",
        lagrangian=OscillatorLagrangian(omega),
        y0=(jnp.array(1.0), jnp.array(0.0)),
        period=2 * math.pi / omega,
        exact=exact,
    )


def duffing(q0: float = 0.5) -> Scene:
    r"""The Duffing oscillator of Hirani (2000), §5.3, from rest at $q_0$ (default
    0.5, inside the right-hand well). The motion is periodic between the roots
    $q_\pm^2 = 1 \pm \sqrt{1 + 4E}$ of $V(q) = E$, with period
    $\sqrt2\,\pi / \operatorname{agm}(q_+, q_-)$ (a complete elliptic integral)."""
    e = -0.5 * q0**2 + 0.25 * q0**4
    if not -0.25 < e < 0:
        raise ValueError(
            f"duffing(q0) needs 0 < |q0| < sqrt(2), q0 != 1, for a periodic orbit in "
            f"one well; got q0={q0}."
        )
    root = math.sqrt(1 + 4 * e)
    period = math.sqrt(2) * math.pi / agm(math.sqrt(1 + root), math.sqrt(1 - root))
    return Scene(
        name="duffing",
        lagrangian=DuffingLagrangian(),
        y0=(jnp.array(q0), jnp.array(0.0)),
        period=period,
    )


def pendulum(amplitude: float = 2.0) -> Scene:
    r"""The pendulum released from rest at angle `amplitude` (default 2 rad, far from
    the linear regime), with period $2\pi / \operatorname{agm}(1, \cos(q_0/2))$."""
    if not 0 < amplitude < math.pi:
        raise ValueError(
            f"pendulum(amplitude) needs 0 < amplitude < pi; got {amplitude}."
        )
    return Scene(
        name="pendulum",
        lagrangian=PendulumLagrangian(),
        y0=(jnp.array(amplitude), jnp.array(0.0)),
        period=2 * math.pi / agm(1.0, math.cos(amplitude / 2)),
    )
