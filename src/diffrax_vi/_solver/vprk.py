import abc
import dataclasses
import functools

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike
from .._lagrangian import lagrangian_value
from .._misc import (
    all_finite,
    default_root_finder,
    momentum_scale,
    split_state,
    state_dtype,
)
from .base import (
    AbstractSymmetricSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    compensated_add,
    hermite_dense_info,
    implicit_vi_init,
    step_result,
    step_times,
    Substep,
    unwrap_term,
)


@dataclasses.dataclass(frozen=True)
class VPRKTableau:
    r"""The coefficients of a variational partitioned Runge–Kutta method (not a
    pytree): $a$ for the positions, $\bar a$ for the momenta, weights $b$, nodes $c$.

    Validated when built: $c = a\mathbf 1$, $\sum_i b_i = 1$, every $b_i \ne 0$ (the
    discrete Lagrangian $h\sum_i b_i L(Q_i, \dot Q_i)$ must see every stage), and the
    symplecticity condition $b_i \bar a_{ij} + b_j a_{ji} = b_i b_j$.
    """

    a: np.ndarray
    a_bar: np.ndarray
    b: np.ndarray
    c: np.ndarray
    order: int

    def __post_init__(self):
        s = self.b.shape[0]
        if self.a.shape != (s, s) or self.a_bar.shape != (s, s) or self.c.shape != (s,):
            raise ValueError("VPRK tableau arrays have inconsistent shapes.")
        if not np.allclose(self.a.sum(axis=1), self.c, atol=1e-13):
            raise ValueError("VPRK tableau: the nodes c must be the row sums of a.")
        if not np.isclose(self.b.sum(), 1.0, atol=1e-13):
            raise ValueError("VPRK tableau: the weights b must sum to 1.")
        if np.any(self.b == 0):
            raise ValueError("VPRK tableau: every weight b_i must be non-zero.")
        defect = (
            self.b[:, None] * self.a_bar
            + (self.b[:, None] * self.a).T
            - self.b[:, None] * self.b[None, :]
        )
        if np.max(np.abs(defect)) > 1e-12:
            raise ValueError(
                "VPRK tableau is not symplectic: b_i abar_ij + b_j a_ji != b_i b_j "
                f"(largest defect {np.max(np.abs(defect)):.1e})."
            )


def _collocation(c: np.ndarray) -> np.ndarray:
    """`a` with the simplifying assumption C(s): sum_j a_ij c_j^(k-1) = c_i^k / k."""
    s = c.shape[0]
    k = np.arange(1, s + 1)
    vandermonde = c[None, :] ** (k[:, None] - 1)  # [k, j]
    rhs = c[:, None] ** k[None, :] / k[None, :]  # [i, k]
    return np.linalg.solve(vandermonde, rhs.T).T


@functools.cache
def gauss_tableau(s: int) -> VPRKTableau:
    """Gauss–Legendre collocation, order 2s; its own momentum coefficients."""
    x, w = np.polynomial.legendre.leggauss(s)
    c, b = (x + 1) / 2, w / 2
    a = _collocation(c)
    return VPRKTableau(a=a, a_bar=a, b=b, c=c, order=2 * s)


@functools.cache
def lobatto_tableau(s: int) -> VPRKTableau:
    """Lobatto IIIA for the positions and IIIB for the momenta, order 2s - 2.

    IIIB is built from its own defining condition D(s),
    sum_i b_i c_i^(k-1) abar_ij = b_j (1 - c_j^k) / k, so the symplecticity check of
    the tableau tests the pair rather than restating it.
    """
    interior = np.polynomial.legendre.Legendre.basis(s - 1).deriv().roots()
    x = np.concatenate([[-1.0], np.sort(interior), [1.0]])
    p = np.polynomial.legendre.Legendre.basis(s - 1)(x)
    w = 2 / (s * (s - 1) * p**2)
    c, b = (x + 1) / 2, w / 2
    a = _collocation(c)
    k = np.arange(1, s + 1)
    weights = b[None, :] * c[None, :] ** (k[:, None] - 1)  # [k, i]
    rhs = b[None, :] * (1 - c[None, :] ** k[:, None]) / k[:, None]  # [k, j]
    a_bar = np.linalg.solve(weights, rhs)
    return VPRKTableau(a=a, a_bar=a_bar, b=b, c=c, order=2 * s - 2)


def _combine(coefficients: np.ndarray, stacked: PyTree) -> PyTree:
    """`sum_j coefficients[..., j] * stacked[j]`, leafwise."""
    return jtu.tree_map(
        lambda x: jnp.tensordot(jnp.asarray(coefficients, x.dtype), x, axes=1), stacked
    )


class AbstractVPRK(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractSymmetricSolver
):
    r"""Variational partitioned Runge–Kutta methods on a
    [`diffrax_vi.LagrangianTerm`][]. The discrete Lagrangian is
    $L_d = h\sum_i b_i L(t_0 + c_i h, Q_i, V_i)$ with
    $Q_i = q_0 + h\sum_j a_{ij} V_j$, which gives the stage equations

    $$\frac{\partial L}{\partial v}(Q_i, V_i) = p_0 + h\sum_j \bar a_{ij}
    \frac{\partial L}{\partial q}(Q_j, V_j),\qquad
    q_1 = q_0 + h\sum_i b_i V_i,\quad p_1 = p_0 + h\sum_i b_i
    \frac{\partial L}{\partial q}(Q_i, V_i),$$

    solved for the stage velocities $V$ by Newton's method.
    """

    stages: int = eqx.field(static=True)
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    @abc.abstractmethod
    def tableau(self) -> VPRKTableau:
        """The method's coefficients."""

    def order(self, terms):
        return self.tableau().order

    def init(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
    ) -> PyTree:
        (v0, _), compensation = implicit_vi_init(
            terms, type(self).__name__, t0, y0, args, self.compensated
        )
        stage_v = jtu.tree_map(lambda v: jnp.stack([v] * self.stages), v0)
        return stage_v, compensation

    def step(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
        *,
        substep: Substep | None = None,
    ):
        name = type(self).__name__
        term, direction = unwrap_term(terms, name)
        lagrangian = term.lagrangian
        q0, p0 = split_state(y0)
        dtype = state_dtype(y0)
        tp0, tp1, h = step_times(terms, direction, t0, t1, dtype, substep)
        tableau = self.tableau()
        root_finder = self.root_finder or default_root_finder(dtype)
        stage_v_prev, compensation = solver_state
        stage_ts = tp0 + jnp.asarray(tableau.c, dtype) * h

        def stage_grads(stage_v):
            stage_q = jtu.tree_map(
                lambda q, dq: q[None] + h * dq, q0, _combine(tableau.a, stage_v)
            )
            grad = jax.grad(
                lambda t, q, v: lagrangian_value(lagrangian, t, q, v, args),
                argnums=(1, 2),
            )
            return jax.vmap(grad)(stage_ts, stage_q, stage_v)

        scale = momentum_scale(p0)

        def residual(stage_v, _):
            dl_dq, dl_dv = stage_grads(stage_v)
            kicks = _combine(tableau.a_bar, dl_dq)
            return jtu.tree_map(
                lambda pv, p, k: (pv - p[None] - h * k) / scale, dl_dv, p0, kicks
            )

        sol = optx.root_find(
            residual,
            root_finder,
            stage_v_prev,
            max_steps=self.root_find_max_steps,
            throw=False,
        )
        stage_v = sol.value
        dl_dq, _ = stage_grads(stage_v)
        dq = jtu.tree_map(lambda x: h * x, _combine(tableau.b, stage_v))
        dp = jtu.tree_map(lambda x: h * x, _combine(tableau.b, dl_dq))
        y1, compensation = compensated_add(y0, (dq, dp), compensation)
        result = step_result(
            dfx.RESULTS.promote(sol.result), y0, y1, all_finite(stage_v_prev)
        )
        v = jtu.tree_map(lambda x: x / h, dq)
        dense_info = hermite_dense_info(lagrangian, tp0, tp1, h, y0, y1, args, v)
        return y1, None, dense_info, (stage_v, compensation), result

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class GaussVPRK(AbstractVPRK):
    r"""Variational partitioned Runge–Kutta method with `s` Gauss–Legendre stages.

    Order $2s$, symmetric, symplectic; conserves every quadratic first integral. One
    nonlinear solve for $s$ stage velocities per step. Fixed step sizes only. Cubic
    Hermite interpolation for dense output. `GaussVPRK(1)` is
    [`diffrax_vi.MidpointVI`][].

    ??? cite "Reference"

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

    def __check_init__(self):
        if self.stages < 1:
            raise ValueError(f"GaussVPRK needs s >= 1 stages, got {self.stages}.")

    def tableau(self) -> VPRKTableau:
        return gauss_tableau(self.stages)


class LobattoVPRK(AbstractVPRK):
    r"""Variational partitioned Runge–Kutta method with `s` Lobatto stages: Lobatto
    IIIA for the positions, IIIB for the momenta.

    Order $2s - 2$, symmetric, symplectic. One nonlinear solve per step.
    `LobattoVPRK(2)` is [`diffrax_vi.TrapezoidalVI`][] (Störmer–Verlet for a separable
    Lagrangian). Fixed step sizes only. Cubic Hermite interpolation for dense output.

    ??? cite "Reference"

        ```bibtex
        @book{hairer2006geometric,
            title={Geometric Numerical Integration},
            author={Hairer, Ernst and Lubich, Christian and Wanner, Gerhard},
            edition={2},
            publisher={Springer},
            year={2006},
        }
        ```
    """

    def __check_init__(self):
        if self.stages < 2:
            raise ValueError(f"LobattoVPRK needs s >= 2 stages, got {self.stages}.")

    def tableau(self) -> VPRKTableau:
        return lobatto_tableau(self.stages)


_ARGS_DOC = """**Arguments:**

- `stages`: the number of stages `s`.
- `root_finder`, `root_find_max_steps`: as for [`diffrax_vi.MidpointVI`][].
- `compensated`: compensated (Kahan) summation of the step's increment, so that
    round-off in the energy grows like the square root of the number of steps.
"""
GaussVPRK.__init__.__doc__ = _ARGS_DOC
LobattoVPRK.__init__.__doc__ = _ARGS_DOC
