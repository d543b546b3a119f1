"""The rotation group SO(2), as a configuration space."""

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._so3 import matmul, rotation_departure
from ._space import AbstractSpace


def _rot2(x: Array) -> Float[Array, "2 2"]:
    c, s = jnp.cos(x), jnp.sin(x)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


class SO2(AbstractSpace):
    r"""The rotation group SO(2): a planar angle kept as a rotation matrix.

    The position is a `(2, 2)` rotation matrix, the velocity the angular velocity
    $\omega$ (a scalar) with $\dot R = R\,\omega J$, $J$ the quarter turn. The group is
    abelian, so `pull`, `transport` and `coadjoint` are trivial and a solver on SO(2)
    steps the angle form of the same Lagrangian, to round-off.
    """

    def retract(self, q, x):
        return matmul(q, _rot2(x))

    def difference(self, q0, q1):
        r = matmul(q0.T, q1)
        return jnp.arctan2(r[1, 0], r[0, 0])

    def tangent(self, q):
        return jnp.zeros((), q.dtype)

    def velocity(self, q, xi):
        return matmul(q, xi * jnp.array([[0.0, -1.0], [1.0, 0.0]], q.dtype))

    def pull(self, x, w):
        return w

    def transport(self, x, w):
        return w

    def coadjoint(self, xi, mu):
        return jnp.zeros_like(mu)

    def departure(self, q):
        return rotation_departure(q)
