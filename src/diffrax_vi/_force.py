r"""Applied (non-conservative) generalised forces: damping, drives, controls.

A force $F(t, q, v, \text{args})$ enters the Lagrange–d'Alembert principle
$\delta\int L\,dt + \int F\cdot\delta q\,dt = 0$, whose Euler–Lagrange equations are
$\frac{d}{dt}\partial_v L = \partial_q L + F$. Its discretisation (Marsden & West
(2001), §3.2) replaces the virtual work over a step by $f^-_k\cdot\delta q_k +
f^+_k\cdot\delta q_{k+1}$, with $f^\pm$ the quadrature of $F$ that the discrete
Lagrangian itself uses; in position–momentum form

$$p_k = -D_1 L_d(q_k, q_{k+1}) - f^-_k,\qquad p_{k+1} = D_2 L_d(q_k, q_{k+1})
+ f^+_k.$$
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import PyTree

from ._custom_types import Args, P, Q, RealScalarLike, V
from ._misc import reads


def applied_force(
    force: Callable[..., PyTree], t: RealScalarLike, q: Q, v: V, args: Args
) -> P:
    """`force(t, q, v, args)`, checked at trace time to have the structure, shapes and
    floating dtype of the velocity `v` (of `q` in a vector space; on a group a force
    is a torque in the algebra, like the momentum), and cast to its dtype."""
    out = force(t, q, v, args)
    if jtu.tree_structure(out) != jtu.tree_structure(v):
        raise ValueError(
            "The force must return a generalised force with the PyTree structure of "
            f"q, one component per degree of freedom; got {jtu.tree_structure(out)} "
            f"for q of structure {jtu.tree_structure(v)} (on a group: of the "
            "velocity, e.g. a body torque of shape (3,) on SO3)."
        )
    for f, vi in zip(jtu.tree_leaves(out), jtu.tree_leaves(v)):
        if jnp.shape(f) != jnp.shape(vi):
            raise ValueError(
                f"The force returned a leaf of shape {jnp.shape(f)} where the "
                f"velocity has shape {jnp.shape(vi)}: it needs one component per "
                "degree of freedom, the shape of the velocity v (of q in a vector "
                "space; on a group the body angular velocity, shape (3,) on SO3 and "
                "() on SO2, not the matrix's). Broadcast it with "
                "`jnp.full_like(v, value)`, v being the force's third argument."
            )
        if not jnp.issubdtype(jnp.result_type(f), jnp.floating):
            raise ValueError(
                f"The force must be real floating point, got dtype "
                f"{jnp.result_type(f)}."
            )
    return jtu.tree_map(lambda f, vi: jnp.asarray(f, jnp.result_type(vi)), out, v)


def depends_on_velocity(
    force: Callable[..., PyTree], t: RealScalarLike, q: Q, v: V, args: Args
) -> bool:
    """Whether `force(t, q, v, args)` reads `v` at all, decided from its traced
    program (structurally, so a force that is zero at this `v` but not elsewhere
    still counts). A force of the positions and time alone keeps the Störmer–Verlet
    step explicit."""
    return reads(lambda _v: force(t, q, _v, args), v)


def power(force: P, v: V) -> jax.Array:
    """$F\\cdot v$."""
    return sum(
        jnp.sum(f * x) for f, x in zip(jtu.tree_leaves(force), jtu.tree_leaves(v))
    )
