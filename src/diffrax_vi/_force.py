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
    floating dtype of `q` (and cast to its dtype)."""
    out = force(t, q, v, args)
    if jtu.tree_structure(out) != jtu.tree_structure(q):
        raise ValueError(
            "The force must return a generalised force with the PyTree structure of "
            f"q, one component per degree of freedom; got {jtu.tree_structure(out)} "
            f"for q of structure {jtu.tree_structure(q)}."
        )
    for f, qi in zip(jtu.tree_leaves(out), jtu.tree_leaves(q)):
        if jnp.shape(f) != jnp.shape(qi):
            raise ValueError(
                f"The force returned a leaf of shape {jnp.shape(f)} for a position "
                f"of shape {jnp.shape(qi)}: it needs one component per degree of "
                "freedom (broadcast it, e.g. `jnp.full_like(q, torque)`)."
            )
        if not jnp.issubdtype(jnp.result_type(f), jnp.floating):
            raise ValueError(
                f"The force must be real floating point, got dtype "
                f"{jnp.result_type(f)}."
            )
    return jtu.tree_map(lambda f, qi: jnp.asarray(f, jnp.result_type(qi)), out, q)


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
