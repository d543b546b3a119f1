from typing import Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.flatten_util
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import P, Q, RealScalarLike
from .._discrete import (
    AbstractDiscreteLagrangian,
    average_grads,
    del_momenta,
    discrete_hamiltonian_map,
    MidpointRule,
)
from .._lagrangian import inverse_legendre, momentum_reads_position
from .._linear import implicit_lu_solve, krylov_solve, linear_matrix
from .._misc import (
    all_finite,
    state_dtype,
    tree_add,
    tree_dtype,
    tree_max_abs,
    tree_size,
    tree_sub,
)
from .._private_api import promote_result, unvmap_any
from .._root_finders import Newton
from .._space import is_euclidean
from .._tolerance import (
    LINEARIZED_DENSE_MAX,
    LINEARIZED_RTOL,
    LINEARIZED_STEPS_PER_UNKNOWN,
    NEWTON_DENSE_MAX,
    newton_is_dense,
)
from .base import (
    AbstractVariationalSolver,
    initial_compensation,
    MethodStep,
    StepInputs,
    VIState,
)
from .unknowns import check_start, start_result


SYMMETRIC_NEGATIVE = frozenset({lx.symmetric_tag, lx.negative_semidefinite_tag})


class History(eqx.Module):
    """The past positions, newest first, `(q_{k-1}, q_{k-2}[, q_{k-3}])`, the steps
    between them, `(t_k - t_{k-1}, t_{k-1} - t_{k-2}[, t_{k-2} - t_{k-3}])`, and the
    largest momentum the discrete Euler–Lagrange equations have balanced so far (the
    scale of the divergence guard: the momenta vanish at a turning point, the
    motion's scale does not)."""

    positions: tuple[Q, ...]
    steps: tuple[Array, ...]
    momentum: Array


def _scale(c, a):
    return jtu.tree_map(lambda x: c * x, a)


# The relative change of step size above which the past is rebuilt.
STEP_CHANGE = 1e-3


class LinearizedVI(AbstractVariationalSolver):
    r"""The linearized variational integrator of Hirani (2000): one linear solve per
    step, no Newton iteration, for any Lagrangian.

    A multistep method on positions. It advances the triple
    $(q_{k-1}, q_k, q_{k+1})$ by the derivative of the discrete Euler–Lagrange
    residual $F(q_{k-1}, q_k, q_{k+1}) = D_2 L_d(q_{k-1}, q_k) + D_1 L_d(q_k, q_{k+1})$
    along the discrete velocities $u$ (Hirani (2000), eq. (4.63)):

    $$\frac{\partial F}{\partial q_{k-1}} u_{k-1} + \frac{\partial F}{\partial q_k} u_k
    + \frac{\partial F}{\partial q_{k+1}} u_{k+1} = 0,$$

    which is linear in $q_{k+2}$, with the matrix $\partial F / \partial q_{k+1}$ that
    a Newton step on the discrete Euler–Lagrange equations uses. With
    `velocity="forward"`, $u_k = (q_{k+1} - q_k)/h$; with `velocity="centered"`, the
    variant of Hirani (2000), §5.6, $u_k = (q_{k+1} - q_{k-1})/(2h)$.

    The state is `y = (q_k, p_k)` with $p_k = D_2 L_d(q_{k-1}, q_k)$ the discrete
    Legendre transform. The past positions and step sizes live in the solver state.
    `init` builds them by stepping the variational integrator of the same discrete
    Lagrangian backwards from `(q0, p0)`, so the start lies on the manifold
    $S = \{F = 0\}$ (eq. (4.72)). A jump (`made_jump`) rebuilds them the same way. On
    $S$ the method is presymplectic (Theorem 2). For a nonlinear Lagrangian the
    triples drift off $S$ (measure it with
    [`diffrax_vi.diagnostics.del_residuals`][]), and the linearized
    method is not more accurate than the variational integrator it linearizes.
    Made for fixed step sizes: a step whose size differs from the last one (by more
    than 0.1%) rebuilds the past at the new size first, as a jump does, so variable
    steps (`diffrax.StepTo`) stay on $S$ at the cost of those backward steps. Cubic
    Hermite interpolation for dense output.

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

    velocity: Literal["forward", "centered"] = eqx.field(static=True, default="forward")
    discrete_lagrangian: AbstractDiscreteLagrangian = MidpointRule()
    linear_solver: lx.AbstractLinearSolver | None = None
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True
    max_del_residual: float | None = 0.5

    def __check_init__(self):
        if self.velocity not in ("forward", "centered"):
            raise ValueError(
                f"LinearizedVI(velocity=...) must be 'forward' or 'centered', got "
                f"{self.velocity!r}."
            )
        bound = self.max_del_residual
        if (
            bound is not None
            and not isinstance(bound, jax.core.Tracer)
            and not (jnp.ndim(bound) == 0 and float(bound) > 0)
        ):
            raise ValueError(
                "LinearizedVI(max_del_residual=...) must be a positive number (a "
                f"fraction of the largest momentum), or None; got {bound!r}."
            )

    def order(self, terms):
        # The global order on a nonlinear problem, fitted in tests/test_seed.py:
        # forward velocities drop to 1 (their O(h) local error, Hirani (2000),
        # §5.5); centered ones (§5.6) keep 2.
        return 1 if self.velocity == "forward" else 2

    def _linear_solve(self, matvec, rhs, guess, tags) -> tuple[PyTree, lx.RESULTS]:
        # No LAPACK call, which would keep XLA from compiling the time-stepping loop
        # whole: an unrolled elimination of the dense matrix for a small system (up
        # to LINEARIZED_DENSE_MAX unknowns where it is symmetric, NEWTON_DENSE_MAX
        # where it is not), else conjugate gradients for a symmetric matrix and
        # BiCGStab for another. Either is differentiated as a linear solve, without
        # a host callback or a scatter in a gradient's loop (`implicit_lu_solve`,
        # `krylov_solve`).
        if self.linear_solver is not None:
            operator = lx.FunctionLinearOperator(matvec, jax.eval_shape(lambda: rhs))
            sol = lx.linear_solve(operator, rhs, self.linear_solver, throw=False)
            return sol.value, sol.result
        n = tree_size(rhs)
        if n <= LINEARIZED_DENSE_MAX or (newton_is_dense(n) and not tags):
            flat_rhs, unravel = jax.flatten_util.ravel_pytree(rhs)
            flat_matvec = lambda x: jax.flatten_util.ravel_pytree(matvec(unravel(x)))[0]
            matrix = linear_matrix(flat_matvec, flat_rhs)
            x = implicit_lu_solve(flat_matvec, matrix, flat_rhs, NEWTON_DENSE_MAX)
            # A singular matrix leaves a non-finite solution, as lineax's LU reports.
            result = lx.RESULTS.where(
                all_finite(x), lx.RESULTS.successful, lx.RESULTS.singular
            )
            return unravel(x), result
        # One solve with no Newton iteration to correct it: to near round-off.
        eps = float(jnp.finfo(tree_dtype(rhs)).eps)
        return krylov_solve(
            matvec,
            rhs,
            LINEARIZED_RTOL * eps,
            tags,
            LINEARIZED_STEPS_PER_UNKNOWN * tree_size(rhs),
            guess=guess,
        )

    def _n_past(self) -> int:
        return 2 if self.velocity == "forward" else 3

    def init_from_history(
        self,
        positions: tuple[Q, ...],
        steps: tuple[RealScalarLike, ...],
        y0: tuple[Q, P],
    ) -> VIState:
        """The solver state that continues a given past instead of building one:
        `positions = (q_{k-1}, q_{k-2}[, q_{k-3}])`, newest first, and the steps
        between them, `(t_k - t_{k-1}, ...)` (two of each for forward velocities,
        three for centered). Pass it to `diffeqsolve(..., solver_state=...)` with
        `y0 = (q_k, p_k)`, e.g. to start from exact positions as Hirani (2000), §5.4,
        does."""
        n = self._n_past()
        if len(positions) < n or len(steps) < n:
            raise ValueError(
                f"LinearizedVI(velocity={self.velocity!r}) needs {n} past positions "
                f"and steps; got {len(positions)} and {len(steps)}."
            )
        dtype = state_dtype(y0)
        history = History(
            tuple(positions[:n]),
            tuple(jnp.asarray(h, dtype) for h in steps[:n]),
            tree_max_abs(y0[1]).astype(dtype),
        )
        return VIState(history, initial_compensation(y0, self.compensated))

    def method_init(self, step: StepInputs) -> History:
        """The past, from backward steps of the variational integrator of the same
        discrete Lagrangian: consecutive triples then satisfy its DEL equations."""
        if step.term.force is not None or step.term.constraint is not None:
            raise ValueError(
                "LinearizedVI linearizes the unforced, unconstrained discrete "
                "Euler-Lagrange equations of Hirani (2000); for a LagrangianTerm "
                "with a force or a constraint use MidpointVI or TrapezoidalVI (or a "
                "Composition of them)."
            )
        if not is_euclidean(step.term.lagrangian.space):
            raise ValueError(
                "LinearizedVI linearizes the discrete Euler-Lagrange equations in "
                "the positions q_{k-1}, q_k, q_{k+1} of a vector space (Hirani "
                "(2000), eq. (4.63)), and this Lagrangian lives on a group, whose "
                "positions do not add. Use MidpointVI or TrapezoidalVI (or a "
                "Composition of them)."
            )
        # The start's velocity (the first Newton guess) and a check of the Lagrangian
        # there: the Legendre map must be invertible.
        start = check_start(step)
        return self._past(step, start.v0, start.result == dfx.RESULTS.successful)

    def _reanchored(self, step: StepInputs) -> History:
        """`method_init`'s past, built in the time-stepping loop (after a jump or a
        new step size) without its checks of the Lagrangian, which the solve's start
        made: an eigensolver's LAPACK call and host callbacks there would keep XLA
        from compiling the loop whole. A past that cannot be built is still
        poisoned (`_past`)."""
        v, result = inverse_legendre(
            step.term.lagrangian,
            step.t0,
            (step.q0, step.p0),
            step.args,
            None,
            "trust",
        )
        return self._past(step, v, result == dfx.RESULTS.successful)

    def _past(self, step: StepInputs, v_guess, ok: Bool[Array, ""]) -> History:
        """The past from backward steps from `step`'s start, the first Newton guess
        `v_guess`; poisoned unless `ok` (the start's velocity was found)."""
        h = step.h
        root_finder = Newton() if self.root_finder is None else self.root_finder

        def backward(carry, _):
            q, p, t, v_guess, ok = carry
            dq, dp, v_guess, result = discrete_hamiltonian_map(
                self.discrete_lagrangian,
                step.term.lagrangian,
                t,
                -h,
                q,
                p,
                step.args,
                v_guess,
                root_finder,
                self.root_find_max_steps,
            )
            q = tree_add(q, dq)
            ok = ok & (result == dfx.RESULTS.successful)
            return (q, tree_add(p, dp), t - h, v_guess, ok), q

        # A loop, not one root find per past step in the program: the past is built
        # at the start and again in the time-stepping loop's branch that re-anchors
        # it, which took a 16-bead wire's solve 25 s to compile with three copies.
        start = (step.q0, step.p0, step.t0, v_guess, ok)
        (*_, ok), qs = lax.scan(backward, start, length=self._n_past())
        # A history that could not be built (singular d2L/dv2, no root) is poisoned,
        # so the first step reports it instead of linearizing about garbage.
        qs = tuple(
            jtu.tree_map(lambda x: jnp.where(ok, x[i], jnp.nan), qs)
            for i in range(self._n_past())
        )
        return History(qs, tuple(h for _ in qs), tree_max_abs(step.p0))

    def method_step(
        self, step: StepInputs, state: History, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        lagrangian = step.term.lagrangian
        # A new step size re-anchors the past on the DEL manifold of the new step,
        # as a jump does: linearized about a triple of other step sizes, the method
        # leaves S (alternating steps diverged at every resolution). Below a relative
        # change of STEP_CHANGE the step is the same one, rounded (diffrax's fixed
        # steps differ by ulps of t).
        changed = jnp.abs(step.h - state.steps[0]) > STEP_CHANGE * jnp.abs(step.h)
        history = lax.cond(
            unvmap_any(made_jump | changed),
            lambda: self._reanchored(step),
            lambda: state,
        )
        qs, hs = history.positions, history.steps
        q0, h, tp0 = step.q0, step.h, step.t0
        # The triple (x, y, z) = (q_{k-2}, q_{k-1}, q_k) and its steps.
        x, y, z = qs[1], qs[0], q0
        h_xy, h_yz = hs[1], hs[0]
        ts = (tp0 - h_yz - h_xy, tp0 - h_yz, tp0)

        def momenta(a, b, c):
            return del_momenta(
                self.discrete_lagrangian, lagrangian, ts, (a, b, c), step.args
            )

        if self.velocity == "forward":
            u_x = _scale(1 / h_xy, tree_sub(y, x))
            u_y = _scale(1 / h_yz, tree_sub(z, y))
            span = h  # q_{k+1} = q_k + h u_k
            base = z
        else:
            h_wx = hs[2]
            u_x = _scale(1 / (h_wx + h_xy), tree_sub(y, qs[2]))
            u_y = _scale(1 / (h_xy + h_yz), tree_sub(z, x))
            span = h_yz + h  # q_{k+1} = q_{k-1} + (h_{k-1} + h) u_k
            base = y
        zeros = jtu.tree_map(jnp.zeros_like, z)
        (left, right), (tangent_left, tangent_right) = jax.jvp(
            momenta, (x, y, z), (u_x, u_y, zeros)
        )
        drift = tree_add(left, right)
        momentum = jnp.maximum(
            history.momentum, jnp.maximum(tree_max_abs(left), tree_max_abs(right))
        )
        rhs = jtu.tree_map(jnp.negative, tree_add(tangent_left, tangent_right))
        # The matrix dF/dq_{k+1}: only D1 Ld(q_k, q_{k+1}) depends on q_{k+1}, so
        # each product of the linear solve differentiates it alone.
        _, matvec = jax.linearize(lambda c: momenta(x, y, c)[1], z)
        # From the last velocity, which differs from the new one by O(h).
        # D2 D1 Ld is symmetric where dL/dv does not read q, and definite for steps
        # that resolve the motion: conjugate gradients.
        symmetric = not momentum_reads_position(lagrangian, tp0, z, u_y, step.args)
        tags = SYMMETRIC_NEGATIVE if symmetric else frozenset()
        u_z, linear_result = self._linear_solve(matvec, rhs, u_y, tags)
        dq = jtu.tree_map(lambda b, u, q: (b - q) + span * u, base, u_z, q0)
        # The discrete Legendre transform p_{k+1} = D2 Ld(q_k, q_{k+1}) through the
        # step's velocity: u_z itself for forward velocities, so nothing cancels.
        if self.velocity == "forward":
            v = u_z
        else:
            v = _scale(1 / h, tree_sub(step.end_position(dq), q0))
        _, p1 = average_grads(
            self.discrete_lagrangian, lagrangian, tp0, h, q0, v, step.args
        )
        result = start_result(
            step, all_finite(qs), promote_result(dfx.RESULTS, linear_result)
        )
        if self.max_del_residual is not None:
            # The triple this step linearized about has left the DEL manifold S: the
            # linearization no longer follows the variational integrator.
            # Relative to the largest momentum balanced so far: the same test in any
            # units.
            off = tree_max_abs(drift) > self.max_del_residual * momentum
            result = dfx.RESULTS.where(
                (result == dfx.RESULTS.successful) & off,
                dfx.RESULTS.nonlinear_divergence,
                result,
            )
        new = History((q0,) + qs[:-1], (h,) + hs[:-1], momentum)
        return MethodStep(dq, tree_sub(p1, step.p0), v, new, result)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


LinearizedVI.__init__.__doc__ = r"""**Arguments:**

- `velocity`: `"forward"` (Hirani (2000), eq. (4.63), $u_k = (q_{k+1} - q_k)/h$) or
    `"centered"` (§5.6, $u_k = (q_{k+1} - q_{k-1})/(2h)$).
- `discrete_lagrangian`: the discrete Lagrangian whose DEL equations are linearized:
    [`diffrax_vi.MidpointRule`][] (default) or [`diffrax_vi.TrapezoidalRule`][].
- `linear_solver`: the lineax solver for the step's linear system. Defaults to an
    unrolled LU elimination with partial pivoting (no LAPACK call: XLA on CPU
    compiles the time-stepping loop whole) up to 4 degrees of freedom, and beyond:
    conjugate gradients to near round-off where $\partial L/\partial v$ does not
    depend on $q$ (the matrix is then symmetric); else the elimination up to 16
    degrees of freedom and BiCGStab to near round-off beyond (conjugate gradients on
    the normal equations where it breaks down). A lineax solver given here is used
    as it is.
- `root_finder`, `root_find_max_steps`: for the backward variational steps that build
    the starting history (at `init` and after a jump); as for
    [`diffrax_vi.MidpointVI`][].
- `compensated`: compensated (Kahan) summation of the new positions (default). The
    momenta are recomputed each step from the positions, so their summation error
    stays at an ulp.
- `max_del_residual`: the step fails with `RESULTS.nonlinear_divergence` once the
    discrete Euler–Lagrange residual of the triple it linearizes about exceeds this
    fraction of the largest momentum the equations have balanced so far, $\max_k
    \max(|D_2 L_d|, |D_1 L_d|)$ (default 0.5; a test that does not depend on the
    units): the triples have left the manifold $S$
    and the method no longer follows the variational integrator (it has no Newton
    iteration whose failure would say so). Healthy runs stay below 0.3 even at 8
    steps per period from rest (where the momenta are small and the relative
    residual largest); the divergences of the centered variant's parasitic mode
    (Kepler, the outer solar system) and blow-ups of the forward variant exceed any
    such bound within a few steps.
    `None` turns the check off. See the [stability page](../stability.md).
"""
