r"""The Lie group variational integrator of Lee, Leok & McClamroch for a rigid body
with constant inertia, in its Cayley form.

For $L = \tfrac12\Omega^\top J\Omega - V(R)$ the discrete Lagrangian

$$L_d(R_k, R_{k+1}) = \tfrac1h\,\mathrm{tr}\big[(I - F_k)J_d\big]
- \tfrac h2 V(R_k) - \tfrac h2 V(R_{k+1}),\qquad F_k = R_k^\top R_{k+1},\quad
J_d = \tfrac12\mathrm{tr}(J)\,I - J,$$

gives the discrete Euler–Poincaré equations
$h\,(\Pi_k + \tfrac h2 M_k)^\wedge = F_k J_d - J_d F_k^\top$ and
$\Pi_{k+1} = F_k^\top(\Pi_k + \tfrac h2 M_k) + \tfrac h2 M_{k+1}$, with $M$ the torque
$-\partial^L_R V$. With $F = \mathrm{cay}(f) = I + \frac{2}{1 + |f|^2}(\hat f +
\hat f^2)$ the first is three equations in $f$,

$$r(f) = 2Jf - g - g \times f - (f\cdot g)\,f = 0,\qquad
g = h\Pi_k + \tfrac{h^2}2 M_k,$$

solved by Newton's method (its Jacobian $2J - \hat g - (f\cdot g)I - f g^\top$ is
$2J$ at $f = 0$). The position moves by the Cayley map, $R_{k+1} = R_k F_k$, and the
momentum update is explicit. The kinetic part is exact for the Cayley parameter, so a
free body's energy $\tfrac12\Pi^\top J^{-1}\Pi$ is kept to round-off, as its Casimir
$|\Pi|$ is; the method is symmetric, so [`diffrax_vi.Composition`][] raises its order.
"""

from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool

from .._lagrangian import AbstractRigidBodyLagrangian, mass_regular
from .._misc import all_finite
from .._root_finders import known_root, Newton, solve
from .._so3 import cross, SO3
from .._space import left_gradient, retract, transport
from .base import (
    AbstractComposableSolver,
    AbstractSymplecticSolver,
    AbstractVariationalSolver,
    after_jump,
    MethodStep,
    StepInputs,
)
from .unknowns import KnownRoot


# The step's own retraction: R_{k+1} = R_k cay(f) = R_k tau(2 f).
_CAYLEY = SO3(retraction="cayley")


class LGVIState(eqx.Module):
    """The torque at the end of the last step (the next step's $M_k$), the mean
    angular velocities $2f/h$ of the last two steps (the next guess is their
    extrapolation: a velocity, unlike $f$, does not change with the step size, which
    a composition's substeps do), and whether the inertia is invertible (checked
    once, at the start)."""

    torque: Array
    last: Array
    before_last: Array
    regular: Bool[Array, ""]

    def __init__(self, torque, last, before_last, regular):
        self.torque = torque
        # Guesses (`unknowns.Unknowns`): held without a derivative.
        self.last, self.before_last = lax.stop_gradient((last, before_last))
        self.regular = regular


def _rigid_body(step: StepInputs) -> AbstractRigidBodyLagrangian:
    term = step.term
    if not isinstance(term.lagrangian, AbstractRigidBodyLagrangian):
        raise ValueError(
            "LGVI steps a rigid body with constant inertia, L = 1/2 Omega^T J Omega "
            f"- V(R), and needs a Lagrangian that declares it; got "
            f"{type(term.lagrangian).__name__}. Subclass "
            "`diffrax_vi.AbstractRigidBodyLagrangian` (`inertia` and `potential`), "
            "or use MidpointVI or TrapezoidalVI, which take any Lagrangian on SO3."
        )
    if term.force is not None or term.constraint is not None:
        raise ValueError(
            "LGVI takes a rigid body without applied forces or constraints; for "
            "those use MidpointVI or TrapezoidalVI."
        )
    return term.lagrangian


def _torque(step: StepInputs, t, R) -> Array:
    r"""$M = -\partial^L_R V$, the body torque of the potential."""
    lagrangian = _rigid_body(step)
    return left_gradient(
        lagrangian.space, lambda _R: -lagrangian.potential(t, _R, step.args), R
    )


def _inertia(step: StepInputs) -> Array:
    return jnp.asarray(_rigid_body(step).inertia, step.dtype)


class LGVI(
    AbstractVariationalSolver, AbstractSymplecticSolver, AbstractComposableSolver
):
    r"""Lie group variational integrator of Lee, Leok & McClamroch for a rigid body.

    2nd order symmetric symplectic variational integrator on SO(3). One Newton solve
    of three unknowns per step, one torque evaluation per step. Keeps a free body's
    energy and Casimir $|\Pi|$ to round-off and the attitude on SO(3). Takes an
    [`diffrax_vi.AbstractRigidBodyLagrangian`][] ($L = \tfrac12\Omega^\top J\Omega
    - V(R)$, constant $J$) without forces or constraints. Fixed step sizes only.
    Cubic Hermite interpolation for dense output.

    Discrete Lagrangian, with $F_k = R_k^\top R_{k+1}$ and $J_d = \tfrac12
    \mathrm{tr}(J) I - J$:

    $$L_d(R_k, R_{k+1}) = \tfrac1h\,\mathrm{tr}\big[(I - F_k)J_d\big]
    - \tfrac h2\big[V(R_k) + V(R_{k+1})\big],$$

    stepped on $y = (R, \Pi)$: $F_k$ from $h(\Pi_k + \tfrac h2 M_k)^\wedge = F_k J_d
    - J_d F_k^\top$ in its Cayley parameters, then $R_{k+1} = R_k F_k$ and $\Pi_{k+1}
    = F_k^\top(\Pi_k + \tfrac h2 M_k) + \tfrac h2 M_{k+1}$, $M = -\partial^L_R V$ the
    torque.

    ??? cite "References"

        ```bibtex
        @article{lee2007lie,
            title={Lie group variational integrators for the full body problem},
            author={Lee, Taeyoung and Leok, Melvin and McClamroch, N. Harris},
            journal={Computer Methods in Applied Mechanics and Engineering},
            volume={196},
            number={29--30},
            pages={2907--2924},
            year={2007},
        }
        @article{lee2005lie,
            title={A {L}ie group variational integrator for the attitude dynamics of
                   a rigid body with applications to the 3{D} pendulum},
            author={Lee, Taeyoung and Leok, Melvin and McClamroch, N. Harris},
            booktitle={Proceedings of the 2005 IEEE Conference on Control
                       Applications},
            pages={962--967},
            year={2005},
        }
        ```
    """

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True

    symmetric: ClassVar[bool] = True

    def order(self, terms):
        return 2

    def method_init(self, step: StepInputs) -> LGVIState:
        inertia = _inertia(step)
        omega = step.p0 / inertia
        return LGVIState(
            _torque(step, step.t0, step.q0),
            omega,
            omega,
            mass_regular(inertia, step.p0),
        )

    def method_step(
        self, step: StepInputs, state: LGVIState, made_jump: Bool[ArrayLike, ""]
    ) -> MethodStep:
        inertia = _inertia(step)
        h, pi0 = step.h, step.p0
        torque0 = after_jump(
            made_jump, lambda: _torque(step, step.t0, step.q0), state.torque
        )
        kicked = pi0 + 0.5 * h * torque0
        g = h * kicked

        def residual(f):
            gf, fg = cross(g, f), jnp.sum(f * g)
            r = 2 * inertia * f - g - gf - fg * f
            s = 2 * inertia * jnp.abs(f) + jnp.abs(g) + jnp.abs(gf) + jnp.abs(fg * f)
            return r, s

        # Second-order extrapolation of the last two steps; after a jump, the
        # velocity at the start.
        omega = jnp.where(made_jump, pi0 / inertia, 2 * state.last - state.before_last)
        guess = 0.5 * h * omega
        if isinstance(self.root_finder, KnownRoot):
            # The step's velocity 2f/h, known from its inverse step's.
            solved = known_root(residual, 0.5 * h * self.root_finder.root)
        else:
            root_finder = Newton() if self.root_finder is None else self.root_finder
            solved = solve(residual, guess, root_finder, self.root_find_max_steps)
        f = solved.value
        dq = 2 * f
        q1 = retract(_CAYLEY, step.q0, dq)
        torque1 = _torque(step, step.t1, q1)
        dp = transport(_CAYLEY, dq, kicked) + 0.5 * h * torque1 - pi0
        result = dfx.RESULTS.where(state.regular, solved.result, dfx.RESULTS.singular)
        # A NaN or inf start is `nonfinite`, whatever the solve says of it: checked
        # on twelve numbers without a branch (a conditional costs the loop more).
        result = dfx.RESULTS.where(
            all_finite((step.q0, step.p0)), result, dfx.RESULTS.nonfinite
        )
        v = dq / h
        new = LGVIState(torque1, v, state.last, state.regular)
        return MethodStep(dq, dp, v, new, result, space=_CAYLEY, q1=q1)

    def root_of_inverse(self, terms, solver_state):
        # The inverse step's Cayley parameter is -f, with -h: the same velocity.
        return solver_state.method.last


LGVI.__init__.__doc__ = """**Arguments:**

- `root_finder`: how the three equations of a step are solved: `None` (the default)
    is [`diffrax_vi.Newton`][]; or any `optimistix.AbstractRootFinder` (given the
    residual relative to its largest term).
- `root_find_max_steps`: iterations after which a step is reported as failed
    (`RESULTS.nonlinear_max_steps_reached`): usually a sign that the step is too large.
- `compensated`: compensated (Kahan) summation of the momentum's increments (default).
"""
