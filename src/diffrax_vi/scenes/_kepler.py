import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._adaptive import PotentialMonitor
from .._lagrangian import AbstractSeparableLagrangian
from ._one_dof import parameter
from ._scene import Scene


class KeplerLagrangian(AbstractSeparableLagrangian):
    r"""The Kepler problem in the plane, $L = \tfrac12 m|v|^2 + \mu m/|q|$, with
    gravitational parameter $\mu = 1$ and unit mass by default."""

    mu: Float[Array, ""] = parameter(1.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        return -self.mu * self.mass / jnp.sqrt(jnp.sum(q**2))


def _angular_momentum(t, y, args):
    q, p = y
    return q[0] * p[1] - q[1] * p[0]


def kepler(eccentricity: float = 0.6) -> Scene:
    r"""The Kepler problem started at pericentre with eccentricity `e` (Hairer, Lubich
    and Wanner, *Geometric Numerical Integration*, I.2.3):
    $q_0 = (1 - e, 0)$, $p_0 = (0, \sqrt{(1 + e)/(1 - e)})$. Semi-major axis 1, period
    $2\pi$; energy $-1/2$ and angular momentum $\sqrt{1 - e^2}$ are conserved. The
    exact solution solves Kepler's equation $E - e\sin E = t$ by Newton's method.
    Its monitor, for reversible adaptive steps, is [`diffrax_vi.PotentialMonitor`][]
    ($s \propto r^{3/2}$); adaptivity pays from about $e = 0.9$ (see
    [Adaptive steps](../adaptive.md)).
    """
    if not 0 <= eccentricity < 1:
        raise ValueError(
            f"Kepler orbits are bounded for eccentricity in [0, 1); got {eccentricity}."
        )
    e = eccentricity
    b = math.sqrt(1 - e**2)

    def exact(t):
        mean = jnp.mod(t, 2 * math.pi)
        anomaly = jax.lax.fori_loop(
            0,
            60,
            lambda _, x: x - (x - e * jnp.sin(x) - mean) / (1 - e * jnp.cos(x)),
            mean + e * jnp.sin(mean),
        )
        rate = 1 / (1 - e * jnp.cos(anomaly))
        q = jnp.stack([jnp.cos(anomaly) - e, b * jnp.sin(anomaly)], axis=-1)
        p = jnp.stack([-jnp.sin(anomaly) * rate, b * jnp.cos(anomaly) * rate], axis=-1)
        return q, p

    lagrangian = KeplerLagrangian()
    return Scene(
        name="kepler",
        lagrangian=lagrangian,
        y0=(jnp.array([1 - e, 0.0]), jnp.array([0.0, math.sqrt((1 + e) / (1 - e))])),
        period=2 * math.pi,
        invariants={"angular_momentum": _angular_momentum},
        exact=exact,
        monitor=PotentialMonitor(lagrangian),
    )
