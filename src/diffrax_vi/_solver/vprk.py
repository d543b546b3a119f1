r"""Variational partitioned Runge–Kutta methods: a method is its tableau.

The discrete Lagrangian $L_d = h\sum_i b_i L(t_0 + c_i h, Q_i, V_i)$ with
$Q_i = q_0 + h\sum_j a_{ij} V_j$, extremised over the stage velocities with
$q_1 = q_0 + h\sum_i b_i V_i$ (the symplectic partitioned Runge–Kutta methods of
Marsden & West (2001), Part 2), gives the stage
equations

$$\frac{\partial L}{\partial v}(Q_i, V_i) = p_0 + h\sum_j \bar a_{ij}
\frac{\partial L}{\partial q}(Q_j, V_j),\qquad
q_1 = q_0 + h\sum_i b_i V_i,\quad p_1 = p_0 + h\sum_i b_i
\frac{\partial L}{\partial q}(Q_i, V_i),$$

with $b_i \bar a_{ij} + b_j a_{ji} = b_i b_j$: the symplecticity condition, which every
tableau is checked against when it is built.

An applied force $F$ joins $\partial L/\partial q$ at the stages,
$\partial L/\partial q(Q_j, V_j) + F(t_0 + c_j h, Q_j, V_j)$ in both sums: the
discrete Lagrange–d'Alembert principle with the forces $f^\pm$ given by the same
quadrature as $L_d$ (Marsden & West (2001), §3.2).
"""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from equinox import AbstractVar
from jaxtyping import Array, PyTree

from .._custom_types import P, Q, V
from .._discrete import MidpointRule
from .._force import applied_force, power
from .._lagrangian import (
    AbstractSeparableLagrangian,
    fixed_point_inverse_mass,
    lagrangian_value,
    momentum_reads_position,
)
from .._space import is_euclidean
from .._tolerance import COEFFICIENT_ATOL, ORDER_CONDITION_ATOL, PRODUCT_TOL
from .._xla import YNN_REDUCTION_MIN
from .base import StepInputs
from .implicit import AbstractImplicitVI, IMPLICIT_ARGS_DOC, SYMMETRIC_POSITIVE
from .rule import rule_increments, rule_residual, rule_step, rule_work
from .trees import satisfied_order, TREE_ORDER_MAX


_MIDPOINT = MidpointRule()

# Past this many stages the construction below is not checked to round-off, and the
# order 2s is far beyond what any floating dtype can resolve.
MAX_STAGES = 24


@dataclasses.dataclass(frozen=True, eq=False)
class VPRKTableau:
    r"""The coefficients of a variational partitioned Runge–Kutta method (not a
    pytree): $a$ for the positions, $\bar a$ for the momenta, weights $b$, nodes $c$,
    and the method's classical order.

    Validated when built: $c = a\mathbf 1$, $\sum_i b_i = 1$, every $b_i \ne 0$ (the
    discrete Lagrangian $h\sum_i b_i L(Q_i, V_i)$ must see every stage), and the
    symplecticity condition $b_i \bar a_{ij} + b_j a_{ji} = b_i b_j$, and the claimed
    `order`: every order condition (bicoloured trees) up to order 8, and the
    quadrature conditions $\sum_i b_i c_i^{k-1} = 1/k$ above it. Two tableaus are
    equal when their coefficients are.

    !!! example

        The 2-stage Lobatto IIIA–IIIB pair, typed by hand:

        ```python
        tableau = diffrax_vi.VPRKTableau(
            a=np.array([[0.0, 0.0], [0.5, 0.5]]),
            a_bar=np.array([[0.5, 0.0], [0.5, 0.0]]),
            b=np.array([0.5, 0.5]),
            c=np.array([0.0, 1.0]),
            order=2,
        )
        solver = diffrax_vi.VPRK(tableau)
        ```
    """

    a: np.ndarray
    a_bar: np.ndarray
    b: np.ndarray
    c: np.ndarray
    order: int

    def __post_init__(self):
        for name in ("a", "a_bar", "b", "c"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            object.__setattr__(self, name, value)
        s = self.b.shape[0] if self.b.ndim == 1 else -1
        if s < 1 or self.a.shape != (s, s) or self.a_bar.shape != (s, s):
            raise ValueError(
                "VPRK tableau arrays have inconsistent shapes: b and c need shape "
                f"(s,) and a, a_bar shape (s, s); got a {self.a.shape}, a_bar "
                f"{self.a_bar.shape}, b {self.b.shape}, c {self.c.shape}."
            )
        if self.c.shape != (s,):
            raise ValueError(f"VPRK tableau: c has shape {self.c.shape}, not ({s},).")
        if (
            isinstance(self.order, bool)
            or not isinstance(self.order, int | np.integer)
            or self.order < 1
        ):
            raise ValueError(
                f"VPRK tableau: order must be a positive int, got {self.order!r}."
            )
        object.__setattr__(self, "order", int(self.order))
        if not np.allclose(self.a.sum(axis=1), self.c, atol=COEFFICIENT_ATOL):
            raise ValueError("VPRK tableau: the nodes c must be the row sums of a.")
        if not np.isclose(self.b.sum(), 1.0, atol=COEFFICIENT_ATOL):
            raise ValueError("VPRK tableau: the weights b must sum to 1.")
        if np.any(self.b == 0):
            raise ValueError("VPRK tableau: every weight b_i must be non-zero.")
        defect = (
            self.b[:, None] * self.a_bar
            + (self.b[:, None] * self.a).T
            - self.b[:, None] * self.b[None, :]
        )
        if np.max(np.abs(defect)) > PRODUCT_TOL:
            raise ValueError(
                "VPRK tableau is not symplectic: b_i abar_ij + b_j a_ji != b_i b_j "
                f"(largest defect {np.max(np.abs(defect)):.1e})."
            )
        # Every order condition up to 8 (9498 trees at order 8, a tenth of a second
        # once per tableau), and beyond it the quadrature conditions.
        checked = min(self.order, TREE_ORDER_MAX)
        met = satisfied_order(self.a, self.a_bar, self.b, checked)
        quadrature = [
            k
            for k in range(checked + 1, self.order + 1)
            if abs(self.b @ self.c ** (k - 1) - 1 / k) > ORDER_CONDITION_ATOL
        ]
        if met < checked or quadrature:
            failed = met + 1 if met < checked else quadrature[0]
            raise ValueError(
                f"VPRK tableau claims order {self.order}, but its coefficients fail "
                f"the order conditions of order {failed} (Hairer, Lubich & Wanner, "
                f"III.2.1). Pass the order they reach, order={failed - 1}."
            )

    @property
    def stages(self) -> int:
        return self.b.shape[0]

    @property
    def symmetric(self) -> bool:
        r"""Whether the method is symmetric: $c_{s+1-i} = 1 - c_i$,
        $b_{s+1-i} = b_i$, and $a_{s+1-i,s+1-j} + a_{ij} = b_j$ (likewise
        $\bar a$)."""
        rev = slice(None, None, -1)
        return bool(
            np.allclose(self.c[rev], 1 - self.c, atol=COEFFICIENT_ATOL)
            and np.allclose(self.b[rev], self.b, atol=COEFFICIENT_ATOL)
            and np.allclose(
                self.a[rev, rev] + self.a, self.b[None], atol=COEFFICIENT_ATOL
            )
            and np.allclose(
                self.a_bar[rev, rev] + self.a_bar, self.b[None], atol=COEFFICIENT_ATOL
            )
        )

    def _key(self):
        arrays = (self.a, self.a_bar, self.b, self.c)
        return (self.order,) + tuple(x.tobytes() for x in arrays)

    def __eq__(self, other):
        return isinstance(other, VPRKTableau) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())


def _lagrange_integrals(c: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`M[i, j]`, the integral of the Lagrange basis polynomial `l_j` on the nodes `c`
    over `[lo[i], hi[i]]`, by Gauss–Legendre quadrature (exact for its degree). Unlike
    a solve with the Vandermonde matrix of `c`, this stays at round-off for every
    `s <= MAX_STAGES` (the Vandermonde solve lost 1e-10 by s = 12)."""
    s = c.shape[0]
    x, w = np.polynomial.legendre.leggauss(s)
    taus = lo[:, None] + (hi - lo)[:, None] * (x[None, :] + 1) / 2  # [i, k]
    weights = (hi - lo)[:, None] * w[None, :] / 2
    ell = np.ones((s, s, s))  # [i, k, j]
    for j in range(s):
        for m in range(s):
            if m != j:
                ell[:, :, j] *= (taus - c[m]) / (c[j] - c[m])
    return np.einsum("ik,ikj->ij", weights, ell)


def _stage_count(s, method: str, least: int) -> int:
    if isinstance(s, bool) or not isinstance(s, int | np.integer):
        raise ValueError(
            f"{method}(s) needs a Python int number of stages, got {s!r} of type "
            f"{type(s).__name__}: the tableau is built at trace time."
        )
    if not least <= s <= MAX_STAGES:
        raise ValueError(
            f"{method} needs {least} <= s <= {MAX_STAGES} stages, got {s}. Past "
            f"{MAX_STAGES} stages the order is far beyond what float64 resolves."
        )
    return int(s)


@functools.cache
def gauss_tableau(s: int) -> VPRKTableau:
    """Gauss–Legendre collocation, order 2s; its own momentum coefficients."""
    x, w = np.polynomial.legendre.leggauss(s)
    c, b = (x + 1) / 2, w / 2
    a = _lagrange_integrals(c, np.zeros(s), c)
    return VPRKTableau(a=a, a_bar=a, b=b, c=c, order=2 * s)


@functools.cache
def lobatto_tableau(s: int) -> VPRKTableau:
    r"""Lobatto IIIA for the positions and IIIB for the momenta, order 2s - 2.

    IIIB is built from its own defining condition D(s),
    $\bar a_{ij} = (b_j / b_i)\int_{c_j}^1 \ell_i$, so the symplecticity check of the
    tableau tests the pair rather than restating it.
    """
    interior = np.polynomial.legendre.Legendre.basis(s - 1).deriv().roots()
    x = np.concatenate([[-1.0], np.sort(interior), [1.0]])
    p = np.polynomial.legendre.Legendre.basis(s - 1)(x)
    w = 2 / (s * (s - 1) * p**2)
    c, b = (x + 1) / 2, w / 2
    a = _lagrange_integrals(c, np.zeros(s), c)
    tail = _lagrange_integrals(c, c, np.ones(s))  # tail[j, i] = int_{c_j}^1 l_i
    a_bar = b[None, :] * tail.T / b[:, None]
    return VPRKTableau(a=a, a_bar=a_bar, b=b, c=c, order=2 * s - 2)


def _each_stage(fn, *stacked: PyTree) -> PyTree:
    """`fn` (the Lagrangian's gradient, the applied force) at each stage's slice of
    `stacked`, stacked again: one call per stage, not `jax.vmap` over the stages.
    Under the vmap a matrix-vector product of the user's (a learned Lagrangian's
    layers) becomes a matrix product, which XLA on CPU makes a custom (YNNPACK)
    fusion that breaks the step's loops into kernels: `GaussVPRK(2)` on the
    `learned` scene 15.9-17.9 us a step with the vmap, 5.7-7.1 us without (and the
    double pendulum 2.49-2.59 against 2.17-2.33 us; in turns). A lax.map over the
    stages (one trace, a loop) was faster still on the double pendulum (1.35 us)
    but 20-50% slower on small scenes (Kepler, the forced Duffing)."""
    stages = jax.tree.leaves(stacked)[0].shape[0]
    outs = [fn(*jtu.tree_map(lambda x: x[i], stacked)) for i in range(stages)]
    return jtu.tree_map(lambda *xs: jnp.stack(xs), *outs)


def _combine(coefficients: np.ndarray, stacked: PyTree) -> PyTree:
    """`sum_j coefficients[..., j] * stacked[j]`, leafwise.

    For a small state, as elementwise products and a sum (as `_linear.product`):
    a `tensordot` is a `dot_general`, which the Jacobian's `vmap` in Newton's loop
    batches, and which XLA on CPU makes a custom fusion that breaks the loop into
    kernels (`diagnostics.loop_breakers`): `GaussVPRK(2)`'s step on the double
    pendulum 9.9-10.0 us with it, 2.5-2.6 us without. For one stage (nothing to
    sum) and for a large state, a `tensordot`: the sum of `YNN_REDUCTION_MIN`
    products or more is a YNNPACK fusion too, and a slower kernel than the
    product's (`GaussVPRK(2)` on `scaling.py`'s chain of 4096 masses 1003-1011
    against 682-685 us a step; on its bead wire of 4096 beads 6153-6178 against
    6549-6592 us). For one stage the elementwise form cost `MidpointVI`'s Kepler
    step 3.5% (0.257-0.259 us against 0.248-0.251 us, in turns)."""
    c = np.asarray(coefficients)

    def combine(x):
        if c.shape[-1] > 1 and c.size * (x.size // len(x)) < YNN_REDUCTION_MIN:
            weights = jnp.asarray(c, x.dtype).reshape(c.shape + (1,) * (x.ndim - 1))
            stages = x.reshape((1,) * (c.ndim - 1) + x.shape)
            return jnp.sum(weights * stages, axis=c.ndim - 1)
        return jnp.tensordot(jnp.asarray(c, x.dtype), x, axes=1)

    return jtu.tree_map(combine, stacked)


class AbstractVPRK(AbstractImplicitVI):
    r"""Variational partitioned Runge–Kutta methods on a
    [`diffrax_vi.LagrangianTerm`][], defined by their
    [`diffrax_vi.VPRKTableau`][]: symmetric when the tableau is, symplectic always.
    One nonlinear solve per step for the $s$ stage velocities $V$.

    A method sets `tableau` (a class variable, a field or a property).
    """

    tableau: AbstractVar[VPRKTableau]

    @property
    def symmetric(self) -> bool:
        return self.tableau.symmetric

    def order(self, terms):
        return self.tableau.order

    def _on_group(self, step: StepInputs) -> bool:
        r"""Whether the Lagrangian lives on a group. There the one-stage method is the
        Lie midpoint rule $L_d = h\,L(g_0\tau(h\xi/2), \xi)$ with $g_1 =
        g_0\tau(h\xi)$, stepped by the discrete Euler–Poincaré equations of
        `_discrete.py`; stages beyond one have no such form here."""
        if is_euclidean(step.term.lagrangian.space):
            return False
        if self.tableau.stages != 1:
            raise ValueError(
                f"{type(self).__name__} has {self.tableau.stages} stages, and only "
                "the one-stage method (MidpointVI) is defined on a group here. For "
                "higher order on a group, compose it: "
                "`Composition(MidpointVI(), 'kahan_li8')`."
            )
        return True

    def stage_guess(self, step: StepInputs, v: V) -> PyTree:
        if self._on_group(step):
            return v
        s = self.tableau.stages
        return jtu.tree_map(lambda x: jnp.broadcast_to(x, (s, *x.shape)), v)

    def _stages(self, step: StepInputs, stage_v: PyTree) -> tuple[PyTree, PyTree]:
        r"""The stage times and positions $Q_i = q_0 + h\sum_j a_{ij} V_j$."""
        tableau = self.tableau
        h = step.h
        stage_ts = step.t0 + jnp.asarray(tableau.c, step.dtype) * h
        stage_q = jtu.tree_map(
            lambda q, dq: q[None] + h * dq, step.q0, _combine(tableau.a, stage_v)
        )
        return stage_ts, stage_q

    def _applied(self, step: StepInputs, stage_v: PyTree) -> PyTree:
        """The applied force at each stage."""
        stage_ts, stage_q = self._stages(step, stage_v)
        force = step.term.force
        return _each_stage(
            lambda t, q, v: applied_force(force, t, q, v, step.args),
            stage_ts,
            stage_q,
            stage_v,
        )

    def _stage_grads(self, step: StepInputs, stage_v: PyTree) -> tuple[PyTree, PyTree]:
        stage_ts, stage_q = self._stages(step, stage_v)
        grad = jax.grad(
            lambda t, q, v: lagrangian_value(step.term.lagrangian, t, q, v, step.args),
            argnums=(1, 2),
        )
        dl_dq, dl_dv = _each_stage(grad, stage_ts, stage_q, stage_v)
        if step.term.force is not None:
            # The forced stage equations: the Lagrange-d'Alembert principle with the
            # force sampled, like dL/dq, at the stages (Marsden & West (2001), §3.2).
            applied = self._applied(step, stage_v)
            dl_dq = jtu.tree_map(lambda a, b: a + b, dl_dq, applied)
        return dl_dq, dl_dv

    def stage_work(self, step: StepInputs, stage_v: PyTree) -> Array:
        if self._on_group(step):
            return rule_work(_MIDPOINT, step, stage_v)
        # h sum_i b_i F(Q_i, V_i) . V_i: the quadrature with which the stages
        # accumulate the force's impulse.
        stage_power = jax.vmap(power)(self._applied(step, stage_v), stage_v)
        return step.h * jnp.sum(jnp.asarray(self.tableau.b, step.dtype) * stage_power)

    def stage_residual(
        self, step: StepInputs, stage_v: PyTree
    ) -> tuple[PyTree, PyTree]:
        if self._on_group(step):
            return rule_residual(_MIDPOINT, step, stage_v)
        dl_dq, dl_dv = self._stage_grads(step, stage_v)
        a_bar = self.tableau.a_bar
        kicks = _combine(a_bar, dl_dq)
        kick_sizes = _combine(np.abs(a_bar), jtu.tree_map(jnp.abs, dl_dq))
        r = jtu.tree_map(
            lambda pv, p, k: pv - p[None] - step.h * k, dl_dv, step.p0, kicks
        )
        s = jtu.tree_map(
            lambda pv, p, k, c: (
                jnp.abs(pv) + jnp.abs(p[None]) + jnp.abs(step.h) * k + c[None]
            ),
            dl_dv,
            step.p0,
            kick_sizes,
            step.momentum_offset,
        )
        return r, s

    def inverse_mass(self, step: StepInputs) -> PyTree | None:
        inverse = fixed_point_inverse_mass(step.term.lagrangian, step.p0)
        if inverse is None:
            return None
        # On a group the unknown is the one velocity of the Lie midpoint rule.
        stages = () if self._on_group(step) else (self.tableau.stages,)
        return jtu.tree_map(
            lambda w: jnp.broadcast_to(w, (*stages, *jnp.shape(w))), inverse
        )

    @property
    def one_stage(self) -> bool:
        return self.tableau.stages == 1

    def fold_residual(self, step: StepInputs):
        r"""Several stages: the midpoint step's residual at the stages' mean velocity
        $\bar V = \sum_i b_i V_i = (q_1 - q_0)/h$, given to stage $i$ with weight
        $b_i$, so that its curvature along the way from the guess is
        $\delta\bar V\cdot J_{\rm mid}(\bar V)\,\delta\bar V$, with $J_{\rm mid} =
        \partial^2 L/\partial v^2 - (h^2/4)\,\partial^2 L/\partial q^2$ up to an
        antisymmetric part. The stage equations' own Jacobian is no such test: the
        curvature it gives (weighted by $b$) fails the oscillator's one root from
        $h\omega = 3.5$ (`GaussVPRK(3)`, `LobattoVPRK(3)`) or 4 (`GaussVPRK(2)`);
        this one is positive wherever the potential curves upwards, at every step
        size, and turns negative only where the step outruns an instability
        ($h\lambda > 2$ for a growth rate $\lambda$), the same test as
        `MidpointVI`'s: a step that jumps across a blow-up (its roots there have
        flipped signs and energies of $10^{15}$) is a failure, not a state."""
        if self.one_stage:
            return super().fold_residual(step)
        b = self.tableau.b

        def residual(stage_v):
            r, s = rule_residual(_MIDPOINT, step, _combine(b, stage_v))
            spread = lambda x: jnp.asarray(b, x.dtype).reshape(-1, *(1,) * x.ndim)
            return jtu.tree_map(lambda x: spread(x) * x[None], r), s

        return residual

    def reversed_stages(self, unknowns: PyTree) -> PyTree:
        # A symmetric tableau's stage i of the step with -h is stage s + 1 - i of
        # the step with h (c_i -> 1 - c_i); one stage has no stage axis on a group.
        if self.tableau.stages == 1:
            return unknowns
        return jtu.tree_map(lambda x: jnp.flip(x, 0), unknowns)

    def jacobian_tags(self, step: StepInputs) -> frozenset:
        # One stage: J = d2L/dv2 - (h^2/4) d2L/dq2 + (h/2) (Lqv - Lqv^T), symmetric
        # where dL/dv does not read q (Lqv = 0: a separable Lagrangian, or any whose
        # momentum is free of q by its trace), and definite for steps that resolve
        # the motion. An applied force adds its own Jacobian, which need not be
        # symmetric.
        lagrangian = step.term.lagrangian
        if self._on_group(step):
            return frozenset()
        symmetric = isinstance(lagrangian, AbstractSeparableLagrangian) or not (
            momentum_reads_position(lagrangian, step.t0, step.q0, step.p0, step.args)
        )
        if symmetric and self.tableau.stages == 1 and step.term.force is None:
            return SYMMETRIC_POSITIVE
        return frozenset()

    def stage_increments(self, step: StepInputs, stage_v: PyTree) -> tuple[Q, P]:
        if self._on_group(step):
            return rule_increments(_MIDPOINT, step, stage_v)
        dl_dq, _ = self._stage_grads(step, stage_v)
        dp = jtu.tree_map(lambda x: step.h * x, _combine(self.tableau.b, dl_dq))
        return self.stage_step(step, stage_v), dp

    def stage_step(self, step: StepInputs, stage_v: PyTree) -> Q:
        if self._on_group(step):
            return rule_step(step, stage_v)
        return jtu.tree_map(lambda x: step.h * x, _combine(self.tableau.b, stage_v))


_VPRK_REFERENCES = r"""
    ??? cite "References"

        ```bibtex
        @article{marsden2001discrete,
            title={Discrete mechanics and variational integrators},
            author={Marsden, Jerrold E. and West, Matthew},
            journal={Acta Numerica},
            volume={10},
            pages={357--514},
            year={2001},
        }
        @book{hairer2006geometric,
            title={Geometric Numerical Integration},
            author={Hairer, Ernst and Lubich, Christian and Wanner, Gerhard},
            edition={2},
            publisher={Springer},
            year={2006},
        }
        ```
"""


class VPRK(AbstractVPRK):
    __doc__ = (
        r"""The variational partitioned Runge–Kutta method of any valid
    [`diffrax_vi.VPRKTableau`][].

    Symplectic; symmetric and of the tableau's order when the tableau is. One
    nonlinear solve for the $s$ stage velocities per step. Fixed step sizes only.
    Cubic Hermite interpolation for dense output. [`diffrax_vi.GaussVPRK`][],
    [`diffrax_vi.LobattoVPRK`][] and [`diffrax_vi.MidpointVI`][] are named tableaus.

    !!! example

        ```python
        solver = diffrax_vi.VPRK(diffrax_vi.GaussVPRK(2).tableau)  # = GaussVPRK(2)
        ```
"""
        + _VPRK_REFERENCES
    )

    tableau: VPRKTableau = eqx.field(static=True)
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    def __check_init__(self):
        if not isinstance(self.tableau, VPRKTableau):
            raise ValueError(
                f"VPRK(tableau) takes a diffrax_vi.VPRKTableau, got "
                f"{type(self.tableau).__name__}."
            )


class GaussVPRK(AbstractVPRK):
    __doc__ = (
        r"""Variational partitioned Runge–Kutta method with `s` Gauss–Legendre
    stages.

    Order $2s$, symmetric, symplectic; conserves every quadratic first integral. One
    nonlinear solve for $s$ stage velocities per step. Fixed step sizes only. Cubic
    Hermite interpolation for dense output. `GaussVPRK(1)` is
    [`diffrax_vi.MidpointVI`][].
"""
        + _VPRK_REFERENCES
    )

    stages: int = eqx.field(
        static=True,
        converter=functools.partial(_stage_count, method="GaussVPRK", least=1),
    )
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    @property
    def tableau(self) -> VPRKTableau:
        return gauss_tableau(self.stages)


class LobattoVPRK(AbstractVPRK):
    __doc__ = (
        r"""Variational partitioned Runge–Kutta method with `s` Lobatto stages:
    Lobatto IIIA for the positions, IIIB for the momenta.

    Order $2s - 2$, symmetric, symplectic. One nonlinear solve per step. For a
    separable Lagrangian `LobattoVPRK(2)` is Störmer–Verlet, like
    [`diffrax_vi.TrapezoidalVI`][] (for a configuration-dependent mass the two are
    different second-order methods). Fixed step sizes only. Cubic Hermite
    interpolation for dense output.
"""
        + _VPRK_REFERENCES
    )

    stages: int = eqx.field(
        static=True,
        converter=functools.partial(_stage_count, method="LobattoVPRK", least=2),
    )
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    @property
    def tableau(self) -> VPRKTableau:
        return lobatto_tableau(self.stages)


_ARGS_DOC = (
    """**Arguments:**

- `stages`: the number of stages `s`, a Python int.
"""
    + IMPLICIT_ARGS_DOC
)
GaussVPRK.__init__.__doc__ = _ARGS_DOC
LobattoVPRK.__init__.__doc__ = _ARGS_DOC
VPRK.__init__.__doc__ = (
    """**Arguments:**

- `tableau`: a [`diffrax_vi.VPRKTableau`][].
"""
    + IMPLICIT_ARGS_DOC
)
