import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._adaptive import PotentialMonitor
from .._lagrangian import AbstractSeparableLagrangian
from ._scene import Scene


# Hairer, Lubich and Wanner, Geometric Numerical Integration, Table I.2.2: the Sun
# (with the inner planets' masses), Jupiter, Saturn, Uranus, Neptune, Pluto on
# 5 September 1994. Masses relative to the Sun, positions in AU, velocities in AU/day.
GRAVITATIONAL_CONSTANT = 2.95912208286e-4
BODIES = ("Sun", "Jupiter", "Saturn", "Uranus", "Neptune", "Pluto")
MASSES = np.array(
    [
        1.00000597682,
        0.000954786104043,
        0.000285583733151,
        0.0000437273164546,
        0.0000517759138449,
        1 / 1.3e8,
    ]
)
POSITIONS = np.array(
    [
        [0.0, 0.0, 0.0],
        [-3.5023653, -3.8169847, -1.5507963],
        [9.0755314, -3.0458353, -1.6483708],
        [8.3101420, -16.2901086, -7.2521278],
        [11.4707666, -25.7294829, -10.8169456],
        [-15.5387357, -25.2225594, -3.1902382],
    ]
)
VELOCITIES = np.array(
    [
        [0.0, 0.0, 0.0],
        [0.00565429, -0.00412490, -0.00190589],
        [0.00168318, 0.00483525, 0.00192462],
        [0.00354178, 0.00137102, 0.00055029],
        [0.00288930, 0.00114527, 0.00039677],
        [0.00276725, -0.00170702, -0.00136504],
    ]
)
JUPITER_PERIOD = 4332.59  # days


class NBodyLagrangian(AbstractSeparableLagrangian):
    r"""Newtonian gravity, $L = \sum_i \tfrac12 m_i |v_i|^2
    + G \sum_{i<j} m_i m_j / |q_i - q_j|$, with `q` of shape `(bodies, 3)`."""

    mass: Float[Array, "bodies 1"] = eqx.field(converter=jnp.asarray)
    gravitational_constant: Float[Array, ""] = eqx.field(converter=jnp.asarray)

    def potential(self, t, q, args):
        # Every pair by broadcasting, the pairs i < j kept by a fixed mask: taking
        # them by index arrays would differentiate to a scatter, which keeps XLA
        # on CPU from compiling the loop whole (`diagnostics.loop_breakers`).
        m = self.mass[:, 0]
        pairs = np.triu(np.ones((q.shape[0],) * 2, bool), 1)
        squared = jnp.sum((q[:, None] - q[None]) ** 2, axis=-1)
        distance = jnp.sqrt(jnp.where(pairs, squared, 1.0))
        terms = jnp.where(pairs, m[:, None] * m[None] / distance, 0.0)
        return -self.gravitational_constant * jnp.sum(terms)


def _linear_momentum(t, y, args):
    return jnp.sum(y[1], axis=0)


def _angular_momentum(t, y, args):
    return jnp.sum(jnp.cross(y[0], y[1]), axis=0)


def outer_solar_system() -> Scene:
    """The Sun and the five outer planets with Hairer–Lubich–Wanner's initial data
    (*Geometric Numerical Integration*, I.2.4): time in days, the time scale is
    Jupiter's period (4332.59 days). Conserves energy (-3.2e-8 in these
    units, so absolute errors are small numbers), total linear momentum and total
    angular momentum (vectors of size about 1e-5; the study reports the largest
    component error)."""
    mass = jnp.asarray(MASSES[:, None])
    lagrangian = NBodyLagrangian(mass, GRAVITATIONAL_CONSTANT)
    return Scene(
        name="outer_solar_system",
        lagrangian=lagrangian,
        y0=(jnp.asarray(POSITIONS), mass * jnp.asarray(VELOCITIES)),
        period=JUPITER_PERIOD,
        invariants={
            "linear_momentum": _linear_momentum,
            "angular_momentum": _angular_momentum,
        },
        monitor=PotentialMonitor(lagrangian),
    )
