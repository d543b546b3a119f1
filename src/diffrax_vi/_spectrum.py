"""Extreme eigenvalues of a symmetric operator: dense for small systems, Lanczos
estimates for large ones (whether d2L/dv2 is regular and definite at the start)."""

from collections.abc import Callable

import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Scalar

from ._linear import unit_scale
from ._tolerance import DENSE_MAX, LANCZOS_STEPS


def lanczos_extremes(
    matvec: Callable[[Array], Array], n: int, dtype, steps: int = LANCZOS_STEPS
) -> tuple[Scalar, Scalar]:
    """Estimates of the smallest and largest eigenvalues of a symmetric operator on
    `R^n`, from `steps` Lanczos iterations (with full reorthogonalisation) from a
    fixed start vector: the extreme Ritz values, which converge first."""
    k = min(steps, n)
    v0 = jnp.cos(jnp.arange(1, n + 1, dtype=dtype) * 1.2345)  # not an eigenvector
    v0 = v0 / jnp.linalg.norm(v0)
    basis = jnp.zeros((k, n), dtype).at[0].set(v0)
    alphas = jnp.zeros(k, dtype)
    betas = jnp.zeros(k, dtype)

    def body(j, carry):
        basis, alphas, betas = carry
        w = matvec(basis[j])
        alpha = jnp.dot(w, basis[j])
        # Full reorthogonalisation against every vector so far (unused rows are 0).
        w = w - basis.T @ (basis @ w)
        w = w - basis.T @ (basis @ w)
        beta = jnp.linalg.norm(w)
        nxt = jnp.where(beta > 0, w / jnp.where(beta > 0, beta, 1), 0.0)
        basis = lax.cond(j + 1 < k, lambda: basis.at[j + 1].set(nxt), lambda: basis)
        return basis, alphas.at[j].set(alpha), betas.at[j].set(beta)

    _, alphas, betas = lax.fori_loop(0, k, body, (basis, alphas, betas))
    tridiagonal = jnp.diag(alphas) + jnp.diag(betas[:-1], 1) + jnp.diag(betas[:-1], -1)
    ritz = jnp.linalg.eigvalsh(tridiagonal)
    return ritz[0], ritz[-1]


def symmetric_extremes(matvec: Callable[[Array], Array], n: int, dtype):
    """The smallest and largest eigenvalues of a symmetric operator `A` on `R^n`
    in units of its diagonal, and the smallest in magnitude: exact from the dense
    matrix up to `DENSE_MAX`, else Lanczos estimates (the smallest magnitude then
    only among the extreme ones).

    In units of its diagonal: of `D A D` with `D = |diag A|^(-1/2)` (a zero entry
    unscaled), whose entries are pure numbers, the same in any units of each
    coordinate (which scale a row and a column of `A`); a congruence, so its
    eigenvalues have the signs of `A`'s. Beyond `DENSE_MAX` the diagonal takes one
    product per coordinate, in a loop (a product with `z = (1, -1, 1, ...)`
    estimates it in one, but is wrong by the ratio of two coordinates' units where
    they are coupled)."""
    if n <= DENSE_MAX:
        matrix = jax.vmap(matvec)(jnp.eye(n, dtype=dtype))
        scale = unit_scale(jnp.diagonal(matrix))
        matrix = scale[:, None] * matrix * scale[None, :]
        eigs = jnp.linalg.eigvalsh(0.5 * (matrix + matrix.T))
        return eigs[0], eigs[-1], jnp.min(jnp.abs(eigs))
    rows = jnp.arange(n)
    diagonal = lax.map(lambda i: matvec((rows == i).astype(dtype))[i], rows)
    scale = unit_scale(diagonal)
    smallest, largest = lanczos_extremes(lambda u: scale * matvec(scale * u), n, dtype)
    size = jnp.maximum(jnp.abs(smallest), jnp.abs(largest))
    # An indefinite operator's smallest magnitude is inside the spectrum, which
    # Lanczos does not resolve: not judged singular.
    least = jnp.where(
        jnp.sign(smallest) == jnp.sign(largest),
        jnp.minimum(jnp.abs(smallest), jnp.abs(largest)),
        size,
    )
    return smallest, largest, least
