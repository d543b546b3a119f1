from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import ArrayLike, PyTree

from ._custom_types import Args, RealScalarLike
from ._lagrangian import (
    AbstractLagrangian,
    AbstractSeparableLagrangian,
    as_lagrangian,
    broadcast_mass,
    generalised_force,
    mass_regular,
    velocity,
)
from ._misc import all_finite, split_state


VF_ERRORS = (
    "The Lagrangian is degenerate at this state: d^2L/dv^2 is singular to working "
    "precision, so the velocity is not determined by the momentum. Make the kinetic "
    "energy positive definite in every velocity component (a zero mass, or a "
    "velocity entering L linearly, is degenerate).",
    "Newton's method could not invert the Legendre map p = dL/dv at this state, "
    "though d^2L/dv^2 is regular there: the momentum may lie outside the map's range "
    "(|p| has no velocity, e.g. beyond the speed limit of a relativistic L). Check "
    "y0 and the step size.",
    "The Lagrangian or its derivatives gave NaN or inf at a finite state: check its "
    "parameters and args.",
)


class LagrangianTerm(dfx.AbstractTerm):
    r"""A Lagrangian as a diffrax term on the phase-space state $y = (q, p)$.

    Its vector field is Hamilton's equations,
    $\dot q = v(q, p)$, $\dot p = \partial L / \partial q\,(t, q, v(q, p))$, with $v$
    the inverse Legendre map ([`diffrax_vi.velocity`][]). So every diffrax ODE solver
    (`Tsit5`, `Dopri8`, `Kvaerno5`, ...) integrates the same term as the variational
    solvers of this package, which instead read the Lagrangian itself.

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
        Runge–Kutta solve would report as a success.
    """

    lagrangian: AbstractLagrangian

    def __init__(self, lagrangian: Callable[..., ArrayLike]):
        """**Arguments:**

        - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][], any `eqx.Module`
            with `__call__(t, q, v, args) -> scalar`, or a plain callable of that form.
        """
        self.lagrangian = as_lagrangian(lagrangian)

    def hamilton(
        self,
        t: RealScalarLike,
        y: PyTree,
        args: Args,
        *,
        v_guess: PyTree | None = None,
    ) -> tuple[tuple[PyTree, PyTree], dfx.RESULTS]:
        r"""Hamilton's equations $(\dot q, \dot p) = (v, \partial L/\partial q)$ at
        $y = (q, p)$, and whether the Legendre map could be inverted there (from the
        guess `v_guess` for a general Lagrangian)."""
        q, p = split_state(y, "y")
        v, result = velocity(self.lagrangian, t, y, args, v_guess=v_guess)
        return (v, generalised_force(self.lagrangian, t, q, v, args)), result

    def vf(self, t: RealScalarLike, y: PyTree, args: Args) -> PyTree:
        f, result = self.hamilton(t, y, args)
        # A vector field cannot return a RESULTS: each cause raises its own message.
        index = jnp.where(
            result == dfx.RESULTS.singular,
            0,
            jnp.where(result == dfx.RESULTS.breakdown, 1, 2),
        )
        return eqx.branched_error_if(
            f,
            (result != dfx.RESULTS.successful) & all_finite(y),
            index,
            VF_ERRORS,
        )

    def contr(self, t0: RealScalarLike, t1: RealScalarLike, **kwargs) -> RealScalarLike:
        return t1 - t0

    def prod(self, vf: PyTree, control: RealScalarLike) -> PyTree:
        return jtu.tree_map(lambda v: control * v, vf)


class _SeparableVelocity(eqx.Module):
    mass: PyTree

    def __call__(self, t, p, args):
        mass = broadcast_mass(self.mass, p)
        return jtu.tree_map(lambda m, pi: pi / m, mass, p)


class _SeparableForce(eqx.Module):
    lagrangian: AbstractSeparableLagrangian

    def __call__(self, t, q, args):
        return generalised_force(self.lagrangian, t, q, None, args)


def separable_terms(
    lagrangian: AbstractLagrangian,
) -> tuple[dfx.ODETerm, dfx.ODETerm]:
    r"""Hamilton's equations of a separable Lagrangian as diffrax's partitioned pair
    `(ODETerm(dq/dt = M^{-1} p), ODETerm(dp/dt = -dV/dq))`, the calling convention of
    `diffrax.SemiImplicitEuler` and [`diffrax_vi.StormerVerlet`][].

    **Arguments:**

    - `lagrangian`: an [`diffrax_vi.AbstractSeparableLagrangian`][].

    **Returns:**

    A pair of `diffrax.ODETerm`s for `y = (q, p)`.

    **Raises:**

    `ValueError` if the Lagrangian is not separable.
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
    mass = jtu.tree_map(jnp.asarray, lagrangian.mass)
    mass = eqx.error_if(
        mass,
        ~mass_regular(mass, mass),
        "The mass of this separable Lagrangian is singular: an entry is zero (or "
        "below eps times the largest), or not finite. Every degree of freedom needs "
        "a positive mass.",
    )
    return dfx.ODETerm(_SeparableVelocity(mass)), dfx.ODETerm(
        _SeparableForce(lagrangian)
    )


def terms_for(
    solver: dfx.AbstractSolver, lagrangian: Callable[..., ArrayLike]
) -> LagrangianTerm | tuple[dfx.ODETerm, dfx.ODETerm]:
    r"""The terms that `solver` takes for `lagrangian`, ready for
    `diffrax.diffeqsolve(terms, solver, ...)` on the state `y = (q, p)`.

    Solvers of partitioned systems ([`diffrax_vi.StormerVerlet`][],
    `diffrax.SemiImplicitEuler`, compositions of them) take Hamilton's equations as
    the pair [`diffrax_vi.separable_terms`][]; every other solver (the variational
    solvers of this package, diffrax's Runge–Kutta solvers, wrappers such as
    `diffrax.HalfSolver`) takes the [`diffrax_vi.LagrangianTerm`][].

    **Arguments:**

    - `solver`: any diffrax solver.
    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][] or any callable
        `L(t, q, v, args)`.

    **Returns:**

    A `LagrangianTerm`, or a pair of `diffrax.ODETerm`s.

    **Raises:**

    `ValueError` if the solver needs a partitioned pair and the Lagrangian is not an
    [`diffrax_vi.AbstractSeparableLagrangian`][], or if the solver takes some other
    structure of terms.
    """
    structure = solver.term_structure
    if isinstance(structure, tuple) and len(structure) == 2:
        lagrangian = as_lagrangian(lagrangian)
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
        return separable_terms(lagrangian)
    if isinstance(structure, type) and issubclass(structure, dfx.AbstractTerm):
        return LagrangianTerm(lagrangian)
    raise ValueError(
        f"{type(solver).__name__} takes terms of structure {structure}, which a "
        "Lagrangian does not provide: it gives one LagrangianTerm, or for separable "
        "Lagrangians the pair (ODETerm(dq/dt), ODETerm(dp/dt))."
    )
