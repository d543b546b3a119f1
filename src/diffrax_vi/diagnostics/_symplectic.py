import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .._constraint import constraint_values
from .._custom_types import Args, RealScalarLike
from .._lagrangian import inverse_legendre
from .._term import LagrangianTerm


@eqx.filter_jit
def step_jacobian(
    solver: dfx.AbstractSolver,
    terms: PyTree[dfx.AbstractTerm],
    y0: PyTree,
    args: Args = None,
    h: RealScalarLike = 0.2,
) -> Float[Array, "n n"]:
    """The Jacobian $M = \\partial y_1 / \\partial y_0$ of one step of `solver` of size
    `h` from `y0` (flattened), by `jax.jacrev` through the step (and implicit
    differentiation through any nonlinear solve in it)."""
    flat, unravel = jax.flatten_util.ravel_pytree(y0)

    def step(x):
        y = unravel(x)
        state = solver.init(terms, 0.0, h, y, args)
        y1, *_ = solver.step(terms, 0.0, h, y, args, state, False)
        return jax.flatten_util.ravel_pytree(y1)[0]

    return jax.jacrev(step)(flat)


def symplecticity_defect(
    solver: dfx.AbstractSolver,
    terms: PyTree[dfx.AbstractTerm],
    y0: tuple[PyTree, PyTree],
    args: Args = None,
    h: RealScalarLike = 0.2,
) -> float:
    r"""$\max|M^\top J M - J|$ for the Jacobian $M$ of one step of `solver` on the
    state `y0 = (q, p)` ([`diffrax_vi.diagnostics.step_jacobian`][]), with
    $J = \begin{pmatrix} 0 & I \\ -I & 0\end{pmatrix}$: zero to round-off for a
    symplectic step, of the size of the local error for a Runge–Kutta step. For a
    [`diffrax_vi.LagrangianTerm`][] with a constraint, $\max|B^\top(M^\top J M -
    J)B|$ with $B$ an orthonormal basis of the tangent space of the constrained phase
    space at `y0` (time-independent constraints): symplecticity on that manifold.

    **Arguments:**

    - `solver`: any diffrax solver.
    - `terms`: its terms, e.g. from [`diffrax_vi.terms_for`][].
    - `y0`: the state `(q, p)` to step from.
    - `args`: as for `diffeqsolve`.
    - `h`: the step.
    """
    m = step_jacobian(solver, terms, y0, args, h)
    n = m.shape[0] // 2
    eye, zero = jnp.eye(n, dtype=m.dtype), jnp.zeros((n, n), m.dtype)
    j = jnp.block([[zero, eye], [-eye, zero]])
    if isinstance(terms, LagrangianTerm) and terms.constraint is not None:
        # Symplectic on the constrained phase space: on its tangent vectors only.
        basis = _tangent_basis(terms, y0, args)
        return float(jnp.max(jnp.abs(basis.T @ (m.T @ j @ m - j) @ basis)))
    return float(jnp.max(jnp.abs(m.T @ j @ m - j)))


def _tangent_basis(term: LagrangianTerm, y0: PyTree, args: Args) -> Array:
    r"""An orthonormal basis of the tangent space at `y0` of the constrained phase
    space $\{g(q) = 0,\ G(q)\,v(q, p) = 0\}$ (flattened): the null space of the
    Jacobian of both constraints."""
    flat, unravel = jax.flatten_util.ravel_pytree(y0)

    def constraints(x):
        q, p = unravel(x)
        v, _ = inverse_legendre(
            term.lagrangian, 0.0, (q, p), args, None, promise="raise"
        )
        g = lambda q_: constraint_values(term.constraint, 0.0, q_, args)
        hidden = jax.jvp(g, (q,), (v,))[1]
        return jnp.concatenate([g(q), hidden])

    jacobian = jax.jacfwd(constraints)(flat)
    _, s, vt = jnp.linalg.svd(jacobian)
    rank = jacobian.shape[0]
    return vt[rank:].T
