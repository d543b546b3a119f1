from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PyTree

from .._force import applied_force, power
from .._lagrangian import inverse_legendre
from .._solver.base import VIState
from .._term import LagrangianTerm


class Worst(eqx.Module):
    """The largest error of each conserved quantity (columns, in the order of
    `TrackWorstError.names`) in each save interval so far (rows; `-inf` where no
    step has ended in the interval yet), and the number of steps taken.

    One array, not one per quantity: with two buffers in the loop state XLA stopped
    updating them in place, which cost a Störmer–Verlet step many times its own
    work."""

    errors: Float[Array, "n_save n_conserved"]
    steps: Int[Array, ""]
    # The work of the applied force so far, for a solver that does not keep its own
    # (None without a force: nothing more in the loop's state).
    work: Float[Array, ""] | None


# Gauss-Legendre nodes and weights on [0, 1], 4 points (exact for degree 7).
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(4)
_NODES, _WEIGHTS = (_NODES + 1) / 2, _WEIGHTS / 2


class EnergyBalance(eqx.Module):
    r"""The energy balance of a forced scene, $E(t) - E(0) - W(t)$ with $W$ the work
    of the applied force, accumulated as the method accumulates the force's impulse:
    a variational solver's own discrete work (the quadrature $f^\pm$ of its discrete
    Lagrange–d'Alembert principle, kept in its state), and for any other solver the
    power $F\cdot v$ integrated along the solver's own dense output of each step by
    4-point Gauss–Legendre quadrature."""

    energy: Callable
    term: LagrangianTerm
    start: Array

    def dense_work(self, interpolation, t0, t1, args) -> Array:
        def power_at(s):
            t = t0 + s * (t1 - t0)
            q, p = interpolation.evaluate(t)
            v, _ = inverse_legendre(
                self.term.lagrangian, t, (q, p), args, None, promise="nan"
            )
            return power(applied_force(self.term.force, t, q, v, args), v)

        nodes = jnp.asarray(_NODES, jnp.result_type(t0, t1))
        return (t1 - t0) * jnp.sum(
            jnp.asarray(_WEIGHTS, nodes.dtype) * jax.vmap(power_at)(nodes)
        )


class Tracked(eqx.Module):
    """The solver state of [`TrackWorstError`][]: the wrapped solver's, and the
    worst errors so far."""

    inner: PyTree
    worst: Worst


def discrete_work(solver_state) -> Array | None:
    """The accumulated work of a variational solver's discrete forces (its state is a
    `VIState`, a composition's that of its base), or `None` for other solvers."""
    if isinstance(solver_state, VIState):
        return solver_state.work
    return None


class TrackWorstError(dfx.AbstractWrappedSolver):
    """Wraps a solver so that its solver state also holds, for each conserved
    quantity, the largest `|I(y) - I(y0)|` (over the components of a vector invariant)
    after any step, per save interval: one solve, taking exactly the steps the solver
    takes alone, records the error of every step.

    A step belongs to the interval that contains its end: for fixed steps, the
    `k`-th step to interval `k // steps_per_interval` (exact, whatever the rounding of
    the times); for adaptive steps, by its end time against `boundaries`, the right
    ends of the intervals. diffrax keeps a solver state only from accepted steps, so
    rejected steps do not count. This costs one evaluation of the invariants and one
    indexed update per step; streaming every step's errors out through
    `SaveAt(steps=True, fn=...)` instead costs a buffer write per step, which on CPU
    is dearer than an explicit step."""

    solver: dfx.AbstractSolver
    # It takes the wrapped solver's steps unchanged, so a check of the solver's
    # symmetry (`ReversibleController`) looks through it.
    steps_as_wrapped: ClassVar[bool] = True
    conserved: dict[str, Callable]
    start: dict[str, Array]
    boundaries: Float[Array, " n_save"]
    steps_per_interval: int | None = eqx.field(static=True, default=None)
    balance: EnergyBalance | None = None

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    @property
    def names(self) -> list[str]:
        """The conserved quantities in the order of the columns of `Worst.errors`
        (sorted: a dict in a pytree comes back with its keys sorted), then
        `energy_balance` for a forced scene."""
        return sorted(self.conserved) + (
            [] if self.balance is None else ["energy_balance"]
        )

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        starts = list(self.start.values())
        if self.balance is not None:
            starts.append(self.balance.start)
        dtype = jnp.result_type(*starts)
        shape = (self.boundaries.shape[0], len(self.names))
        errors = jnp.full(shape, -jnp.inf, dtype)
        work = None if self.balance is None else jnp.zeros((), dtype)
        worst = Worst(errors, jnp.zeros((), jnp.int32), work)
        return Tracked(self.solver.init(terms, t0, t1, y0, args), worst)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner, worst = solver_state.inner, solver_state.worst
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, inner, made_jump
        )
        if self.steps_per_interval is None:
            index = jnp.searchsorted(self.boundaries, t1, side="left")
        else:
            index = worst.steps // self.steps_per_interval
        index = jnp.minimum(index, self.boundaries.shape[0] - 1)
        columns = [
            max_error(self.conserved[k](t1, y1, args), self.start[k])
            for k in sorted(self.conserved)
        ]
        work = worst.work
        if self.balance is not None:
            own = discrete_work(inner)
            if own is None:
                interpolation = self.solver.interpolation_cls(
                    t0=t0, t1=t1, **dense_info
                )
                work = work + self.balance.dense_work(interpolation, t0, t1, args)
            else:
                work = own
            gained = self.balance.energy(t1, y1, args) - self.balance.start
            columns.append(jnp.abs(gained - work))
        errors = jnp.stack(columns).astype(worst.errors.dtype)
        # A dynamic slice update, which XLA does in place inside the loop.
        row = jax.lax.dynamic_slice_in_dim(worst.errors, index, 1)
        errors = jax.lax.dynamic_update_slice_in_dim(
            worst.errors, jnp.maximum(row, errors[None]), index, 0
        )
        worst = Worst(errors, worst.steps + 1, work)
        return y1, y_error, dense_info, Tracked(inner, worst), result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


def max_error(value: Array, start: Array) -> Array:
    """The largest component of `|value - start|`."""
    return jnp.max(jnp.abs(jnp.ravel(value - start)))
