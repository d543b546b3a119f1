import copy
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, PyTree

from ._constraint import multiplier_force
from ._custom_types import Args, RealScalarLike
from ._force import applied_force, depends_on_velocity
from ._lagrangian import (
    AbstractLagrangian,
    AbstractSeparableLagrangian,
    as_lagrangian,
    broadcast_mass,
    broken_promise,
    declared_mass,
    generalised_force,
    inverse_legendre,
    mass_regular,
    NOT_QUADRATIC,
)
from ._misc import all_finite, at_trace_time, error_if, split_state, traced
from ._space import coadjoint, is_euclidean, velocity as space_velocity


VF_ERRORS = (
    "The Lagrangian is degenerate at this state: d^2L/dv^2 is singular to working "
    "precision, so the velocity is not determined by the momentum. Make the kinetic "
    "energy positive definite in every velocity component (a zero mass, or a "
    "velocity entering L linearly, is degenerate).",
    "Newton's method could not invert the Legendre map p = dL/dv at this state, "
    "though d^2L/dv^2 is regular there: the momentum may lie outside the map's range "
    "(|p| has no velocity, e.g. beyond the speed limit of a relativistic L). Check "
    "y0 and the step size.",
    "The Lagrangian, its derivatives or the applied force gave NaN or inf at a "
    "finite state: check their parameters and args, and a force such as -c v/|v| "
    "that is undefined at rest.",
    "The constraint forces cannot be solved at this state: G (d2L/dv2)^-1 G^T is "
    "singular, with G = dg/dq, or d2L/dv2 itself is. A Runge-Kutta solver "
    "integrates the index-reduced equations, drifts off g = 0 and can reach a "
    "singular configuration of the mechanism: take smaller steps or a tighter "
    "rtol, or use MidpointVI or TrapezoidalVI, which keep g = 0 at every step. If "
    "the start is singular, the constraints are redundant or q0 is a singular "
    "configuration.",
    NOT_QUADRATIC,
)


SINGULAR_MASS = (
    "The mass of this separable Lagrangian is singular: an entry is zero (or below "
    "eps times the largest), or not finite. Every degree of freedom needs a positive "
    "mass."
)


def mass_settles_velocity(lagrangian: AbstractLagrangian) -> bool:
    """Whether the Legendre map is settled for every state of a solve by one check
    of the Lagrangian, made here: a declared constant mass (a separable Lagrangian's
    mass, a rigid body's inertia, or both of bodies) that is concrete and regular.

    Its velocity $M^{-1}p$ fails only for a singular mass, fixed for the solve. A
    check in every vector field would put a host callback in XLA's time-stepping
    loop, which then cannot be compiled as one function: Runge–Kutta steps on small
    systems several times slower (`benchmarks/step_cost.py`). A mass traced where
    the term is built (one being fitted inside `jax.jit`), or a singular one, keeps
    the check in every vector field, which reports it.
    """
    mass = declared_mass(lagrangian)
    if mass is None:
        return False
    if traced(mass):
        return False
    return not bool(_mass_checked_when_known(mass)[1])


def mass_is_definite(lagrangian: AbstractLagrangian) -> bool:
    r"""Whether the Lagrangian declares a constant mass (`declared_mass`) that is
    known where the term is built and positive in every entry. A constrained step's
    momentum projection then solves $G M^{-1} G^\top$, symmetric positive definite
    where the constraints are independent, without pivoting (`project_affine`). A
    mass traced where the term is built, or one with an entry that is not positive
    (an indefinite $\partial^2 L/\partial v^2$, which the start admits), is
    eliminated with partial pivoting."""
    mass = declared_mass(lagrangian)
    if mass is None or traced(mass):
        return False
    m, _ = _mass_checked_when_known(mass)
    return all(bool(np.all(np.asarray(x) > 0)) for x in jtu.tree_leaves(m))


def _mass_checked_when_known(mass: PyTree) -> tuple[PyTree, bool | Array]:
    """A declared mass as arrays, and whether it is singular: computed now, in
    NumPy, where the mass is known (in JAX each operation of the check was a
    program of its own to compile: 0.2 s of a process's first term), else traced."""
    m = at_trace_time(lambda mass: jtu.tree_map(jnp.asarray, mass), mass)
    if traced(m):
        return m, ~mass_regular(m, m)
    return m, not mass_regular(m, m, xp=np)


class LagrangianTerm(dfx.AbstractTerm):
    r"""A Lagrangian as a diffrax term on the phase-space state $y = (q, p)$.

    Its vector field is Hamilton's equations,
    $\dot q = v(q, p)$, $\dot p = \partial L / \partial q\,(t, q, v(q, p))$, with $v$
    the inverse Legendre map ([`diffrax_vi.velocity`][]). So every diffrax ODE solver
    (`Tsit5`, `Dopri8`, `Kvaerno5`, ...) integrates the same term as the variational
    solvers of this package, which instead read the Lagrangian itself.

    With a `force` $F(t, q, v)$, $\dot p$ gains $F$ (the Lagrange–d'Alembert
    principle); the variational solvers apply its discrete version. With a
    `constraint` $g(t, q) = 0$, $\dot p$ gains the constraint force
    $-G^\top\lambda$, $G = \partial g/\partial q$, with $\lambda$ chosen so that
    the hidden constraint $G v = 0$ stays constant: the index-reduced equations,
    along which a Runge–Kutta solver drifts off $g = 0$, while the variational
    solvers keep $g(q_k) = 0$ and $G v_k = 0$ at every step.

    !!! example

        ```python
        term = diffrax_vi.LagrangianTerm(lambda t, q, v, args: 0.5 * v**2 + jnp.cos(q))
        y0 = (jnp.array(1.0), jnp.array(0.0))  # (q0, p0)
        sol = diffrax.diffeqsolve(term, diffrax_vi.MidpointVI(), 0, 10, 0.01, y0)
        sol = diffrax.diffeqsolve(term, diffrax.Tsit5(), 0, 10, 0.01, y0)
        ```

    !!! warning

        A diffrax vector field cannot report a failed step. If the Legendre map cannot
        be inverted at a finite state, `vf` raises an `EquinoxRuntimeError` that names
        the cause (a degenerate Lagrangian; a momentum Newton's method cannot invert;
        NaN from the Lagrangian) rather than return a NaN that a fixed-step
        Runge–Kutta solve would report as a success. A separable Lagrangian's map is
        settled when the term is built (its mass is checked then), so its vector
        field carries no such check and runs at the speed of Hamilton's equations
        written by hand; a mass replaced in the term afterwards is not checked again.
        There a NaN from the potential or the force is carried to the end of a
        fixed-step Runge–Kutta solve, as for any diffrax `ODETerm`, unless the term
        is built with `check_every_step=True`. With a constraint, the term also
        records then whether its declared constant mass is positive, which lets
        each step project its momentum without pivoting; build a new term, rather
        than replace the mass in this one, to give it a mass that is not.
    """

    lagrangian: AbstractLagrangian
    force: Callable[..., PyTree] | None
    constraint: Callable[..., ArrayLike] | None
    # Whether the vector field skips its per-step check; see `mass_settles_velocity`.
    mass_checked: bool = eqx.field(static=True)
    # Whether a constraint's momentum projection eliminates without pivoting; see
    # `mass_is_definite`.
    mass_definite: bool = eqx.field(static=True)
    # Whether a solve's start is taken as checked already; see `start_checked`.
    start_checked: bool = eqx.field(static=True)
    # Whether the vector field makes NaN where it would raise; see `nan_on_failure`.
    nan_on_failure: bool = eqx.field(static=True)

    def __init__(
        self,
        lagrangian: Callable[..., ArrayLike],
        force: Callable[..., PyTree] | None = None,
        constraint: Callable[..., ArrayLike] | None = None,
        *,
        check_every_step: bool = False,
    ):
        """**Arguments:**

        - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][], any `eqx.Module`
            with `__call__(t, q, v, args) -> scalar`, or a plain callable of that form.
        - `force`: an applied generalised force `force(t, q, v, args)` with the
            structure of `q` (damping, drives; control inputs through `args`), or
            `None`. An `eqx.Module` force can be differentiated through like the
            Lagrangian.
        - `constraint`: holonomic constraints `constraint(t, q, args)`, an array of
            `m` values that the motion keeps at zero, or `None`. Start from a
            consistent state: [`diffrax_vi.project_onto_constraints`][].
        - `check_every_step`: make the vector field raise at every evaluation that
            gives NaN or inf at a finite state, also for a separable Lagrangian
            without constraints, whose vector field otherwise carries no check. The
            check is a host callback in the time-stepping loop, which XLA then no
            longer compiles as one function: a diffrax Runge–Kutta step on a small
            system costs several times more (`benchmarks/step_cost.py`). The
            variational solvers and [`diffrax_vi.solve_fixed_steps`][] report such a
            NaN without it.
        """
        self.lagrangian = as_lagrangian(lagrangian)
        for name, fn in (("force", force), ("constraint", constraint)):
            if fn is not None and not callable(fn):
                raise ValueError(f"`{name}` must be callable or None; got {fn!r}.")
        self.force = force
        self.constraint = constraint
        if not is_euclidean(self.lagrangian.space):
            if isinstance(self.lagrangian, AbstractSeparableLagrangian):
                raise ValueError(
                    "AbstractSeparableLagrangian takes dV/dq as a gradient in a "
                    "vector space, and this one's `space` is a group. Write it as "
                    "`diffrax_vi.Lagrangian(fn, space=...)`."
                )
        self.mass_checked = (
            not check_every_step
            and constraint is None
            and mass_settles_velocity(self.lagrangian)
        )
        self.mass_definite = constraint is not None and mass_is_definite(
            self.lagrangian
        )
        self.start_checked = False
        self.nan_on_failure = False

    def hamilton(
        self,
        t: RealScalarLike,
        y: PyTree,
        args: Args,
        *,
        v_guess: PyTree | None = None,
    ) -> tuple[tuple[PyTree, PyTree], dfx.RESULTS]:
        r"""Hamilton's equations $(\dot q, \dot p) = (v, \partial L/\partial q + F
        - G^\top\lambda)$ at $y = (q, p)$, and whether the Legendre map could be
        inverted there (from the guess `v_guess` for a general Lagrangian). $F$ is
        the applied force, $-G^\top\lambda$ the constraint force of the
        index-reduced equations (zero without a constraint). On a group the first
        entry is the velocity $\xi$ (`vf` turns it into $\dot q$) and $\dot p$ the
        Euler–Poincaré equation $\partial^L_q L + \mathrm{ad}^*_\xi p + F$."""
        if v_guess is None:
            # The Legendre map's default guess, given here rather than inside, so
            # that every call (diffrax's check of the term, the stages of a
            # Runge-Kutta step, both ends of a step's dense output) shares a trace.
            v_guess = jtu.tree_map(jnp.zeros_like, y[1])
        return _hamilton(self, t, y, args, v_guess)

    def _hamilton(self, t, y, args, v_guess):
        space = self.lagrangian.space
        q, p = split_state(y, "y", space)
        # The quadratic marker is checked by `vf`, which must raise, not here: a
        # step's dense output (on the same trace) is inside its loop, where the
        # start has checked it and a callback would break the loop into kernels.
        v, result = inverse_legendre(
            self.lagrangian, t, y, args, v_guess, promise="trust"
        )
        dp = generalised_force(self.lagrangian, t, q, v, args)
        if not is_euclidean(space):
            # The Euler-Poincare equations: the group's own term ad*_v p.
            dp = jtu.tree_map(lambda a, b: a + b, dp, coadjoint(space, v, p))
        if self.force is not None:
            force = applied_force(self.force, t, q, v, args)
            dp = jtu.tree_map(lambda a, b: a + b, dp, force)
        if self.constraint is not None:
            reaction, solvable = multiplier_force(self, t, q, p, v, dp, args)
            dp = jtu.tree_map(lambda a, b: a + b, dp, reaction)
            result = dfx.RESULTS.where(
                result == dfx.RESULTS.successful, solvable, result
            )
        return (v, dp), result

    def vf(self, t: RealScalarLike, y: PyTree, args: Args) -> PyTree:
        (v, dp), result = self.hamilton(t, y, args)
        f = (space_velocity(self.lagrangian.space, y[0], v), dp)
        if self.mass_checked:
            return f
        # A vector field cannot return a RESULTS: each cause raises its own message.
        ok = result == dfx.RESULTS.successful
        broken = ok & broken_promise(self.lagrangian, t, y, args, v)
        failed = (~ok | broken | ~all_finite(f)) & all_finite(y)
        if self.nan_on_failure:
            return jtu.tree_map(lambda x: jnp.where(failed, jnp.nan, x), f)
        index = jnp.where(
            broken,
            4,
            jnp.where(
                result == dfx.RESULTS.singular,
                0 if self.constraint is None else 3,
                jnp.where(result == dfx.RESULTS.breakdown, 1, 2),
            ),
        )
        return eqx.branched_error_if(f, failed, index, VF_ERRORS)

    def contr(self, t0: RealScalarLike, t1: RealScalarLike, **kwargs) -> RealScalarLike:
        return t1 - t0

    def prod(self, vf: PyTree, control: RealScalarLike) -> PyTree:
        return jtu.tree_map(lambda v: control * v, vf)


def start_checked(terms: PyTree) -> PyTree:
    """`terms` with each `LagrangianTerm` marked as having its start checked: a
    solver's `init` then leaves out the checks it makes by host callback (that the
    start lies on its group and on the constraints, and that a Lagrangian marked
    quadratic keeps its promise there), so that the solve holds no callback and an
    executable of it can be kept between processes. For a caller that checks the
    same start first, with `init` on `terms` themselves (the studies do). The steps
    and the vector field keep their own checks. A marked term traces apart from its
    original in every cache, as its mark is a static field."""

    return _marked(terms, "start_checked", lambda term: True)


def nan_on_failure(terms: PyTree) -> PyTree:
    """`terms` with the vector field of each `LagrangianTerm` that checks its
    evaluations (a constraint's, or a Lagrangian's whose velocity the momentum
    alone does not settle) making NaN where it would raise, with no host callback:
    a Runge-Kutta solve of them compiles its loop whole (several times faster
    steps) and an executable of it can be kept between processes. For a
    caller that runs the same solve of `terms` themselves to learn why it failed
    where this one ends in NaN (a study's tracked solve, beside its timed one). A
    marked term traces apart from its original in every cache, as its mark is a
    static field."""
    return _marked(terms, "nan_on_failure", lambda term: not term.mass_checked)


def _marked(terms: PyTree, field: str, applies: Callable) -> PyTree:
    """`terms` with each `LagrangianTerm` for which `applies(term)` a copy whose
    static `field` is True (`terms` itself where none is)."""
    is_term = lambda x: isinstance(x, LagrangianTerm)
    if not any(
        applies(t) for t in jtu.tree_leaves(terms, is_leaf=is_term) if is_term(t)
    ):
        return terms

    def mark(term):
        if not is_term(term) or not applies(term):
            return term
        marked = copy.copy(term)  # Not through `__init__`, which unmarks it.
        object.__setattr__(marked, field, True)
        return marked

    return jtu.tree_map(mark, terms, is_leaf=is_term)


# Traced once per program: a solve evaluates Hamilton's equations at every stage of
# a Runge-Kutta step and at both ends of each step for dense output, and diffrax
# traces a step up to three times; the nested jit is inlined by XLA.
_hamilton = eqx.filter_jit(
    lambda term, t, y, args, v_guess: term._hamilton(t, y, args, v_guess)
)


class _SeparableVelocity(eqx.Module):
    mass: PyTree

    def __call__(self, t, p, args):
        mass = broadcast_mass(self.mass, p)
        return jtu.tree_map(lambda m, pi: pi / m, mass, p)


class _SeparableForce(eqx.Module):
    lagrangian: AbstractSeparableLagrangian
    force: Callable[..., PyTree] | None = None

    def __call__(self, t, q, args):
        force = generalised_force(self.lagrangian, t, q, None, args)
        if self.force is None:
            return force
        zeros = jtu.tree_map(jnp.zeros_like, q)
        if depends_on_velocity(self.force, t, q, zeros, args):
            raise ValueError(
                "A partitioned pair (dq/dt = f(p), dp/dt = g(q)), as StormerVerlet "
                "and SemiImplicitEuler take, has no velocity in dp/dt, but this force "
                "reads its velocity argument. Integrate "
                "`LagrangianTerm(L, force=...)` with TrapezoidalVI or MidpointVI "
                "instead (the discrete Lagrange-d'Alembert principle)."
            )
        applied = applied_force(self.force, t, q, zeros, args)
        return jtu.tree_map(lambda a, b: a + b, force, applied)


def separable_terms(
    lagrangian: AbstractLagrangian, force: Callable[..., PyTree] | None = None
) -> tuple[dfx.ODETerm, dfx.ODETerm]:
    r"""Hamilton's equations of a separable Lagrangian as diffrax's partitioned pair
    `(ODETerm(dq/dt = M^{-1} p), ODETerm(dp/dt = -dV/dq + F))`, the calling
    convention of `diffrax.SemiImplicitEuler` and [`diffrax_vi.StormerVerlet`][].

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractSeparableLagrangian`][].
    - `force`: an applied force `force(t, q, v, args)` of the positions and time
        alone (it is called with `v = 0`; one that reads `v` raises a `ValueError`
        when traced), or `None`.

    **Returns:**

    A pair of `diffrax.ODETerm`s for `y = (q, p)`.

    **Raises:**

    `ValueError` if the Lagrangian is not separable, or if its mass is singular
    (a mass traced where the terms are built, inside `jax.jit`, is checked when the
    solve runs).
    """
    if not isinstance(lagrangian, AbstractSeparableLagrangian):
        raise ValueError(
            "Partitioned terms exist only for separable Lagrangians "
            "L = 1/2 v^T M v - V(t, q); got "
            f"{type(lagrangian).__name__}. Subclass "
            "`diffrax_vi.AbstractSeparableLagrangian` or use "
            "`diffrax_vi.SeparableLagrangian(potential, mass)`."
        )
    # Checked once, here, rather than at every step: a zero mass would give a NaN
    # position that the momentum, which every step checks, need not see.
    mass, singular = _mass_checked_when_known(lagrangian.mass)
    mass = error_if(mass, singular, SINGULAR_MASS)
    return dfx.ODETerm(_SeparableVelocity(mass)), dfx.ODETerm(
        _SeparableForce(lagrangian, force)
    )


def terms_for(
    solver: dfx.AbstractSolver, lagrangian: Callable[..., ArrayLike] | LagrangianTerm
) -> LagrangianTerm | tuple[dfx.ODETerm, dfx.ODETerm]:
    r"""The terms that `solver` takes for `lagrangian` (or for a
    [`diffrax_vi.LagrangianTerm`][] with its force and constraint), ready for
    `diffrax.diffeqsolve(terms, solver, ...)` on the state `y = (q, p)`.

    Solvers of partitioned systems ([`diffrax_vi.StormerVerlet`][],
    `diffrax.SemiImplicitEuler`, compositions of them) take Hamilton's equations as
    the pair [`diffrax_vi.separable_terms`][]; every other solver (the variational
    solvers of this package, diffrax's Runge–Kutta solvers, wrappers such as
    `diffrax.HalfSolver`) takes the [`diffrax_vi.LagrangianTerm`][].

    **Arguments:**

    - `solver`: any diffrax solver.
    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][], any callable
        `L(t, q, v, args)`, or a `LagrangianTerm`.

    **Returns:**

    A `LagrangianTerm`, or a pair of `diffrax.ODETerm`s.

    **Raises:**

    `ValueError` if the solver needs a partitioned pair and the Lagrangian is not an
    [`diffrax_vi.AbstractSeparableLagrangian`][] or the term has a constraint, or if
    the solver takes some other structure of terms.
    """
    structure = solver.term_structure
    term = lagrangian if isinstance(lagrangian, LagrangianTerm) else None
    if term is not None:
        lagrangian = term.lagrangian
    if isinstance(structure, tuple) and len(structure) == 2:
        lagrangian = as_lagrangian(lagrangian)
        if not is_euclidean(lagrangian.space):
            raise ValueError(
                f"{type(solver).__name__} integrates a partitioned system in a vector "
                "space (dq/dt = M^-1 p), and this Lagrangian lives on a group. Use "
                "MidpointVI or TrapezoidalVI (or a Composition of them) on the "
                "LagrangianTerm."
            )
        if term is not None and term.constraint is not None:
            raise ValueError(
                f"{type(solver).__name__} integrates a partitioned system, which "
                "cannot keep holonomic constraints. Use TrapezoidalVI (RATTLE for a "
                "separable Lagrangian) or MidpointVI on the LagrangianTerm."
            )
        if not isinstance(lagrangian, AbstractSeparableLagrangian):
            raise ValueError(
                "Partitioned terms exist only for separable Lagrangians "
                "L = 1/2 v^T M v - V(t, q), and "
                f"{type(solver).__name__} integrates a partitioned system "
                f"(dq/dt = f(p), dp/dt = g(q)); got {type(lagrangian).__name__}. "
                "Subclass "
                "`diffrax_vi.AbstractSeparableLagrangian`, use "
                "`diffrax_vi.SeparableLagrangian(potential, mass)`, or choose a "
                "solver of a LagrangianTerm (e.g. `diffrax_vi.TrapezoidalVI()`)."
            )
        return separable_terms(lagrangian, None if term is None else term.force)
    if isinstance(structure, type) and issubclass(structure, dfx.AbstractTerm):
        return LagrangianTerm(lagrangian) if term is None else term
    raise ValueError(
        f"{type(solver).__name__} takes terms of structure {structure}, which a "
        "Lagrangian does not provide: it gives one LagrangianTerm, or for separable "
        "Lagrangians the pair (ODETerm(dq/dt), ODETerm(dp/dt))."
    )
