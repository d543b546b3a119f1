from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._discrete import TrapezoidalRule
from .._force import applied_force, depends_on_velocity
from .._lagrangian import (
    AbstractSeparableLagrangian,
    broadcast_mass,
    fixed_point_inverse_mass,
    generalised_force,
    mass_regular,
)
from .._root_finders import Newton
from .base import (
    AbstractComposableSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    after_jump,
    MethodStep,
    StepInputs,
    without_force,
)
from .constrained import constrained_step, init_constrained
from .implicit import IMPLICIT_ARGS_DOC
from .rattle import rattle_init, rattle_step, RattleState
from .rule import rule_increments, rule_residual, rule_step, rule_work
from .stormer_verlet import kick_drift_kick
from .unknowns import (
    init_unknowns,
    inverse_root,
    resume_unknowns,
    root_finding,
    solve_step,
    StepEquations,
    Unknowns,
)


_RULE = TrapezoidalRule()


def _force(step: StepInputs, t, q) -> PyTree:
    """$-\nabla V$, plus the applied force (of the positions alone, on this path)."""
    force = generalised_force(step.term.lagrangian, t, q, None, step.args)
    if step.term.force is None:
        return force
    zeros = jtu.tree_map(jnp.zeros_like, q)
    applied = applied_force(step.term.force, t, q, zeros, step.args)
    return jtu.tree_map(lambda a, b: a + b, force, applied)


def _work(step: StepInputs, v) -> PyTree:
    return rule_work(_RULE, step, v)


def _positional(step: StepInputs) -> bool:
    """Whether the step's momenta are explicit: a separable Lagrangian and no force
    or one of the positions and time alone."""
    term = step.term
    if not isinstance(term.lagrangian, AbstractSeparableLagrangian):
        return False
    return term.force is None or not depends_on_velocity(
        term.force, step.t0, step.q0, step.p0, step.args
    )


def _explicit(step: StepInputs) -> bool:
    """Whether the step is Störmer–Verlet: explicit momenta and no constraint."""
    return step.term.constraint is None and _positional(step)


def _rattle(step: StepInputs) -> bool:
    """Whether the step is RATTLE on the multipliers alone: explicit momenta and a
    constraint."""
    return step.term.constraint is not None and _positional(step)


def _residual(step: StepInputs, v) -> tuple[PyTree, PyTree]:
    return rule_residual(_RULE, step, v)


def _increments(step: StepInputs, v) -> tuple[PyTree, PyTree]:
    return rule_increments(_RULE, step, v)


class TrapezoidalVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractComposableSolver
):
    r"""Trapezoidal variational integrator.

    2nd order symmetric symplectic variational integrator. Explicit (Störmer–Verlet,
    one force evaluation per step) for an
    [`diffrax_vi.AbstractSeparableLagrangian`][] with no applied force or one of the
    positions and time alone, and with holonomic constraints RATTLE, solved for the
    multipliers alone (one force evaluation, Newton's method on the $m$ position
    multipliers and one $m \times m$ solve per step); one nonlinear solve per step
    otherwise. Fixed step sizes only. Cubic Hermite interpolation for dense output.

    Discrete Lagrangian, with $v = (q_1 - q_0)/h$:

    $$L_d(q_0, q_1) = \tfrac h2\big[L(t_0, q_0, v) + L(t_0 + h, q_1, v)\big],$$

    stepped in position–momentum form on $y = (q, p)$ through the discrete Legendre
    transforms $p_0 = -D_1 L_d$, $p_1 = D_2 L_d$ (Hirani (2000), eq. (3.4)). For
    $L = \tfrac12 v^\top M v - V(t, q)$ the step equations are explicit and are exactly
    [`diffrax_vi.StormerVerlet`][] on Hamilton's equations (Marsden & West (2001),
    Part 2). For a configuration-dependent mass it differs from `LobattoVPRK(2)`,
    whose two stages have their own velocities.

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
        ```
    """

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    symmetric: ClassVar[bool] = True

    def order(self, terms):
        return 2

    def method_init(self, step: StepInputs) -> PyTree:
        lagrangian = step.term.lagrangian
        if _explicit(step):
            # The force as it is, even at a NaN or inf start: the engine checks both
            # halves of the new state, which carry it (`q0 + dq`, `p0 + dp`).
            # Poisoned by a check of the start (`poisoned_force`, which
            # StormerVerlet needs: it checks the momentum alone), Kepler's start
            # compiled to three more kernels outside the loop.
            mass = broadcast_mass(lagrangian.mass, step.p0)
            return ExplicitState(
                _force(step, step.t0, step.q0), mass_regular(mass, step.p0)
            )
        if _rattle(step):
            return rattle_init(step, lambda t, q: _force(step, t, q))
        if step.term.constraint is not None:
            return init_constrained(step, lambda v: v, root_finding(self.root_finder))
        return init_unknowns(step, lambda v: v, root_finding(self.root_finder))

    def method_resume(self, step: StepInputs, state: PyTree) -> PyTree:
        if not isinstance(state, Unknowns):  # Explicit, or RATTLE.
            return self.method_init(step)
        return resume_unknowns(step, lambda v: v, root_finding(self.root_finder), state)

    def method_step(
        self, step: StepInputs, state: PyTree, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        if _explicit(step):
            return self._explicit_step(step, state, made_jump)
        if _rattle(step):
            return rattle_step(
                step,
                state,
                made_jump,
                lambda t, q: _force(step, t, q),
                None if step.term.force is None else (lambda v: _work(step, v)),
                Newton() if self.root_finder is None else self.root_finder,
                self.root_find_max_steps,
            )
        assert isinstance(state, Unknowns)
        if step.term.constraint is not None:
            # The constrained trapezoidal step of a general Lagrangian.
            return constrained_step(
                step,
                state,
                made_jump,
                _residual,
                _increments,
                rule_step,
                root_finding(self.root_finder),
                self.root_find_max_steps,
                None if step.term.force is None else _work,
                fixed_point_inverse_mass(step.term.lagrangian, step.p0),
            )
        equations = StepEquations(
            residual=lambda v: _residual(step, v),
            increments=lambda v: _increments(step, v),
            # One velocity: the curvature of the discrete action tests the root.
            fold_residual=lambda v: _residual(without_force(step), v),
            work=None if step.term.force is None else (lambda v: _work(step, v)),
        )
        return solve_step(
            step,
            state,
            made_jump,
            equations,
            root_finding(self.root_finder),
            self.root_find_max_steps,
        )

    def root_of_inverse(self, terms, solver_state):
        if isinstance(solver_state.method, RattleState):
            # RATTLE's multipliers: the inverse step's projection's, as for any
            # constrained step (`unknowns.inverse_root`).
            return solver_state.method.projection
        # The velocity of the general implicit step, with a constrained step's
        # multipliers (None for the explicit step).
        return inverse_root(solver_state)

    def _explicit_step(
        self, step: StepInputs, state: "ExplicitState", made_jump
    ) -> MethodStep:
        # After a jump the cached force belongs to the state before the jump.
        force0 = after_jump(
            made_jump, lambda: _force(step, step.t0, step.q0), state.force
        )
        h = step.h
        mass = broadcast_mass(step.term.lagrangian.mass, step.p0)
        dq, kick0, kick1, force1 = kick_drift_kick(
            step.p0,
            force0,
            kick=lambda g: jtu.tree_map(lambda x: 0.5 * h * x, g),
            drift=lambda p: jtu.tree_map(lambda m, x: h * x / m, mass, p),
            force=lambda q: _force(step, step.t1, q),
            end_position=step.end_position,
        )
        dp = jtu.tree_map(lambda a, b: a + b, kick0, kick1)
        v = jtu.tree_map(lambda x: x / h, dq)
        # The engine checks the new state for NaN and inf.
        result = dfx.RESULTS.where(
            state.regular, dfx.RESULTS.successful, dfx.RESULTS.singular
        )
        work = None
        if step.term.force is not None:
            # The trapezoidal rule's discrete forces, of the positions alone here.
            work = _work(step, v)
        new = ExplicitState(force1, state.regular)
        return MethodStep(dq, dp, v, new, result, work)


class ExplicitState(eqx.Module):
    """The force at the end of the last step (the first kick of the next one), and
    whether the mass is invertible (checked once, at the start)."""

    force: PyTree
    regular: Bool[Array, ""]


TrapezoidalVI.__init__.__doc__ = "**Arguments:**\n\n" + IMPLICIT_ARGS_DOC
