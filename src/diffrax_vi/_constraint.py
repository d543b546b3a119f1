r"""Holonomic constraints $g(t, q) = 0$ ($m$ values): their Jacobian $G = \partial g /
\partial q$, the hidden constraint on the momenta, and the projections onto both.

A constrained motion satisfies $g(t, q) = 0$ and, differentiating once, the hidden
constraint $G(q)\,v(q, p) = 0$ (for constraints that do not depend on time): the
state lives on a submanifold of phase space of dimension $2(n - m)$. The constraint
forces $-G^\top\lambda$ keep it there (Marsden & West (2001), §3.5; Hairer, Lubich &
Wanner (2006), VII.1).

On a Lie group (a Lagrangian whose `space` is [`diffrax_vi.SO3`][], or a product
with one) $G$ is taken along the space's tangent directions, left-trivialised:
$G\eta = \frac{d}{ds} g(q \oplus s\eta)|_{s=0}$, so that $G\xi$ is $\dot g$ for
the body velocity $\xi$ and a multiplier acts through $G^\top\lambda$ as a force
and a body torque in the dual algebra, where the momentum lives (Leyendecker,
Marsden & Ortiz (2008); Lee, Leok & McClamroch (2005)). In a vector space this is
the usual Jacobian.

Every tolerance here is relative to the terms the equation balances (for $g$, the
linearised sizes $|G|\,|q|$, with an angle counted as 1), so that it does not
depend on the units.
"""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
from jaxtyping import Array, Float, PyTree

from ._custom_types import Args, P, Q, RealScalarLike
from ._lagrangian import (
    constant_mass,
    inverse_legendre,
    legendre_residual,
    momentum,
    velocity_is_explicit,
)
from ._linear import (
    dense_jacobian,
    pivot_ratio,
    product,
    unit_scale,
    unpivoted_solve,
    unrolled_lu_apply,
    unrolled_lu_factor,
    unrolled_lu_solve,
)
from ._misc import all_finite, call_traced_once, split_state, state_dtype
from ._root_finders import known_root, Newton, solve
from ._space import (
    is_euclidean,
    retract,
    scale as space_scale,
    tangent,
    tangent_line,
    velocity as space_velocity,
)
from ._tolerance import (
    newton_is_dense,
    newton_tolerance,
    scaled_norm,
    singular_threshold,
)


def constraint_values(
    constraint: Callable[..., PyTree], t: RealScalarLike, q: Q, args: Args
) -> Float[Array, " m"]:
    """`g(t, q, args)` as a flat array (an array or any pytree of them, in the order
    of its leaves), checked at trace time to be real floating in at least the
    precision of the state."""
    values = call_traced_once(constraint, t, q, args)
    leaves = [jnp.asarray(x) for x in jtu.tree_leaves(values)]
    if sum(x.size for x in leaves) == 0:
        raise ValueError(
            "The constraint returned no values: pass `constraint=None` for an "
            "unconstrained system."
        )
    dtype = state_dtype(q)
    for x in leaves:
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(
                f"The constraint must return real floating values g(t, q, args), got "
                f"dtype {x.dtype}."
            )
        if jnp.finfo(x.dtype).eps > jnp.finfo(dtype).eps:
            raise ValueError(
                f"The constraint returns {x.dtype} values in a {dtype} solve: their "
                f"round-off ({jnp.finfo(x.dtype).eps:.0e}) is above the accuracy the "
                "solve keeps g = 0 to, so no step could meet it. Compute the "
                "constraint in the dtype of q (no float32 constants or casts)."
            )
    return jnp.concatenate([jnp.ravel(x).astype(dtype) for x in leaves])


def _along(constraint, t, q: Q, args: Args, space) -> tuple[Callable, PyTree]:
    """`g` as a function of a tangent increment at `q` (the position itself in a
    vector space; along the tangent line $q + \\dot q(\\eta)$ on a group, equal to
    $q \\oplus \\eta$ to first order), and the point to differentiate it at."""
    if space is None or is_euclidean(space):
        return (lambda x: constraint_values(constraint, t, x, args)), q
    return (
        lambda eta: constraint_values(constraint, t, tangent_line(space, q, eta), args)
    ), tangent(space, q)


def constraint_jacobian(
    constraint: Callable[..., PyTree], t: RealScalarLike, q: Q, args: Args, space=None
) -> Float[Array, "m n"]:
    """$G = \\partial g / \\partial q$ as a dense `(m, n)` matrix over the flattened
    tangent directions of `space` (`None`: a vector space, `n` the size of `q`),
    one reverse pass per constraint."""
    fn, at = _along(constraint, t, q, args, space)
    flat, unravel = jax.flatten_util.ravel_pytree(at)
    return jax.jacrev(lambda x: fn(unravel(x)))(flat)


def transpose_product(
    constraint: Callable[..., PyTree], t: RealScalarLike, q: Q, args: Args, space=None
) -> Callable[[Array], P]:
    """`lam -> G(q)^T lam`, a generalised force with the structure of a momentum
    (of `q` in a vector space)."""
    fn, at = _along(constraint, t, q, args, space)
    _, vjp = jax.vjp(fn, at)
    return lambda lam: vjp(lam)[0]


def constraint_scale(jacobian: Array, q: Q, space=None) -> Float[Array, " m"]:
    """$|G|\\,|q|$: the size of the terms a constraint value balances, to which its
    residual is compared (on a group, an angle counts as 1: `AbstractSpace.scale`)."""
    size = q if space is None else space_scale(space, q)
    return product(jnp.abs(jacobian), jnp.abs(_flat(size)))


def _flat(tree: PyTree) -> Array:
    return jax.flatten_util.ravel_pytree(tree)[0]


def constraint_rate(
    constraint: Callable[..., PyTree], t: RealScalarLike, q: Q, args: Args
) -> Float[Array, " m"]:
    """$\\partial g/\\partial t$ (zero for a constraint independent of time)."""
    dtype = state_dtype(q)
    return jax.jvp(
        lambda s: constraint_values(constraint, s, q, args),
        (jnp.asarray(t, dtype),),
        (jnp.ones((), dtype),),
    )[1]


def hidden_constraint(jacobian: Array, v: PyTree, rate: Array) -> tuple[Array, Array]:
    """The hidden constraint $G v + \\partial g/\\partial t$ and its scale
    $|G|\\,|v| + |\\partial g/\\partial t|$."""
    flat = _flat(v)
    return (
        product(jacobian, flat) + rate,
        product(jnp.abs(jacobian), jnp.abs(flat)) + jnp.abs(rate),
    )


def rank_ok(jacobian: Array) -> Array:
    """Whether $G$ has full row rank to working precision (its singular values),
    each constraint's row scaled to a largest entry of one (a zero row left as it
    is): a constraint's unit scales its row, which changes the ratio of the
    singular values but not the rank (a closure constraint in units 1e8 times
    smaller than the other made the four-bar's constraints look redundant in
    float32). Coordinates' units scale columns and move the ratio by at most their
    own ratio; scaling the columns too cost the four-bar's first call 0.1-0.2 s of
    compilation (a few operations on a 2 x 3 matrix before LAPACK's SVD), so they
    are left as they are."""
    m, n = jacobian.shape
    if m > n:
        return jnp.array(False)
    largest = jnp.max(jnp.abs(jacobian), axis=1, keepdims=True)
    jacobian = jacobian / jnp.where(largest > 0, largest, 1)
    # Of the transpose: with XLA on CPU (jax 0.10.2), `svd(G)` in a program that
    # also multiplies G by the velocity returned that product with another
    # column of G (a hinge's start refused as off its constraint;
    # `tests/test_joints.py`, the Lie groups page's mechanism).
    s = jnp.linalg.svd(jacobian.T, compute_uv=False)
    return (s[-1] > singular_threshold(n, jacobian.dtype) * s[0]) & jnp.all(
        jnp.isfinite(s)
    )


class Projected(eqx.Module):
    """A momentum projected onto the hidden constraint, the constraint impulse
    $-G^\\top\\mu$ that moved it there, its multiplier $\\mu$, and whether the
    projection succeeded."""

    p: P
    impulse: P
    multiplier: Array
    result: dfx.RESULTS


def project_momentum(
    term,
    t: RealScalarLike,
    q: Q,
    p: P,
    args: Args,
) -> Projected:
    r"""$p - G(q)^\top\mu$ with $\mu$ such that $G(q)\,v(q, p - G^\top\mu)
    + \partial g/\partial t = 0$: the momentum on the hidden constraint (RATTLE's
    projection, Hairer, Lubich & Wanner (2006), VII.1.4). Where the velocity is
    affine in the momentum, $v(q, p - G^\top\mu) = v(q, p) - M^{-1}G^\top\mu$ (a
    Lagrangian that declares a constant mass: separable, or rigid bodies in the body
    frame; or one marked quadratic in $v$ with at most 16 degrees of freedom), the
    equation is linear, $(G M^{-1} G^\top)\mu = G v(q, p) + \partial g/\partial t$:
    up to 16 constraints (`newton_is_dense`), one $m \times m$ solve by unrolled
    elimination (`project_affine`; `RESULTS.singular` where $G M^{-1} G^\top$ is
    singular to working precision). Beyond 16 constraints, Newton's method on $\mu$,
    which one iteration solves.

    Where the velocity is itself a root (a Lagrangian not known to be quadratic in
    $v$, or one of more than 16 degrees of freedom), Newton's method solves for
    $v$ and $\mu$ together, $\partial L/\partial v(q, v) = p - G^\top\mu$ and
    $G v + \partial g/\partial t = 0$, rather than differentiate the inner root:
    the implicit derivative of that root is a linear solve that raises on a NaN
    state instead of letting the step report `nonfinite`."""
    g = term.constraint
    space = term.lagrangian.space
    jacobian = constraint_jacobian(g, t, q, args, space)
    rate = constraint_rate(g, t, q, args)
    m = jacobian.shape[0]

    # Inside a step the solve's start has checked the quadratic marker.
    def velocity(p):
        return inverse_legendre(term.lagrangian, t, (q, p), args, None, "trust")

    if newton_is_dense(m) and constant_mass(term.lagrangian, p) is not None:
        return project_constant_mass(
            term.lagrangian, jacobian, rate, p, term.mass_definite
        )
    if newton_is_dense(m) and velocity_is_explicit(term.lagrangian, p):
        return project_affine(jacobian, rate, p, velocity)
    # Newton's method on the multipliers: G^T mu by a reverse pass of the
    # constraint, traced only here.
    push = transpose_product(g, t, q, args, space)
    mu0 = jnp.zeros((m,), state_dtype(p))

    def impulse(mu):
        return jtu.tree_map(jnp.negative, push(mu))

    def moved(mu):
        return jtu.tree_map(lambda a, b: a + b, p, impulse(mu))

    if velocity_is_explicit(term.lagrangian, p):

        def residual(mu):
            return hidden_constraint(jacobian, velocity(moved(mu))[0], rate)

        solved = solve(residual, mu0, Newton(), 16)
        mu = solved.value
    else:

        def residual(unknowns):
            v, mu = unknowns
            legendre = legendre_residual(term.lagrangian, t, q, moved(mu), args)(v)
            return tuple(zip(legendre, hidden_constraint(jacobian, v, rate)))

        zeros = jtu.tree_map(jnp.zeros_like, p)
        solved = solve(residual, (zeros, mu0), Newton(), 32)
        mu = solved.value[1]
    kick = impulse(mu)
    return Projected(jtu.tree_map(lambda a, b: a + b, p, kick), kick, mu, solved.result)


def _reduced_solve(
    matrix: Array, b: Array, solve=unrolled_lu_solve
) -> tuple[Array, Array]:
    r"""`matrix^-1 b` for $G W G^\top$ ($W$ an inverse mass), and the pivot ratio,
    in units of its diagonal: `solve` of $D\,G W G^\top D$, $D =
    |\mathrm{diag}|^{-1/2}$ (a zero entry unscaled). Each constraint's unit scales a
    row and a column of $G W G^\top$ (and coordinates' units cancel in it), so the
    ratio, tested against $m\,\varepsilon$, is the same in any units: of the matrix as
    given, the rigid double pendulum with every other joint constraint in units
    $10^4$ times smaller was judged unsolvable in float32 under Tsit5."""
    if b.shape[0] == 1:  # Its ratio is 1 (or 0) in any units; no scaling.
        return solve(matrix, b)
    scale = unit_scale(jnp.diagonal(matrix))
    y, ratio = solve(scale[:, None] * matrix * scale[None, :], scale * b)
    return scale * y, ratio


def project_affine(
    jacobian: Array,
    rate: Array,
    p: P,
    velocity: Callable[[P], tuple[PyTree, dfx.RESULTS]],
    definite: bool = False,
) -> Projected:
    r"""`project_momentum` where `velocity(p) -> (v, result)` is affine in `p`,
    $v(p - G^\top\mu) = v(p) - M^{-1}G^\top\mu$, given the constraint Jacobian $G$
    and rate $\partial g/\partial t$ at the point: one $m \times m$ solve of
    $(G M^{-1} G^\top)\mu = G v(p) + \partial g/\partial t$ by unrolled elimination
    (no LAPACK call in the step), with $M^{-1}G^\top$ from the velocity's derivative
    along the rows of $G$. On a group $G$ is left-trivialised and $p$ the body-frame
    momentum. The matrix is symmetric and definite where the mass is definite and
    the constraints are independent; where that is known when the step is traced
    (`definite`: a declared constant mass, known where the term was built and
    positive, `LagrangianTerm.mass_definite`) the elimination needs no pivoting
    (`unpivoted_solve`): the rigid double pendulum's first call about 10% shorter,
    and its step 1% faster, than with partial pivoting. Otherwise (a mass that
    depends on $q$, one traced where the term was built, or an indefinite
    $\partial^2 L/\partial v^2$, which the start admits) it pivots
    (`unrolled_lu_solve`): without pivoting, a small leading minor of an indefinite
    matrix would give a multiplier with no error bound. Newton's
    method on $\mu$ reaches the same root in one iteration, but puts a loop and its
    termination in every step's program (the four-bar's, whose mass depends on its
    angles, too).

    $\mu$ is differentiated as the root of the hidden constraint
    (`known_root`), as Newton's was: differentiating the elimination itself made
    the four-bar's gradient programs larger to compile (its `ReversibleAdjoint`
    gradient 7.1-8.5 s against 5.2-5.7 s)."""
    flat_p, unravel = jax.flatten_util.ravel_pytree(p)

    def flat_velocity(x):
        v, result = velocity(unravel(x))
        return _flat(v), result

    def residual(mu):
        return hidden_constraint(
            jacobian, velocity(unravel(flat_p - product(jacobian.T, mu)))[0], rate
        )

    v, along, result = jax.linearize(flat_velocity, flat_p, has_aux=True)
    weighted = jax.vmap(along)(jacobian)  # Row j: M^-1 G^T e_j.
    mu, ratio = _reduced_solve(
        product(weighted, jacobian.T),
        product(jacobian, v) + rate,
        unpivoted_solve if definite else unrolled_lu_solve,
    )
    mu = known_root(residual, mu).value
    # NaN pivots (a NaN state) are not a singular matrix: the step's check of the
    # new state reports them.
    regular = ~(ratio <= singular_threshold(jacobian.shape[0], jacobian.dtype))
    result = dfx.RESULTS.where(
        regular | (result != dfx.RESULTS.successful), result, dfx.RESULTS.singular
    )
    impulse = -product(jacobian.T, mu)
    return Projected(unravel(flat_p + impulse), unravel(impulse), mu, result)


def project_constant_mass(
    lagrangian, jacobian: Array, rate: Array, p: P, definite: bool
) -> Projected:
    """`project_affine` for a Lagrangian that declares a constant mass
    (`constant_mass`), $v = M^{-1}p$; `definite` where that mass is known to be
    positive (`LagrangianTerm.mass_definite`)."""
    inverse_mass = jtu.tree_map(lambda m: 1 / m, constant_mass(lagrangian, p))
    return project_affine(
        jacobian,
        rate,
        p,
        lambda p: (jtu.tree_map(jnp.multiply, inverse_mass, p), dfx.RESULTS.successful),
        definite,
    )


# One compiled program, like `velocity` and `energy`: op by op, its Newton solves,
# projection and checks were compiled apart and dispatched again on every call.
@eqx.filter_jit
def project_onto_constraints(
    term, t0: RealScalarLike, y0: tuple[Q, P], args: Args = None
) -> tuple[tuple[Q, P], dfx.RESULTS]:
    r"""Consistent initial data for a constrained [`diffrax_vi.LagrangianTerm`][]: the
    state nearest to `y0` with $g(t_0, q) = 0$ and $G(q)\,v(q, p) = 0$.

    The positions move along the constraint normals at `q0`,
    $q = q_0 \oplus G(q_0)^\top\lambda$ ($q_0 + G^\top\lambda$ in a vector
    space), with $\lambda$ from Newton's method on $g(q) = 0$ (to first order the
    Euclidean projection); the momentum is then
    projected onto the hidden constraint, $p = p_0 - G(q)^\top\mu$ (the projection of
    the velocity in the metric $\partial^2 L/\partial v^2$).

    **Arguments:**

    - `term`: a [`diffrax_vi.LagrangianTerm`][] with a `constraint`.
    - `t0`, `y0 = (q0, p0)`, `args`: as for `diffeqsolve`.

    Like [`diffrax_vi.energy`][], one compiled program when called outside `jit`.

    **Returns:**

    `((q, p), result)`, `result` a `diffrax.RESULTS`: successful, or why Newton's
    method failed (a constraint Jacobian that loses rank, a `y0` too far from the
    constraint manifold for Newton's method to reach it).

    **Raises:**

    `ValueError` if the term has no constraint.
    """
    if term.constraint is None:
        raise ValueError(
            "project_onto_constraints needs a LagrangianTerm with a constraint: "
            "`LagrangianTerm(L, constraint=g)`."
        )
    space = term.lagrangian.space
    q0, p0 = split_state(y0, "y0", space)
    g = term.constraint
    push = transpose_product(g, t0, q0, args, space)
    jacobian0 = constraint_jacobian(g, t0, q0, args, space)
    m = jacobian0.shape[0]

    def moved(lam):
        return retract(space, q0, push(lam))

    def residual(lam):
        q = moved(lam)
        return constraint_values(g, t0, q, args), constraint_scale(jacobian0, q, space)

    solved = solve(residual, jnp.zeros((m,), state_dtype(q0)), Newton(), 32)
    q = moved(solved.value)
    projected = project_momentum(term, t0, q, p0, args)
    ok = rank_ok(jacobian0)
    result = dfx.RESULTS.where(ok, solved.result, dfx.RESULTS.singular)
    result = dfx.RESULTS.where(
        result == dfx.RESULTS.successful, projected.result, result
    )
    return (q, projected.p), result


OFF_MANIFOLD = (
    "y0 is not on the constraint manifold: |g(t0, q0)| or the hidden constraint "
    "|G(q0) v(q0, p0)| exceeds sqrt(eps) of the terms it balances, so a constrained "
    "solver would first jump onto it and every invariant would be wrong. Start from "
    "`diffrax_vi.project_onto_constraints(term, t0, y0, args)[0]`."
)

NON_FINITE_CONSTRAINT = (
    "The constraint g(t0, q0) or its Jacobian dg/dq is NaN or inf at a finite q0: "
    "check the constraint function and its parameters in args."
)

RANK_DEFICIENT = (
    "The constraint Jacobian dg/dq at q0 does not have full row rank to working "
    "precision: the constraints are redundant (remove the dependent ones) or q0 is a "
    "singular configuration of the mechanism."
)


def check_start(
    term, t: RealScalarLike, q: Q, p: P, v: PyTree, args: Args, value: PyTree
) -> PyTree:
    """`value`, or an error if the start is off the constraint manifold (beyond
    $\\sqrt{\\varepsilon}$ relative) or the constraint Jacobian loses rank there
    (unless the term's start is checked already: `start_checked`)."""
    if term.start_checked:
        return value
    g = term.constraint
    space = term.lagrangian.space
    jacobian = constraint_jacobian(g, t, q, args, space)
    values = constraint_values(g, t, q, args)
    tol = newton_tolerance(state_dtype(q))
    hidden = hidden_constraint(jacobian, v, constraint_rate(g, t, q, args))
    off = (scaled_norm(values, constraint_scale(jacobian, q, space)) > tol) | (
        scaled_norm(*hidden) > tol
    )
    finite = all_finite((values, jacobian))
    value = eqx.error_if(value, ~finite & all_finite(q), NON_FINITE_CONSTRAINT)
    value = eqx.error_if(value, ~rank_ok(jacobian) & finite, RANK_DEFICIENT)
    return eqx.error_if(value, off & all_finite((q, p, v)), OFF_MANIFOLD)


def _lu_solve(matrix: Array, b: Array) -> tuple[Array, Array]:
    """lineax's LU solve of a system too large to unroll, with the pivot ratio
    `unrolled_lu_solve` returns (zero where the solve failed)."""
    solution = lx.linear_solve(lx.MatrixLinearOperator(matrix), b, lx.LU(), throw=False)
    ok = solution.result == lx.RESULTS.successful
    return solution.value, jnp.where(ok, jnp.ones((), b.dtype), jnp.zeros((), b.dtype))


def multiplier_force(
    term, t, q: Q, p: P, v: PyTree, force: P, args: Args
) -> tuple[P, dfx.RESULTS]:
    r"""The constraint force $-G^\top\lambda$ of the index-reduced equations of motion
    at $(q, p)$ with velocity $v$: $\lambda$ such that the hidden constraint
    $G(q)\,v + \partial g/\partial t$ stays constant along
    $(\dot q, \dot p) = (v, f - G^\top\lambda)$, where $f$ is the rest of $\dot p$.

    With $W = (\partial^2 L/\partial v^2)^{-1}$, $\dot v = W(\dot p - m)$ where $m$
    is the derivative of $\partial L/\partial v$ along $(\dot t, \dot q) = (1, v)$,
    so $(G W G^\top)\lambda = G W (f - m) + c$ with $c$ the second derivative of $g$
    along $(1, v)$. On a group $v$ is the body velocity $\xi$, $G$ is
    left-trivialised, and both derivatives follow $\dot q = q\hat\xi$. With a
    declared constant mass $W = M^{-1}$ and $m = 0$. Only forward linear solves (no
    derivative of a solve is taken, whose tangent solves lineax always checks), and
    a `RESULTS.singular` where $G W G^\top$ cannot be solved (a Jacobian losing
    rank)."""
    g = term.constraint
    lagrangian = term.lagrangian
    space = lagrangian.space
    dtype = state_dtype(q)
    t = jnp.asarray(t, dtype)
    one = jnp.ones((), dtype)
    flat_v, unravel = jax.flatten_util.ravel_pytree(v)

    # How q moves at the velocity v (v itself in a vector space, q v^ on SO(3)).
    moving = lambda q_: space_velocity(space, q_, v)
    jacobian = constraint_jacobian(g, t, q, args, space)

    def rate(t_, q_):
        return jax.jvp(
            lambda s, x: constraint_values(g, s, x, args), (t_, q_), (one, moving(q_))
        )[1]

    curvature = jax.jvp(rate, (t, q), (one, moving(q)))[1]
    n, m = flat_v.shape[0], jacobian.shape[0]
    mass = constant_mass(lagrangian, v)
    if mass is not None:
        # A declared constant mass: W = M^-1, and dL/dv = M v reads neither t nor q.
        inverse = 1 / _flat(mass)
        w_gt, w_f = jacobian.T * inverse[:, None], _flat(force) * inverse
        lam, reduced_ratio = _reduced_solve(
            product(jacobian, w_gt),
            product(jacobian, w_f) + curvature,
            unrolled_lu_solve if newton_is_dense(m) else _lu_solve,
        )
        ok = ~(reduced_ratio <= singular_threshold(m, dtype)) & all_finite(lam)
        result = dfx.RESULTS.where(ok, dfx.RESULTS.successful, dfx.RESULTS.singular)
        return unravel(-product(jacobian.T, lam)), result

    def dl_dv(t_, q_, v_):
        return _flat(momentum(lagrangian, t_, q_, v_, args))

    # W applied to the columns of G^T and to f - m.
    hessian = dense_jacobian(lambda x: dl_dv(t, q, unravel(x)), flat_v)
    mixed = jax.jvp(lambda t_, q_: dl_dv(t_, q_, v), (t, q), (one, moving(q)))[1]
    rhs = jnp.concatenate([jacobian.T, (_flat(force) - mixed)[:, None]], axis=1)
    if newton_is_dense(n) and newton_is_dense(m):
        # Unrolled eliminations, not LAPACK's: this runs in a Runge-Kutta solver's
        # vector field, inside its time-stepping loop, which a LAPACK call would
        # break into kernels (`diagnostics.loop_breakers`).
        lu, perm = unrolled_lu_factor(hessian)
        solved = jax.vmap(lambda b: unrolled_lu_apply(lu, perm, b))(rhs.T)
        w_gt, w_f = solved[:-1].T, solved[-1]
        lam, reduced_ratio = _reduced_solve(
            product(jacobian, w_gt), product(jacobian, w_f) + curvature
        )
        # As lineax's LU: a solution that is not finite (at a singular
        # configuration, G W G^T loses rank) is a failed solve.
        ok = (
            ~(pivot_ratio(lu) <= singular_threshold(n, dtype))
            & ~(reduced_ratio <= singular_threshold(m, dtype))
            & all_finite((solved, lam))
        )
    else:
        operator = lx.MatrixLinearOperator(hessian, lx.symmetric_tag)
        solve_w = lambda b: lx.linear_solve(operator, b, lx.LU(), throw=False)
        solved = jax.vmap(solve_w)(rhs.T)
        w_gt, w_f = solved.value[:-1].T, solved.value[-1]
        reduced = lx.MatrixLinearOperator(jacobian @ w_gt)
        solution = lx.linear_solve(
            reduced, jacobian @ w_f + curvature, lx.LU(), throw=False
        )
        lam = solution.value
        ok = (solution.result == lx.RESULTS.successful) & jnp.all(
            solved.result == lx.RESULTS.successful
        )
    result = dfx.RESULTS.where(ok, dfx.RESULTS.successful, dfx.RESULTS.singular)
    return unravel(-product(jacobian.T, lam)), result
