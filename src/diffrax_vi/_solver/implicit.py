r"""One-step implicit variational integrators: a method is its stage equations.

A subclass says what its unknowns are (the step velocity of a discrete Lagrangian, the
stage velocities of a VPRK method), the equations they satisfy with the size of the
momenta each equation balances, and the increments of $(q, p)$ they give;
`unknowns.py` solves them, `constrained.py` adds the multipliers of holonomic
constraints.
"""

import abc
from collections.abc import Callable

import lineax as lx
import optimistix as optx
from equinox import AbstractVar
from jaxtyping import Array, ArrayLike, Bool, PyTree

from .._custom_types import P, Q, V
from .base import (
    AbstractComposableSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    MethodStep,
    StepInputs,
    without_force,
)
from .constrained import constrained_step, init_constrained
from .unknowns import (
    init_unknowns,
    inverse_root,
    resume_unknowns,
    root_finding,
    solve_step,
    StepEquations,
    Unknowns,
)


class AbstractImplicitVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractComposableSolver
):
    """Base class for one-step implicit variational integrators on a
    [`diffrax_vi.LagrangianTerm`][]: symmetric and symplectic, one nonlinear solve per
    step for the method's unknowns.

    A subclass implements `stage_guess`, `stage_residual`, `stage_increments`,
    `stage_work`, `inverse_mass` and `jacobian_tags`.
    """

    root_finder: AbstractVar[optx.AbstractRootFinder | None]
    root_find_max_steps: AbstractVar[int]

    @abc.abstractmethod
    def stage_guess(self, step: StepInputs, v: V) -> PyTree:
        """The unknowns of a step at the constant velocity `v`: the first guess."""

    @abc.abstractmethod
    def stage_residual(
        self, step: StepInputs, unknowns: PyTree
    ) -> tuple[PyTree, PyTree]:
        """The step's equations (momenta, zero at the solution) and the size of the
        momenta each balances."""

    @abc.abstractmethod
    def stage_increments(self, step: StepInputs, unknowns: PyTree) -> tuple[Q, P]:
        """The increments `(q1 - q0, p1 - p0)` of the step with these unknowns."""

    def stage_step(self, step: StepInputs, unknowns: PyTree) -> Q:
        """The position increment `q1 - q0` of the step with these unknowns: the
        first of `stage_increments`. A constrained step's equations read it at
        every iterate, where the momenta's increments would be traced for nothing."""
        return self.stage_increments(step, unknowns)[0]

    @abc.abstractmethod
    def stage_work(self, step: StepInputs, unknowns: PyTree) -> Array:
        """The work of the step's discrete applied forces with these unknowns, by
        the quadrature that the method applies to the force."""

    @abc.abstractmethod
    def inverse_mass(self, step: StepInputs) -> PyTree | None:
        """One over the mass of each unknown for a separable Lagrangian (the
        fixed-point iteration's preconditioner), or `None`."""

    @abc.abstractmethod
    def jacobian_tags(self, step: StepInputs) -> frozenset:
        """`lineax` tags of the stage equations' Jacobian (e.g. symmetric positive
        definite for the midpoint step of a separable Lagrangian)."""

    def method_init(self, step: StepInputs) -> Unknowns:
        if step.term.constraint is not None:
            if not self.one_stage:
                raise ValueError(
                    f"{type(self).__name__} has several stages, whose positions "
                    "would need constraints of their own; holonomic constraints are "
                    "supported by MidpointVI, TrapezoidalVI and compositions of them "
                    "(for higher order, e.g. "
                    "`Composition(MidpointVI(), 'kahan_li8')`)."
                )
            return init_constrained(
                step,
                lambda v: self.stage_guess(step, v),
                root_finding(self.root_finder),
            )
        return init_unknowns(
            step, lambda v: self.stage_guess(step, v), root_finding(self.root_finder)
        )

    def method_resume(self, step: StepInputs, state: Unknowns) -> Unknowns:
        return resume_unknowns(
            step,
            lambda v: self.stage_guess(step, v),
            root_finding(self.root_finder),
            state,
        )

    def method_step(
        self, step: StepInputs, state: Unknowns, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        if step.term.constraint is not None:
            return constrained_step(
                step,
                state,
                made_jump,
                self.stage_residual,
                self.stage_increments,
                self.stage_step,
                root_finding(self.root_finder),
                self.root_find_max_steps,
                None if step.term.force is None else self.stage_work,
                self.inverse_mass(step),
            )
        residual = lambda w: self.stage_residual(step, w)
        if self.one_stage and step.term.force is None:
            # The root finder's own Jacobian measures the curvature.
            fold_residual = residual
        else:
            fold_residual = self.fold_residual(without_force(step))
        equations = StepEquations(
            residual=residual,
            increments=lambda w: self.stage_increments(step, w),
            inverse_mass=self.inverse_mass(step),
            tags=self.jacobian_tags(step),
            fold_residual=fold_residual,
            work=None
            if step.term.force is None
            else (lambda w: self.stage_work(step, w)),
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
        return inverse_root(solver_state, self.reversed_stages)

    def reversed_stages(self, unknowns: PyTree) -> PyTree:
        """The unknowns with their stages in reverse order: the inverse step's, for
        a symmetric method."""
        return unknowns

    def fold_residual(
        self, step: StepInputs
    ) -> Callable[[PyTree], tuple[PyTree, PyTree]] | None:
        """The residual whose curvature along the way from the guess to a root tells
        whether the root continues the motion (`StepEquations.fold_residual`), for
        `step` without applied forces: the stage equations themselves where the
        unknowns are one velocity, `None` (no test) otherwise."""
        if self.one_stage:
            return lambda w: self.stage_residual(step, w)
        return None

    @property
    def one_stage(self) -> bool:
        """Whether the unknowns are one velocity, so that the Jacobian of the step's
        equation is, up to an antisymmetric part, the Hessian of the discrete action
        and its curvature along the Newton path tests the root. The stage equations
        of a multi-stage method have no such structure: their Jacobian can be
        indefinite at the one good root of a linear problem (Gauss and Lobatto
        methods on the oscillator past their stability interval), so their test is
        their own (`fold_residual`)."""
        return False


SYMMETRIC_POSITIVE = frozenset({lx.symmetric_tag, lx.positive_semidefinite_tag})


IMPLICIT_ARGS_DOC = """- `root_finder`: how the implicit equations are solved: `None`
    (the default) chooses the fixed-point iteration for a separable Lagrangian, falling
    back to Newton's method where it does not converge (stiff steps), and Newton's
    method otherwise: with dense LU up to 16 unknowns and matrix-free Krylov
    iterations beyond (conjugate gradients where its matrix is symmetric, as for the
    midpoint step of a Lagrangian whose momentum does not depend on $q$); or
    [`diffrax_vi.Newton`][], [`diffrax_vi.SimplifiedNewton`][],
    [`diffrax_vi.FixedPoint`][], or any `optimistix.AbstractRootFinder` (given the
    residual relative to its largest term). Every tolerance is relative to the size
    of the momenta the equations balance, so results do not depend on the units.
- `root_find_max_steps`: iterations after which a step is reported as failed
    (`RESULTS.nonlinear_max_steps_reached`): usually a sign that the step is too large.
- `compensated`: compensated (Kahan) summation of each step's increment (default),
    so that round-off in the energy grows like the square root of the number of steps
    rather than linearly (Brouwer's law). Costs a few additions per step.
"""
