import diffrax as dfx
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import Args, Q, RealScalarLike
from .._discrete import (
    AbstractDiscreteLagrangian,
    average_grads,
    del_residual,
    discrete_hamiltonian_map,
    MidpointRule,
)
from .._lagrangian import AbstractLagrangian
from .._misc import (
    all_finite,
    default_root_finder,
    momentum_scale,
    split_state,
    state_dtype,
    tree_max_abs,
    unvmap_any,
)
from .._term import hamilton_vector_field
from .base import (
    AbstractVariationalSolver,
    compensated_add,
    hermite_dense_info,
    initial_compensation,
    step_result,
    step_times,
    unwrap_term,
)


# The past positions, newest first, `(q_{k-1}, q_{k-2}[, q_{k-3}])`, the steps
# between them, `(t_k - t_{k-1}, t_{k-1} - t_{k-2}[, t_{k-2} - t_{k-3}])`, and the
# compensation of the summation of positions.
_History = tuple[tuple[Q, ...], tuple[Array, ...], Q]


def _sub(a, b):
    return jtu.tree_map(lambda x, y: x - y, a, b)


def _scale(c, a):
    return jtu.tree_map(lambda x: c * x, a)


class LinearizedVI(AbstractVariationalSolver):
    r"""The seed's linearized variational integrator: one linear solve per step, no
    Newton iteration, for any Lagrangian.

    A multistep method on positions. It advances the triple
    $(q_{k-1}, q_k, q_{k+1})$ by the derivative of the discrete Euler–Lagrange
    residual $F(q_{k-1}, q_k, q_{k+1}) = D_2 L_d(q_{k-1}, q_k) + D_1 L_d(q_k, q_{k+1})$
    along the discrete velocities $u$ (the seed's (4.63)):

    $$\frac{\partial F}{\partial q_{k-1}} u_{k-1} + \frac{\partial F}{\partial q_k} u_k
    + \frac{\partial F}{\partial q_{k+1}} u_{k+1} = 0,$$

    which is linear in $q_{k+2}$, with the matrix $\partial F / \partial q_{k+1}$ that
    a Newton step on the discrete Euler–Lagrange equations uses. With
    `velocity="forward"`, $u_k = (q_{k+1} - q_k)/h$; with `velocity="centered"`, the
    seed's Section 5.6 variant, $u_k = (q_{k+1} - q_{k-1})/(2h)$.

    The state is `y = (q_k, p_k)` with $p_k = D_2 L_d(q_{k-1}, q_k)$ the discrete
    Legendre transform. The past positions and step sizes live in the solver state.
    `init` builds them by stepping the variational integrator of the same discrete
    Lagrangian backwards from `(q0, p0)`, so the start lies on the manifold
    $S = \{F = 0\}$ (4.72). A jump (`made_jump`) rebuilds them the same way. On $S$
    the method is presymplectic (Theorem 2). For a nonlinear Lagrangian the triples
    drift off $S$ (measure it with [`diffrax_vi.del_residuals`][]), and the linearized
    method is not more accurate than the variational integrator it linearizes.
    Fixed step sizes only. Cubic Hermite interpolation for dense output.

    ??? cite "Reference"

        ```bibtex
        @mastersthesis{hirani2000linearization,
            title={Linearization methods for variational integrators and
                   {E}uler--{L}agrange equations},
            author={Hirani, Anil N.},
            school={California Institute of Technology},
            year={2000},
        }
        ```
    """

    velocity: str = eqx.field(static=True, default="forward")
    discrete_lagrangian: AbstractDiscreteLagrangian = MidpointRule()
    linear_solver: lx.AbstractLinearSolver = lx.LU()
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True
    max_del_residual: float | None = 0.1

    def __check_init__(self):
        if self.velocity not in ("forward", "centered"):
            raise ValueError(
                f"LinearizedVI(velocity=...) must be 'forward' or 'centered', got "
                f"{self.velocity!r}."
            )

    def order(self, terms):
        return None

    def _n_past(self) -> int:
        return 2 if self.velocity == "forward" else 3

    def _history(self, lagrangian: AbstractLagrangian, tp0, h, y0, args) -> _History:
        """The past, from backward steps of the variational integrator of the same
        discrete Lagrangian: consecutive triples then satisfy its DEL equations."""
        q, p = y0
        dtype = state_dtype(y0)
        root_finder = self.root_finder or default_root_finder(dtype)
        qs = []
        t = tp0
        # The start's velocity: the first Newton guess, and a check that the Legendre
        # map can be inverted there at all.
        (v_guess, _), result = hamilton_vector_field(lagrangian, tp0, q, p, args)
        ok = result == dfx.RESULTS.successful
        for _ in range(self._n_past()):
            dq, dp, v, result = discrete_hamiltonian_map(
                self.discrete_lagrangian,
                lagrangian,
                t,
                -h,
                q,
                p,
                args,
                v_guess,
                root_finder,
                self.root_find_max_steps,
            )
            q = jtu.tree_map(lambda a, b: a + b, q, dq)
            p = jtu.tree_map(lambda a, b: a + b, p, dp)
            qs.append(q)
            t = t - h
            v_guess = v
            ok = ok & (result == dfx.RESULTS.successful)
        # A history that could not be built (singular d2L/dv2, no root) is poisoned,
        # so the first step reports it instead of linearizing about garbage.
        qs = jtu.tree_map(lambda x: jnp.where(ok, x, jnp.nan), qs)
        compensation = initial_compensation(y0[0], self.compensated)
        return tuple(qs), tuple(h for _ in qs), compensation

    def init(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
    ) -> _History:
        term, direction = unwrap_term(terms, "LinearizedVI")
        split_state(y0)
        tp0, _, h = step_times(terms, direction, t0, t1, state_dtype(y0))
        return self._history(term.lagrangian, tp0, h, y0, args)

    def step(
        self,
        terms: dfx.AbstractTerm,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: tuple[PyTree, PyTree],
        args: Args,
        solver_state: _History,
        made_jump: bool | Bool[ArrayLike, ""],
    ):
        term, direction = unwrap_term(terms, "LinearizedVI")
        lagrangian = term.lagrangian
        q0, _ = split_state(y0)
        tp0, tp1, h = step_times(terms, direction, t0, t1, state_dtype(y0))
        qs, hs, compensation = lax.cond(
            unvmap_any(made_jump),
            lambda: self._history(lagrangian, tp0, h, y0, args),
            lambda: solver_state,
        )
        # The triple (x, y, z) = (q_{k-2}, q_{k-1}, q_k) and its steps.
        x, y, z = qs[1], qs[0], q0
        h_xy, h_yz = hs[1], hs[0]
        ts = (tp0 - h_yz - h_xy, tp0 - h_yz, tp0)

        def residual(a, b, c):
            return del_residual(
                self.discrete_lagrangian, lagrangian, ts, (a, b, c), args
            )

        drift, linear = jax.linearize(residual, x, y, z)
        if self.velocity == "forward":
            u_x = _scale(1 / h_xy, _sub(y, x))
            u_y = _scale(1 / h_yz, _sub(z, y))
            span = h  # q_{k+1} = q_k + h u_k
            base = z
        else:
            h_wx = hs[2]
            u_x = _scale(1 / (h_wx + h_xy), _sub(y, qs[2]))
            u_y = _scale(1 / (h_xy + h_yz), _sub(z, x))
            span = h_yz + h  # q_{k+1} = q_{k-1} + (h_{k-1} + h) u_k
            base = y
        zeros = jtu.tree_map(jnp.zeros_like, z)
        rhs = jtu.tree_map(jnp.negative, linear(u_x, u_y, zeros))
        operator = lx.FunctionLinearOperator(
            lambda w: linear(zeros, zeros, w), jax.eval_shape(lambda: z)
        )
        sol = lx.linear_solve(operator, rhs, self.linear_solver, throw=False)
        u_z = sol.value
        dq = jtu.tree_map(lambda b, u, q: (b - q) + span * u, base, u_z, q0)
        q1, compensation = compensated_add(q0, dq, compensation)
        # The discrete Legendre transform p_{k+1} = D2 Ld(q_k, q_{k+1}) through the
        # step's velocity: u_z itself for forward velocities, so nothing cancels.
        v = u_z if self.velocity == "forward" else _scale(1 / h, _sub(q1, z))
        _, p1 = average_grads(self.discrete_lagrangian, lagrangian, tp0, h, q0, v, args)
        y1 = (q1, p1)
        result = step_result(dfx.RESULTS.promote(sol.result), y0, y1, all_finite(qs))
        if self.max_del_residual is not None:
            # The triple this step linearized about has left the DEL manifold S: the
            # linearization no longer follows the variational integrator.
            off = tree_max_abs(drift) > self.max_del_residual * momentum_scale(y0[1])
            result = dfx.RESULTS.where(
                (result == dfx.RESULTS.successful) & off,
                dfx.RESULTS.nonlinear_divergence,
                result,
            )
        dense_info = hermite_dense_info(lagrangian, tp0, tp1, h, y0, y1, args, v)
        new_qs = (q0,) + qs[:-1]
        new_hs = (h,) + hs[:-1]
        return y1, None, dense_info, (new_qs, new_hs, compensation), result

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


LinearizedVI.__init__.__doc__ = """**Arguments:**

- `velocity`: `"forward"` (the seed's (4.63), $u_k = (q_{k+1} - q_k)/h$) or
    `"centered"` (Section 5.6, $u_k = (q_{k+1} - q_{k-1})/(2h)$).
- `discrete_lagrangian`: the discrete Lagrangian whose DEL equations are linearized:
    [`diffrax_vi.MidpointRule`][] (default) or [`diffrax_vi.TrapezoidalRule`][].
- `linear_solver`: the lineax solver for the step's linear system. Defaults to LU.
- `root_finder`, `root_find_max_steps`: for the backward variational steps that build
    the starting history (at `init` and after a jump); as for
    [`diffrax_vi.MidpointVI`][].
- `compensated`: compensated (Kahan) summation of the new positions (default). The
    momenta are recomputed each step, not summed.
- `max_del_residual`: the step fails with `RESULTS.nonlinear_divergence` once the
    discrete Euler–Lagrange residual of the triple it linearizes about exceeds this
    multiple of `1 + max|p|` (default 0.1): the triples have left the manifold $S$
    and the method no longer follows the variational integrator (it has no Newton
    iteration whose failure would say so). Healthy runs stay below 0.005; the
    divergences of the centered variant's parasitic mode (Kepler, the double
    pendulum) and blow-ups of the forward variant cross it within a few steps.
    `None` turns the check off. See the [stability page](../stability.md).
"""
