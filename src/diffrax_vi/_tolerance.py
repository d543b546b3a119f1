r"""The tolerance policy: every threshold and tolerance multiplier of the numerics, in
one place.

Tolerances on states are multiples of the dtype's machine epsilon $\epsilon$ (or of
$\sqrt\epsilon$) applied to residuals measured relative to the terms they balance
(`scaled_norm`), so none depends on the units chosen. Size limits choose between a
dense and a matrix-free linear algebra. Tolerances on method coefficients (tableaus,
compositions) are absolute, as the coefficients are pure numbers given in float64.
"""

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import PyTree, Scalar


# --- Dense or matrix-free -------------------------------------------------------

# Symmetric eigenvalue problems and linear solves with d2L/dv2 of at most this many
# unknowns are done densely (exact extremes, one factorisation).
DENSE_MAX = 64

# Newton's method factorises the dense Jacobian of at most this many unknowns, and
# goes matrix-free beyond: the Jacobian costs n products, while a Krylov solve of a
# well-conditioned step takes a few (`benchmarks/scaling.py` measures both). Small
# systems keep the dense solve, whose pivots also detect a singular Jacobian.
NEWTON_DENSE_MAX = 16

# The constrained step equations (a step's unknowns and its multipliers) have an
# indefinite saddle-point Jacobian. A matrix-free solve takes it by BiCGStab with the
# normal equations as its fallback, which compiled in 30 s against 8 s for the dense
# LU on `scenes.rigid_double_pendulum` (18 unknowns) and broke down on
# `scenes.rigid_chain(links=8)` (72). Such systems are factorised densely up to this
# size without LAPACK (`_solver/unknowns.constrained_solver`): unrolled up to
# `NEWTON_DENSE_MAX` unknowns, rolled into a loop beyond (`_linear.dense_lu_solve`).
CONSTRAINED_DENSE_MAX = 128

# A linearized step's symmetric system of at most this many unknowns is eliminated
# densely, as its other small systems are; beyond, conjugate gradients take it. The
# elimination's steps take 0.34-0.79x CG's up to 4 unknowns, 1.02x and 1.09x at 6
# and 8 (`benchmarks/results/linearized_cost_cpu.txt`).
LINEARIZED_DENSE_MAX = 4


def newton_is_dense(n: int) -> bool:
    """Whether a Newton-type linear solve with `n` unknowns factorises a dense
    matrix (else it is matrix-free): the one place this choice is made."""
    return n <= NEWTON_DENSE_MAX


# --- Multiples of epsilon ---------------------------------------------------------

# A residual component is measured against at least this many `sqrt(eps)` of the
# largest term (see `scaled_norm`).
SCALE_FLOOR = 64

# A Newton residual this many `eps` below its terms is at round-off: the iterate is
# the root to working precision, and one more solve could not improve it.
ROUNDOFF_RESIDUAL = 4

# The most a matrix-free solve is asked for, in `eps` relative to its terms: below
# it round-off would stop the solve first. Also the fixed-point iteration's default
# tolerance (it converges linearly, so it runs to near round-off) and the Jacobi
# test of a diagonal mass.
KRYLOV_FLOOR = 64

# The one linear solve of a linearized step has no Newton iteration to correct it:
# it runs to this many `eps`.
LINEARIZED_RTOL = 100

# --- Iteration counts -------------------------------------------------------------

# Halvings of a damped Newton step before the line search gives up.
MAX_HALVINGS = 40

# Lanczos iterations for the extreme eigenvalues of d2L/dv2 beyond `DENSE_MAX`.
LANCZOS_STEPS = 24

# Conjugate-gradient iterations of the matrix-free inverse of an affine Legendre map
# before Newton's method takes over (at most n + 1 for n coordinates: exact in n
# steps, and lineax's test on the last update takes one more).
AFFINE_MAX_STEPS = 100

# Newton iterations of the inverse Legendre map of a general Lagrangian.
LEGENDRE_MAX_STEPS = 32

# Krylov iterations of a linearized step's solve, per unknown.
LINEARIZED_STEPS_PER_UNKNOWN = 10

# The default root-finding policy gives the fixed-point iteration this many times
# a solver's `root_find_max_steps` (it converges linearly) before Newton's method.
FIXED_POINT_STEPS_FACTOR = 3

# A fixed-point iteration that once contracted by this factor or more in one update
# and then slows below sqrt(eps) has reached the round-off of its equations, not a
# slow rate: the rate of a fixed-point iteration is set by the step, not the
# iterate. (The multipliers of a constraint carry the position residual's round-off
# divided by h into the momenta: 140 eps on the Cartesian pendulum at 100 steps a
# period, above the iteration's 64 eps tolerance.)
FAST_CONTRACTION = 1e-2


# --- Method coefficients (float64 numbers, absolute) -----------------------------

# Identities that hold exactly for coefficients given to 16 digits: row sums of a
# tableau, weights summing to one, a symmetric tableau's reflection.
COEFFICIENT_ATOL = 1e-13

# A composition's coefficients read the same backwards.
PALINDROME_ATOL = 1e-14

# Identities that are sums of products of coefficients: the symplecticity condition
# of a VPRK tableau, a composition's order conditions (absolute, or relative to the
# size of the terms of a sum that must not vanish).
PRODUCT_TOL = 1e-12

# Order conditions `b . c^(k-1) = 1/k` of tableaus built by a Vandermonde solve,
# which loses digits with the number of stages, and of an effective order's
# processor.
ORDER_CONDITION_ATOL = 1e-10


def newton_tolerance(dtype) -> float:
    """`sqrt(eps)`: once a Newton residual is below it, relative to the terms it
    balances, the next update leaves an error at round-off."""
    return float(jnp.finfo(dtype).eps) ** 0.5


def singular_threshold(n: int, dtype) -> float:
    """A matrix whose smallest pivot or eigenvalue is below this fraction of its
    largest is singular to working precision."""
    return n * float(jnp.finfo(dtype).eps)


def scaled_norm(f: PyTree, scale: PyTree) -> Scalar:
    """`max |f| / s`, the dimensionless size of a residual (0 where `f = s = 0`).

    Component by component, so that coordinates in different units are each measured
    against their own terms; but never against less than `SCALE_FLOOR sqrt(eps)` of
    the largest term: a component whose terms cancel (a momentum `p = M v + A(q)`
    that is zero while `M v` is not) keeps the round-off of the others in its
    residual, which its own vanishing scale must not magnify. Invariant under any
    common change of units."""
    leaves = jtu.tree_leaves(f)
    scales = jtu.tree_leaves(scale)
    eps = jnp.finfo(jnp.result_type(*leaves)).eps
    peak = jnp.max(jnp.stack([jnp.max(si, initial=0.0) for si in scales]))
    floor = SCALE_FLOOR * jnp.sqrt(eps) * peak
    ratios = []
    for fi, si in zip(leaves, scales):
        si = jnp.maximum(si, floor)
        ratios.append(jnp.max(jnp.abs(fi) / jnp.where(si > 0, si, 1), initial=0.0))
    return jnp.max(jnp.stack(ratios))


def check_fraction(owner: str, name: str, value) -> None:
    """A `ValueError` unless `value` is `None`, traced, or a number in (0, 1): a
    relative tolerance or a contraction rate."""
    if value is None or isinstance(value, jax.core.Tracer):
        return
    if not (jnp.ndim(value) == 0 and 0 < float(value) < 1):
        raise ValueError(
            f"{owner}({name}=...) must be a number between 0 and 1 (exclusive); got "
            f"{value!r}."
        )
