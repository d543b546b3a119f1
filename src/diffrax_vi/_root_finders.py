r"""The root finders of the implicit steps and of the inverse Legendre map.

Every equation solved here balances momenta, $r(w) = a(w) - b(w) = 0$, and its
residual function returns, beside $r$, the size of the terms it balances,
$s = |a| + |b| \ge |r|$ (elementwise). The solves stop when $\max_i |r_i|/s_i$ is
small: a dimensionless test, unchanged by any choice of units of mass, length and
time, with no absolute tolerance to tune, which also holds at a turning point (where
the momenta cancel rather than vanish) and at rest (where $r = s = 0$).

The root finders are `optimistix.AbstractRootFinder`s, so `optimistix.root_find` runs
them, reports how they ended, and differentiates through the root implicitly:

- [`diffrax_vi.Newton`][]: Newton's method with a dense LU solve (small systems) or a
  matrix-free Krylov solve of Jacobian–vector products (large ones), with
  Eisenstat–Walker forcing terms and a diagonal preconditioner; optionally damped by
  backtracking.
- [`diffrax_vi.SimplifiedNewton`][]: the chord method, with one LU factorisation kept
  across iterations and steps and refreshed when convergence slows.
- [`diffrax_vi.FixedPoint`][]: $w \leftarrow w - P^{-1}r(w)$ with the mass matrix $P$,
  for separable Lagrangians: one force evaluation per iteration, no Jacobian.
"""

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
import optimistix as optx
from equinox import AbstractClassVar, AbstractVar
from jaxtyping import Array, Int, PyTree, Scalar

from ._linear import (
    dense_jacobian,
    dense_lu_solve,
    implicit_lu_solve,
    krylov_iterate,
    krylov_solve,
    linear_matrix,
    pivot_ratio,
    product,
    unpivoted_solve,
    unrolled_lu_apply,
    unrolled_lu_factor,
)
from ._misc import tree_dtype, tree_size, tree_sub
from ._private_api import promote_result, unvmap_any
from ._tolerance import (
    check_fraction,
    FAST_CONTRACTION,
    KRYLOV_FLOOR,
    LINEARIZED_RTOL,
    LINEARIZED_STEPS_PER_UNKNOWN,
    MAX_HALVINGS,
    NEWTON_DENSE_MAX,
    newton_is_dense,
    newton_tolerance,
    ROUNDOFF_RESIDUAL,
    scaled_norm,
)


LinearSolverName = Literal["auto", "dense", "krylov"]


class AbstractVIRootFinder(optx.AbstractRootFinder):
    """Base class of this package's root finders. The function given to
    `optimistix.root_find` must have `has_aux=True` and return `(r, s)`: the residual
    and the size of the terms it balances.

    Options: `"preconditioner"`, positive weights like the unknowns approximating the
    inverse of the Jacobian's diagonal (one over the mass), or `None`; `"carry"`,
    what the previous solve handed on ([`diffrax_vi.SimplifiedNewton`][]'s
    factorisation); `"curvature"`, whether to measure `curvature` (default no).

    Each iterate of these root finders is computed from the residual at the one
    before, so a non-finite residual leaves a non-finite root: a step tells a NaN
    force (`RESULTS.nonfinite`) from a diverged iteration by the root alone, with no
    second evaluation of its equations."""

    rtol: AbstractVar[float | None]
    # optimistix's absolute tolerance and norm: unused, as every test here is on a
    # residual relative to the size of its terms, in the max norm.
    atol: ClassVar[float] = 0.0
    norm: ClassVar[Callable] = staticmethod(optx.max_norm)
    # Whether converging certifies that a step's root continues the motion (the
    # iteration contracts towards it from the guess), so that no fold test is
    # needed.
    certifies_continuation: AbstractClassVar[bool]

    def __check_init__(self):
        check_fraction(type(self).__name__, "rtol", self.rtol)

    @abc.abstractmethod
    def tolerance(self, y: PyTree) -> float:
        """The dimensionless tolerance for unknowns like `y`."""

    @abc.abstractmethod
    def carry_init(self, y: PyTree) -> PyTree:
        """What the first solve starts from and hands on to the next."""

    @abc.abstractmethod
    def final_carry(self, state) -> PyTree:
        """What a solve that ended in `state` hands on to the next."""

    @abc.abstractmethod
    def pivot_ratio(self, state) -> Scalar:
        """The smallest over the largest pivot of the last dense factorisation of a
        solve that ended in `state` (1 if it made none): the step's test of a
        singular Jacobian."""

    def measures_curvature(self, y: PyTree) -> bool:
        """Whether a solve for unknowns like `y` measures `curvature`."""
        return False

    @abc.abstractmethod
    def curvature(self, state, guess: PyTree, root: PyTree) -> Scalar:
        """`d . J d` for the way `d` from `guess` to `root`, the root of a solve
        that ended in `state`, with the residual's Jacobian `J` at the last iterate
        but one, where `measures_curvature` (else NaN): the curvature a step's test
        of a fold needs, without another derivative of the residual. `+inf` where
        the solve's convergence certifies the root (`certifies_continuation`)."""

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class NewtonState(eqx.Module):
    """`rho`: the dimensionless residual of the iterate the last update started from;
    `pivot_ratio`: the smallest over the largest pivot of the last dense
    factorisation (1 if none); `carry`: what is handed to the next solve;
    `jacobian`: the last dense Jacobian, where the solve measures the curvature
    along its way (`Newton.measures_curvature`; else an empty array)."""

    rho: Scalar
    rho_prev: Scalar
    pivot_ratio: Scalar
    step: Int[Array, ""]
    result: optx.RESULTS
    carry: PyTree
    jacobian: Array


def _newton_init(y, carry, keeps_jacobian: bool = False) -> NewtonState:
    dtype = tree_dtype(y)
    inf = jnp.array(jnp.inf, dtype)
    n = tree_size(y) if keeps_jacobian else 0
    return NewtonState(
        inf,
        inf,
        jnp.ones((), dtype),
        jnp.array(0),
        optx.RESULTS.successful,
        carry,
        jnp.full((n, n), jnp.nan, dtype),
    )


def _newton_terminate(tol: float, state: NewtonState):
    started = state.step > 0
    converged = started & (state.rho <= tol)
    diverged = started & ~jnp.isfinite(state.rho)
    failed = state.result != optx.RESULTS.successful
    result = optx.RESULTS.where(
        failed,
        state.result,
        optx.RESULTS.where(
            diverged, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful
        ),
    )
    return converged | diverged | failed, result


class AbstractNewtonFamily(AbstractVIRootFinder):
    """Newton's method and its variants: a `NewtonState`, the tolerance
    `sqrt(eps)` by default, and the pivots of their dense factorisations."""

    def tolerance(self, y: PyTree) -> float:
        return newton_tolerance(tree_dtype(y)) if self.rtol is None else self.rtol

    def pivot_ratio(self, state: NewtonState) -> Scalar:
        return state.pivot_ratio

    def curvature(self, state: NewtonState, guess: PyTree, root: PyTree) -> Scalar:
        if state.jacobian.size == 0:
            return jnp.full((), jnp.nan, state.rho.dtype)
        way = jax.flatten_util.ravel_pytree(tree_sub(root, guess))[0]
        return jnp.sum(way * product(state.jacobian, way))

    def terminate(self, fn, y, args, options, state, tags):
        return _newton_terminate(self.tolerance(y), state)


class Newton(AbstractNewtonFamily):
    r"""Newton's method for the implicit steps of the variational solvers and for
    the inverse Legendre map, as an `optimistix` root finder.

    Each iteration solves $J\Delta = r$ for the Jacobian $J$ of the residual: by LU
    on the dense Jacobian for at most 16 unknowns, else matrix-free by a Krylov method
    on Jacobian–vector products (conjugate gradients where $J$ is symmetric and
    definite, as for the midpoint step of a Lagrangian whose momentum does not
    depend on $q$ and for the Legendre map; BiCGStab otherwise, conjugate gradients
    on the normal equations where it breaks down), preconditioned by the
    inverse mass and solved only as accurately as Newton's progress needs
    (Eisenstat–Walker forcing, choice 2). It
    stops after the update from an iterate whose residual is below `rtol` relative
    to the terms it balances: with quadratic convergence the error left is at
    round-off, as with a dense solve.

    **Arguments:**

    - `rtol`: the dimensionless tolerance; `None` for $\sqrt\epsilon$ of the dtype.
    - `linear_solver`: `"auto"` (dense up to 16 unknowns, Krylov beyond), `"dense"`,
        `"krylov"`, or any `lineax.AbstractLinearSolver`. Dense solves take no
        LAPACK call: an unrolled elimination up to 16 unknowns, the same elimination
        in a loop over the columns beyond (it compiles in constant time).
    - `damped`: backtrack along each Newton direction until the residual decreases
        and stays finite: convergence from a poor start for monotone problems such
        as the inverse Legendre map of a relativistic particle.
    - `krylov_max_steps`: the iterations one Krylov solve may take.
    """

    certifies_continuation: ClassVar[bool] = False
    rtol: float | None = None
    linear_solver: LinearSolverName | lx.AbstractLinearSolver = eqx.field(
        static=True, default="auto"
    )
    damped: bool = eqx.field(static=True, default=False)
    krylov_max_steps: int = eqx.field(static=True, default=200)

    def __check_init__(self):
        if isinstance(self.linear_solver, str) and self.linear_solver not in (
            "auto",
            "dense",
            "krylov",
        ):
            raise ValueError(
                "Newton(linear_solver=...) must be 'auto', 'dense', 'krylov' or a "
                f"lineax solver; got {self.linear_solver!r}."
            )

    def dense(self, y: PyTree) -> bool:
        """Whether the linear solves are dense LU."""
        if self.linear_solver == "auto":
            return newton_is_dense(tree_size(y))
        return self.linear_solver == "dense"

    def measures_curvature(self, y: PyTree) -> bool:
        # The dense Jacobian is at hand (kept up to 16 unknowns); a matrix-free
        # solve would need another Jacobian-vector product in every iteration.
        return self.dense(y) and newton_is_dense(tree_size(y))

    def carry_init(self, y: PyTree) -> PyTree:
        return None

    def final_carry(self, state: NewtonState) -> PyTree:
        return None

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        keeps_jacobian = options.get("curvature", False) and self.measures_curvature(y)
        return _newton_init(y, options.get("carry"), keeps_jacobian)

    def step(self, fn, y, args, options, state, tags):
        f, lin, scale = jax.linearize(lambda _y: fn(_y, args), y, has_aux=True)
        rho = scaled_norm(f, scale)
        # An iterate whose residual is at round-off (after one update: the first
        # iterate of a Lagrangian quadratic in v, or of a linear step equation) is
        # the root to working precision; one more solve could not improve it, and
        # a Krylov solve asked to reduce a residual at round-off breaks down.
        eps = float(jnp.finfo(tree_dtype(y)).eps)
        exact = (state.step > 0) & (rho <= ROUNDOFF_RESIDUAL * eps)

        def update():
            pivot_ratio = state.pivot_ratio
            matrix = None
            if not isinstance(self.linear_solver, str):
                operator = lx.FunctionLinearOperator(
                    lin, jax.eval_shape(lambda: y), tags=tags
                )
                sol = lx.linear_solve(operator, f, self.linear_solver, throw=False)
                delta, result = sol.value, promote_result(optx.RESULTS, sol.result)
            elif self.dense(y):
                flat_f, _ = jax.flatten_util.ravel_pytree(f)
                flat_y, unravel = jax.flatten_util.ravel_pytree(y)
                flat_lin = lambda x: jax.flatten_util.ravel_pytree(lin(unravel(x)))[0]
                matrix = linear_matrix(flat_lin, flat_y)
                flat_delta, pivot_ratio = dense_lu_solve(
                    matrix, flat_f, NEWTON_DENSE_MAX
                )
                delta = unravel(flat_delta)
                result = optx.RESULTS.successful
            else:
                # Eisenstat-Walker choice 2 (gamma = 0.9, alpha = 2), never asking
                # for a residual below `KRYLOV_FLOOR eps` of the terms, which
                # round-off would not let the solve reach. The last update (from
                # below the Newton tolerance) then leaves the residual at round-off,
                # as a dense solve does; a forcing term bounded below by `tol / rho`
                # would stop it at about `tol / 2`.
                floor = KRYLOV_FLOOR * eps
                forcing = jnp.clip(
                    0.9 * (rho / state.rho_prev) ** 2,
                    floor / jnp.maximum(rho, floor),
                    0.5,
                )
                forcing = jnp.where(jnp.isfinite(state.rho_prev), forcing, 0.5)
                delta, linear_result = krylov_iterate(
                    lin,
                    f,
                    forcing,
                    tags,
                    self.krylov_max_steps,
                    _plain_preconditioner(options.get("preconditioner")),
                )
                # A Krylov solve breaks down where the Newton matrix is singular or
                # indefinite, far from a root (a step too large): Newton's method has
                # failed there, as when a dense factorisation returns inf. Report that,
                # not lineax's advice to change the linear solver.
                result = optx.RESULTS.where(
                    linear_result == lx.RESULTS.successful,
                    optx.RESULTS.successful,
                    optx.RESULTS.nonlinear_divergence,
                )
                # From a non-finite residual a Krylov solve stops with whatever its
                # breakdown left, which may be finite: the update is NaN, as a
                # dense solve's is, so that the iterate shows it (see
                # `AbstractVIRootFinder`).
                delta = jtu.tree_map(
                    lambda d: jnp.where(jnp.isfinite(rho), d, jnp.nan), delta
                )
            if self.damped:
                y_new = _backtrack(fn, y, args, delta, rho, scale)
            else:
                y_new = tree_sub(y, delta)
            jacobian = state.jacobian
            if matrix is not None and jacobian.size:
                jacobian = matrix
            return y_new, pivot_ratio, result, jacobian

        if isinstance(self.linear_solver, str) and self.dense(y) and not self.damped:
            # An unrolled LU costs less than the branch that would skip it (a
            # conditional in the loop costs a third of a RATTLE step on the
            # Cartesian pendulum): at round-off its update is at round-off too.
            y_new, pivot_ratio, result, jacobian = update()
        else:
            y_new, pivot_ratio, result, jacobian = lax.cond(
                unvmap_any(~exact),
                update,
                lambda: (
                    y,
                    state.pivot_ratio,
                    optx.RESULTS.successful,
                    state.jacobian,
                ),
            )
        new = NewtonState(
            rho,
            rho,
            pivot_ratio,
            state.step + 1,
            result,
            state.carry,
            jacobian,
        )
        return y_new, new, scale


def _backtrack(fn, y, args, delta, rho, scale):
    """The first of `y - delta`, `y - delta/2`, ... (at most `MAX_HALVINGS`) whose
    residual is finite and below `(1 - alpha/4) rho` (Armijo's sufficient decrease),
    both measured against the scale `scale` of the iterate the search starts from: a
    scale that moved with the trial point could make a worse point look better (the
    terms of a relativistic Legendre map grow without bound towards |v| = 1, so
    their ratio to the residual falls there)."""

    def trial(alpha):
        y_new = jtu.tree_map(lambda a, b: a - alpha * b, y, delta)
        f, _ = fn(y_new, args)
        return scaled_norm(f, scale)

    def rejected(carry):
        alpha, k = carry
        rho_new = trial(alpha)
        bad = ~(jnp.isfinite(rho_new) & (rho_new <= (1 - alpha / 4) * rho))
        return bad & (k < MAX_HALVINGS) & (rho > 0)

    alpha, _ = lax.while_loop(
        rejected, lambda c: (c[0] / 2, c[1] + 1), (jnp.ones_like(rho), 0)
    )
    return jtu.tree_map(lambda a, b: a - alpha * b, y, delta)


class SimplifiedNewton(AbstractNewtonFamily):
    r"""The simplified Newton (chord) method, with one dense LU factorisation of the
    Jacobian kept across iterations *and steps*.

    An iteration costs one residual evaluation and two triangular solves. The
    Jacobian is refactorised at the first step and whenever an iteration contracts
    the residual by less than `kappa`; for smooth motion at moderate steps that is
    rare, so a step costs little more than the fixed-point iteration, while, unlike
    it, converging on stiff problems. Dense, so for small and medium systems.

    It stops where Newton's method does, after the update from an iterate whose
    residual is below `rtol` ($\sqrt\epsilon$ by default). That update leaves
    round-off only under Newton's quadratic convergence; the chord method converges
    linearly, so its steps are solved to about $\sqrt\epsilon$ times its
    contraction, and the step map is symplectic to that level rather than to
    round-off. Running it on to round-off would take many more iterations than
    Newton's method. For round-off symplecticity use [`diffrax_vi.Newton`][].

    **Arguments:**

    - `rtol`: as for [`diffrax_vi.Newton`][].
    - `kappa`: the contraction per iteration below which the factorisation is kept
        (default 0.25).
    """

    certifies_continuation: ClassVar[bool] = False
    rtol: float | None = None
    kappa: float = 0.25

    def __check_init__(self):
        check_fraction("SimplifiedNewton", "kappa", self.kappa)

    def carry_init(self, y: PyTree) -> PyTree:
        n = tree_size(y)
        dtype = tree_dtype(y)
        # A placeholder factorisation, marked stale so that the first step factorises.
        return (
            jnp.eye(n, dtype=dtype),
            jnp.arange(n, dtype=jnp.int32),
            jnp.array(False),
        )

    def final_carry(self, state: NewtonState) -> PyTree:
        return state.carry

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        carry = options.get("carry")
        return _newton_init(y, self.carry_init(y) if carry is None else carry)

    def step(self, fn, y, args, options, state, tags):
        flat, unravel = jax.flatten_util.ravel_pytree(y)
        f, scale = fn(y, args)
        rho = scaled_norm(f, scale)
        lu, piv, fresh = state.carry
        refactor = ~fresh | ~(rho <= self.kappa * state.rho_prev)

        # Small systems factorise without LAPACK, as Newton's dense solves do, so
        # that XLA can compile the loop around them whole; `piv` is then the row
        # order, else LAPACK's pivots.
        unrolled = newton_is_dense(flat.shape[0])

        def factorise():
            def flat_residual(x):
                return jax.flatten_util.ravel_pytree(fn(unravel(x), args)[0])[0]

            jac = dense_jacobian(flat_residual, flat)
            factors = unrolled_lu_factor if unrolled else jax.scipy.linalg.lu_factor
            lu, piv = factors(jac)
            return lu, piv.astype(jnp.int32), jnp.array(True)

        lu, piv, fresh = lax.cond(refactor, factorise, lambda: (lu, piv, fresh))
        flat_f = jax.flatten_util.ravel_pytree(f)[0]
        if unrolled:
            delta = unrolled_lu_apply(lu, piv, flat_f)
        else:
            delta = jax.scipy.linalg.lu_solve((lu, piv), flat_f)
        result = optx.RESULTS.where(
            jnp.all(jnp.isfinite(delta)), optx.RESULTS.successful, optx.RESULTS.singular
        )
        new = NewtonState(
            rho,
            rho,
            pivot_ratio(lu),
            state.step + 1,
            result,
            (lu, piv, fresh),
            state.jacobian,
        )
        return unravel(flat - delta), new, scale


class WithMultipliers(eqx.Module):
    """The preconditioner of the unknowns `(w, lam)` of a constrained step of a
    separable Lagrangian: one over the mass of each of the step's unknowns `w`; the
    constraint multipliers `lam` have no mass, and [`diffrax_vi.FixedPoint`][]
    solves for them exactly in each iteration (`_with_multipliers`)."""

    inverse_mass: PyTree


def _plain_preconditioner(preconditioner: PyTree | None) -> PyTree | None:
    """The diagonal preconditioner of a Krylov solve: none for `WithMultipliers`,
    whose multipliers have no mass."""
    return None if isinstance(preconditioner, WithMultipliers) else preconditioner


def _with_multipliers(fn, y, args, f, inverse_mass) -> tuple[PyTree, PyTree]:
    r"""The fixed-point update `(dw, dlam)` of the constrained step equations
    $r = (r_w, r_g)$ in $(w, \lambda)$: the Newton update with the Jacobian's block
    $\partial r_w/\partial w$ replaced by the mass matrix $P$, as in the
    unconstrained iteration, and the other blocks exact. With
    $B = \partial r_w/\partial\lambda$, $C = \partial r_g/\partial w$ and
    $D = \partial r_g/\partial\lambda$, the multipliers solve the $m \times m$
    Schur complement $(D - C P^{-1} B)\,\delta\lambda = r_g - C P^{-1} r_w$ and
    $\delta w = P^{-1}(r_w - B\,\delta\lambda)$. $B$, $C$ and $D$ are
    Jacobian-vector products along the multipliers and of $r_g$ alone: no
    derivative of the force. Also returns $P^{-1} B\,\delta\lambda$, the part
    of the update the multipliers make."""
    w, lam = y
    r_w, r_g = f
    m = lam.shape[0]
    weigh = lambda tree: jtu.tree_map(lambda p, x: p * x, inverse_mass, tree)

    def along_multipliers(d):
        return jax.jvp(lambda x: fn((w, x), args)[0], (lam,), (d,))[1]

    def constraint_along(dw):
        return jax.jvp(lambda x: fn((x, lam), args)[0][1], (w,), (dw,))[1]

    eye = jnp.eye(m, dtype=lam.dtype)
    b_cols, d_cols = jax.vmap(along_multipliers)(eye)  # row j: column j
    weighted_b = jax.vmap(weigh)(b_cols)
    weighted_r = weigh(r_w)
    # C P^-1 B and C P^-1 r_w in one batch of m + 1 directions: one trace of the
    # constraint's derivative, not two.
    directions = jtu.tree_map(
        lambda cols, x: jnp.concatenate([cols, x[None]]), weighted_b, weighted_r
    )
    c_directions = jax.vmap(constraint_along)(directions)
    schur = (d_cols - c_directions[:m]).T
    rhs = r_g - c_directions[m]
    if newton_is_dense(m):
        # The Schur complement of a constrained step, G(q1) M^-1 G(q0)^T up to
        # its sign and h: definite where the constraints are independent and the
        # step resolves their motion, so eliminated without pivoting; a zero
        # pivot gives NaN, and the iteration then falls back to Newton's method.
        dlam = unpivoted_solve(schur, rhs)[0]
    else:
        dlam = lx.linear_solve(
            lx.MatrixLinearOperator(schur), rhs, lx.LU(), throw=False
        ).value
    from_multipliers = jtu.tree_map(
        lambda x: jnp.sum(jnp.reshape(dlam, (m,) + (1,) * (x.ndim - 1)) * x, axis=0),
        weighted_b,
    )
    dw = jtu.tree_map(lambda a, b: a - b, weighted_r, from_multipliers)
    return (dw, dlam), from_multipliers


class FixedPointState(eqx.Module):
    """The dimensionless size of the last update and of the one before, and the
    smallest ratio of successive sizes so far (1 before there is one)."""

    size: Scalar
    size_prev: Scalar
    fastest: Scalar
    step: Int[Array, ""]


class FixedPoint(AbstractVIRootFinder):
    r"""The fixed-point iteration $w \leftarrow w - P^{-1}r(w)$ with the mass matrix
    $P$: for the stage equations of a separable Lagrangian,
    $V = M^{-1}\big(p_0 + h\,\bar a\,F(Q(V))\big)$, one force evaluation per iteration
    and no Jacobian.

    It converges while $h^2\lVert M^{-1}\nabla^2 V\rVert$ is small (non-stiff steps),
    and stops with `RESULTS.nonlinear_divergence` as soon as an iteration contracts
    by less than `max_rate`, unless it has already contracted a hundredfold in one
    update and is below $\sqrt\epsilon$: it has then reached the round-off of its
    equations and stops there. Where it converges, the Jacobian of the stage equations
    is within a factor `max_rate` of the mass matrix, so the root is the one that
    continues the motion.

    With holonomic constraints the unknowns are the velocities and the constraint
    multipliers $\lambda$: each iteration solves for $\lambda$ exactly given the
    velocities' update (an $m \times m$ Schur complement, from derivatives of the
    constraint alone), so it converges as fast as without constraints.

    **Arguments:**

    - `rtol`: the tolerance on an update relative to the size of the terms of the
        equation; `None` for `64 eps` of the dtype (the iteration converges
        linearly, so it runs to near round-off).
    - `max_rate`: the slowest contraction per iteration accepted (default 0.5).
    """

    certifies_continuation: ClassVar[bool] = True
    rtol: float | None = None
    max_rate: float = 0.5

    def __check_init__(self):
        check_fraction("FixedPoint", "max_rate", self.max_rate)

    def tolerance(self, y: PyTree) -> float:
        if self.rtol is not None:
            return self.rtol
        return KRYLOV_FLOOR * float(jnp.finfo(tree_dtype(y)).eps)

    def carry_init(self, y: PyTree) -> PyTree:
        return None

    def final_carry(self, state: FixedPointState) -> PyTree:
        return None

    def pivot_ratio(self, state: FixedPointState) -> Scalar:
        return jnp.ones((), state.size.dtype)

    def measures_curvature(self, y: PyTree) -> bool:
        return True

    def curvature(self, state: FixedPointState, guess: PyTree, root: PyTree) -> Scalar:
        return jnp.full((), jnp.inf, state.size.dtype)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        if options.get("preconditioner") is None:
            raise ValueError(
                "FixedPoint iterates with the mass matrix of a separable Lagrangian "
                "(diffrax_vi.AbstractSeparableLagrangian); for this Lagrangian use "
                "diffrax_vi.Newton() or diffrax_vi.SimplifiedNewton()."
            )
        dtype = tree_dtype(y)
        inf = jnp.array(jnp.inf, dtype)
        return FixedPointState(inf, inf, jnp.ones((), dtype), jnp.array(0))

    def step(self, fn, y, args, options, state, tags):
        f, scale = fn(y, args)
        preconditioner = options["preconditioner"]
        constrained = isinstance(preconditioner, WithMultipliers)
        inverse_mass = preconditioner.inverse_mass if constrained else preconditioner
        weigh = lambda tree: jtu.tree_map(lambda p, x: p * x, inverse_mass, tree)
        if constrained:
            delta, from_multipliers = _with_multipliers(fn, y, args, f, inverse_mass)
            # The velocities' update, and the part of it the multipliers' update
            # makes (a multiplier still moving shows there even where the two
            # cancel).
            terms = weigh(scale[0])
            size = jnp.maximum(
                scaled_norm(delta[0], terms), scaled_norm(from_multipliers, terms)
            )
        else:
            delta = weigh(f)
            size = scaled_norm(delta, weigh(scale))
        ratio = jnp.where(jnp.isfinite(state.size), size / state.size, 1.0)
        fastest = jnp.minimum(state.fastest, ratio)
        return (
            tree_sub(y, delta),
            FixedPointState(size, state.size, fastest, state.step + 1),
            scale,
        )

    def terminate(self, fn, y, args, options, state, tags):
        converged = state.size <= self.tolerance(y)
        slow = (
            (state.step >= 2)
            & ~converged
            & ~(state.size <= self.max_rate * state.size_prev)
        )
        # Slowing down below sqrt(eps) after a fast contraction: round-off.
        at_roundoff = (
            slow
            & (state.size <= newton_tolerance(tree_dtype(y)))
            & (state.fastest <= FAST_CONTRACTION)
        )
        converged = converged | at_roundoff
        too_slow = slow & ~at_roundoff
        result = optx.RESULTS.where(
            too_slow, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful
        )
        return (state.step > 0) & (converged | too_slow), result


class Solved(eqx.Module):
    """The outcome of [`solve`][]: the root, how the solve ended, the smallest over
    the largest pivot of its last dense factorisation (1 if it made none), what it
    hands to the next solve, and the curvature along the way from the guess that the
    root finder measured (`AbstractVIRootFinder.curvature`; NaN if it did not)."""

    value: PyTree
    result: dfx.RESULTS
    pivot_ratio: Scalar
    carry: PyTree
    curvature: Scalar


def solve(
    residual: Callable[[PyTree], tuple[PyTree, PyTree]],
    guess: PyTree,
    root_finder: optx.AbstractRootFinder,
    max_steps: int,
    *,
    preconditioner: PyTree | None = None,
    tags: frozenset = frozenset(),
    carry: PyTree = None,
    curvature: bool = False,
) -> Solved:
    """The root of `residual(w) -> (r, s)` from `guess`, and with `curvature` the
    curvature along the way where the root finder measures it.

    Any other `optimistix` root finder gets the residual divided by the size of its
    largest term, so that its own tolerances are relative."""
    dtype = tree_dtype(guess)
    if isinstance(root_finder, AbstractVIRootFinder):
        find = _finder(root_finder, max_steps, tags, curvature)
        return _differentiated(
            find, residual, guess, preconditioner, carry, root_finder, tags
        )

    def relative(w, _):
        r, s = residual(w)
        size = lax.stop_gradient(
            jnp.max(jnp.stack([jnp.max(x, initial=0.0) for x in jtu.tree_leaves(s)]))
        )
        return jtu.tree_map(lambda x: x / jnp.where(size > 0, size, 1), r)

    sol = optx.root_find(
        relative, root_finder, guess, max_steps=max_steps, tags=tags, throw=False
    )
    return Solved(
        sol.value,
        promote_result(dfx.RESULTS, sol.result),
        jnp.ones((), dtype),
        carry,
        jnp.full((), jnp.nan, dtype),
    )


def _finder(
    root_finder: AbstractVIRootFinder,
    max_steps: int,
    tags: frozenset,
    curvature: bool = False,
):
    """`find(fn, guess, preconditioner, carry) -> Solved`: `optimistix.root_find`
    of `fn` (returning `(r, s)`) by `root_finder`."""

    def find(fn, guess, preconditioner, carry):
        options = dict(preconditioner=preconditioner, carry=carry, curvature=curvature)
        sol = optx.root_find(
            lambda w, _: fn(w),
            root_finder,
            guess,
            options=options,
            has_aux=True,
            max_steps=max_steps,
            tags=tags,
            throw=False,
        )
        return Solved(
            sol.value,
            promote_result(dfx.RESULTS, sol.result),
            root_finder.pivot_ratio(sol.state),
            root_finder.final_carry(sol.state),
            root_finder.curvature(sol.state, guess, sol.value),
        )

    return find


def dense_derivative(root_finder: AbstractVIRootFinder, guess: PyTree) -> bool:
    """Whether the root `root_finder` finds from `guess` is differentiated by a dense
    elimination (`_implicit_solve`): where Newton's method factorises its Jacobian
    densely (`Newton.dense`: up to `NEWTON_DENSE_MAX` unknowns, and a constrained
    step's equations up to `CONSTRAINED_DENSE_MAX`, `constrained_solver`), and for
    any other of this package's root finders up to `NEWTON_DENSE_MAX` unknowns."""
    if isinstance(root_finder, Newton):
        return root_finder.dense(guess)
    return newton_is_dense(tree_size(guess))


def optimistix_differentiates(root_finder: AbstractVIRootFinder) -> bool:
    """Whether the roots `root_finder` finds are left to optimistix's
    `ImplicitAdjoint`, one per root find: those of a `Newton` given a lineax solver
    of the user's. Every other root of this package's root finders is
    differentiated by `_implicit_solve` (`_differentiated`)."""
    return isinstance(root_finder, Newton) and not isinstance(
        root_finder.linear_solver, str
    )


def _differentiated(
    find, residual, guess, preconditioner, carry, root_finder, tags
) -> Solved:
    """`find(residual, guess, preconditioner, carry)`, differentiated by the implicit
    function theorem at the root it returns (`_implicit_solve`): by a dense
    elimination where `root_finder` would factorise densely (`dense_derivative`),
    else matrix-free, as Newton's method solves such a system, by a Krylov method
    on Jacobian-vector products (`tags`: the Jacobian's); or by optimistix
    (`optimistix_differentiates`)."""
    if optimistix_differentiates(root_finder):
        return find(residual, guess, preconditioner, carry)
    krylov_tags = None if dense_derivative(root_finder, guess) else tags
    return _implicit_solve(find, residual, guess, preconditioner, carry, krylov_tags)


def known_root(
    residual: Callable[[PyTree], tuple[PyTree, PyTree]],
    root: PyTree,
    *,
    preconditioner: PyTree | None = None,
    carry: PyTree = None,
    newton: "Newton | None" = None,
    tags: frozenset = frozenset(),
) -> Solved:
    """`root`, a root of `residual` found elsewhere, as `solve` would return it,
    differentiated by the implicit function theorem there: no iteration in the
    program. As `_differentiated` takes the root that `newton` (the Newton method
    that would solve the system; `tags`: its Jacobian's) finds, densely or
    matrix-free; by a dense elimination without `newton`. Not for a root that
    optimistix would differentiate (`optimistix_differentiates`): `find` here
    solves nothing, so its derivative would be lost."""
    assert newton is None or not optimistix_differentiates(newton)
    dtype = tree_dtype(root)

    def find(fn, guess, preconditioner, carry):
        return Solved(
            guess,
            dfx.RESULTS.successful,
            jnp.ones((), dtype),
            carry,
            jnp.full((), jnp.nan, dtype),
        )

    if newton is None:
        return _implicit_solve(find, residual, root, preconditioner, carry)
    return _differentiated(find, residual, root, preconditioner, carry, newton, tags)


def solve_with_fallback(
    residual: Callable[[PyTree], tuple[PyTree, PyTree]],
    guess: PyTree,
    first: tuple[AbstractVIRootFinder, int],
    fallback: tuple[AbstractVIRootFinder, int],
    *,
    preconditioner: PyTree | None = None,
    tags: frozenset = frozenset(),
    curvature: bool = False,
) -> Solved:
    """`solve` by the root finder `first[0]` in at most `first[1]` iterations, and
    where it fails by `fallback` from the same guess (`tags` and `curvature` as for
    `solve`). The root is differentiated once, whichever found it: a gradient's
    program holds one implicit derivative of the step rather than one per root
    finder."""
    first_find = _finder(*first, frozenset(), curvature)
    fallback_find = _finder(*fallback, tags, curvature)

    def find(fn, guess, preconditioner, carry):
        solved = first_find(fn, guess, preconditioner, carry)
        failed = unvmap_any(solved.result != dfx.RESULTS.successful)
        return lax.cond(
            failed,
            lambda: fallback_find(fn, guess, preconditioner, carry),
            lambda: solved,
        )

    return _differentiated(
        find, residual, guess, preconditioner, None, fallback[0], tags
    )


def _implicit_solve(
    find, residual, guess, preconditioner, carry, krylov_tags=None
) -> Solved:
    """`find(residual, guess, preconditioner, carry)`, differentiated by the
    implicit function theorem as optimistix's `ImplicitAdjoint` does, but with the
    forward solves' linear algebra in place of lineax's LU: the dense elimination
    (`dense_lu_solve`: unrolled up to `NEWTON_DENSE_MAX` unknowns, rolled into a
    loop beyond), or where `krylov_tags` is given (a matrix-free Newton solve's
    Jacobian tags) `krylov_solve` on Jacobian-vector products, preconditioned as
    Newton's Krylov solves are. No LAPACK call and no host callback
    (lineax checks its solves) in a gradient's backward loop, either of which
    breaks it into kernels dispatched one by one (`diagnostics.loop_breakers`).
    Gradients of the Kepler, double pendulum, free rigid body, heavy top and
    four-bar solves run 4.0-12.9x faster, the same to round-off, and the rigid
    double pendulum's, whose constrained steps have 18 unknowns, 2.1x faster
    (`benchmarks/gradient_loops.py`). A Jacobian singular at the root (which a
    Newton-type solve has already reported as `RESULTS.singular`) gives a gradient
    that is not finite."""
    fn = eqx.filter_closure_convert(residual, guess)
    structure = {}

    def leaves_of_find(fn, guess, preconditioner, carry):
        # A custom derivative returns arrays: the `Solved` flattened, the value's
        # leaves first.
        solved = find(fn, guess, preconditioner, carry)
        dynamic, static = eqx.partition(solved, eqx.is_array)
        leaves, treedef = jtu.tree_flatten(dynamic)
        structure["out"] = (treedef, static)
        return leaves

    # The root depends on neither the guess nor the solve's aids.
    aids = lax.stop_gradient((guess, preconditioner, carry))
    leaves = _implicit(fn, *aids, find=leaves_of_find, krylov_tags=krylov_tags)
    treedef, static = structure["out"]
    return eqx.combine(jtu.tree_unflatten(treedef, leaves), static)


@eqx.filter_custom_jvp
def _implicit(fn, guess, preconditioner, carry, *, find, krylov_tags):
    return find(fn, guess, preconditioner, carry)


@_implicit.def_jvp
def _implicit_jvp(primals, tangents, *, find, krylov_tags):
    fn, guess, preconditioner, carry = primals
    t_fn = tangents[0]
    leaves = _implicit(
        fn, guess, preconditioner, carry, find=find, krylov_tags=krylov_tags
    )
    no_tangent = [None] * len(leaves)
    if t_fn is None:
        return leaves, no_tangent
    n_value = len(jtu.tree_leaves(guess))
    root = jtu.tree_unflatten(jtu.tree_structure(guess), leaves[:n_value])
    flat_root, unravel = jax.flatten_util.ravel_pytree(root)
    residual_at = lambda f, w: jax.flatten_util.ravel_pytree(f(w)[0])[0]
    # The residual's change with the closed-over values at the root, and its
    # Jacobian in the unknowns there: J dw = -(dr/dtheta) dtheta.
    _, moved = eqx.filter_jvp(lambda f: residual_at(f, root), (fn,), (t_fn,))
    if moved is None:  # The differentiated values do not enter the residual.
        return leaves, no_tangent
    residual_of = lambda w: residual_at(fn, unravel(w))
    if krylov_tags is None:
        jacobian = dense_jacobian(residual_of, flat_root)
        t_root = implicit_lu_solve(
            lambda x: product(jacobian, x), jacobian, -moved, NEWTON_DENSE_MAX
        )
    else:
        weights = _plain_preconditioner(preconditioner)
        if weights is not None:
            weights = jax.flatten_util.ravel_pytree(weights)[0]
        eps = float(jnp.finfo(flat_root.dtype).eps)
        t_root, _ = krylov_solve(
            jax.linearize(residual_of, flat_root)[1],
            -moved,
            LINEARIZED_RTOL * eps,
            krylov_tags,
            LINEARIZED_STEPS_PER_UNKNOWN * flat_root.size,
            preconditioner=weights,
            # A non-symmetric Jacobian by conjugate gradients on the normal
            # equations alone: BiCGStab with them as its fallback made the
            # reversible gradient of a two-stage Gauss step on 36 unknowns compile
            # in 33 against 27 s (CHANGELOG).
            normal=True,
        )
    return leaves, jtu.tree_leaves(unravel(t_root)) + no_tangent[n_value:]
