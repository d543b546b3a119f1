"""Diagnostics along solutions: DEL residuals, and the 2-forms of Hirani (2000),
eq. (4.68)."""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._custom_types import Args, Q, RealScalarLike, Scalar
from .._discrete import (
    AbstractDiscreteLagrangian,
    del_residual,
    discrete_lagrangian,
    MidpointRule,
)
from .._lagrangian import as_lagrangian


def del_residuals(
    lagrangian: Callable[..., ArrayLike],
    ts: Float[ArrayLike, " n"],
    qs: PyTree[Array],
    args: Args = None,
    discrete_lagrangian: AbstractDiscreteLagrangian = MidpointRule(),
) -> PyTree[Array]:
    r"""The discrete Euler–Lagrange residual
    $F(q_{k-1}, q_k, q_{k+1}) = D_2 L_d(q_{k-1}, q_k) + D_1 L_d(q_k, q_{k+1})$ at every
    interior point of a discrete trajectory: how far its triples lie from the manifold
    $S = \{F = 0\}$ (Hirani (2000), eq. (4.72)).

    Zero to round-off along a [`diffrax_vi.MidpointVI`][] trajectory; for
    [`diffrax_vi.LinearizedVI`][] it measures the drift off $S$.

    **Arguments:**

    - `lagrangian`: the Lagrangian.
    - `ts`: the times of the trajectory, shape `(n,)`, e.g. `sol.ts` of a solve with
        `SaveAt(t0=True, steps=True)` (trailing `inf` padding is not allowed: slice it
        off).
    - `qs`: the positions, each leaf with leading axis `n`.
    - `args`: as passed to the solve.
    - `discrete_lagrangian`: the discrete Lagrangian. Defaults to the midpoint rule.

    **Returns:**

    The residuals, with the structure of `q` and leading axis `n - 2`.
    """
    lagrangian = as_lagrangian(lagrangian)
    ts = jnp.asarray(ts)
    take = lambda i: jtu.tree_map(lambda x: x[i], qs)
    triples = (take(slice(None, -2)), take(slice(1, -1)), take(slice(2, None)))
    times = (ts[:-2], ts[1:-1], ts[2:])
    return jax.vmap(
        lambda t, q: del_residual(discrete_lagrangian, lagrangian, t, q, args)
    )(times, triples)


def tangent_discrete_lagrangian(
    rule: AbstractDiscreteLagrangian,
    lagrangian: Callable[..., ArrayLike],
    t0: RealScalarLike,
    t1: RealScalarLike,
    z0: tuple[Q, Q],
    z1: tuple[Q, Q],
    args: Args = None,
) -> Scalar:
    r"""The discrete linearization of Hirani (2000), eq. (4.34),
    $L_d^{(2)}((q_0, u_0), (q_1, u_1)) = dL_d(q_0, q_1)\cdot(u_0, u_1)$, with
    $z_i = (q_i, u_i)$."""
    lagrangian = as_lagrangian(lagrangian)
    (q0, u0), (q1, u1) = z0, z1
    _, out = jax.jvp(
        lambda a, b: discrete_lagrangian(rule, lagrangian, t0, t1, a, b, args),
        (q0, q1),
        (u0, u1),
    )
    return out


def tangent_symplectic_form(
    rule: AbstractDiscreteLagrangian,
    lagrangian: Callable[..., ArrayLike],
    t0: RealScalarLike,
    t1: RealScalarLike,
    z: tuple[tuple[Q, Q], tuple[Q, Q]],
    xi: tuple[tuple[Q, Q], tuple[Q, Q]],
    eta: tuple[tuple[Q, Q], tuple[Q, Q]],
    args: Args = None,
) -> Scalar:
    r"""The symplectic form (4.68) on $TQ \times TQ$,
    $\Omega = \sum \frac{\partial^2 L_d^{(2)}}{\partial z_1^j \partial z_0^i}\,
    dz_0^i \wedge dz_1^j$, at the point `z = (z0, z1)` on the tangent vectors
    `xi = (xi0, xi1)`, `eta = (eta0, eta1)`."""
    z0, z1 = z

    def mixed(a0, b1):
        # a0^T (d^2 Ld2 / dz0 dz1) b1, by two nested directional derivatives.
        def along_z0(s):
            z0s = jtu.tree_map(lambda x, d: x + s * d, z0, a0)
            return jax.jvp(
                lambda w1: tangent_discrete_lagrangian(
                    rule, lagrangian, t0, t1, z0s, w1, args
                ),
                (z1,),
                (b1,),
            )[1]

        return jax.jvp(along_z0, (jnp.zeros(()),), (jnp.ones(()),))[1]

    return mixed(xi[0], eta[1]) - mixed(eta[0], xi[1])


def presymplectic_form(
    rule: AbstractDiscreteLagrangian,
    lagrangian: Callable[..., ArrayLike],
    ts: tuple[RealScalarLike, RealScalarLike, RealScalarLike],
    triple: tuple[Q, Q, Q],
    xi: tuple[Q, Q, Q],
    eta: tuple[Q, Q, Q],
    args: Args = None,
) -> Scalar:
    r"""The 2-form $\omega = i^*\Omega$ on triples $(q_0, q_1, q_2)$ (Hirani (2000),
    §4.7.2), pulled back from eq. (4.68) by
    $i(q_0, q_1, q_2) = ((q_0, u_0), (q_1, u_1))$ with forward velocities
    $u_j = (q_{j+1} - q_j)/h_j$. [`diffrax_vi.LinearizedVI`][] preserves it on
    tangent vectors of $S$ (Theorem 2)."""
    t0, t1, t2 = ts

    def embed(q):
        q0, q1, q2 = q
        u0 = jtu.tree_map(lambda a, b: (b - a) / (t1 - t0), q0, q1)
        u1 = jtu.tree_map(lambda a, b: (b - a) / (t2 - t1), q1, q2)
        return (q0, u0), (q1, u1)

    z, dxi = jax.jvp(embed, (triple,), (xi,))
    _, deta = jax.jvp(embed, (triple,), (eta,))
    return tangent_symplectic_form(rule, lagrangian, t0, t1, z, dxi, deta, args)
