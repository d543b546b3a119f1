r"""Reversible adaptive time steps (Hairer & Söderlind 2005; Hairer, Lubich & Wanner,
*Geometric Numerical Integration*, VIII.3.2).

A step-size monitor `s(t, y)` says how long a step the motion wants at `y` (up to a
constant). The controller carries a step density `z`, about `s(y0) / s(y)`, and
integrates its law of motion $\dot z = z\,G(y)$ with
$G = -\tfrac{d}{dt}\log s(y(t))$ in the fictive time that counts steps:

$$z_{n+1/2} = z_{n-1/2} + h_0\,G(y_n), \qquad y_{n+1} = \Phi_{h_0/z_{n+1/2}}(y_n),$$

with $h_0$ the user's `dt0`. The node value $w_n = z_{n-1/2} + \tfrac{h_0}{2}G(y_n)$
is what the controller keeps between steps; it makes the extended map
$(y_n, w_n) \mapsto (y_{n+1}, w_{n+1})$ symmetric whenever the one-step method $\Phi$
is: integrating back from $(y_N, w_N)$ retraces the forward steps. $G$ is explicit
(one directional derivative of $\log s$ along the vector field), so no step is solved
for or rejected, and for a constant monitor every step is exactly `dt0`.
"""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, ArrayLike, Bool, Float, PyTree

from ._custom_types import Args, RealScalarLike
from ._lagrangian import AbstractLagrangian, AbstractSeparableLagrangian
from ._private_api import WrapTerm
from ._solver.base import is_symmetric


def _unwrap(terms: PyTree) -> PyTree:
    """The user's terms inside diffrax's `WrapTerm`s (time in physical units)."""
    return jtu.tree_map(
        lambda t: t.term if isinstance(t, WrapTerm) else t,
        terms,
        is_leaf=lambda t: isinstance(t, dfx.AbstractTerm),
    )


def _optional_array(x):
    return None if x is None else jnp.asarray(x)


class _Field(eqx.Module):
    """A closure-converted function carried through diffrax's loop: its arrays as
    leaves, the rest (the traced program) as static data compared by identity."""

    arrays: PyTree
    rest: PyTree = eqx.field(static=True)

    def __call__(self, *args):
        return eqx.combine(self.arrays, self.rest)(*args)


class ReversibleState(eqx.Module):
    """The state of a [`diffrax_vi.ReversibleController`][] between steps.

    **Fields:**

    - `density`: the step density $w_n$ at the last node (the step is about
        `dt0 / density`).
    - `rate`: $G(y_n)$ there, in diffrax's time.
    - `dt0`: the step at density 1 (the user's `dt0`).
    - `ok`: whether every monitor value and density so far was positive and finite.
    - `field`: the solve's physical vector field `f(t, y, args)`, as a pytree
        (closure-converted: a controller sees the terms only in `init`).
    """

    density: Float[Array, ""]
    rate: Float[Array, ""]
    dt0: Float[Array, ""]
    ok: Bool[Array, ""]
    field: Callable


def _check_symmetric(solver) -> None:
    """A `ValueError` unless `solver` (the solver whose `func` diffrax handed the
    controller, through wrappers that take its steps unchanged) is symmetric."""
    while getattr(solver, "steps_as_wrapped", False):
        solver = solver.solver
    if isinstance(solver, dfx.AbstractSolver) and not is_symmetric(solver):
        raise ValueError(
            "ReversibleController keeps a solve time-reversible only with a "
            f"symmetric solver, and {type(solver).__name__} is not one (a wrapper "
            "such as diffrax.HalfSolver is not either, nor a VPRK whose tableau is "
            "not symmetric). Use StormerVerlet, "
            "MidpointVI, TrapezoidalVI, a symmetric VPRK or a Composition; for "
            "other solvers, diffrax.PIDController."
        )


class ReversibleController(dfx.AbstractStepSizeController):
    r"""Time-reversible adaptive steps driven by a monitor, for symmetric solvers
    (Hairer & Söderlind 2005, *Explicit, time reversible, adaptive step size
    control*; Hairer, Lubich & Wanner VIII.3.2).

    Pass it as `stepsize_controller` with a symmetric solver of this package
    ([`diffrax_vi.StormerVerlet`][], [`diffrax_vi.MidpointVI`][], a
    [`diffrax_vi.Composition`][], Gauss or Lobatto VPRK) and `dt0`, the step at
    density 1 (at the initial state, unless `density` says otherwise). Each step's
    size follows the monitor, $h_{n+1/2} = h_0 / z_{n+1/2}$ with
    $z \approx s(y_0)/s(y)$ integrated explicitly along the motion (see
    [Adaptive steps](../adaptive.md)), so that:

    - every step is one step of the symplectic method, so momentum maps of a
      symmetry (angular momentum of a central force) are conserved to round-off;
    - the pair (state, step density) is mapped reversibly: integrated back from the
      end, with `density` the final `sol.controller_state.density`
      (`SaveAt(controller_state=True)`), the solve returns to its start to
      round-off;
    - for reversible problems the energy error stays bounded with no drift over
      long times (the theory of reversible methods on integrable systems: the
      extended map is reversible, not symplectic);
    - the method keeps its order in `dt0`; with a constant monitor it takes exactly
      the fixed steps `dt0`.

    No step is rejected. `diffeqsolve` still ends exactly on `t1` (it shortens the
    last step) and `SaveAt(ts=...)` interpolates between steps (cubic Hermite).

    **Arguments:**

    - `monitor`: `monitor(t, y, args) -> scalar`, positive and finite, proportional
        to the step wanted at `y` (only ratios matter, so its units do not). For
        reversibility it must be even in the momenta (e.g. a function of the
        positions). For gravitational problems, [`diffrax_vi.PotentialMonitor`][].
    - `density`: the step density at the initial state (default 1: the first step
        is about `dt0`).
    - `step_ts`: times the steps must land on, or `None`. A step that would pass
        one is shortened to end on it, so that `SaveAt(ts=step_ts)` saves states of
        the method rather than of the cubic Hermite interpolant between steps (on
        Kepler at e = 0.9, kahan_li8 at 130 steps per orbit: energy error 3e-12 at
        the steps, 9e-6 interpolated). The steps after it follow the density as
        before; each shortened step perturbs the reversible sequence once.

    **Failures:** a monitor that is zero, negative, NaN or inf at a step, or a step
    density that falls to zero or below (`dt0` too large for how fast the monitor
    changes along the motion), ends the solve with `RESULTS.nonfinite`.
    """

    monitor: Callable[..., ArrayLike]
    density: float | Array = 1.0
    step_ts: Array | None = eqx.field(default=None, converter=_optional_array)
    direction: int | Array | None = None

    def wrap(self, direction) -> "ReversibleController":
        step_ts = self.step_ts
        if step_ts is not None:
            # In diffrax's time, increasing.
            step_ts = jnp.sort(direction * step_ts)
        return eqx.tree_at(
            lambda c: (c.direction, c.step_ts),
            self,
            (direction, step_ts),
            is_leaf=lambda x: x is None,
        )

    def _clip(self, t: RealScalarLike, t_next: Array) -> Array:
        """`t_next`, or the first of `step_ts` after `t` if that comes sooner."""
        if self.step_ts is None:
            return t_next
        ts = self.step_ts.astype(t_next.dtype)
        i = jnp.searchsorted(ts, t, side="right")
        stop = jnp.where(i < ts.size, ts[jnp.minimum(i, ts.size - 1)], jnp.inf)
        return jnp.minimum(t_next, stop)

    def _rate(
        self, state: ReversibleState, t: RealScalarLike, y: PyTree, args: Args
    ) -> tuple[Array, Bool[Array, ""]]:
        """`G = -d/dt log s` along the motion in diffrax's time (negated when
        integrating backwards), and whether the monitor is positive and finite."""
        direction = self._direction(state.dt0.dtype)
        t_phys = direction * jnp.asarray(t, state.dt0.dtype)

        def log_monitor(t, y):
            s = jnp.asarray(self.monitor(t, y, args))
            if s.shape != ():
                raise ValueError(
                    f"The step-size monitor must return a scalar; got shape {s.shape}."
                )
            return jnp.log(s), s

        tangent = (jnp.ones_like(t_phys), state.field(t_phys, y, args))
        (_, s), (dlog, _) = jax.jvp(log_monitor, (t_phys, y), tangent)
        ok = (s > 0) & jnp.isfinite(s) & jnp.isfinite(dlog)
        return (-direction * dlog).astype(state.dt0.dtype), ok

    def _direction(self, dtype) -> Array:
        return jnp.asarray(1 if self.direction is None else self.direction, dtype)

    def _step(self, state: ReversibleState) -> tuple[Array, Array, Bool[Array, ""]]:
        """The step from the state's node: half the density update at the node
        opens it (Hairer & Söderlind's symmetric form), `z = w + dt0 G / 2`."""
        z = state.density + 0.5 * state.dt0 * state.rate
        ok = state.ok & (z > 0) & jnp.isfinite(z)
        # After a failure, a finite step: the failure is reported, not spun on.
        return state.dt0 / jnp.where(ok, z, 1), z, ok

    def init(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        dt0: RealScalarLike | None,
        args: Args,
        func: Callable,
        error_order: RealScalarLike | None,
    ) -> tuple[RealScalarLike, ReversibleState]:
        if dt0 is None:
            raise ValueError(
                "ReversibleController needs `dt0`, the step at the initial state: "
                "the monitor sets the steps after it relative to this one. Pass "
                "e.g. `dt0=period / 100`."
            )
        _check_symmetric(getattr(func, "__self__", None))
        raw = _unwrap(terms)
        dtype = jnp.result_type(t0, dt0, float)
        t_phys = self._direction(dtype) * jnp.asarray(t0, dtype)
        field = _Field(
            *eqx.partition(
                eqx.filter_closure_convert(
                    lambda t, y, args: func(raw, t, y, args), t_phys, y0, args
                ),
                eqx.is_array,
            )
        )
        density = jnp.asarray(self.density, dtype)
        state = ReversibleState(
            density,
            jnp.zeros((), dtype),
            jnp.asarray(dt0, dtype),
            jnp.array(True),
            field,
        )
        rate, ok = self._rate(state, t0, y0, args)
        state = eqx.tree_at(
            lambda s: (s.rate, s.ok),
            state,
            (
                jnp.where(ok, rate, 0),
                ok
                & (density > 0)
                & jnp.isfinite(density)
                & (state.dt0 != 0)
                & jnp.isfinite(state.dt0),
            ),
        )
        t_next, ok = self.next_time(state, t0)
        return t_next, eqx.tree_at(lambda s: s.ok, state, ok)

    def adapt_step_size(
        self,
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        y1_candidate: PyTree,
        args: Args,
        y_error: PyTree | None,
        error_order: RealScalarLike,
        controller_state: ReversibleState,
    ) -> tuple[
        Bool[Array, ""],
        RealScalarLike,
        RealScalarLike,
        Bool[Array, ""],
        ReversibleState,
        dfx.RESULTS,
    ]:
        state = controller_state
        _, z, _ = self._step(state)
        rate, ok = self._rate(state, t1, y1_candidate, args)
        # The second half of the update closes the step at the new node.
        w = z + 0.5 * state.dt0 * rate
        ok = state.ok & ok & (w > 0) & jnp.isfinite(w)
        state = eqx.tree_at(
            lambda s: (s.density, s.rate, s.ok),
            state,
            (jnp.where(ok, w, state.density), jnp.where(ok, rate, 0), ok),
        )
        t_next, ok = self.next_time(state, t1)
        state = eqx.tree_at(lambda s: s.ok, state, ok)
        result = dfx.RESULTS.where(ok, dfx.RESULTS.successful, dfx.RESULTS.nonfinite)
        return jnp.array(True), t1, t_next, jnp.array(False), state, result

    # The step sequence as a function of the state, for the reversible adjoint, which
    # rebuilds the controller's state at each node instead of storing it and
    # differentiates through it.

    def next_time(
        self, state: ReversibleState, t: RealScalarLike
    ) -> tuple[Array, Bool[Array, ""]]:
        """The end of the step that starts at node `t` in `state` (before diffrax
        clips it to `t1`), and whether the step density is positive and finite."""
        h, _, ok = self._step(state)
        return self._clip(t, t + h), ok

    def node(
        self,
        terms: PyTree[dfx.AbstractTerm],
        func: Callable,
        t: RealScalarLike,
        y: PyTree,
        args: Args,
        density: Array,
        dt0: Array,
    ) -> ReversibleState:
        """The state the controller holds at node `(t, y)` with step density
        `density`: its rate computed afresh from `terms` (through `func`, the
        solver's vector field), so that it depends on them differentiably."""
        raw = _unwrap(terms)
        state = ReversibleState(
            density,
            jnp.zeros_like(dt0),
            dt0,
            jnp.array(True),
            lambda t, y, args: func(raw, t, y, args),
        )
        rate, ok = self._rate(state, t, y, args)
        return eqx.tree_at(lambda s: (s.rate, s.ok), state, (rate, ok))

    def density_before(
        self, state: ReversibleState, t: RealScalarLike, y: PyTree, args: Args
    ) -> tuple[Array, Bool[Array, ""]]:
        r"""The density $w_n$ at the node `(t, y)` before the node that `state`
        holds: the density update run backwards,
        $w_n = w_{n+1} - \tfrac{h_0}{2}(G(y_{n+1}) + G(y_n))$."""
        rate, ok = self._rate(state, t, y, args)
        return state.density - 0.5 * state.dt0 * (state.rate + rate), ok


class PotentialMonitor(eqx.Module):
    r"""The default step-size monitor for gravitational problems:
    $s(q) = (-V(t, q))^{-a}$ with $V < 0$ the potential, so that the step follows the
    local dynamical time of the closest encounter. With $a = 3/2$ on Kepler,
    $s \propto r^{3/2}$ (Hairer, Lubich & Wanner VIII.3.2); an $N$-body potential
    $-\sum G m_i m_j / r_{ij}$ is dominated by the closest pair.

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractSeparableLagrangian`][] (its `potential`
        is used), or any Lagrangian whose value at zero velocity is $-V$.
    - `power`: the exponent $a$ (default 1.5; 1 is Sundman's transformation).

    The monitor reads the positions only, so the steps it makes are reversible. Where
    $V \geq 0$ it is not positive, and the solve fails with `RESULTS.nonfinite`.
    """

    lagrangian: AbstractLagrangian | Callable
    power: float = eqx.field(static=True, default=1.5)

    def __call__(self, t, y, args):
        q = y[0]
        if isinstance(self.lagrangian, AbstractSeparableLagrangian):
            potential = self.lagrangian.potential(t, q, args)
        else:
            zero = jtu.tree_map(jnp.zeros_like, q)
            potential = -self.lagrangian(t, q, zero, args)
        return (-potential) ** (-self.power)
