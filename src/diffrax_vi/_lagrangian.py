import abc
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import optimistix as optx
from jaxtyping import Array, ArrayLike, PyTree

from ._custom_types import Args, P, Q, RealScalarLike, Scalar, V
from ._misc import (
    all_finite,
    default_root_finder,
    momentum_scale,
    split_state,
    state_dtype,
)


class AbstractLagrangian(eqx.Module):
    r"""Abstract base class for Lagrangians $L(t, q, v, \text{args})$.

    Subclass it and implement `__call__`; any field of the module (weights of a neural
    network, physical parameters) can be differentiated through the solvers.
    `q` and `v` are PyTrees of arrays with the same structure.

    A Lagrangian that is a polynomial of degree at most two in `v` should subclass
    [`diffrax_vi.AbstractQuadraticLagrangian`][] instead, and one of the form
    $\tfrac12 v^\top M v - V(t, q)$ with constant diagonal $M$
    [`diffrax_vi.AbstractSeparableLagrangian`][]: the solvers then take cheaper paths.
    """

    @abc.abstractmethod
    def __call__(self, t: RealScalarLike, q: Q, v: V, args: Args) -> Scalar:
        """**Arguments:**

        - `t`: the time.
        - `q`: the configuration, a PyTree of arrays.
        - `v`: the velocity, a PyTree of arrays with the structure of `q`.
        - `args`: any static or dynamic arguments, as passed to `diffeqsolve`.

        **Returns:**

        The value of the Lagrangian, a scalar.
        """


class Lagrangian(AbstractLagrangian):
    """Wraps a plain callable `fn(t, q, v, args) -> scalar` as a Lagrangian.

    Nothing is assumed of `fn`: the inverse Legendre map is found by Newton's method.

    !!! example

        ```python
        pendulum = diffrax_vi.Lagrangian(lambda t, q, v, args: 0.5 * v**2 + jnp.cos(q))
        ```
    """

    fn: Callable[..., ArrayLike]

    def __call__(self, t: RealScalarLike, q: Q, v: V, args: Args) -> Array:
        # Not annotated as a scalar: callers check that with an error that says how
        # to fix it.
        return jnp.asarray(self.fn(t, q, v, args))


class AbstractQuadraticLagrangian(AbstractLagrangian):
    r"""Marker for Lagrangians that are polynomials of degree at most two in `v`,
    $L = \tfrac12 v^\top M(t, q) v + a(t, q)\cdot v - V(t, q)$ (e.g. a double pendulum).

    The inverse Legendre map is then a single linear solve with $M = \partial^2 L /
    \partial v^2$ instead of a Newton iteration. Subclass it and implement `__call__`.
    """


class AbstractSeparableLagrangian(AbstractQuadraticLagrangian):
    r"""Abstract base class for separable Lagrangians
    $L = \tfrac12 v^\top M v - V(t, q, \text{args})$ with a constant diagonal mass $M$.

    The Hamiltonian $H = \tfrac12 p^\top M^{-1} p + V$ is then separable:
    [`diffrax_vi.TrapezoidalVI`][] becomes the explicit Störmer–Verlet method, and the
    Legendre map is a division by the mass.

    Subclasses implement `potential` and define `mass`: a scalar, or a PyTree with the
    structure of `q` whose leaves broadcast against those of `q` (e.g. masses of shape
    `(n_bodies, 1)` for positions of shape `(n_bodies, 3)`).
    """

    mass: eqx.AbstractVar[PyTree[ArrayLike]]

    @abc.abstractmethod
    def potential(self, t: RealScalarLike, q: Q, args: Args) -> Scalar:
        """The potential energy $V(t, q, \\text{args})$, a scalar."""

    def __call__(self, t: RealScalarLike, q: Q, v: V, args: Args) -> Scalar:
        mass = broadcast_mass(self.mass, v)
        kinetic = sum(
            jnp.sum(0.5 * m * vi**2)
            for m, vi in zip(jtu.tree_leaves(mass), jtu.tree_leaves(v))
        )
        return kinetic - self.potential(t, q, args)


class SeparableLagrangian(AbstractSeparableLagrangian):
    r"""A separable Lagrangian $L = \tfrac12 v^\top M v - V(t, q, \text{args})$ from a
    potential function and a constant diagonal mass.

    **Arguments:**

    - `potential`: a callable `(t, q, args) -> scalar`.
    - `mass`: a scalar, or a PyTree with the structure of `q` whose leaves broadcast
        against those of `q`. Defaults to `1.0`.

    !!! example

        ```python
        kepler = diffrax_vi.SeparableLagrangian(
            lambda t, q, args: -1 / jnp.linalg.norm(q)
        )
        ```
    """

    potential_fn: Callable[..., ArrayLike]
    mass: PyTree[ArrayLike] = 1.0

    def potential(self, t: RealScalarLike, q: Q, args: Args) -> Scalar:
        value = jnp.asarray(self.potential_fn(t, q, args))
        if value.shape != ():
            raise ValueError(
                f"The potential must return a scalar; got shape {value.shape}. Sum "
                "over degrees of freedom, e.g. `jnp.sum(0.5 * q**2)`."
            )
        return value


class TangentLift(AbstractLagrangian):
    r"""The tangent lift of a Lagrangian, the continuous linearization of Hirani (2000),
    eq. (4.20),

    $$L^{(2)}(q, u, v, w) = \frac{\partial L}{\partial q}(q, v)\cdot u
    + \frac{\partial L}{\partial v}(q, v)\cdot w,$$

    the derivative of $L$ along $(u, w)$: a Lagrangian on the doubled configuration
    `(q, u)` with velocity `(v, w)` and momentum `(p_q, p_u)`, where
    $p_u = \partial L / \partial v$ is the momentum of $L$.

    Its Euler–Lagrange equations are those of $L$ (in $u$) together with their
    variational equation (in $q$); with $u = \dot q$ the latter is the time derivative
    of the Euler–Lagrange equations of $L$ (Hirani (2000), Lemma 3). Any variational
    solver applied to `LagrangianTerm(TangentLift(L))` is Hirani's algorithm on
    $TQ \times TQ$, eqs. (4.61)–(4.62), and equals the tangent map of the solver's
    flow of $L$ (Theorem 1).

    **Arguments:**

    - `lagrangian`: the Lagrangian $L$ to lift: any
        [`diffrax_vi.AbstractLagrangian`][] or callable `L(t, q, v, args)`.

    The state of the lifted system is `y = ((q, u), (p_q, p_u))`.
    """

    lagrangian: AbstractLagrangian

    def __init__(self, lagrangian: Callable[..., ArrayLike]):
        self.lagrangian = as_lagrangian(lagrangian)

    def __call__(self, t: RealScalarLike, q: Q, v: V, args: Args) -> Scalar:
        if not (isinstance(q, tuple) and len(q) == 2):
            raise ValueError(
                "TangentLift(L) acts on the doubled configuration `(q, u)` and "
                "velocity `(v, w)`: its state is `y = ((q, u), (p_q, p_u))`."
            )
        (q, u), (v, w) = q, v
        _, tangent = jax.jvp(
            lambda _q, _v: lagrangian_value(self.lagrangian, t, _q, _v, args),
            (q, v),
            (u, w),
        )
        return tangent


def broadcast_mass(mass: PyTree[ArrayLike], q: Q) -> Q:
    """The mass as a PyTree with the structure of `q` (a scalar mass is shared)."""
    if jtu.tree_structure(mass) == jtu.tree_structure(q):
        return mass
    if len(jtu.tree_leaves(mass)) == 1 and jnp.ndim(jtu.tree_leaves(mass)[0]) == 0:
        (m,) = jtu.tree_leaves(mass)
        return jtu.tree_map(lambda _: m, q)
    raise ValueError(
        f"The mass must be a scalar or a PyTree with the structure of q; got mass "
        f"structure {jtu.tree_structure(mass)} and q structure "
        f"{jtu.tree_structure(q)}."
    )


def as_lagrangian(lagrangian: Callable[..., ArrayLike]) -> AbstractLagrangian:
    """Any callable `L(t, q, v, args)` as an [`diffrax_vi.AbstractLagrangian`][]."""
    if isinstance(lagrangian, AbstractLagrangian):
        return lagrangian
    if not callable(lagrangian):
        raise ValueError(
            f"A Lagrangian must be callable as `L(t, q, v, args)`; got {lagrangian!r}."
        )
    return Lagrangian(lagrangian)


def lagrangian_value(
    lagrangian: AbstractLagrangian, t: RealScalarLike, q: Q, v: V, args: Args
) -> Scalar:
    """`L(t, q, v, args)`, checked at trace time to be a real scalar."""
    out = lagrangian(t, q, v, args)
    shape = jnp.shape(out)
    if shape != ():
        raise ValueError(
            f"The Lagrangian must return a scalar, but returned an array of shape "
            f"{shape}. Sum the energies over particles and dimensions, e.g. "
            "`0.5 * jnp.sum(m * v**2) - V(q)`."
        )
    if not jnp.issubdtype(jnp.result_type(out), jnp.floating):
        raise ValueError(
            f"The Lagrangian must return a real floating scalar, got dtype "
            f"{jnp.result_type(out)}."
        )
    return out


def momentum(
    lagrangian: Callable[..., ArrayLike],
    t: RealScalarLike,
    q: Q,
    v: V,
    args: Args = None,
) -> P:
    r"""The momentum $p = \partial L / \partial v$ (the Legendre map).

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][] or any callable
        `L(t, q, v, args)`.
    - `t`, `q`, `v`, `args`: where to evaluate it.

    **Returns:**

    The momentum, a PyTree with the structure of `v`.
    """
    lagrangian = as_lagrangian(lagrangian)
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        mass = broadcast_mass(lagrangian.mass, v)
        return jtu.tree_map(lambda m, vi: m * vi, mass, v)
    return jax.grad(lambda _v: lagrangian_value(lagrangian, t, q, _v, args))(v)


def generalised_force(
    lagrangian: AbstractLagrangian, t: RealScalarLike, q: Q, v: V, args: Args
) -> P:
    r"""$\partial L / \partial q$."""
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        grad_v = jax.grad(lambda _q: lagrangian.potential(t, _q, args))(q)
        return jtu.tree_map(jnp.negative, grad_v)
    return jax.grad(lambda _q: lagrangian_value(lagrangian, t, _q, v, args))(q)


def velocity(
    lagrangian: Callable[..., ArrayLike],
    t: RealScalarLike,
    y: tuple[Q, P],
    args: Args = None,
    *,
    v_guess: V | None = None,
) -> tuple[V, dfx.RESULTS]:
    r"""The inverse Legendre map: the velocity $v$ with $\partial L / \partial v
    (t, q, v) = p$ at the state $y = (q, p)$.

    A division by the mass for an [`diffrax_vi.AbstractSeparableLagrangian`][], one
    linear solve with $\partial^2 L / \partial v^2$ for an
    [`diffrax_vi.AbstractQuadraticLagrangian`][], and Newton's method (optimistix, with
    a lineax LU solve) otherwise.

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][] or any callable
        `L(t, q, v, args)`.
    - `t`, `y = (q, p)`, `args`: where to invert it, in diffrax's `(t, y, args)`
        order.
    - `v_guess`: Newton's initial guess for a general Lagrangian. Defaults to zero,
        from which the first Newton iterate is the exact answer for a Lagrangian
        quadratic in `v`.

    **Returns:**

    A pair `(v, result)`. `result` is a `diffrax.RESULTS`: `RESULTS.singular` where
    $\partial^2 L / \partial v^2$ is singular (a degenerate Lagrangian), a nonlinear
    solver failure where Newton did not converge.
    """
    lagrangian = as_lagrangian(lagrangian)
    q, p = split_state(y, "y")
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        mass = broadcast_mass(lagrangian.mass, p)
        v = jtu.tree_map(lambda m, pi: pi / m, mass, p)
        zero_mass = jnp.any(jnp.stack([jnp.any(m == 0) for m in jtu.tree_leaves(mass)]))
        result = dfx.RESULTS.where(
            zero_mass, dfx.RESULTS.singular, dfx.RESULTS.successful
        )
        return v, result

    dtype = state_dtype(p)

    scale = momentum_scale(p)

    def residual(v, _):
        dp = momentum(lagrangian, t, q, v, args)
        return jtu.tree_map(lambda a, b: (a - b) / scale, dp, p)

    if isinstance(lagrangian, AbstractQuadraticLagrangian):
        # `dL/dv` is affine in `v`: `dL/dv(v) = dL/dv(0) + M v`.
        zeros = jtu.tree_map(jnp.zeros_like, p)
        r0, linear = jax.linearize(lambda v: residual(v, None), zeros)
        operator = lx.FunctionLinearOperator(
            linear, jax.eval_shape(lambda: zeros), tags=lx.symmetric_tag
        )
        sol = lx.linear_solve(
            operator, jtu.tree_map(jnp.negative, r0), lx.LU(), throw=False
        )
        v = sol.value
        result = dfx.RESULTS.promote(sol.result)
    else:
        guess = jtu.tree_map(jnp.zeros_like, p) if v_guess is None else v_guess
        sol = optx.root_find(
            residual,
            default_root_finder(dtype),
            guess,
            max_steps=32,
            throw=False,
        )
        v = sol.value
        result = dfx.RESULTS.promote(sol.result)
    # An exactly singular LU can still return finite garbage; catch it by its output.
    result = dfx.RESULTS.where(
        all_finite(v) | ~all_finite(p), result, dfx.RESULTS.singular
    )
    return v, result


def energy(
    lagrangian: Callable[..., ArrayLike],
    t: RealScalarLike,
    y: tuple[Q, P],
    args: Args = None,
) -> Scalar:
    r"""The energy $E = p \cdot v - L(t, q, v)$ at a point $y = (q, p)$ of phase
    space, with $v$ from the inverse Legendre map.

    For a time-independent Lagrangian this is the conserved Hamiltonian. The
    arguments after the first are diffrax's `(t, y, args)`, so
    `functools.partial(diffrax_vi.energy, L)` is a `diffrax.SaveAt(fn=...)`.

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][] or any callable
        `L(t, q, v, args)`.
    - `t`, `y = (q, p)`, `args`: where to evaluate it; `p` has the structure of `q`.

    **Returns:**

    The energy, a scalar; NaN if the Legendre map cannot be inverted there.
    """
    lagrangian = as_lagrangian(lagrangian)
    q, p = split_state(y, "y")
    v, result = velocity(lagrangian, t, y, args)
    pv = sum(jnp.sum(pi * vi) for pi, vi in zip(jtu.tree_leaves(p), jtu.tree_leaves(v)))
    value = pv - lagrangian_value(lagrangian, t, q, v, args)
    return jnp.where(result == dfx.RESULTS.successful, value, jnp.nan)
