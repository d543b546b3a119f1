r"""Configuration spaces: how a position moves, as data.

Every solver, term and discrete Lagrangian moves a position $q$ by a tangent increment
$x$ through its space, $q \oplus x$, and never adds to $q$ itself. A vector space
([`diffrax_vi.Euclidean`][]) adds, $q \oplus x = q + x$. A Lie group $G$ with the
left-trivialised velocity $\xi = g^{-1}\dot g$ in its algebra $\mathfrak g \cong
\mathbb R^k$ multiplies, $g \oplus x = g\,\tau(x)$ with $\tau = \exp$ (Marsden & West
(2001), §4; Bou-Rabee & Marsden (2009)), and its momentum $\mu = \partial L/\partial
\xi$ lives in the dual algebra.

A discrete Lagrangian $L_d(g_0, g_1) = h\,\Lambda(g_0, \xi)$ with $g_1 = g_0\tau(h\xi)$
then gives the position–momentum step

$$\partial_\xi\Lambda = (d\tau^R_{h\xi})^\top\big(\mu_0 + h\,\partial^L_g\Lambda +
f^-\big),\qquad \mu_1 = \mathrm{Ad}^*_{\tau(h\xi)}\big(\mu_0 + h\,\partial^L_g\Lambda
+ f^-\big) + f^+,$$

with $\partial^L_g$ the left-trivialised derivative, $d\tau^R_x(y) = D\tau(x)[y]\,
\tau(x)^{-1}$ and $\mathrm{Ad}^*_g = \mathrm{Ad}_g^\top$: a space supplies `pull`
($(d\tau^R_x)^\top$) and `transport` ($\mathrm{Ad}^*_{\tau(x)}$), both the identity
in a vector space, where the step is the usual one. The continuous equations are the
Euler–Poincaré equations $\dot g = g\hat\xi$, $\dot\mu = \mathrm{ad}^*_\xi\mu +
\partial^L_g L$ (`velocity`, `coadjoint`).

Spaces combine by PyTree: `space=(Euclidean(), SO3())` for `q = (x, R)`, with
velocity `(xdot, Omega)` and momentum `(p_x, Pi)`.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, PyTree


class AbstractSpace(eqx.Module):
    """A configuration space: how a position moves by a tangent increment.

    A subclass is one file (`_so3.py`, `_so2.py`): `retract`, `difference`,
    `tangent`, `velocity`, `pull`, `transport` and `coadjoint` (see the module's
    docstring for their mathematics).
    """

    @abc.abstractmethod
    def retract(self, q: PyTree, x: PyTree) -> PyTree:
        r"""$q \oplus x$: the position reached from `q` by the increment `x`."""

    @abc.abstractmethod
    def difference(self, q0: PyTree, q1: PyTree) -> PyTree:
        r"""The increment $x$ with $q_0 \oplus x = q_1$ (near zero)."""

    @abc.abstractmethod
    def tangent(self, q: PyTree) -> PyTree:
        """Zeros with the structure of a velocity (and a momentum) at `q`."""

    @abc.abstractmethod
    def velocity(self, q: PyTree, xi: PyTree) -> PyTree:
        r"""$\dot q$ for the velocity $\xi$: what a Runge–Kutta solver integrates."""

    @abc.abstractmethod
    def pull(self, x: PyTree, w: PyTree) -> PyTree:
        r"""$(d\tau^R_x)^\top w$."""

    @abc.abstractmethod
    def transport(self, x: PyTree, w: PyTree) -> PyTree:
        r"""$\mathrm{Ad}^*_{\tau(x)} w$: a momentum at $q$ seen at $q \oplus x$."""

    @abc.abstractmethod
    def coadjoint(self, xi: PyTree, mu: PyTree) -> PyTree:
        r"""$\mathrm{ad}^*_\xi \mu$, the term a group adds to $\dot\mu$."""

    def scale(self, q: PyTree) -> PyTree:
        """The size of `q` along each tangent direction, with the structure of a
        velocity, against which a linearised change $G x$ is compared: ones on a
        group, whose increments are angles (pure numbers)."""
        return jtu.tree_map(jnp.ones_like, self.tangent(q))

    def departure(self, q: PyTree) -> Array:
        """How far `q` lies off the space, a pure number (unit-free): 0 in a vector
        space, which holds every array of its shape."""
        return jnp.zeros(())


class Euclidean(AbstractSpace):
    """A vector space, of any PyTree of arrays: positions add. The default space of a
    Lagrangian, in which velocities and momenta have the structure of `q`."""

    def retract(self, q, x):
        return jtu.tree_map(lambda qi, xi: xi + qi, q, x)

    def difference(self, q0, q1):
        return jtu.tree_map(lambda a, b: b - a, q0, q1)

    def tangent(self, q):
        return jtu.tree_map(jnp.zeros_like, q)

    def scale(self, q):
        return jtu.tree_map(jnp.abs, q)

    def velocity(self, q, xi):
        return xi

    def pull(self, x, w):
        return w

    def transport(self, x, w):
        return w

    def coadjoint(self, xi, mu):
        return jtu.tree_map(jnp.zeros_like, mu)


def is_space(x) -> bool:
    return isinstance(x, AbstractSpace)


def is_euclidean(space: PyTree[AbstractSpace]) -> bool:
    """Whether every part of `space` is a vector space: then positions add, and the
    solvers take their vector-space paths unchanged."""
    return all(
        isinstance(s, Euclidean) for s in jtu.tree_leaves(space, is_leaf=is_space)
    )


def _map(method: str, space, *trees):
    return jtu.tree_map(
        lambda s, *xs: getattr(s, method)(*xs), space, *trees, is_leaf=is_space
    )


def retract(space, q, x):
    r"""$q \oplus x$ in a space or a product of spaces."""
    return _map("retract", space, q, x)


def difference(space, q0, q1):
    return _map("difference", space, q0, q1)


def tangent(space, q):
    return _map("tangent", space, q)


def velocity(space, q, xi):
    return _map("velocity", space, q, xi)


def pull(space, x, w):
    return _map("pull", space, x, w)


def transport(space, x, w):
    return _map("transport", space, x, w)


def coadjoint(space, xi, mu):
    return _map("coadjoint", space, xi, mu)


def scale(space, q):
    """`scale` of each part of `q`, with the structure of a velocity."""
    return _map("scale", space, q)


def departure(space, q) -> Array:
    """The largest `departure` of the parts of `q` from their spaces."""
    parts = jtu.tree_leaves(_map("departure", space, q))
    return jnp.max(jnp.stack([jnp.asarray(x, float) for x in parts]))


def tangent_line(space, q, eta):
    r"""$q + \dot q(\eta)$, the velocity $\eta$ added to $q$ in the space's
    embedding: equal to $q \oplus \eta$ to first order at $\eta = 0$, so a first
    derivative at $\eta = 0$ may differentiate along it, which costs less than
    differentiating the exponential (`benchmarks/lie_groups.py`)."""
    return jtu.tree_map(lambda a, b: a + b, q, velocity(space, q, eta))


def left_gradient(space, fn, q):
    r"""$\partial^L_q f$: the derivative of `fn` along $\eta \mapsto q \oplus \eta$
    at $\eta = 0$, with the structure of a momentum (the gradient, in a vector
    space)."""
    if is_euclidean(space):
        return jax.grad(fn)(q)
    return jax.grad(lambda eta: fn(tangent_line(space, q, eta)))(tangent(space, q))
