import math

import equinox as eqx
import jax.numpy as jnp

from .._lagrangian import AbstractSeparableLagrangian
from ._scene import Scene


class KeplerLagrangian(AbstractSeparableLagrangian):
    r"""The Kepler problem in the plane, $L = \tfrac12 |v|^2 + 1/|q|$
    (unit masses and gravitational constant)."""

    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        return -1 / jnp.sqrt(jnp.sum(q**2))


def _angular_momentum(t, y, args):
    q, p = y
    return q[0] * p[1] - q[1] * p[0]


def kepler(eccentricity: float = 0.6) -> Scene:
    r"""The Kepler problem started at pericentre with eccentricity `e` (Hairer, Lubich
    and Wanner, *Geometric Numerical Integration*, I.2.3):
    $q_0 = (1 - e, 0)$, $p_0 = (0, \sqrt{(1 + e)/(1 - e)})$. Period $2\pi$; energy
    $-1/2$ and angular momentum $\sqrt{1 - e^2}$ are conserved.
    """
    if not 0 <= eccentricity < 1:
        raise ValueError(
            f"Kepler orbits are bounded for eccentricity in [0, 1); got {eccentricity}."
        )
    e = eccentricity
    q0 = jnp.array([1 - e, 0.0])
    p0 = jnp.array([0.0, math.sqrt((1 + e) / (1 - e))])
    return Scene(
        name="kepler",
        lagrangian=KeplerLagrangian(),
        y0=(q0, p0),
        period=2 * math.pi,
        invariants={"angular_momentum": _angular_momentum},
    )
