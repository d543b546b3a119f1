"""Extreme eigenvalues of a symmetric operator: dense for small systems, Lanczos
estimates for large ones (whether d2L/dv2 is regular and definite at the start), and
the solve that comes with a small one's eigendecomposition."""

from collections.abc import Callable

import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Scalar

from ._linear import product, unit_scale
from ._tolerance import DENSE_MAX, LANCZOS_STEPS, singular_threshold


Extremes = tuple[Scalar, Scalar, Scalar]


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


def _unit_scaled(matrix: Array) -> tuple[Array, Array]:
    """`D A D` for `A = matrix`, symmetrised, with `D = |diag A|^(-1/2)` (a zero
    entry unscaled), and the diagonal of `D`."""
    scale = unit_scale(jnp.diagonal(matrix))
    scaled = scale[:, None] * matrix * scale[None, :]
    return 0.5 * (scaled + scaled.T), scale


def _extremes(eigs: Array) -> Extremes:
    """The smallest, the largest and the smallest in magnitude of eigenvalues sorted
    in increasing order."""
    return eigs[0], eigs[-1], jnp.min(jnp.abs(eigs))


def invertible(extremes: Extremes, n: int, dtype) -> Bool[Array, ""]:
    """Whether an operator on `R^n` with these `symmetric_extremes` is invertible to
    working precision: its smallest eigenvalue in magnitude above
    `singular_threshold` of its largest (NaN is not regular)."""
    smallest, largest, least = extremes
    size = jnp.maximum(jnp.abs(smallest), jnp.abs(largest))
    return least > singular_threshold(n, dtype) * size


def symmetric_solve(matrix: Array, b: Array) -> tuple[Array, Extremes]:
    """`matrix^-1 b` for a small symmetric `matrix`, and its `symmetric_extremes`,
    from one eigendecomposition in units of its diagonal,
    `D A D = Q diag(lambda) Q^T`: `x = D Q diag(1/lambda) Q^T D b`. Where both are
    wanted, as at the start of a Lagrangian marked quadratic in `v` (its velocity
    and the check of `d2L/dv2`), it takes one matrix and one LAPACK call in place of
    an elimination, a second matrix and the eigenvalues: outside a loop, where XLA
    on CPU compiles each fused kernel on its own, the double pendulum's solve holds
    22 kernels against 41. Not finite where `matrix` is singular."""
    scaled, scale = _unit_scaled(matrix)
    eigs, vectors = jnp.linalg.eigh(scaled)
    x = scale * product(vectors, product(vectors.T, scale * b) / eigs)
    return x, _extremes(eigs)


def symmetric_extremes(matvec: Callable[[Array], Array], n: int, dtype) -> Extremes:
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
        scaled, _ = _unit_scaled(jax.vmap(matvec)(jnp.eye(n, dtype=dtype)))
        return _extremes(jnp.linalg.eigvalsh(scaled))
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
