import jax.numpy as jnp
import numpy as np

from .._adaptive import PotentialMonitor
from ._scene import Scene
from ._solar import NBodyLagrangian


# Burrau (1913); Szebehely & Peters (1967), Astron. J. 72, 876: masses 3, 4, 5 at rest
# on the vertices of a 3-4-5 right triangle, opposite the sides of their length.
MASSES = np.array([3.0, 4.0, 5.0])
POSITIONS = np.array([[1.0, 3.0], [-2.0, -1.0], [1.0, -1.0]])


def _linear_momentum(t, y, args):
    return jnp.sum(y[1], axis=0)


def _angular_momentum(t, y, args):
    q, p = y
    return jnp.sum(q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0])


def pythagorean_three_body() -> Scene:
    r"""Burrau's Pythagorean three-body problem (Szebehely & Peters 1967): masses 3, 4
    and 5 start at rest at $(1, 3)$, $(-2, -1)$ and $(1, -1)$, with $G = 1$. The
    motion is a sequence of close encounters (distances 0.0097 at $t = 1.879$,
    0.0085 at $t = 8.760$, 0.00041 at $t = 15.830$, measured with scipy's DOP853 at
    rtol $10^{-13}$) that ends with a binary and an escaping third body: a step that
    resolves the closest encounter is far smaller than the motion needs elsewhere.
    Energy $-769/60$, linear and angular momentum (zero) are conserved. The time
    scale ("period") is 10. Its monitor is [`diffrax_vi.PotentialMonitor`][]: the
    step follows the closest pair's free-fall time. The motion is chaotic: a
    reference trajectory is meaningful over a few encounters, the conserved
    quantities over any horizon.
    """
    mass = jnp.asarray(MASSES[:, None])
    lagrangian = NBodyLagrangian(mass, 1.0)
    return Scene(
        name="pythagorean_three_body",
        lagrangian=lagrangian,
        y0=(jnp.asarray(POSITIONS), jnp.zeros((3, 2))),
        period=10.0,
        invariants={
            "linear_momentum": _linear_momentum,
            "angular_momentum": _angular_momentum,
        },
        monitor=PotentialMonitor(lagrangian),
    )
