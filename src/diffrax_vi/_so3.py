"""The rotation group SO(3), as a configuration space."""

import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Float

from ._space import AbstractSpace


def hat(omega: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    r"""$\hat\omega$, the skew matrix with $\hat\omega u = \omega \times u$."""
    x, y, z = omega[0], omega[1], omega[2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y]),
            jnp.stack([z, zero, -x]),
            jnp.stack([-y, x, zero]),
        ]
    )


def vee(skew: Float[Array, "3 3"]) -> Float[Array, " 3"]:
    """The vector of a skew matrix (of its skew part), the inverse of `hat`."""
    return 0.5 * jnp.stack(
        [skew[2, 1] - skew[1, 2], skew[0, 2] - skew[2, 0], skew[1, 0] - skew[0, 1]]
    )


def _exp3(x: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    return jaxlie.SO3.exp(x).as_matrix()


class SO3(AbstractSpace):
    r"""The rotation group SO(3): attitudes of a rigid body.

    The position is a rotation matrix `R` of shape `(3, 3)`, the velocity the body
    angular velocity $\Omega$ (shape `(3,)`) with $\dot R = R\hat\Omega$, the momentum
    the body angular momentum $\Pi = \partial L/\partial\Omega$. A step moves
    $R \mapsto R\exp(\hat x)$ (jaxlie's exponential), so `R` stays a rotation to
    round-off. $\mathrm{Ad}_R = R$ and $\mathrm{ad}^*_\Omega\Pi = \Pi \times \Omega$.
    """

    def retract(self, q, x):
        return q @ _exp3(x)

    def difference(self, q0, q1):
        return jaxlie.SO3.from_matrix(q0.T @ q1).log()

    def tangent(self, q):
        return jnp.zeros(q.shape[:-1], q.dtype)

    def velocity(self, q, xi):
        return q @ hat(xi)

    def pull(self, x, w):
        # d tau^R_x is the left Jacobian J(x) = I + a x^ + b x^2 of SO(3)
        # (D exp(x)[y] exp(x)^T = hat(J(x) y)), and J(x)^T = J(-x). Below |x| = 1e-2
        # the series, whose next terms are below 1e-17; 1 - cos t as 2 sin^2(t/2)
        # so that nothing cancels above.
        t2 = jnp.sum(x**2)
        small = t2 < 1e-4
        safe = jnp.where(small, jnp.ones_like(t2), t2)
        t = jnp.sqrt(safe)
        a = jnp.where(
            small, 0.5 - t2 / 24 + t2**2 / 720, 2 * jnp.sin(0.5 * t) ** 2 / safe
        )
        b = jnp.where(
            small, 1 / 6 - t2 / 120 + t2**2 / 5040, (t - jnp.sin(t)) / (safe * t)
        )
        xw = jnp.cross(x, w)
        return w - a * xw + b * jnp.cross(x, xw)

    def transport(self, x, w):
        return _exp3(x).T @ w

    def coadjoint(self, xi, mu):
        return jnp.cross(mu, xi)
