r"""Gradients through long solves at constant memory: the reversible adjoint of the
symmetric solvers.

A symmetric one-step method $\Phi_h$ is its own inverse with the sign of the step
reversed, $\Phi_{-h} \circ \Phi_h = \mathrm{id}$. The backward pass therefore needs no
stored states: from $y_{k+1}$ it rebuilds $y_k = \Phi_{-h_k}(y_{k+1})$ and
differentiates the forward step there, $a_k = (\partial\Phi_{h_k}/\partial y)^\top
a_{k+1}$, accumulating the parameters' cotangents on the way (the discrete adjoint of
the forward solve: Matsubara, Miyatake & Yaguchi (2021), *Symplectic adjoint
method*; McCallum & Foster (2024), *Efficient, accurate and stable gradients for
neural ODEs*, for the algebraically reversible case). Memory is that of a few states
and one time per step; the work is an inverse step, a repeated forward step and its
vector-Jacobian product for each step.
"""

import functools as ft

import diffrax as dfx
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu

from ._adaptive import ReversibleController
from ._force import depends_on_velocity
from ._private_api import (
    clip_to_end,
    is_subsaveat,
    nondiff_solver_controller_state,
    only_transpose_ys,
    save_y,
    WrapTerm,
)
from ._solver.base import AbstractSymmetricSolver
from ._solver.composition import Composition
from ._solver.vprk import AbstractVPRK
from ._term import LagrangianTerm


REBUILD_FAILED = (
    "ReversibleAdjoint could not rebuild a state of the forward solve by an inverse "
    "step (the implicit step's root finder failed going backwards, or a state became "
    "NaN): the gradient would be wrong. Use diffrax.RecursiveCheckpointAdjoint for "
    "this solve, or smaller steps."
)


def _symmetric(solver: dfx.AbstractSolver) -> bool:
    """Whether `solver` is a symmetric method of this package (a VPRK whose tableau
    is symmetric; a composition of such a base)."""
    if isinstance(solver, Composition):
        return _symmetric(solver.base)
    if isinstance(solver, AbstractVPRK):
        return bool(solver.tableau.symmetric)
    return isinstance(solver, AbstractSymmetricSolver)


def _check_forces(terms, t0, y0, args) -> None:
    """A `ValueError` for a force that reads the velocity: friction and other
    dissipative forces make the flow irreversible, so no inverse step exists."""
    for term in jtu.tree_leaves(
        terms, is_leaf=lambda x: isinstance(x, (LagrangianTerm, WrapTerm))
    ):
        while isinstance(term, WrapTerm):
            term = term.term
        if not isinstance(term, LagrangianTerm) or term.force is None:
            continue
        q = y0[0]
        zeros = jtu.tree_map(jnp.zeros_like, q)
        if depends_on_velocity(term.force, t0, q, zeros, args):
            raise ValueError(
                "ReversibleAdjoint rebuilds each state from the next by a step "
                "backwards in time, and this term's force reads the velocity "
                "(friction, damping): such a flow is not time-reversible, and the "
                "backward steps would amplify round-off without bound. Use "
                "diffrax.RecursiveCheckpointAdjoint."
            )


class ReversibleAdjoint(dfx.AbstractAdjoint):
    r"""Backpropagate through `diffrax.diffeqsolve` by stepping backwards: the
    states of the forward solve are rebuilt by inverse steps of the symmetric solver,
    so memory does not grow with the number of steps (one stored time per step, no
    stored states).

    Pass it as `adjoint=` with a symmetric solver of this package
    ([`diffrax_vi.StormerVerlet`][], [`diffrax_vi.MidpointVI`][],
    [`diffrax_vi.TrapezoidalVI`][], a symmetric [`diffrax_vi.VPRK`][], a
    [`diffrax_vi.Composition`][]) at fixed steps (`diffrax.ConstantStepSize`,
    `diffrax.StepTo`) and `SaveAt(t1=True)` (optionally with `t0=True`). Gradients
    flow to `y0`, `args` and every array of the terms (the Lagrangian's
    parameters, a force's, a constraint's).

    The forward solve is the plain solve. The gradient is the derivative of the
    discrete solve (as `diffrax.RecursiveCheckpointAdjoint` computes it), evaluated at
    rebuilt states: these carry the round-off and the root finder's tolerance of each
    inverse step, amplified as the problem amplifies perturbations. For regular
    motion that is near round-off (see [Gradients through long
    solves](../gradients.md) for measured errors); for chaotic motion over many
    Lyapunov times it is not, and `RecursiveCheckpointAdjoint` is the choice.

    **Arguments:**

    - `checkpoint_every`: `None` (the default) to rebuild every state by inverse
        steps; or `k`, to re-anchor the rebuilt states on the forward solve's own
        every `k` steps. The backward pass then first repeats the forward solve,
        keeping every `k`-th state (memory: `max_steps / k` states), so the inverse
        steps' errors grow over at most `k` steps: for chaotic problems.

    **Failures:** an inverse step that fails (its root finder, or a NaN) raises
    an `EquinoxRuntimeError` in the backward pass, as the gradient would be wrong.
    Unsupported settings raise a `ValueError` when traced, naming the alternative.
    """

    checkpoint_every: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        every = self.checkpoint_every
        if every is not None and (
            isinstance(every, bool) or not isinstance(every, int) or every < 1
        ):
            raise ValueError(
                "ReversibleAdjoint(checkpoint_every=...) must be None or an integer "
                f"of at least 1; got {every!r}."
            )

    def loop(
        self,
        *,
        args,
        terms,
        solver,
        stepsize_controller,
        event,
        saveat,
        t0,
        t1,
        dt0,
        max_steps,
        throw,
        init_state,
        passed_solver_state,
        passed_controller_state,
        progress_meter,
    ):
        if not _symmetric(solver):
            raise ValueError(
                "ReversibleAdjoint needs a symmetric solver, whose step with -h "
                f"inverts its step with h; {type(solver).__name__} is not one. Use "
                "StormerVerlet, MidpointVI, TrapezoidalVI, GaussVPRK, LobattoVPRK "
                "or a Composition of them; for other solvers (LinearizedVI, "
                "Runge-Kutta), diffrax.RecursiveCheckpointAdjoint."
            )
        if isinstance(stepsize_controller, ReversibleController):
            raise ValueError(
                "ReversibleAdjoint does not support ReversibleController yet: its "
                "step sizes depend on the state through the monitor, whose "
                "derivative the backward pass does not take. Use fixed steps "
                "(ConstantStepSize, StepTo), or diffrax.RecursiveCheckpointAdjoint."
            )
        if not isinstance(stepsize_controller, (dfx.ConstantStepSize, dfx.StepTo)):
            raise ValueError(
                "ReversibleAdjoint steps back along the forward time grid, which "
                "it rebuilds for diffrax.ConstantStepSize and diffrax.StepTo; got "
                f"{type(stepsize_controller).__name__}. An error-controlled "
                "(PIDController) grid depends on rejected steps and cannot be "
                "rebuilt: use fixed steps, or diffrax.RecursiveCheckpointAdjoint."
            )
        if event is not None:
            raise ValueError(
                "ReversibleAdjoint does not support events (the time of the event "
                "would need its own adjoint). Use diffrax.RecursiveCheckpointAdjoint."
            )
        if max_steps is None:
            raise ValueError(
                "ReversibleAdjoint needs a finite max_steps (it keeps one time per "
                "step for the backward pass)."
            )
        subs = saveat.subs
        if (
            jtu.tree_structure(subs, is_leaf=is_subsaveat) != jtu.tree_structure(0)
            or not subs.t1
            or subs.ts is not None
            or subs.steps
            or saveat.dense
            or subs.fn is not save_y
        ):
            raise ValueError(
                "ReversibleAdjoint supports SaveAt(t1=True), with or without "
                "t0=True (save more states by solving from one to the next). For "
                "SaveAt(ts=...), steps=True, dense=True, fn=... or subs=..., use "
                "diffrax.RecursiveCheckpointAdjoint."
            )
        _check_forces(terms, t0, init_state.y, args)
        y = init_state.y
        init_state = eqx.tree_at(lambda s: s.y, init_state, object())
        init_state = nondiff_solver_controller_state(
            self, init_state, passed_solver_state, passed_controller_state
        )
        final_state, aux_stats = _loop_reversible(
            (y, args, terms),
            self=self,
            solver=solver,
            stepsize_controller=stepsize_controller,
            event=event,
            saveat=saveat,
            t0=t0,
            t1=t1,
            dt0=dt0,
            max_steps=max_steps,
            throw=throw,
            init_state=init_state,
            progress_meter=progress_meter,
        )
        return only_transpose_ys(final_state), aux_stats


@eqx.filter_custom_vjp
def _loop_reversible(y__args__terms, *, self, throw, init_state, **kwargs):
    del throw
    y, args, terms = y__args__terms
    init_state = eqx.tree_at(lambda s: s.y, init_state, y)
    return self._loop(
        args=args,
        terms=terms,
        init_state=init_state,
        inner_while_loop=ft.partial(eqxi.while_loop, kind="lax"),
        outer_while_loop=ft.partial(eqxi.while_loop, kind="lax"),
        **kwargs,
    )


@_loop_reversible.def_fwd
def _loop_reversible_fwd(perturbed, y__args__terms, **kwargs):
    del perturbed
    final_state, aux_stats = _loop_reversible(y__args__terms, **kwargs)
    residuals = (
        final_state.y,
        final_state.save_state.ys,
        final_state.solver_state,
        final_state.num_steps,
    )
    return (final_state, aux_stats), residuals


def _time_grid(controller, init_state, t1, num_steps, max_steps, args):
    """The forward solve's step times `t_0 ... t_N` (in a buffer of `max_steps + 1`),
    made by the same controller calls and clipping as diffrax's loop."""
    t1_clip_floor = t1
    for _ in range(100):
        t1_clip_floor = eqxi.prevbefore(t1_clip_floor)
    times = jnp.zeros(max_steps + 1, jnp.result_type(init_state.tprev))
    times = times.at[0].set(init_state.tprev)

    def body(i, carry):
        tprev, tnext, controller_state, times = carry
        times = times.at[i + 1].set(tnext)
        keep, tprev, tnext, _, controller_state, _ = controller.adapt_step_size(
            tprev, tnext, None, None, args, None, None, controller_state
        )
        tprev = jnp.minimum(tprev, t1)
        tnext = clip_to_end(tprev, tnext, t1, t1_clip_floor, keep)
        return tprev, tnext, controller_state, times

    carry = (init_state.tprev, init_state.tnext, init_state.controller_state, times)
    return lax.fori_loop(0, num_steps, body, carry)[3]


def _anchors(step, times, y0, diff_args, diff_terms, init_state, n, max_steps, every):
    """The forward solve repeated, keeping the states at steps 0, k, 2k, ..."""
    anchors = jtu.tree_map(
        lambda x: jnp.zeros((max_steps // every + 1,) + x.shape, x.dtype), y0
    )

    def body(i, carry):
        y, state, anchors = carry
        j, offset = divmod(i, every)
        anchors = jtu.tree_map(
            lambda a, x: a.at[j].set(jnp.where(offset == 0, x, a[j])), anchors, y
        )
        y, (state, _) = step(times[i], times[i + 1], y, diff_args, diff_terms, state)
        return y, state, anchors

    carry = (y0, init_state.solver_state, anchors)
    return lax.fori_loop(0, n, body, carry)[2]


def _materialise(x, cotangent):
    if cotangent is None and eqx.is_inexact_array(x):
        return jnp.zeros_like(x)
    return cotangent


@_loop_reversible.def_bwd
def _loop_reversible_bwd(
    residuals,
    grad_final_state__aux_stats,
    perturbed,
    y__args__terms,
    *,
    self,
    solver,
    stepsize_controller,
    event,
    saveat,
    t0,
    t1,
    dt0,
    max_steps,
    throw,
    init_state,
    progress_meter,
):
    del perturbed, event, t0, dt0, progress_meter
    y_final, ys, solver_state, num_steps = residuals
    grad_final_state, _ = grad_final_state__aux_stats
    grad_ys = jtu.tree_map(_materialise, ys, grad_final_state.save_state.ys)
    y0, args, terms = y__args__terms
    diff_args, nondiff_args = eqx.partition(args, eqx.is_inexact_array)
    diff_terms, nondiff_terms = eqx.partition(terms, eqx.is_inexact_array)
    times = _time_grid(stepsize_controller, init_state, t1, num_steps, max_steps, args)

    # Every step is taken as after a jump: what a solver caches from its last step
    # (the force at its end, the first kick of the next step) is recomputed from
    # the state the step starts from, through which it is then differentiated.
    def step(t_start, t_end, y, d_args, d_terms, state):
        step_args = eqx.combine(d_args, nondiff_args)
        step_terms = eqx.combine(d_terms, nondiff_terms)
        y_next, _, _, state, result = solver.step(
            step_terms, t_start, t_end, y, step_args, state, True
        )
        return y_next, (state, result)

    # Two sequences of solver states, each guessing its root finder's unknowns from
    # its last step: the inverse steps', and the repeated forward steps' (taken in
    # reverse order). The unknowns of a step and of its inverse need not agree (a
    # multiplier changes sign with h), so neither can guess for the other.
    def body(carry):
        k, y, a_y, a_args, a_terms, back_state, fwd_state, ok = carry
        t_start, t_end = times[k - 1], times[k]
        y_prev, (back_state, back_result) = step(
            t_end, t_start, y, diff_args, diff_terms, back_state
        )
        if anchors is not None:
            i, stored = divmod(k - 1, every)
            y_prev = jtu.tree_map(
                lambda a, x: jnp.where(stored == 0, a[i], x), anchors, y_prev
            )
        _, vjp, (fwd_state, result) = jax.vjp(
            lambda y_, a_, t_: step(t_start, t_end, y_, a_, t_, fwd_state),
            y_prev,
            diff_args,
            diff_terms,
            has_aux=True,
        )
        d_y, d_args, d_terms = vjp(a_y)
        ok = ok & (back_result == dfx.RESULTS.successful)
        ok = ok & (result == dfx.RESULTS.successful)
        add = lambda a, b: jtu.tree_map(jnp.add, a, b)
        a_args, a_terms = add(a_args, d_args), add(a_terms, d_terms)
        return k - 1, y_prev, d_y, a_args, a_terms, back_state, fwd_state, ok

    every = self.checkpoint_every
    anchors = None
    if every is not None:
        anchors = _anchors(
            step,
            times,
            y0,
            diff_args,
            diff_terms,
            init_state,
            num_steps,
            max_steps,
            every,
        )
    last = jnp.maximum(num_steps - 1, 0)
    back_state = solver.init(terms, times[num_steps], times[last], y_final, args)
    carry = (
        num_steps,
        y_final,
        jtu.tree_map(lambda g: g[-1], grad_ys),
        jtu.tree_map(jnp.zeros_like, diff_args),
        jtu.tree_map(jnp.zeros_like, diff_terms),
        back_state,
        solver_state,
        jnp.array(True),
    )
    _, _, a_y, a_args, a_terms, _, _, ok = lax.while_loop(
        lambda carry: carry[0] > 0, body, carry
    )
    if saveat.subs.t0:
        a_y = jtu.tree_map(lambda a, g: a + g[0], a_y, grad_ys)
    if throw:
        a_y, a_args, a_terms = eqx.error_if((a_y, a_args, a_terms), ~ok, REBUILD_FAILED)
    else:
        nan = lambda x: jnp.where(ok, x, jnp.nan)
        a_y, a_args, a_terms = jtu.tree_map(nan, (a_y, a_args, a_terms))
    return a_y, a_args, a_terms
