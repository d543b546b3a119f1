"""Linear stability of any diffrax solver on the harmonic oscillator."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._lagrangian import SeparableLagrangian
from .._term import terms_for


_OSCILLATOR = SeparableLagrangian(lambda t, q, args: 0.5 * q**2)


def oscillator_step_matrix(
    solver: dfx.AbstractSolver, omega_h: float | Float[ArrayLike, ""]
) -> Float[Array, "n n"]:
    r"""The matrix of one step of `solver` on the harmonic oscillator
    $L = \tfrac12 v^2 - \tfrac12 q^2$ ($\omega = 1$) with step `omega_h`, acting on the
    whole state the solver carries: `(q, p)` and every floating leaf of its solver
    state (the past positions of [`diffrax_vi.LinearizedVI`][], a cached force, a
    Newton guess, a compensation).

    Its nonzero eigenvalues are the roots of the method's characteristic polynomial:
    the principal pair, which approximates $e^{\pm i\omega h}$, and, for a multistep
    method, its parasitic roots. The method is linearly stable at this step when every
    eigenvalue lies in the closed unit disc (simple on the circle).

    The oscillator is linear, so the matrix is exact (by `jax.jacrev` through the
    step, and implicit differentiation through any Newton solve).
    """
    terms = terms_for(solver, _OSCILLATOR)
    h = jnp.asarray(omega_h, dtype=float)
    y0 = (jnp.ones((), h.dtype), jnp.zeros((), h.dtype))
    state0 = solver.init(terms, 0.0, h, y0, None)
    floats, static = eqx.partition((y0, state0), eqx.is_inexact_array)
    flat, unravel = jax.flatten_util.ravel_pytree(floats)

    def step(x):
        y, state = eqx.combine(unravel(x), static)
        y1, _, _, state1, _ = solver.step(terms, 0.0, h, y, None, state, False)
        out = eqx.filter((y1, state1), eqx.is_inexact_array)
        return jax.flatten_util.ravel_pytree(out)[0]

    return jax.jacrev(step)(flat)


def _radius_fn(solver: dfx.AbstractSolver):
    matrices = jax.jit(jax.vmap(lambda x: oscillator_step_matrix(solver, x)))

    def radius(omega_h):
        m = np.asarray(matrices(jnp.asarray(omega_h, dtype=float)))
        return np.abs(np.linalg.eigvals(m)).max(axis=-1)

    return radius


def spectral_radius(
    solver: dfx.AbstractSolver, omega_h: Float[ArrayLike, " n"]
) -> np.ndarray:
    """The largest eigenvalue modulus of
    [`diffrax_vi.diagnostics.oscillator_step_matrix`][] at each step in `omega_h`."""
    return _radius_fn(solver)(np.atleast_1d(omega_h))


def stability_limit(
    solver: dfx.AbstractSolver,
    omega_h_max: float = 10.0,
    *,
    points: int = 2000,
    tol: float = 1e-6,
) -> float:
    r"""The largest $\omega h$ up to which `solver` is linearly stable on the harmonic
    oscillator (spectral radius $\le 1 + $ `tol`), found on a grid up to
    `omega_h_max` and refined by bisection to about 1e-9; `inf` if it is stable on
    the whole grid.

    `tol` absorbs the round-off of a double eigenvalue at the edge of the interval,
    where the spectral radius departs from 1 like the square root of the distance.
    """
    radius = _radius_fn(solver)
    grid = np.linspace(omega_h_max / points, omega_h_max, points)
    unstable = radius(grid) > 1 + tol
    if not unstable.any():
        return float("inf")
    first = int(np.argmax(unstable))
    lo = grid[first - 1] if first else 0.0
    hi = grid[first]
    # Bisect a batch at a time: 16 points shrink the bracket 17-fold per call.
    while hi - lo > 1e-9 * hi:
        points_in = np.linspace(lo, hi, 18)[1:-1]
        bad = radius(points_in) > 1 + tol
        k = int(np.argmax(bad)) if bad.any() else len(points_in)
        lo = points_in[k - 1] if k else lo
        hi = points_in[k] if k < len(points_in) else hi
    return float(lo)
