r"""The linear solves of the Newton steps, the linearized steps and the inverse
Legendre map: an unrolled dense elimination for small systems, and a matrix-free
Krylov driver, in units that make lineax's absolute tests relative."""

import math
from collections.abc import Callable

import jax
import jax.extend.core as jex
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
from jaxtyping import Array, PyTree, Scalar

from ._misc import holds, tree_max_abs
from ._private_api import unvmap_any


# Products of at most this many multiplications are written as sums (`product`).
SMALL_PRODUCT = 1 << 14


def product(a: Array, b: Array) -> Array:
    """`a @ b` for a matrix `a` and a vector or matrix `b`, as elementwise products
    and a sum where it is small: inside a step's loop (batched by a Jacobian's
    `vmap`) XLA on CPU can make a small `dot_general` a custom fusion, which breaks
    the loop into kernels dispatched one by one (`diagnostics.loop_breakers`).
    Larger products keep `@`, whose kernel then costs less than the loop's
    overhead."""
    columns = 1 if b.ndim == 1 else b.shape[1]
    if a.size * columns > SMALL_PRODUCT:
        return a @ b
    if b.ndim == 1:
        return jnp.sum(a * b[None, :], axis=1)
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def holds_product(fn: Callable[[Array], Array], x: Array) -> bool:
    """Whether a Jacobian of `fn`, a function of flat vectors like `x` (a step's
    residual, or its linearisation), is taken column by column (`columns`) rather
    than by `jax.vmap` over the identity, as lineax's `as_matrix` and `jax.jacfwd`
    take it: where `fn` holds a matrix-vector product (`dot_general` summing more
    than one product: a user's MLP layers, `equinox.nn.Linear`). `vmap` makes it a
    matrix product, which XLA on CPU runs as a YNNPACK fusion that breaks the loop
    around it into kernels dispatched one by one (`diagnostics.loop_breakers`):
    `MidpointVI` on a neural Lagrangian of two degrees of freedom took 10.5 against
    3.4 us a step (CHANGELOG). One column needs no batch."""
    return x.shape[0] > 1 and holds(jax.make_jaxpr(fn)(x).jaxpr, _sums_products)


def _sums_products(eqn: jex.JaxprEqn) -> bool:
    """A `dot_general` that sums more than one product: a matrix-vector product, not
    a scaling (a one-stage step's tableau, contracted over its one stage)."""
    if eqn.primitive.name != "dot_general":
        return False
    (contracting, _), _ = eqn.params["dimension_numbers"]
    shape = eqn.invars[0].aval.shape
    return math.prod(shape[axis] for axis in contracting) > 1


def columns(linear: Callable[[Array], Array], x: Array) -> Array:
    """The matrix of `linear`, a linear map of flat vectors like `x`: its columns
    `linear(e_j)` taken one at a time in a loop (`lax.map`), each product in it a
    matrix-vector one (`holds_product`)."""
    return lax.map(linear, jnp.eye(x.shape[0], dtype=x.dtype)).T


def linear_matrix(linear: Callable[[Array], Array], x: Array) -> Array:
    """The matrix of `linear`, a linear map of flat vectors like `x`: by `columns`
    where it holds a matrix-vector product (`holds_product`), else by `vmap` over the
    identity, as lineax's `as_matrix` takes it."""
    if holds_product(linear, x):
        return columns(linear, x)
    return jax.vmap(linear, out_axes=1)(jnp.eye(x.shape[0], dtype=x.dtype))


def dense_jacobian(fn: Callable[[Array], Array], x: Array) -> Array:
    """`jax.jacfwd(fn)(x)` for a function of a flat vector, column by column where
    `fn` holds a matrix-vector product (`holds_product`)."""
    if holds_product(fn, x):
        return columns(jax.linearize(fn, x)[1], x)
    return jax.jacfwd(fn)(x)


def _ratio(small: Scalar, large: Scalar) -> Scalar:
    """`small / large` for `0 <= small <= large`, and 0 for a zero matrix (0/0
    would be NaN, which a test `ratio <= threshold` reads as regular); NaN stays NaN
    (a NaN Lagrangian is not a singular one). (`pivot_ratio` tests its pivots for
    zeros, which covers the zero matrix.)"""
    return jnp.where(large == 0, jnp.zeros_like(large), small / large)


def unit_scale(diagonal: Array) -> Array:
    """`|d|^(-1/2)` for the diagonal `d` of a matrix whose rows and columns carry
    the units of the same coordinates (or constraints), 1 where `d = 0`: `D A D`
    with `D = diag` of it has pure numbers for entries, the same in any units."""
    size = jnp.abs(diagonal)
    return 1 / jnp.sqrt(jnp.where(size > 0, size, 1))


def pivot_ratio(lu: Array) -> Scalar:
    """The smallest over the largest pivot; 0 where a pivot is zero (a column
    with nothing left to pivot on: the elimination then divides 0 by 0 below it,
    and the NaN it leaves in later pivots must not read as regular)."""
    pivots = jnp.abs(jnp.diagonal(lu))
    ratio = jnp.min(pivots) / jnp.max(pivots)
    return jnp.where(jnp.any(pivots == 0), jnp.zeros_like(ratio), ratio)


def unrolled_lu_factor(matrix: Array) -> tuple[Array, Array]:
    """Gaussian elimination with partial pivoting, unrolled into XLA operations:
    `(lu, perm)` with `matrix[perm] = L U`, the unit lower factor `L` below the
    diagonal of `lu` and `U` on and above it.

    For the dense solves of small systems in place of LAPACK's, whose call keeps XLA
    on CPU from compiling the surrounding loop whole, which costs a small system's
    step several times its arithmetic (`benchmarks/step_cost.py`)."""
    n = matrix.shape[0]
    a, perm = matrix, jnp.arange(n)
    for k in range(n):
        if k < n - 1:  # The last column has no choice of pivot.
            i = k + jnp.argmax(jnp.abs(a[k:, k]))
            a = a.at[k].set(a[i]).at[i].set(a[k])
            perm = perm.at[k].set(perm[i]).at[i].set(perm[k])
        factors = a[k + 1 :, k] / a[k, k]
        a = a.at[k + 1 :, k + 1 :].add(-factors[:, None] * a[k, k + 1 :][None, :])
        a = a.at[k + 1 :, k].set(factors)
    return a, perm


def unrolled_lu_apply(lu: Array, perm: Array, b: Array) -> Array:
    """`matrix^-1 b` from `unrolled_lu_factor(matrix)`: two triangular solves."""
    n = b.shape[0]
    y = b[perm]
    for k in range(n):
        y = y.at[k + 1 :].add(-lu[k + 1 :, k] * y[k])
    x = jnp.zeros_like(b)
    for k in reversed(range(n)):
        x = x.at[k].set((y[k] - lu[k, k + 1 :] @ x[k + 1 :]) / lu[k, k])
    return x


def unpivoted_solve(matrix: Array, b: Array) -> tuple[Array, Scalar]:
    """`matrix^-1 b` by Gaussian elimination without pivoting, unrolled, and the
    ratio of its smallest to its largest pivot (`pivot_ratio`): for a matrix whose
    leading minors are all regular, as a definite one's are. No pivot search and no
    row exchange: a third of `unrolled_lu_solve`'s operations (the rigid double
    pendulum's `TrapezoidalVI` program: 7279 optimised instructions with both of
    its 6 x 6 solves pivoted, 6568 with its multipliers' not, 5761 with its
    projection's not either), and its pivots do not depend on the units of the
    rows and columns. A zero pivot reads as a ratio of zero; the NaN it leaves in
    the solution is the caller's to tell apart (the fixed-point iteration's
    multipliers then fall back to Newton's method). For a symmetric definite
    matrix (a constrained step's momentum projection, $G M^{-1} G^\top$ with a
    definite mass and independent constraints) the elimination is backward stable
    without pivoting, and a pivot near zero is a matrix singular to working
    precision."""
    n = b.shape[0]
    for k in range(n - 1):
        factors = matrix[k + 1 :, k] / matrix[k, k]
        update = factors[:, None] * matrix[k, k + 1 :][None, :]
        matrix = matrix.at[k + 1 :, k + 1 :].add(-update)
        b = b.at[k + 1 :].add(-factors * b[k])
    x = jnp.zeros_like(b)
    for k in reversed(range(n)):
        done = jnp.sum(matrix[k, k + 1 :] * x[k + 1 :])
        x = x.at[k].set((b[k] - done) / matrix[k, k])
    return x, pivot_ratio(matrix)


def unrolled_lu_solve(matrix: Array, b: Array) -> tuple[Array, Scalar]:
    """`matrix^-1 b` by `unrolled_lu_factor`, and the ratio of the smallest to the
    largest pivot; for Newton's dense solves (`newton_is_dense`) in place of
    `lineax.LU`. A 2 x 2 or 3 x 3 system is solved in closed form
    (`cofactor_solve`), the 3 x 3 in half the time of the elimination."""
    if matrix.shape in ((2, 2), (3, 3)):
        return cofactor_solve(matrix, b)
    lu, perm = unrolled_lu_factor(matrix)
    return unrolled_lu_apply(lu, perm, b), pivot_ratio(lu)


def rolled_lu_factor(matrix: Array) -> tuple[Array, Array]:
    """`unrolled_lu_factor`'s elimination (the same pivots, the same `(lu, perm)`)
    as a loop over the columns: its program does not grow with the size, so it
    compiles in a constant time, where the unrolled one grows with the size (18
    unknowns: 22.5 against 14.1 s for a Newton-only rigid double pendulum solve),
    and runs about a third slower. Each column's pivot, swap and update are whole-
    matrix selects: no scatter and no LAPACK call, so the loop around it still
    compiles whole."""
    n = matrix.shape[0]
    rows = jnp.arange(n)

    def column(k, carry):
        a, perm = carry
        i = jnp.argmax(jnp.where(rows >= k, jnp.abs(a[:, k]), -1))
        row_k, row_i = a[k], a[i]
        a = jnp.where(
            (rows == k)[:, None], row_i, jnp.where((rows == i)[:, None], row_k, a)
        )
        perm_k, perm_i = perm[k], perm[i]
        perm = jnp.where(rows == k, perm_i, jnp.where(rows == i, perm_k, perm))
        below = rows > k
        factors = jnp.where(below, a[:, k] / a[k, k], 0)
        a = a - factors[:, None] * jnp.where(below, a[k], 0)[None, :]
        a = jnp.where(below[:, None] & (rows == k)[None, :], factors[:, None], a)
        return a, perm

    return lax.fori_loop(0, n, column, (matrix, rows))


def rolled_lu_apply(lu: Array, perm: Array, b: Array) -> Array:
    """`matrix^-1 b` from `rolled_lu_factor(matrix)`: the two triangular solves as
    loops."""
    n = b.shape[0]
    rows = jnp.arange(n)
    y = lax.fori_loop(
        0, n, lambda k, y: y - jnp.where(rows > k, lu[:, k], 0) * y[k], b[perm]
    )

    def back(j, x):
        k = n - 1 - j
        done = jnp.sum(jnp.where(rows > k, lu[k], 0) * x)
        return jnp.where(rows == k, (y[k] - done) / lu[k, k], x)

    return lax.fori_loop(0, n, back, jnp.zeros_like(b))


def dense_lu_solve(matrix: Array, b: Array, unrolled_max: int) -> tuple[Array, Scalar]:
    """`unrolled_lu_solve` up to `unrolled_max` unknowns, where the step's speed
    decides; beyond, the same elimination rolled into loops (`rolled_lu_factor`),
    where the compile time does. Newton's dense solves of constrained steps (their
    saddle-point systems up to `CONSTRAINED_DENSE_MAX`) take the rolled one: on the
    rigid double pendulum (18 unknowns) a default `TrapezoidalVI` solve compiled in
    21.2 s against 33.7 s at the same step time, its Newton fallback rarely taken;
    a 4-link chain's in 32.7 against 77.9 s, its steps 37% slower."""
    if matrix.shape[0] <= unrolled_max:
        return unrolled_lu_solve(matrix, b)
    lu, perm = rolled_lu_factor(matrix)
    return rolled_lu_apply(lu, perm, b), pivot_ratio(lu)


def implicit_lu_solve(
    matvec: Callable[[Array], Array], matrix: Array, b: Array, unrolled_max: int
) -> Array:
    """`matrix^-1 b` by `dense_lu_solve`, for `matrix` the matrix of the linear map
    `matvec`, differentiated as the solution of `matvec(x) = b`
    (`lax.custom_linear_solve`): a derivative is one more solve with the same
    matrix, in reverse mode by eliminating `matrix.T` itself. Differentiating the
    elimination would transpose its row permutation (a gather) into a scatter,
    which breaks the loop around it into kernels dispatched one by one
    (`diagnostics.loop_breakers`)."""
    return lax.custom_linear_solve(
        matvec,
        b,
        lambda _, c: dense_lu_solve(matrix, c, unrolled_max)[0],
        lambda _, c: dense_lu_solve(matrix.T, c, unrolled_max)[0],
    )


def cofactor_solve(matrix: Array, b: Array) -> tuple[Array, Scalar]:
    r"""`matrix^-1 b` for a 2 x 2 or 3 x 3 matrix by its cofactors
    ($A^{-1} = \mathrm{cof}(A)^\top/\det A$; for 3 x 3, cross products of its rows),
    and, in place of the pivot ratio, $|\det A'| / \max_i |a'_i|^n$ for $A' = DAD$
    in units of the diagonal, $D = |\mathrm{diag}\,A|^{-1/2}$ (a zero entry
    unscaled): a measure that is at most one (Hadamard's inequality) and vanishes
    with $\det A$, below which $A$ is singular to working precision as the pivot
    ratio says of an elimination. The Jacobians solved here (of momenta in
    velocities: $d^2L/dv^2$, a step's Newton matrix) scale a row and a column with
    the units of each coordinate, which $D$ takes out: the same measure in any units
    (of $A$ itself, a four-bar with one angle in units $10^4$ times smaller read
    $10^{-17}$ and singular)."""
    n = matrix.shape[0]
    if n == 2:
        (a00, a01), (a10, a11) = matrix
        det = a00 * a11 - a01 * a10
        x = jnp.stack([a11 * b[0] - a01 * b[1], a00 * b[1] - a10 * b[0]]) / det
    else:
        a0, a1, a2 = matrix[0], matrix[1], matrix[2]
        c0, c1, c2 = jnp.cross(a1, a2), jnp.cross(a2, a0), jnp.cross(a0, a1)
        det = jnp.sum(a0 * c0)
        x = (c0 * b[0] + c1 * b[1] + c2 * b[2]) / det
    diagonal = jnp.abs(jnp.diagonal(matrix))
    scale = 1 / jnp.where(diagonal > 0, diagonal, 1)  # D^2
    largest = jnp.max(scale * jnp.sum(matrix**2 * scale[None, :], axis=1))
    return x, _ratio(jnp.abs(det) * jnp.prod(scale), largest ** (n / 2))


def _magnitude(tree: PyTree) -> Scalar:
    """The largest `|x|` over the leaves, or 1 if all are zero: a scale, not
    differentiated."""
    size = tree_max_abs(tree)
    return lax.stop_gradient(jnp.where(size > 0, size, 1))


def krylov_solve(
    matvec: Callable[[PyTree], PyTree],
    rhs: PyTree,
    rtol: float | Scalar,
    tags: frozenset,
    max_steps: int,
    preconditioner: PyTree | None = None,
    guess: PyTree | None = None,
    normal: bool = False,
) -> tuple[PyTree, lx.RESULTS]:
    """`krylov_iterate`'s solve of a system whose solution is differentiated (a
    linearized step's, an affine Legendre map's), by the implicit function theorem:
    a derivative is a solve of the same system (of its transpose in reverse mode)
    by the same iteration, to the same tolerance, rather than lineax's derivative
    of its own solve, whose tangent and transposed solves check themselves with a
    host callback that breaks the loop around them into kernels dispatched one by
    one (`diagnostics.loop_breakers`): `LinearizedVI`'s checkpointed gradient on
    Kepler took 19.5 against 1.38 us a step (CHANGELOG). The iteration starts from
    zero on `rhs - A guess` and adds `guess` back, so that the solves of the
    derivatives start from zero too. `normal`: as `krylov_iterate`."""
    # The guess and the preconditioner do not change the solution, and the solve
    # does not differentiate its aids: their derivatives are dropped.
    guess, preconditioner = lax.stop_gradient((guess, preconditioner))
    if guess is not None:
        rhs = jtu.tree_map(lambda b, a: b - a, rhs, matvec(guess))
    symmetric = lx.symmetric_tag in tags

    def solve(operator, b):
        return krylov_iterate(
            operator, b, rtol, tags, max_steps, preconditioner, normal
        )

    value, result = lax.custom_linear_solve(
        matvec,
        rhs,
        solve,
        None if symmetric else solve,
        symmetric=symmetric,
        has_aux=True,
    )
    if guess is not None:
        value = jtu.tree_map(lambda x, g: x + g, value, guess)
    return value, result


def krylov_iterate(
    matvec: Callable[[PyTree], PyTree],
    rhs: PyTree,
    rtol: float | Scalar,
    tags: frozenset,
    max_steps: int,
    preconditioner: PyTree | None = None,
    normal: bool = False,
) -> tuple[PyTree, lx.RESULTS]:
    """`A^{-1} b` for the operator `matvec`, matrix-free, from zero: conjugate
    gradients where `tags` say symmetric positive or negative (semi)definite, else
    BiCGStab, and conjugate gradients on the normal equations where BiCGStab breaks
    down (with `normal`, those alone, which do not break down as BiCGStab can: half
    the program, for a derivative's solve); to relative accuracy `rtol`,
    preconditioned by positive diagonal weights `preconditioner`. Newton's updates
    call it as it is (the root, not the iteration, is differentiated); a solution
    that is differentiated takes `krylov_solve`. (Not lineax's GMRES: it makes all
    20 Arnoldi steps of a cycle before it tests convergence, 20 products where a
    nearly diagonal Newton matrix needs 2; and its least-squares solve is a LAPACK
    call, which even as a branch never taken keeps XLA on CPU from compiling a
    small loop whole.)

    The solve runs on `A / c` and `b / |b|`, with `c` the size of `A` along `b`:
    lineax's tests are absolute (GMRES broke down on a right-hand side below about
    1e-16) and its tolerances componentwise, so the solve must not see the units.
    In those units `atol = rtol`: a component of the solution that happens to be
    near zero then does not demand more than `rtol` of the whole (with `atol = 0`,
    GMRES reported the lucky breakdown of an exactly captured solution as a
    failure)."""
    preconditioner = lax.stop_gradient(preconditioner)
    b_size = _magnitude(rhs)
    b = jtu.tree_map(lambda x: x / b_size, rhs)
    weigh = lambda tree: (
        tree
        if preconditioner is None
        else jtu.tree_map(lambda p, x: p * x, preconditioner, tree)
    )
    a_size = _magnitude(weigh(matvec(b)))
    b_struct = jax.eval_shape(lambda: rhs)
    operator = lx.FunctionLinearOperator(
        lambda w: jtu.tree_map(lambda x: x / a_size, matvec(w)), b_struct, tags=tags
    )
    options = {}
    if preconditioner is not None:
        options["preconditioner"] = lx.FunctionLinearOperator(
            weigh, b_struct, tags=(lx.symmetric_tag, lx.positive_semidefinite_tag)
        )

    def solve(solver):
        sol = lx.linear_solve(operator, b, solver, options=options, throw=False)
        return sol.value, sol.result

    normal_cg = lx.Normal(lx.CG(rtol=rtol, atol=rtol, max_steps=max_steps))
    if tags & {lx.positive_semidefinite_tag, lx.negative_semidefinite_tag}:
        value, result = solve(lx.CG(rtol=rtol, atol=rtol, max_steps=max_steps))
    elif normal:
        value, result = solve(normal_cg)
    else:
        value, result = solve(lx.BiCGStab(rtol=rtol, atol=rtol, max_steps=max_steps))
        failed = unvmap_any(result != lx.RESULTS.successful)
        value, result = lax.cond(
            failed, lambda: solve(normal_cg), lambda: (value, result)
        )
    return jtu.tree_map(lambda x: x * (b_size / a_size), value), result
