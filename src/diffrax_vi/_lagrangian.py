import abc
from collections.abc import Callable
from typing import ClassVar, Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
from jaxtyping import Array, ArrayLike, Bool, PyTree

from ._custom_types import Args, P, Q, RealScalarLike, Scalar, V
from ._linear import dense_jacobian, krylov_solve, unrolled_lu_solve
from ._misc import (
    all_finite,
    call_traced_once,
    reads,
    split_state,
    state_dtype,
    tree_max_abs,
)
from ._private_api import unvmap_any
from ._root_finders import Newton, solve
from ._so3 import SO3
from ._space import AbstractSpace, Euclidean, is_euclidean, left_gradient, tangent
from ._spectrum import Extremes, invertible, symmetric_solve
from ._tolerance import (
    AFFINE_MAX_STEPS,
    KRYLOV_FLOOR,
    LEGENDRE_MAX_STEPS,
    newton_is_dense,
    newton_tolerance,
    scaled_norm,
    singular_threshold,
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

    Its configuration space is the class variable `space`,
    [`diffrax_vi.Euclidean`][] unless a subclass sets another (`space = SO3()` for a
    rigid body's attitude): then `v` and the momentum have the structure of the
    space's velocities ([`diffrax_vi.SO3`][]: the body angular velocity).
    """

    space: ClassVar[PyTree[AbstractSpace]] = Euclidean()

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
    `space` is its configuration space ([`diffrax_vi.Euclidean`][] by default;
    [`diffrax_vi.SO3`][], [`diffrax_vi.SO2`][], or a PyTree of spaces for a product,
    `(Euclidean(), SO3())` for `q = (x, R)`): on a group `fn(t, R, Omega, args)`
    takes the body velocity.

    !!! example

        ```python
        pendulum = diffrax_vi.Lagrangian(lambda t, q, v, args: 0.5 * v**2 + jnp.cos(q))
        ```
    """

    fn: Callable[..., ArrayLike]
    space: PyTree[AbstractSpace]  # pyright: ignore

    def __init__(
        self, fn: Callable[..., ArrayLike], space: PyTree[AbstractSpace] = Euclidean()
    ):
        self.fn = fn
        self.space = space

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


class AbstractRigidBodyLagrangian(AbstractQuadraticLagrangian):
    r"""Abstract base class for a rigid body on SO(3) with constant principal moments
    of inertia, $L(t, R, \Omega) = \tfrac12\Omega^\top J\Omega - V(t, R,
    \text{args})$, $J$ diagonal.

    The velocity is then $\Omega = J^{-1}\Pi$, settled when the term is built (no
    check in a Runge–Kutta solver's vector field), and [`diffrax_vi.LGVI`][], the
    Lie group variational integrator of Lee, Leok & McClamroch, can step it.

    Subclasses implement `potential` and define `inertia`, shape `(3,)`. `space` is
    [`diffrax_vi.SO3`][] with the exponential map; a subclass may set
    `space = SO3(retraction="cayley")`.
    """

    inertia: eqx.AbstractVar[ArrayLike]
    space: ClassVar[PyTree[AbstractSpace]] = SO3()

    @abc.abstractmethod
    def potential(self, t: RealScalarLike, R: Q, args: Args) -> Scalar:
        """The potential energy $V(t, R, \\text{args})$, a scalar."""

    def __call__(self, t: RealScalarLike, q: Q, v: V, args: Args) -> Scalar:
        return 0.5 * jnp.sum(self.inertia * v**2) - self.potential(t, q, args)


class AbstractMultibodyLagrangian(AbstractQuadraticLagrangian):
    r"""Abstract base class for $n$ rigid bodies, each with its centre of mass
    $x_i \in \mathbb R^3$ and attitude $R_i \in SO(3)$, constant masses $m_i$ and
    principal moments of inertia $J_i$:

    $$L = \sum_i \tfrac12 m_i|\dot x_i|^2 + \tfrac12\Omega_i^\top J_i\Omega_i
    - V(t, q, \text{args}).$$

    The position is `q = (x, R)`, shapes `(n, 3)` and `(n, 3, 3)` (space
    `(Euclidean(), SO3())`, $(\mathbb R^3)^n \times SO(3)^n$), the velocity
    `(xdot, Omega)` and the momentum `(m xdot, J Omega)`, both of shapes
    `((n, 3), (n, 3))`, Omega the body angular velocities. The velocity map is a
    division, settled when the term is built. Joints between the bodies are
    holonomic constraints on `q` ([`diffrax_vi.BallJoint`][],
    [`diffrax_vi.HingeJoint`][]).

    Subclasses implement `potential` and define `mass`, shape `(n,)`, and
    `inertia`, shape `(n, 3)`.
    """

    mass: eqx.AbstractVar[ArrayLike]
    inertia: eqx.AbstractVar[ArrayLike]
    space: ClassVar[PyTree[AbstractSpace]] = (Euclidean(), SO3())

    @abc.abstractmethod
    def potential(self, t: RealScalarLike, q: Q, args: Args) -> Scalar:
        """The potential energy $V(t, q, \text{args})$, `q = (x, R)`, a scalar."""

    def __call__(self, t: RealScalarLike, q: Q, v: V, args: Args) -> Scalar:
        xdot, omega = v
        mass = jnp.asarray(self.mass)[..., None]
        kinetic = jnp.sum(mass * xdot**2) + jnp.sum(self.inertia * omega**2)
        return 0.5 * kinetic - self.potential(t, q, args)


def declared_mass(lagrangian: AbstractLagrangian) -> PyTree[ArrayLike] | None:
    """The constant diagonal mass a Lagrangian declares, as declared (the `mass` of a
    separable Lagrangian, the `inertia` of a rigid body, both of bodies), or `None`
    for a Lagrangian that declares none."""
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        return lagrangian.mass
    if isinstance(lagrangian, AbstractRigidBodyLagrangian):
        return lagrangian.inertia
    if isinstance(lagrangian, AbstractMultibodyLagrangian):
        return (lagrangian.mass, lagrangian.inertia)
    return None


def constant_mass(lagrangian: AbstractLagrangian, p: P) -> P | None:
    """The constant diagonal mass that a Lagrangian declares (`declared_mass`), with
    the structure of `p`, or `None` for a Lagrangian that declares none."""
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        return broadcast_mass(lagrangian.mass, p)
    if isinstance(lagrangian, AbstractRigidBodyLagrangian):
        inertia = _floating(jnp.asarray(lagrangian.inertia), p)
        return jnp.broadcast_to(inertia, jnp.shape(p))
    if isinstance(lagrangian, AbstractMultibodyLagrangian):
        p_x, p_r = p
        mass = _floating(jnp.asarray(lagrangian.mass), p_x)[..., None]
        inertia = _floating(jnp.asarray(lagrangian.inertia), p_r)
        return (
            jnp.broadcast_to(mass, jnp.shape(p_x)),
            jnp.broadcast_to(inertia, jnp.shape(p_r)),
        )
    return None


def fixed_point_inverse_mass(lagrangian: AbstractLagrangian, p: P) -> P | None:
    """One over the declared mass of a separable Lagrangian or of bodies, with the
    structure of `p`: the fixed-point iteration's preconditioner, or `None` where a
    step takes Newton's method (a single rigid body, any other Lagrangian)."""
    if not isinstance(
        lagrangian, AbstractSeparableLagrangian | AbstractMultibodyLagrangian
    ):
        return None
    return jtu.tree_map(
        lambda m, x: jnp.broadcast_to(1 / jnp.abs(m), jnp.shape(x)).astype(x.dtype),
        constant_mass(lagrangian, p),
        p,
    )


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
        if not is_euclidean(self.lagrangian.space):
            raise ValueError(
                "TangentLift(L) doubles the configuration to (q, u) with u a "
                "displacement added to q, which needs a vector space; this Lagrangian "
                "lives on a group. Differentiate the solve instead (jax.jvp through "
                "diffeqsolve gives the same tangent flow)."
            )

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


def _floating(mass: ArrayLike, like: ArrayLike) -> ArrayLike:
    """An integer mass (`mass=2`, as typed) in the dtype of `like`; any other as it
    is."""
    if jnp.issubdtype(jnp.result_type(mass), jnp.inexact):
        return mass
    return jnp.asarray(mass, jnp.result_type(like))


def broadcast_mass(mass: PyTree[ArrayLike], q: Q) -> Q:
    """The mass as a PyTree with the structure of `q` (a scalar mass is shared), an
    integer mass in the dtype of `q`."""
    if jtu.tree_structure(mass) == jtu.tree_structure(q):
        for m, qi in zip(jtu.tree_leaves(mass), jtu.tree_leaves(q)):
            try:
                shape = jnp.broadcast_shapes(jnp.shape(m), jnp.shape(qi))
            except ValueError:
                shape = None
            if shape != jnp.shape(qi):
                raise ValueError(
                    f"A mass of shape {jnp.shape(m)} does not broadcast against "
                    f"positions of shape {jnp.shape(qi)}: give one mass per degree of "
                    "freedom, a scalar, or a shape that broadcasts (e.g. (bodies, 1) "
                    "for positions of shape (bodies, 3))."
                )
        return jtu.tree_map(_floating, mass, q)
    if len(jtu.tree_leaves(mass)) == 1 and jnp.ndim(jtu.tree_leaves(mass)[0]) == 0:
        (m,) = jtu.tree_leaves(mass)
        return jtu.tree_map(lambda qi: _floating(m, qi), q)
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
    out = call_traced_once(lagrangian, t, q, v, args)
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
    mass = constant_mass(lagrangian, v)
    if mass is not None:
        return jtu.tree_map(lambda m, vi: m * vi, mass, v)
    return jax.grad(lambda _v: lagrangian_value(lagrangian, t, q, _v, args))(v)


def generalised_force(
    lagrangian: AbstractLagrangian, t: RealScalarLike, q: Q, v: V, args: Args
) -> P:
    r"""$\partial L / \partial q$, left-trivialised on a group."""
    if isinstance(lagrangian, AbstractSeparableLagrangian):
        grad_v = jax.grad(lambda _q: lagrangian.potential(t, _q, args))(q)
        return jtu.tree_map(jnp.negative, grad_v)
    return left_gradient(
        lagrangian.space, lambda _q: lagrangian_value(lagrangian, t, _q, v, args), q
    )


def mass_regular(mass: PyTree[ArrayLike], like: PyTree, xp=jnp) -> Bool[ArrayLike, ""]:
    """Whether a diagonal mass is invertible: every entry finite and nonzero. Each
    velocity `p / m` is then as accurate as its momentum, however the entries
    compare: no ratio between them is a test, since it would change with the units
    of each coordinate and call a planet of 1e-8 solar masses beside the Sun
    singular in float32. Computed in the array module `xp` (JAX, or NumPy for a
    mass known now)."""
    dtype = jnp.result_type(*jtu.tree_leaves(like))
    if not jnp.issubdtype(dtype, jnp.inexact):
        # An integer mass (`mass=2`) checked against itself: in the default float.
        dtype = jnp.result_type(float)
    leaves = [xp.asarray(m, dtype) for m in jtu.tree_leaves(mass)]
    return xp.all(xp.stack([xp.all(xp.isfinite(m) & (m != 0)) for m in leaves]))


def momentum_offset(lagrangian: AbstractLagrangian, t, q: Q, args: Args) -> P:
    """`|dL/dv(t, q, 0)|`, the size of the part of the momentum that does not
    depend on the velocity (a magnetic or Coriolis term `A(q)` in `M v + A(q)`); zero
    for a separable Lagrangian. A residual's scale includes it: the momentum can
    vanish while its terms do not, and then only they say what round-off is."""
    zeros = tangent(lagrangian.space, q)
    if constant_mass(lagrangian, zeros) is not None:
        return zeros
    return jtu.tree_map(jnp.abs, momentum(lagrangian, t, q, zeros, args))


def legendre_residual(lagrangian: AbstractLagrangian, t, q: Q, p: P, args: Args):
    """`v -> (dL/dv(t, q, v) - p, |dL/dv| + |p| + |dL/dv(0)|)`: the equation of the
    inverse Legendre map and the size of the momenta it balances."""
    offset = momentum_offset(lagrangian, t, q, args)

    def residual(v):
        dp = momentum(lagrangian, t, q, v, args)
        r = jtu.tree_map(lambda a, b: a - b, dp, p)
        s = jtu.tree_map(lambda a, b, c: jnp.abs(a) + jnp.abs(b) + c, dp, p, offset)
        return r, s

    return residual


NOT_QUADRATIC = (
    "This Lagrangian is marked `AbstractQuadraticLagrangian` but is not quadratic in "
    "the velocity: dL/dv(v) != p at the velocity of the one linear solve the marker "
    "allows, so every velocity would be wrong. Subclass `AbstractLagrangian` instead."
)


# How the velocity of a Lagrangian marked quadratic in `v` checks that marker, a
# promise (`_explicit_velocity`): "raise", a host callback, where the caller cannot
# report a result (the public functions, a start, a vector field); "nan", a NaN
# velocity, which the caller reports, for what is traced into a time-stepping loop
# whose solve checked its own start (a study's energy at every step: with a callback
# there XLA no longer compiles the loop whole, and the double pendulum's tracked
# `TrapezoidalVI` solve took 0.97-1.19 against 0.18-0.19 s); "trust", no check,
# inside a solve's steps and their dense output, after its start has checked it.
Promise = Literal["raise", "nan", "trust"]


def quadratic_in_velocity(
    lagrangian: AbstractLagrangian, t: RealScalarLike, q: Q, args: Args
) -> bool:
    r"""Whether $\partial^2 L/\partial v^2$ provably does not depend on $v$: its
    products $w \mapsto \partial^2 L/\partial v^2\,w$, as traced, never read $v$.
    Structural and conservative (a Lagrangian quadratic in $v$ in a way the trace
    does not show, e.g. through `jnp.linalg.norm(v) ** 2`, is not recognised), and
    decided at trace time. Then $\partial L/\partial v$ is affine in $v$ and one
    linear solve inverts it exactly."""
    zeros = tangent(lagrangian.space, q)

    def hvp(v, w):
        return jax.jvp(lambda _v: momentum(lagrangian, t, q, _v, args), (v,), (w,))[1]

    return not reads(hvp, zeros, zeros)


def momentum_reads_position(
    lagrangian: AbstractLagrangian, t: RealScalarLike, q: Q, v: V, args: Args
) -> bool:
    r"""Whether $\partial L/\partial v$ may depend on $q$, decided from its traced
    program (structural and conservative, as `quadratic_in_velocity`). Where it
    does not, $\partial^2 L/\partial q\,\partial v = 0$ and the Jacobians of the
    midpoint step and of the linearized step are symmetric."""
    return reads(lambda _q: momentum(lagrangian, t, _q, v, args), q)


def _diagonal_estimate(matvec, like: PyTree) -> tuple[PyTree, Bool[Array, ""]]:
    """Positive weights approximating one over the diagonal of a symmetric matrix,
    from one product with the alternating vector `z = (1, -1, 1, ...)`: `z * (A z)`
    is the diagonal of a diagonal matrix exactly, and of a diagonally dominant one
    nearly. Entries the probe cannot estimate (not above `sqrt(eps)` of the largest)
    get the smallest weight; the flag says whether there were none."""
    signs = jtu.tree_map(
        lambda x: (
            jnp.where(jnp.arange(x.size) % 2 == 0, 1, -1)
            .reshape(x.shape)
            .astype(x.dtype)
        ),
        like,
    )
    diagonal = jtu.tree_map(lambda z, az: z * az, signs, matvec(signs))
    largest = jnp.max(
        jnp.stack([jnp.max(jnp.abs(d)) for d in jtu.tree_leaves(diagonal)])
    )
    floor = jnp.sqrt(jnp.finfo(largest.dtype).eps) * largest
    weights = jtu.tree_map(
        lambda d: 1 / jnp.where(d > floor, d, jnp.where(largest > 0, largest, 1)),
        diagonal,
    )
    regular = jnp.all(
        jnp.stack([jnp.all(d > floor) for d in jtu.tree_leaves(diagonal)])
    )
    return weights, regular


def _affine_velocity(lagrangian, t, q, p, args, krylov: bool) -> tuple[V, dfx.RESULTS]:
    """The velocity of a Lagrangian whose momentum is affine in `v`, matrix-free: the
    Jacobi step `D^{-1} b` from an estimate `D` of the diagonal of `d2L/dv2` where
    it solves the system to round-off (a diagonal mass: point masses, beads on
    wires), else (with `krylov`) one conjugate-gradient solve of Hessian-vector
    products to round-off from there, preconditioned by `D^{-1}`. `breakdown` where
    it does not converge (an ill-conditioned or indefinite d2L/dv2, or a mass that
    is not diagonal without `krylov`); `singular` for a diagonal mass with a zero
    entry."""
    zeros = jtu.tree_map(jnp.zeros_like, p)
    p_rest, hvp = jax.linearize(lambda v: momentum(lagrangian, t, q, v, args), zeros)
    rhs = jtu.tree_map(lambda a, b: a - b, p, p_rest)
    eps = float(jnp.finfo(state_dtype(p)).eps)
    n = sum(jnp.size(x) for x in jtu.tree_leaves(p))
    weights, regular = _diagonal_estimate(hvp, p)
    jacobi = jtu.tree_map(lambda w, b: w * b, weights, rhs)
    r = jtu.tree_map(lambda b, a: b - a, rhs, hvp(jacobi))
    # One more Jacobi sweep: where D = d2L/dv2 it leaves the value at round-off and
    # makes the derivative the implicit one, D^{-1} (db - dD v), even at a point
    # where the mass happens to be diagonal and its derivative is not.
    v = jtu.tree_map(lambda x, w, ri: x + w * ri, jacobi, weights, r)
    # The Jacobi step solved the system (so `D` is d2L/dv2) where it leaves a
    # residual at round-off of a right-hand side that is not zero. A zero one (the
    # momentum at rest) is solved by v = 0 whatever the matrix, and tells nothing
    # of it: the diagonal estimate of a coupled mass (the double pendulum's) can
    # vanish there, which must not read as a singular diagonal mass.
    size = tree_max_abs(rhs)
    diagonal = lax.stop_gradient(
        (size > 0) & (tree_max_abs(r) <= KRYLOV_FLOOR * eps * size)
    )
    solved = diagonal & regular

    def conjugate_gradients():
        return krylov_solve(
            hvp,
            rhs,
            KRYLOV_FLOOR * eps,
            frozenset({lx.symmetric_tag, lx.positive_semidefinite_tag}),
            min(n + 1, AFFINE_MAX_STEPS),
            preconditioner=weights,
            guess=v,
        )

    if krylov:
        v, linear_result = lax.cond(
            unvmap_any(~solved),
            conjugate_gradients,
            lambda: (v, lx.RESULTS.successful),
        )
    else:
        linear_result = lx.RESULTS.where(
            solved, lx.RESULTS.successful, lx.RESULTS.breakdown
        )
    result = dfx.RESULTS.where(
        linear_result == lx.RESULTS.successful,
        dfx.RESULTS.successful,
        dfx.RESULTS.breakdown,
    )
    # A diagonal mass with an entry at zero: CG would solve a consistent system
    # (zero momentum there) and hide it.
    return v, dfx.RESULTS.where(diagonal & ~regular, dfx.RESULTS.singular, result)


# Newton for the inverse Legendre map of a general Lagrangian: damped, so that it
# converges from a poor start (the relativistic particle's velocity from v = 0 at
# p0 = 3 overshoots |v| < 1 without damping).
_LEGENDRE_NEWTON = Newton(damped=True)


# The public functions a user calls outside `jit` (after a solve, over its saved
# states) are one compiled program each, as `diffrax.diffeqsolve` is; op by op their
# first calls took 2-9 times longer (benchmarks/helpers_first_call.py). The package
# itself calls `inverse_legendre` and `energy_value`, inside its own programs.
@eqx.filter_jit
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

    A division by the mass for an [`diffrax_vi.AbstractSeparableLagrangian`][]; one
    dense linear solve with $\partial^2 L / \partial v^2$ for an
    [`diffrax_vi.AbstractQuadraticLagrangian`][] of at most 16 degrees of freedom;
    for any other Lagrangian whose traced Hessian–vector products do not read $v$
    (quadratic in $v$, whatever its class beyond 16 degrees of freedom), a division
    by the diagonal of $\partial^2 L / \partial v^2$ where that solves it to
    round-off (a diagonal mass; `RESULTS.singular` if an entry is zero), else beyond
    16 degrees of freedom a conjugate-gradient solve to round-off; and damped Newton
    iterations
    ([`diffrax_vi.Newton`][], dense or matrix-free by size) otherwise, or where the
    matrix-free solve fails. Where it factorises $\partial^2 L / \partial v^2$ (or
    the mass) it checks that it is invertible to working precision.

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][] or any callable
        `L(t, q, v, args)`.
    - `t`, `y = (q, p)`, `args`: where to invert it, in diffrax's `(t, y, args)`
        order.
    - `v_guess`: Newton's initial guess. Defaults to zero, from which the first
        Newton iterate is the answer for a Lagrangian quadratic in `v`.

    Like [`diffrax_vi.energy`][], one compiled program when called outside `jit`.

    **Returns:**

    A pair `(v, result)`, `result` a `diffrax.RESULTS`: `RESULTS.singular` where
    $\partial^2 L / \partial v^2$ (or the mass) is singular to working precision (a
    degenerate Lagrangian), `RESULTS.breakdown` where Newton's method could not
    invert the map of a regular Lagrangian, `RESULTS.nonfinite` where a finite state
    gave a NaN or inf velocity (NaN in the Lagrangian, its parameters or `args`).
    """
    return inverse_legendre(lagrangian, t, y, args, v_guess, promise="raise")


def inverse_legendre(
    lagrangian: Callable[..., ArrayLike],
    t: RealScalarLike,
    y: tuple[Q, P],
    args: Args,
    v_guess: V | None,
    promise: Promise,
) -> tuple[V, dfx.RESULTS]:
    """[`diffrax_vi.velocity`][], checking as `promise` says that a Lagrangian
    marked quadratic in `v` is (`Promise`)."""
    lagrangian = as_lagrangian(lagrangian)
    q, p = split_state(y, "y", lagrangian.space)
    mass = constant_mass(lagrangian, p)
    if mass is not None:
        v = jtu.tree_map(lambda m, pi: pi / m, mass, p)
        result = dfx.RESULTS.where(
            mass_regular(mass, p), dfx.RESULTS.successful, dfx.RESULTS.singular
        )
        return v, result_or_nonfinite(v, p, result)

    n = sum(jnp.size(x) for x in jtu.tree_leaves(p))
    dtype = state_dtype(p)
    if velocity_is_explicit(lagrangian, p):
        # By unrolled elimination. Differentiated (RATTLE's projection
        # differentiates the velocity), lineax's solve would check its tangent solve
        # and raise on a NaN state, where this returns NaN for the step to report.
        def eliminate(matrix, b):
            x, ratio = unrolled_lu_solve(matrix, b)
            # NaN pivots (a NaN Lagrangian) are not a singular one: `nonfinite`.
            return x, ~(ratio <= singular_threshold(n, dtype)), None

        v, result, _ = _explicit_velocity(lagrangian, t, q, p, args, promise, eliminate)
        return v, result

    residual = legendre_residual(lagrangian, t, q, p, args)
    zeros = jtu.tree_map(jnp.zeros_like, p)

    def newton(v_guess):
        solved = solve(
            residual,
            v_guess,
            _LEGENDRE_NEWTON,
            max_steps=LEGENDRE_MAX_STEPS,
            tags=frozenset({lx.symmetric_tag, lx.positive_semidefinite_tag}),
        )
        regular = ~(solved.pivot_ratio <= singular_threshold(n, dtype))
        converged = solved.result == dfx.RESULTS.successful
        return solved.value, dfx.RESULTS.where(
            ~regular,
            dfx.RESULTS.singular,
            dfx.RESULTS.where(converged, dfx.RESULTS.successful, dfx.RESULTS.breakdown),
        )

    guess = zeros if v_guess is None else v_guess
    if quadratic_in_velocity(lagrangian, t, q, args):
        # One solve (Newton's first iterate, to round-off) without its two
        # evaluations of the residual; Newton from there where it fails. Up to
        # 16 degrees of freedom a mass that is not diagonal goes to Newton's
        # dense LU, whose pivots tell a singular one.
        krylov = not newton_is_dense(n)
        v, result = _affine_velocity(lagrangian, t, q, p, args, krylov)
        failed = result == dfx.RESULTS.breakdown
        v_newton, result_newton = lax.cond(
            unvmap_any(failed), lambda: newton(guess), lambda: (v, result)
        )
        v = jtu.tree_map(lambda a, b: jnp.where(failed, b, a), v, v_newton)
        result = dfx.RESULTS.where(failed, result_newton, result)
    else:
        v, result = newton(guess)
    return v, result_or_nonfinite(v, p, result)


def _explicit_velocity(
    lagrangian: AbstractLagrangian,
    t: RealScalarLike,
    q: Q,
    p: P,
    args: Args,
    promise: Promise,
    linear_solve: Callable[[Array, Array], tuple[Array, Bool[Array, ""], PyTree]],
) -> tuple[V, dfx.RESULTS, PyTree]:
    """The velocity of a Lagrangian marked quadratic in `v` (`velocity_is_explicit`,
    without a constant mass), whose `dL/dv` is affine in `v`: one solve
    `linear_solve(M, b) -> (x, regular, extra)` with `M = d2L/dv2` from `v = 0`; its
    result, and `extra`."""
    residual = legendre_residual(lagrangian, t, q, p, args)
    flat_zeros, unravel = jax.flatten_util.ravel_pytree(jtu.tree_map(jnp.zeros_like, p))

    def flat_residual(x):
        return jax.flatten_util.ravel_pytree(residual(unravel(x))[0])[0]

    r0 = flat_residual(flat_zeros)
    x, regular, extra = linear_solve(dense_jacobian(flat_residual, flat_zeros), -r0)
    # The marker is a promise: if `L` is not quadratic in `v` after all, the one
    # solve is wrong, and the residual at its answer says so.
    v = unravel(x)
    if promise != "trust":
        broken = regular & _breaks(residual, v, flat_zeros.dtype)
        if promise == "raise":
            v = eqx.error_if(v, broken, NOT_QUADRATIC)
        else:
            v = jtu.tree_map(lambda x: jnp.where(broken, jnp.nan, x), v)
    result = dfx.RESULTS.where(regular, dfx.RESULTS.successful, dfx.RESULTS.singular)
    return v, result_or_nonfinite(v, p, result), extra


def _breaks(residual, v: V, dtype) -> Bool[Array, ""]:
    # The marker's promise broken: dL/dv(v) != p at the one solve's velocity.
    return scaled_norm(*residual(v)) > newton_tolerance(dtype)


def broken_promise(
    lagrangian: AbstractLagrangian, t: RealScalarLike, y: tuple[Q, P], args: Args, v: V
) -> Bool[ArrayLike, ""]:
    """Where a Lagrangian marked quadratic in `v`, whose velocity
    `inverse_legendre` takes from one linear solve, is not: `v` (that solve's,
    taken with `promise="trust"`) has `dL/dv(v) != p` (`NOT_QUADRATIC`). `False`
    where no such solve is made (a constant mass, a general Lagrangian)."""
    q, p = split_state(y, "y", lagrangian.space)
    if constant_mass(lagrangian, p) is not None or not velocity_is_explicit(
        lagrangian, p
    ):
        return False
    residual = legendre_residual(lagrangian, t, q, p, args)
    return _breaks(residual, v, state_dtype(p))


def explicit_start(
    lagrangian: AbstractLagrangian,
    t: RealScalarLike,
    y: tuple[Q, P],
    args: Args,
    promise: Promise = "raise",
) -> tuple[V, dfx.RESULTS, Extremes]:
    """`inverse_legendre` at a solve's start for a Lagrangian marked quadratic in
    `v` (`velocity_is_explicit`, without a constant mass), with the
    `symmetric_extremes` of `d2L/dv2` that the start checks: both from one
    eigendecomposition of one matrix (`symmetric_solve`), not an elimination and a
    second matrix. Checks the promise as `promise` says (`inverse_legendre`)."""
    q, p = split_state(y, "y", lagrangian.space)

    def by_spectrum(matrix, b):
        x, extremes = symmetric_solve(matrix, b)
        return x, invertible(extremes, b.shape[0], b.dtype), extremes

    return _explicit_velocity(lagrangian, t, q, p, args, promise, by_spectrum)


def velocity_is_explicit(lagrangian: AbstractLagrangian, p: P) -> bool:
    """Whether `velocity` computes $v(q, p)$ without a root finder, by
    differentiable arithmetic: a separable Lagrangian ($M^{-1}p$), or one marked
    quadratic in $v$ with few enough degrees of freedom for a dense solve
    (`newton_is_dense`: one unrolled elimination)."""
    if constant_mass(lagrangian, p) is not None:
        return True
    n = sum(jnp.size(x) for x in jtu.tree_leaves(p))
    return isinstance(lagrangian, AbstractQuadraticLagrangian) and newton_is_dense(n)


def result_or_nonfinite(v: V, p: P, result: dfx.RESULTS) -> dfx.RESULTS:
    """`RESULTS.nonfinite` for a NaN or inf velocity from a finite momentum that no
    other check explains (NaN from the Lagrangian, its parameters or `args`, with
    which Newton's method cannot converge either)."""
    bad = (result != dfx.RESULTS.singular) & ~all_finite(v) & all_finite(p)
    return dfx.RESULTS.where(bad, dfx.RESULTS.nonfinite, result)


@eqx.filter_jit
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

    Called outside `jit` (over a solve's saved states, say, under `jax.vmap`), it
    is one compiled program, as `diffrax.diffeqsolve` is: a Python number among
    its arguments is part of that program, so a new value of `t` compiles again
    where a JAX array would not ([Benchmarks](../benchmarks.md#helpers-first-call)).

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][] or any callable
        `L(t, q, v, args)`.
    - `t`, `y = (q, p)`, `args`: where to evaluate it; `p` has the structure of `q`.

    **Returns:**

    The energy, a scalar; NaN if the Legendre map cannot be inverted there.
    """
    return energy_value(lagrangian, t, y, args)


def energy_value(
    lagrangian: Callable[..., ArrayLike],
    t: RealScalarLike,
    y: tuple[Q, P],
    args: Args,
    promise: Promise = "raise",
) -> Scalar:
    """[`diffrax_vi.energy`][], traced into the caller's program (`promise` as for
    `inverse_legendre`)."""
    lagrangian = as_lagrangian(lagrangian)
    q, p = split_state(y, "y", lagrangian.space)
    v, result = inverse_legendre(lagrangian, t, y, args, None, promise)
    pv = sum(jnp.sum(pi * vi) for pi, vi in zip(jtu.tree_leaves(p), jtu.tree_leaves(v)))
    value = pv - lagrangian_value(lagrangian, t, q, v, args)
    return jnp.where(result == dfx.RESULTS.successful, value, jnp.nan)
