"""The rotation group SO(3), as a configuration space."""

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._space import AbstractSpace


def hat(omega: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    r"""$\hat\omega$, the skew matrix with $\hat\omega u = \omega \times u$ (of each
    vector of a stack)."""
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def vee(skew: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """The vector of a skew matrix (of its skew part), the inverse of `hat`."""
    return 0.5 * jnp.stack(
        [
            skew[..., 2, 1] - skew[..., 1, 2],
            skew[..., 0, 2] - skew[..., 2, 0],
            skew[..., 1, 0] - skew[..., 0, 1],
        ],
        axis=-1,
    )


def cross(a: Float[Array, "*batch 3"], b: Float[Array, "*batch 3"]) -> Array:
    """`a x b` (of each pair of a stack). For one pair, `hat(a) b`: `jnp.cross`
    slices its arguments and concatenates the products, which a step's
    reverse-mode derivatives of the Lagrangian transpose into pads, and one rigid
    body's `MidpointVI` and `TrapezoidalVI` steps took 1.6 against 1.1 us
    (`benchmarks/lie_groups.py`). For a stack, `jnp.cross`: as `hat(a) b`, the
    products of a 16-link chain's Newton matrix became YNNPACK reductions, which
    break its loop into more kernels, and its step took 3338 against 2433 us
    (`benchmarks/multibody.py`)."""
    if a.ndim > 1:
        return jnp.cross(a, b)
    return matvec(hat(a), b)


def matmul(
    a: Float[Array, "*batch n k"], b: Float[Array, "*batch k m"]
) -> Float[Array, "*batch n m"]:
    """`a @ b` (of each pair of a stack) as elementwise products and a sum: a
    `dot_general` of small matrices can become a custom fusion that keeps XLA from
    compiling a loop whole (`diagnostics.loop_breakers`)."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def matvec(a: Float[Array, "*batch 3 3"], x: Float[Array, "*batch 3"]) -> Array:
    """`a @ x`, written out as `matmul` is."""
    return jnp.sum(a * x[..., None, :], axis=-1)


def rmatvec(a: Float[Array, "*batch 3 3"], x: Float[Array, "*batch 3"]) -> Array:
    """`a.T @ x`, written out as `matmul` is."""
    return jnp.sum(a * x[..., :, None], axis=-2)


def transpose(a: Float[Array, "*batch n m"]) -> Float[Array, "*batch m n"]:
    return jnp.swapaxes(a, -1, -2)


def rotation_departure(R: Float[Array, "*batch n n"]) -> Float[Array, ""]:
    r"""How far `R` (or the farthest matrix of a stack) is from a rotation, a pure
    number: the largest entry of $|R^\top R - I|$, or at least 2 for a reflection
    ($\det R < 0$), which no rotation is near."""
    eye = jnp.broadcast_to(jnp.eye(R.shape[-1], dtype=R.dtype), R.shape)
    off = jnp.max(jnp.abs(matmul(transpose(R), R) - eye), axis=(-2, -1))
    if R.shape[-2:] == (2, 2):
        det = R[..., 0, 0] * R[..., 1, 1] - R[..., 0, 1] * R[..., 1, 0]
    else:
        det = jnp.sum(R[..., 0, :] * cross(R[..., 1, :], R[..., 2, :]), axis=-1)
    return jnp.max(jnp.where(det < 0, jnp.maximum(off, 2.0), off))


@jax.custom_jvp
def _exp_coefficients(x: Float[Array, "*batch 3"]) -> tuple[Array, Array, Array]:
    r"""$(\sin t/t,\ (1 - \cos t)/t^2,\ (t - \sin t)/t^3)$ at $t = |x|$, shape
    `batch`, from one sine and one cosine of $t/2$; below $|x| = 10^{-2}$ their
    series, whose next terms are below $10^{-17}$; $1 - \cos t$ as $2\sin^2(t/2)$,
    so that nothing cancels above. Unbroadcast: with a trailing axis of one, XLA
    fused their derivatives into the Newton matrix's 3x3x3 loops, and a single
    body's step took 9-12% longer.

    Each coefficient and each derivative (`_exp_coefficients_jvp`) is one quotient,
    the series in its numerator over a denominator that is one (or two, the series
    doubled: the same bits) below the threshold: XLA computes a quotient once and
    reads it, where it copied a polynomial into every fused loop that read it (the
    four of a Newton matrix's cofactor solve). The free body's `MidpointVI` step
    took 0.286-0.290 against 0.321-0.323 us, its Newton loop 550 against 754
    instructions (`benchmarks/lie_groups.py`)."""
    t2 = jnp.sum(x**2, axis=-1)
    small = t2 < 1e-4
    safe = jnp.where(small, jnp.ones_like(t2), t2)
    t = jnp.sqrt(safe)
    s, c = jnp.sin(0.5 * t), jnp.cos(0.5 * t)
    sin_t = 2 * s * c
    return (
        jnp.where(small, 1 - t2 / 6 + t2**2 / 120, sin_t) / t,
        jnp.where(small, 0.5 - t2 / 24 + t2**2 / 720, 2 * s**2) / safe,
        jnp.where(small, 1 / 6 - t2 / 120 + t2**2 / 5040, t - sin_t) / (safe * t),
    )


def _series_slope(s: Array, m: int) -> Array:
    # d/ds of sum_k (-1)^k s^k / (2k + m)!, the coefficient c_m in s = t^2, to s^6:
    # below s = 1/4 the next term is below 1e-17 of the first.
    slope = jnp.zeros_like(s)
    for k in range(7, 0, -1):
        slope = slope * s + (-1) ** k * k / math.factorial(2 * k + m)
    return slope


@_exp_coefficients.defjvp
def _exp_coefficients_jvp(primals, tangents):
    r"""Their derivatives in $s = t^2$ from the coefficients themselves, with no
    second sine and cosine and no derivative of both sides of each `where`:
    $c_1' = (\cos t - c_1)/2s$, $c_2' = (c_1/2 - c_2)/s$, $c_3' = (c_2 - 3c_3)/2s$,
    below $s = 1/4$ (where they cancel) their series. A step's Newton matrix takes
    these derivatives: by autodiff of the coefficients, which also cancelled (a
    relative error of $5 \times 10^{-7}$ just above $|x| = 10^{-2}$), the free
    body's and the heavy top's `MidpointVI` steps took a fifth longer
    (`benchmarks/lie_groups.py`)."""
    (x,), (dx,) = primals, tangents
    c1, c2, c3 = _exp_coefficients(x)
    t2 = jnp.sum(x**2, axis=-1)
    dt2 = 2 * jnp.sum(x * dx, axis=-1)
    small = t2 < 0.25
    safe = jnp.where(small, jnp.ones_like(t2), t2)
    twice = 2 * safe
    slopes = (
        jnp.where(small, twice * _series_slope(t2, 1), 1 - t2 * c2 - c1) / twice,
        jnp.where(small, _series_slope(t2, 2), c1 / 2 - c2) / safe,
        jnp.where(small, twice * _series_slope(t2, 3), c2 - 3 * c3) / twice,
    )
    return (c1, c2, c3), tuple(d * dt2 for d in slopes)


def _rodrigues(x: Float[Array, "*batch 3"], coefficients) -> Array:
    # exp(x) = I + (sin t/t) x^ + ((1 - cos t)/t^2) x^2.
    sin_c, cos_c, _ = coefficients
    x_hat = hat(x)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), x_hat.shape)
    return (
        eye
        + sin_c[..., None, None] * x_hat
        + cos_c[..., None, None] * matmul(x_hat, x_hat)
    )


def _right_jacobian(x: Float[Array, "*batch 3"], w, coefficients) -> Array:
    # J(x)^T w = J(-x) w for the left Jacobian J(x) = I + a x^ + b x^2 of SO(3),
    # D exp(x)[y] exp(x)^T = hat(J(x) y).
    _, a, b = coefficients
    xw = cross(x, w)
    return w - a[..., None] * xw + b[..., None] * cross(x, xw)


# The exponential and its derivative in closed form (Rodrigues' formula; jaxlie's
# goes through a quaternion, whose derivatives autodiff then takes). A step's Newton
# matrix differentiates the derivative again, and the closed form shares one sine
# and cosine with it (`benchmarks/multibody.py`, `benchmarks/lie_groups.py`; the
# figures against jaxlie's are in the CHANGELOG).
@jax.custom_jvp
def _exp(x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    return _rodrigues(x, _exp_coefficients(x))


@_exp.defjvp
def _exp_jvp(primals, tangents):
    # D exp(x)[y] = exp(x) hat(J(x)^T y).
    (x,), (y,) = primals, tangents
    coefficients = _exp_coefficients(x)
    e = _rodrigues(x, coefficients)
    return e, matmul(e, hat(_right_jacobian(x, y, coefficients)))


def _log(F: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    # Imported where a difference of attitudes is first traced, not with the
    # package: jaxlie imports jax_dataclasses, which imports flax where it is
    # installed, which nearly doubled the time of `import diffrax_vi` (the CHANGELOG
    # has the figures).
    import jaxlie

    return jaxlie.SO3.from_matrix(F).log()


def _exp_pull(
    x: Float[Array, "*batch 3"], w: Float[Array, "*batch 3"]
) -> Float[Array, "*batch 3"]:
    # d tau^R_x is the left Jacobian J(x), whose transpose is taken here.
    return _right_jacobian(x, w, _exp_coefficients(x))


def _exp_transport(
    x: Float[Array, "*batch 3"], w: Float[Array, "*batch 3"]
) -> Float[Array, "*batch 3"]:
    return rmatvec(_exp(x), w)


def cayley(x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    r"""$\tau(x) = (I - \hat x/2)^{-1}(I + \hat x/2) = I + \frac{4}{4 + |x|^2}
    (\hat x + \tfrac12\hat x^2)$, the Cayley map, rational in $x$."""
    c = (4 / (4 + jnp.sum(x**2, axis=-1)))[..., None, None]
    x_hat = hat(x)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), x_hat.shape)
    return eye + c * (x_hat + 0.5 * matmul(x_hat, x_hat))


def _cayley_log(F: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    # tau^{-1}(F) = 2 vee(F - F^T) / (1 + tr F), with `vee` of the skew part.
    trace = F[..., 0, 0] + F[..., 1, 1] + F[..., 2, 2]
    return 4 * vee(F) / (1 + trace)[..., None]


def _cayley_pull(
    x: Float[Array, "*batch 3"], w: Float[Array, "*batch 3"]
) -> Float[Array, "*batch 3"]:
    # d tau^R_x y = (I - x^/2)^{-1} y^ (I + x^/2)^{-1} = hat(4 (I + x^/2) y /
    # (4 + |x|^2)), whose transpose is taken here.
    c = 4 / (4 + jnp.sum(x**2, axis=-1, keepdims=True))
    return c * (w - 0.5 * cross(x, w))


def _cayley_transport(
    x: Float[Array, "*batch 3"], w: Float[Array, "*batch 3"]
) -> Float[Array, "*batch 3"]:
    # tau(x)^T w, with hat(x)^T = -hat(x).
    xw = cross(x, w)
    c = 4 / (4 + jnp.sum(x**2, axis=-1, keepdims=True))
    return w + c * (0.5 * cross(x, xw) - xw)


# Each retraction: (tau, its inverse near the identity, (d tau^R_x)^T, Ad*_tau(x)).
_RETRACTIONS = {
    "exp": (_exp, _log, _exp_pull, _exp_transport),
    "cayley": (cayley, _cayley_log, _cayley_pull, _cayley_transport),
}


class SO3(AbstractSpace):
    r"""The rotation group SO(3): attitudes of a rigid body.

    The position is a rotation matrix `R` of shape `(3, 3)`, the velocity the body
    angular velocity $\Omega$ (shape `(3,)`) with $\dot R = R\hat\Omega$, the momentum
    the body angular momentum $\Pi = \partial L/\partial\Omega$. A stack of `n`
    attitudes, shape `(n, 3, 3)` with velocities `(n, 3)`, is the product
    $SO(3)^n$, one space for the bodies of a mechanism. A step moves
    $R \mapsto R\,\tau(x)$, so `R` stays a rotation to round-off, with $\tau$ the
    exponential map (the default; Rodrigues' formula, with its derivative in closed
    form) or the Cayley map
    $\tau(x) = (I - \hat x/2)^{-1}(I + \hat x/2)$ (Bou-Rabee & Marsden (2009)),
    which is rational in $x$: no sine or cosine, and a cheaper derivative. Both are
    second-order accurate retractions, so a solver keeps its order with either.
    $\mathrm{Ad}_R = R$ and $\mathrm{ad}^*_\Omega\Pi = \Pi \times \Omega$.

    Small products are written as sums (`matmul`), so that no step's compiled loop
    holds a matrix-product kernel (`diagnostics.loop_breakers`).

    **Arguments:**

    - `retraction`: `"exp"` (the default) or `"cayley"`.

    ??? cite "Reference"

        ```bibtex
        @article{bourabee2009hamilton,
            title={Hamilton--{P}ontryagin integrators on {L}ie groups part {I}:
                   introduction and structure-preserving properties},
            author={Bou-Rabee, Nawaf and Marsden, Jerrold E.},
            journal={Foundations of Computational Mathematics},
            volume={9},
            number={2},
            pages={197--219},
            year={2009},
        }
        ```
    """

    retraction: Literal["exp", "cayley"] = eqx.field(static=True, default="exp")

    def __check_init__(self):
        if self.retraction not in _RETRACTIONS:
            raise ValueError(
                f"SO3(retraction=...) takes 'exp' or 'cayley'; got {self.retraction!r}."
            )

    def retract(self, q, x):
        return matmul(q, _RETRACTIONS[self.retraction][0](x))

    def difference(self, q0, q1):
        return _RETRACTIONS[self.retraction][1](matmul(transpose(q0), q1))

    def tangent(self, q):
        return jnp.zeros(q.shape[:-1], q.dtype)

    def velocity(self, q, xi):
        return matmul(q, hat(xi))

    def pull(self, x, w):
        return _RETRACTIONS[self.retraction][2](x, w)

    def transport(self, x, w):
        return _RETRACTIONS[self.retraction][3](x, w)

    def coadjoint(self, xi, mu):
        return cross(mu, xi)

    def departure(self, q):
        return rotation_departure(q)
