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
vector-Jacobian product for each step. The repeated forward step of an implicit
method takes the root of the inverse step that has just undone it
(`root_of_inverse`), so each backward step solves one step's equations, not two.
"""

import functools as ft

import diffrax as dfx
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu

from ._adaptive import ReversibleController, ReversibleState
from ._force import depends_on_velocity
from ._lagrangian import Lagrangian
from ._misc import call_traced_once, traced
from ._private_api import (
    clip_to_end,
    is_subsaveat,
    nondiff_solver_controller_state,
    only_transpose_ys,
    save_y,
    WrapTerm,
)
from ._root_finders import optimistix_differentiates
from ._solver.base import (
    AbstractVariationalSolver,
    is_symmetric,
    Substep,
    unwrap_term,
)
from ._solver.unknowns import KnownRoot, step_newton
from ._space import tangent
from ._term import LagrangianTerm


REBUILD_FAILED = (
    "ReversibleAdjoint could not rebuild a state of the forward solve by an inverse "
    "step (the implicit step's root finder failed going backwards, or a state became "
    "NaN): the gradient would be wrong. Use diffrax.RecursiveCheckpointAdjoint for "
    "this solve, or smaller steps."
)


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


# What ReversibleAdjoint differentiates: y0, args and the arrays the terms hold.
NOT_DIFFERENTIATED = (
    "ReversibleAdjoint differentiates with respect to y0, args and the arrays the "
    "terms hold, not {name}, and this solve is differentiated with respect to "
    "{name}. Use diffrax.RecursiveCheckpointAdjoint() for that derivative, or make "
    "the quantity a parameter in args (a time scale: solve in rescaled time)."
)


def _not_differentiated(x, name):
    return eqxi.nondifferentiable(x, msg=NOT_DIFFERENTIATED.format(name=name))


def _hoisted(fn, *example):
    """`fn`, or, if it closes over an array being differentiated (a lambda that
    captures it), the same function with that array as one of its leaves
    (equinox's closure conversion), so that the adjoint differentiates with respect
    to it as it does to `args`."""
    if fn is None:
        return None
    converted = eqx.filter_closure_convert(fn, *example)
    if traced(converted):
        return converted
    return fn


def _hoist_closures(terms, t0, y, args):
    """The terms with the user's functions closure-converted where they close over
    a differentiated array: a `Lagrangian`'s function, the force and the
    constraint of a `LagrangianTerm`, or the vector fields of a pair of `ODETerm`s
    (dq/dt = f(t, p), dp/dt = g(t, q))."""
    q, p = y
    if isinstance(terms, WrapTerm):  # diffeqsolve's wrapper of every solve's terms
        return eqx.tree_at(
            lambda w: w.term, terms, _hoist_closures(terms.term, t0, y, args)
        )
    if isinstance(terms, tuple) and all(isinstance(t, WrapTerm) for t in terms):
        inner = _hoist_closures(tuple(t.term for t in terms), t0, y, args)
        return tuple(eqx.tree_at(lambda w: w.term, t, i) for t, i in zip(terms, inner))
    if isinstance(terms, LagrangianTerm):
        lagrangian = terms.lagrangian
        v = tangent(lagrangian.space, q)
        if isinstance(lagrangian, Lagrangian):
            fn = _hoisted(lagrangian.fn, t0, q, v, args)
            lagrangian = eqx.tree_at(lambda L: L.fn, lagrangian, fn)
        force = _hoisted(terms.force, t0, q, v, args)
        constraint = _hoisted(terms.constraint, t0, q, args)
        return eqx.tree_at(
            lambda term: (term.lagrangian, term.force, term.constraint),
            terms,
            (lagrangian, force, constraint),
            is_leaf=lambda x: x is None,
        )
    if isinstance(terms, tuple) and all(isinstance(t, dfx.ODETerm) for t in terms):
        f, g = terms
        return (
            dfx.ODETerm(_hoisted(f.vector_field, t0, p, args)),
            dfx.ODETerm(_hoisted(g.vector_field, t0, q, args)),
        )
    return terms


class ReversibleAdjoint(dfx.AbstractAdjoint):
    r"""Backpropagate through `diffrax.diffeqsolve` by stepping backwards: the
    states of the forward solve are rebuilt by inverse steps of the symmetric solver,
    so memory does not grow with the number of steps (one stored time per step,
    recorded by the forward solve; no stored states).

    Pass it as `adjoint=` with a symmetric solver of this package
    ([`diffrax_vi.StormerVerlet`][], [`diffrax_vi.MidpointVI`][],
    [`diffrax_vi.TrapezoidalVI`][], a symmetric [`diffrax_vi.VPRK`][], a
    [`diffrax_vi.Composition`][]) at fixed steps (`diffrax.ConstantStepSize`,
    `diffrax.StepTo`) or reversible adaptive ones
    ([`diffrax_vi.ReversibleController`][]), saving at `t0`, `t1` and `ts`.
    Gradients flow to `y0`, `args`, every array of the terms (the Lagrangian's
    parameters, a force's, a constraint's) and of a `ReversibleController` (its
    monitor's parameters, its initial `density`); the backward pass differentiates
    each step with respect to those a gradient asks for only (a gradient with
    respect to `y0` carries no cotangent of the Lagrangian's parameters through
    the steps). Under `ReversibleController` the step sizes depend on the state,
    and the gradient includes that dependence, as diffrax's own adjoints do; the
    step density is rebuilt backwards with the states.

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
        if not is_symmetric(solver):
            raise ValueError(
                "ReversibleAdjoint needs a symmetric solver, whose step with -h "
                f"inverts its step with h; {type(solver).__name__} is not one. Use "
                "StormerVerlet, MidpointVI, TrapezoidalVI, GaussVPRK, LobattoVPRK "
                "or a Composition of them; for other solvers (LinearizedVI, "
                "Runge-Kutta), diffrax.RecursiveCheckpointAdjoint."
            )
        if not isinstance(
            stepsize_controller,
            (dfx.ConstantStepSize, dfx.StepTo, ReversibleController),
        ):
            raise ValueError(
                "ReversibleAdjoint steps back along the forward time grid, which "
                "it rebuilds for diffrax.ConstantStepSize, diffrax.StepTo and "
                "ReversibleController; got "
                f"{type(stepsize_controller).__name__}. An error-controlled "
                "(PIDController) grid depends on rejected steps and cannot be "
                "rebuilt: use fixed steps, ReversibleController, or "
                "diffrax.RecursiveCheckpointAdjoint."
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
            or subs.steps
            or saveat.dense
            or subs.fn is not save_y
        ):
            raise ValueError(
                "ReversibleAdjoint supports SaveAt with t0, t1 and ts. For "
                "SaveAt(steps=True), dense=True, fn=... or subs=..., use "
                "diffrax.RecursiveCheckpointAdjoint."
            )
        _check_forces(terms, t0, init_state.y, args)
        # The time grid is not differentiated: a derivative with respect to it
        # would otherwise end in equinox's "Unexpected tangent".
        t0 = _not_differentiated(t0, "t0")
        t1 = _not_differentiated(t1, "t1")
        dt0 = _not_differentiated(dt0, "dt0")
        saveat = _not_differentiated(saveat, "SaveAt(ts=...)")
        y = init_state.y
        init_state = eqx.tree_at(lambda s: s.y, init_state, object())
        init_state = nondiff_solver_controller_state(
            self, init_state, passed_solver_state, passed_controller_state
        )
        # The first step's end depends on y0 under ReversibleController; the
        # backward pass recomputes it from y0 and differentiates it there.
        init_state = eqx.tree_at(
            lambda s: s.tnext, init_state, replace_fn=lax.stop_gradient
        )
        final_state, aux_stats, _ = _loop_reversible(
            (y, args, _hoist_closures(terms, t0, y, args), stepsize_controller),
            self=self,
            solver=solver,
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


class _Recorder(dfx.AbstractStepSizeController):
    """The steps of `controller`, unchanged, with the end of each written into a
    buffer of `max_steps + 1` times: the forward solve's time grid, along which the
    backward pass steps back."""

    controller: dfx.AbstractStepSizeController

    def wrap(self, direction):
        return self

    def init(self, *args, **kwargs):
        raise NotImplementedError("diffeqsolve initialises the recorded controller")

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, order, state):
        inner, times, count = state
        keep, tprev, tnext, jump, inner, result = self.controller.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, order, inner
        )
        times = times.at[count + 1].set(t1)
        return keep, tprev, tnext, jump, (inner, times, count + 1), result


_is_none = lambda x: x is None


# One object, so that the nested jit below sees equal static arguments each time.
_LAX_WHILE = ft.partial(eqxi.while_loop, kind="lax")


def _forward_loop(adjoint, **kwargs):
    """`adjoint._loop(**kwargs)` traced once per program. JAX traces a custom VJP's
    function, and then its forward rule, which runs the function again, through a
    nested jit whose cache is keyed on the abstract mesh in use: unset in a user's
    trace, set (empty) where JAX traces a rule from a traced program. Pinned here to
    the mesh in use, both traces of the loop share one entry, and so do the steps
    traced in it and in the backward pass (`benchmarks/first_call.py`)."""
    with jax.sharding.use_abstract_mesh(jax.sharding.get_abstract_mesh()):
        return call_traced_once(adjoint._loop, **kwargs)


@eqx.filter_custom_vjp
def _loop_reversible(vjp_arg, *, self, throw, init_state, max_steps, **kwargs):
    del throw
    y, args, terms, controller = vjp_arg
    times = jnp.zeros(max_steps + 1, jnp.result_type(init_state.tprev))
    recording = (
        init_state.controller_state,
        times.at[0].set(init_state.tprev),
        jnp.array(0),
    )
    init_state = eqx.tree_at(
        lambda s: (s.y, s.controller_state),
        init_state,
        (y, recording),
        is_leaf=_is_none,
    )
    final_state, aux_stats = _forward_loop(
        self,
        args=args,
        terms=terms,
        stepsize_controller=_Recorder(controller),
        init_state=init_state,
        max_steps=max_steps,
        inner_while_loop=_LAX_WHILE,
        outer_while_loop=_LAX_WHILE,
        **kwargs,
    )
    inner, times, _ = final_state.controller_state
    final_state = eqx.tree_at(
        lambda s: s.controller_state, final_state, inner, is_leaf=_is_none
    )
    return final_state, aux_stats, times


@_loop_reversible.def_fwd
def _loop_reversible_fwd(perturbed, vjp_arg, **kwargs):
    del perturbed
    final_state, aux_stats, times = _loop_reversible(vjp_arg, **kwargs)
    controller_state = final_state.controller_state
    density = (
        controller_state.density
        if isinstance(controller_state, ReversibleState)
        else jnp.zeros(())
    )
    residuals = (
        final_state.y,
        density,
        final_state.save_state.ys,
        final_state.solver_state,
        final_state.num_steps,
        times,
    )
    return (final_state, aux_stats, times), residuals


def _clip_floor(t1):
    """`t1` less 100 ulps: where diffrax's loop rounds a step's end to `t1`."""
    floor = t1
    for _ in range(100):
        floor = eqxi.prevbefore(floor)
    return floor


def _materialise(x, cotangent):
    if cotangent is None and eqx.is_inexact_array(x):
        return jnp.zeros_like(x)
    return cotangent


@_loop_reversible.def_bwd
def _loop_reversible_bwd(
    residuals,
    grad_out,
    perturbed,
    vjp_arg,
    *,
    self,
    solver,
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
    del event, t0, dt0, progress_meter
    y_final, w_final, ys, solver_state, num_steps, times = residuals
    grad_ys = jtu.tree_map(_materialise, ys, grad_out[0].save_state.ys)
    y0, args, terms, controller = vjp_arg
    # Only what is differentiated (`perturbed`) gets a cotangent: a gradient with
    # respect to the initial state does not differentiate each step through the
    # Lagrangian's parameters too.
    _, p_args, p_terms, p_ctrl = perturbed
    diff_args, nondiff_args = eqx.partition(args, p_args)
    diff_terms, nondiff_terms = eqx.partition(terms, p_terms)
    diff_ctrl, nondiff_ctrl = eqx.partition(controller, p_ctrl)
    reversible = isinstance(controller, ReversibleController)
    if reversible:
        dt0 = init_state.controller_state.dt0
    floor = _clip_floor(t1)
    subs = saveat.subs
    ts = subs.ts

    # Every step is taken as after a jump: what a solver caches from its last step
    # (the force at its end, the first kick of the next step) is recomputed from
    # the state the step starts from, through which it is then differentiated. Its
    # dense output only where SaveAt(ts=...) interpolates it: JAX would otherwise
    # differentiate the vector field at both ends of every step before XLA removed
    # it (the first calls it cost are in the CHANGELOG).
    def step(t_start, t_end, y, args, terms, state, solver=solver, dense=False):
        y_next, _, dense_info, state, result = solver.fractional_step(
            terms,
            t_start,
            t_end,
            y,
            args,
            state,
            True,
            Substep(1.0, t_start, t_end),
            dense=dense,
        )
        return y_next, dense_info, state, result

    # The inverse step's first state, and whether the forward steps take the roots
    # the inverse steps found (`_takes_inverse_roots`).
    last = jnp.maximum(num_steps - 1, 0)
    # Its start is the forward solve's end, which the forward steps reached from a
    # checked start: `resume` does not check it again.
    back_state = solver.resume(
        terms, times[num_steps], times[last], y_final, args, solver_state
    )
    takes_roots = _takes_inverse_roots(solver, terms, back_state, self.checkpoint_every)

    # Step k of the forward solve (from times[k - 1]) as a function of what it
    # depends on. At fixed steps that is the state `y`, the step's ends being fixed
    # times. Under ReversibleController it is `(t, y, w)`: the step's size follows
    # the state and the step density `w`, and the step's end and the next density
    # are outputs of the step. The interpolant between the step's ends is an output
    # too when SaveAt(ts=...) saves from it.
    def advance(k, ext, d_args, d_terms, d_ctrl, state, solver=solver):
        args = eqx.combine(d_args, nondiff_args)
        terms = eqx.combine(d_terms, nondiff_terms)
        if reversible:
            t, y, w = ext
            ctrl = eqx.combine(d_ctrl, nondiff_ctrl)
            node = ctrl.node(terms, solver.func, t, y, args, w, dt0)
            t_next, _ = ctrl.next_time(node, t)
            t_next = clip_to_end(t, t_next, t1, floor, True)
        else:
            t, y, t_next = times[k - 1], ext, times[k]
        y_next, dense, state, result = step(
            t, t_next, y, args, terms, state, solver, dense=ts is not None
        )
        if reversible:
            node = ctrl.adapt_step_size(t, t_next, y, y_next, args, None, 0, node)
            node = node[4]
            result = dfx.RESULTS.where(node.ok, result, dfx.RESULTS.nonfinite)
            ext = (t_next, y_next, node.density)
        else:
            ext = y_next
        interp = None
        if ts is not None:
            interp = solver.interpolation_cls(t0=t, t1=t_next, **dense)
        return (ext, interp), (state, result)

    # Step k undone: the state at times[k - 1] rebuilt from the one at times[k].
    def retreat(k, ext, state):
        t, t_next = times[k - 1], times[k]
        y_next = ext[1] if reversible else ext
        y, _, state, result = step(t_next, t, y_next, args, terms, state)
        if not reversible:
            return y, state, result
        node = controller.node(terms, solver.func, t_next, y_next, args, ext[2], dt0)
        w, ok = controller.density_before(node, t, y, args)
        ok = ok & node.ok & (w > 0)
        return (t, y, w), state, dfx.RESULTS.where(ok, result, dfx.RESULTS.nonfinite)

    # The cotangent of step k's interpolant from the states it saved (the
    # SaveAt(ts=...) times in (times[k - 1], times[k]], and t0 too for the first).
    offset = 1 if subs.t0 else 0

    def saved(k, interp):
        def add(j, acc):
            _, vjp = jax.vjp(lambda i: i.evaluate(ts[j]), interp)
            g = jtu.tree_map(lambda gy: gy[offset + j], grad_ys)
            return jtu.tree_map(jnp.add, acc, vjp(g)[0])

        after = jnp.searchsorted(ts, times[k - 1], side="right")
        first = jnp.where(k == 1, 0, after)
        last = jnp.searchsorted(ts, times[k], side="right")
        return lax.fori_loop(first, last, add, jtu.tree_map(jnp.zeros_like, interp))

    # Two sequences of solver states, each guessing its root finder's unknowns from
    # its last step: the inverse steps', and the repeated forward steps' (taken in
    # reverse order). The unknowns of a step and of its inverse need not agree (a
    # multiplier changes sign with h), so neither can guess for the other.
    def body(carry):
        k, ext, a_ext, a_args, a_terms, a_ctrl, back_state, fwd_state, ok = carry
        ext_prev, back_state, back_result = retreat(k, ext, back_state)
        forward = solver
        if takes_roots:
            root = KnownRoot(solver.root_of_inverse(terms, back_state))
            forward = eqx.tree_at(
                lambda s: s.root_finder, solver, root, is_leaf=_is_none
            )
        if anchors is not None:
            i, stored = divmod(k - 1, every)
            ext_prev = jtu.tree_map(
                lambda a, x: jnp.where(stored == 0, a[i], x), anchors, ext_prev
            )
        (_, interp), vjp, (fwd_state, result) = jax.vjp(
            lambda e, a, tr, c: advance(k, e, a, tr, c, fwd_state, forward),
            ext_prev,
            diff_args,
            diff_terms,
            diff_ctrl,
            has_aux=True,
        )
        a_interp = None if ts is None else saved(k, interp)
        a_ext, d_args, d_terms, d_ctrl = vjp((a_ext, a_interp))
        ok = ok & (back_result == dfx.RESULTS.successful)
        ok = ok & (result == dfx.RESULTS.successful)
        add = lambda a, b: jtu.tree_map(jnp.add, a, b)
        a_args, a_terms, a_ctrl = add(
            (a_args, a_terms, a_ctrl), (d_args, d_terms, d_ctrl)
        )
        return (
            k - 1,
            ext_prev,
            a_ext,
            a_args,
            a_terms,
            a_ctrl,
            back_state,
            fwd_state,
            ok,
        )

    if subs.t1:
        a_y = jtu.tree_map(lambda g: g[-1], grad_ys)
    else:
        a_y = jtu.tree_map(jnp.zeros_like, y_final)
    if reversible:
        zero = jnp.zeros((), w_final.dtype)
        ext, a_ext = (times[num_steps], y_final, w_final), (zero, a_y, zero)
        ext0 = (times[0], y0, init_state.controller_state.density)
    else:
        ext, a_ext, ext0 = y_final, a_y, y0
    every = self.checkpoint_every
    anchors = None
    if every is not None:
        anchors = _anchors(
            lambda k, e, s: advance(k, e, diff_args, diff_terms, diff_ctrl, s),
            ext0,
            init_state.solver_state,
            num_steps,
            max_steps,
            every,
        )
    zeros = ft.partial(jtu.tree_map, jnp.zeros_like)
    carry = (
        num_steps,
        ext,
        a_ext,
        zeros(diff_args),
        zeros(diff_terms),
        zeros(diff_ctrl),
        back_state,
        solver_state,
        jnp.array(True),
    )
    carry = lax.while_loop(lambda carry: carry[0] > 0, body, carry)
    _, _, a_ext, a_args, a_terms, a_ctrl, _, _, ok = carry
    a_y = a_ext[1] if reversible else a_ext
    if subs.t0:
        a_y = jtu.tree_map(lambda a, g: a + g[0], a_y, grad_ys)
    if reversible and p_ctrl.density is True:
        a_ctrl = eqx.tree_at(lambda c: c.density, a_ctrl, a_ctrl.density + a_ext[2])
    grads = (a_y, a_args, a_terms, a_ctrl)
    if throw:
        grads = eqx.error_if(grads, ~ok, REBUILD_FAILED)
    else:
        grads = jtu.tree_map(lambda x: jnp.where(ok, x, jnp.nan), grads)
    return grads


def _takes_inverse_roots(solver, terms, back_state, checkpoint_every) -> bool:
    """Whether the forward steps of the backward pass take the roots of the inverse
    steps rather than solving their equations again.

    Each forward step that the backward pass differentiates is the one that the
    inverse step has just undone, and a symmetric implicit method knows that step's
    root from the inverse step's (`root_of_inverse`): taken as it is
    (`KnownRoot`) and differentiated by the implicit function theorem there, no
    step's equations are solved twice, and a gradient's program holds one root
    solve less (`benchmarks/reversible_roots.py`). Not with `checkpoint_every`: a
    step from an anchor starts from the forward solve's own state, not from the
    inverse step's, whose root it would not be; and not where optimistix
    differentiates the step's roots (`optimistix_differentiates` of its Newton
    method, `step_newton`: a constrained step beyond `CONSTRAINED_DENSE_MAX`
    unknowns, which LAPACK's LU solves). The root is differentiated as the step's
    own would be (`known_root`): by a dense elimination up to `NEWTON_DENSE_MAX`
    unknowns (a constrained step's up to `CONSTRAINED_DENSE_MAX`: the rigid double
    pendulum's 18), matrix-free beyond (the outer solar system's 18, the bead
    wire's)."""
    if checkpoint_every is not None or not isinstance(
        solver, AbstractVariationalSolver
    ):
        return False
    root = solver.root_of_inverse(terms, back_state)
    if root is None:
        return False
    term, _ = unwrap_term(terms, type(solver).__name__)
    return not optimistix_differentiates(step_newton(term.constraint is not None, root))


def _anchors(advance, ext0, solver_state, n, max_steps, every):
    """The forward solve repeated, keeping its states at steps 0, k, 2k, ..."""
    anchors = jtu.tree_map(
        lambda x: jnp.zeros((max_steps // every + 1,) + jnp.shape(x), x.dtype), ext0
    )

    def body(i, carry):
        ext, state, anchors = carry
        j, offset = divmod(i, every)
        anchors = jtu.tree_map(
            lambda a, x: a.at[j].set(jnp.where(offset == 0, x, a[j])), anchors, ext
        )
        (ext, _), (state, _) = advance(i + 1, ext, state)
        return ext, state, anchors

    return lax.fori_loop(0, n, body, (ext0, solver_state, anchors))[2]
