"""Forced, controlled and constrained systems: each models only what it needs (a
force, a control input through `args`, holonomic constraints)."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._lagrangian import (
    AbstractQuadraticLagrangian,
    AbstractSeparableLagrangian,
    inverse_legendre,
    momentum,
)
from ._one_dof import DuffingLagrangian, parameter, PendulumLagrangian
from ._scene import agm, check_count, check_positive, entries, GENERAL_SOLVERS, Scene


class DampedDrive(eqx.Module):
    r"""Linear damping and a harmonic drive, $F = -\delta v + \gamma\cos\omega t$."""

    damping: Float[Array, ""] = parameter(0.3)
    amplitude: Float[Array, ""] = parameter(0.5)
    frequency: Float[Array, ""] = parameter(1.2)

    def __call__(self, t, q, v, args):
        return -self.damping * v + self.amplitude * jnp.cos(self.frequency * t)


def forced_duffing(
    damping: float = 0.3, amplitude: float = 0.5, frequency: float = 1.2
) -> Scene:
    r"""The damped, driven Duffing oscillator
    $\ddot q + \delta\dot q - q + q^3 = \gamma\cos\omega t$: Hirani's (2000, §5.3)
    double well with the force [`diffrax_vi.scenes.DampedDrive`][]. At the defaults
    ($\delta = 0.3$, $\gamma = 0.5$, $\omega = 1.2$) its motion settles on a strange
    attractor. From rest at $q = 1$; time scale one drive period $2\pi/\omega$.
    Nothing is conserved: a study checks the energy balance
    $E(t) - E(0) - W(t)$ instead."""
    check_positive("forced_duffing", frequency=frequency)
    return Scene(
        name="forced_duffing",
        # Partitioned solvers cannot tell the applied force's work apart.
        solvers=GENERAL_SOLVERS,
        lagrangian=DuffingLagrangian(),
        y0=(jnp.array(1.0), jnp.array(0.0)),
        period=2 * math.pi / frequency,
        force=DampedDrive(damping, amplitude, frequency),
    )


class CartesianPendulumLagrangian(AbstractSeparableLagrangian):
    r"""A point mass in uniform gravity in the plane, $L = \tfrac12 m|v|^2 - m g y$,
    $q = (x, y)$; [`diffrax_vi.scenes.Circle`][] keeps it on the pendulum's circle."""

    g: Float[Array, ""] = parameter(1.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        return self.mass * self.g * q[1]


class Circle(eqx.Module):
    r"""The holonomic constraint $|q|^2 - \ell^2 = 0$."""

    length: Float[Array, ""] = parameter(1.0)

    def __call__(self, t, q, args):
        return jnp.sum(q**2) - self.length**2


def cartesian_pendulum(amplitude: float = 2.0) -> Scene:
    r"""The pendulum of [`diffrax_vi.scenes.pendulum`][] in Cartesian coordinates: a
    point mass constrained to the unit circle, released from rest at the angle
    `amplitude` from the downward vertical. Period $2\pi/\operatorname{agm}(1,
    \cos(q_0/2))$, as for the angle; its angle $\operatorname{atan2}(x, -y)$ follows
    the angle pendulum's."""
    if not 0 < amplitude < math.pi:
        raise ValueError(
            f"cartesian_pendulum(amplitude) needs 0 < amplitude < pi; got {amplitude}."
        )
    q0 = jnp.array([math.sin(amplitude), -math.cos(amplitude)])
    lagrangian, circle = CartesianPendulumLagrangian(), Circle()
    return Scene(
        name="cartesian_pendulum",
        solvers=GENERAL_SOLVERS,
        lagrangian=lagrangian,
        y0=(q0, jnp.zeros(2)),
        period=2 * math.pi / agm(1.0, math.cos(amplitude / 2)),
        invariants=ConstraintResiduals(lagrangian, circle).invariants(),
        constraint=circle,
    )


class FourBarLagrangian(AbstractQuadraticLagrangian):
    r"""Three uniform rods of a four-bar linkage (crank, coupler, rocker; lengths
    $\ell_1, \ell_2, \ell_3$, masses $m_1, m_2, m_3$) in gravity $g$, in the absolute
    angles $q = (\theta_1, \theta_2, \theta_3)$ of the rods: the crank turns about the
    origin, the rocker about $(\ell_0, 0)$, and the coupler joins their free ends.
    With $e(\theta) = (\cos\theta, \sin\theta)$ the coupler's centre moves at
    $\ell_1\dot\theta_1 e'(\theta_1) + \tfrac12\ell_2\dot\theta_2 e'(\theta_2)$, so
    the mass matrix depends on $\theta_1 - \theta_2$. Not separable; the closure of the
    loop is the constraint [`diffrax_vi.scenes.LoopClosure`][]."""

    l1: Float[Array, ""] = parameter(0.4)
    l2: Float[Array, ""] = parameter(1.2)
    l3: Float[Array, ""] = parameter(1.0)
    m1: Float[Array, ""] = parameter(1.0)
    m2: Float[Array, ""] = parameter(1.0)
    m3: Float[Array, ""] = parameter(1.0)
    g: Float[Array, ""] = parameter(1.0)

    def __call__(self, t, q, v, args):
        l1, l2, l3, m1, m2, m3 = self.l1, self.l2, self.l3, self.m1, self.m2, self.m3
        # In whole vectors where the terms allow (see `scenes._scene.entries`).
        (q1, q2, _), (v1, v2, _) = entries(q), entries(v)
        inertia = jnp.stack([(m1 / 3 + m2) * l1**2, m2 * l2**2 / 3, m3 * l3**2 / 3])
        coupling = m2 * l1 * l2 * v1 * v2 * jnp.cos(q1 - q2)
        kinetic = 0.5 * (jnp.sum(inertia * v**2) + coupling)
        moments = jnp.stack([(m1 / 2 + m2) * l1, m2 * l2 / 2, m3 * l3 / 2])
        return kinetic - self.g * jnp.sum(moments * jnp.sin(q))


class LoopClosure(eqx.Module):
    r"""The two closure constraints of a four-bar linkage whose ground link runs from
    the origin to $(\ell_0, 0)$:
    $\ell_1 e(\theta_1) + \ell_2 e(\theta_2) - \ell_3 e(\theta_3) - (\ell_0, 0) = 0$."""

    l0: Float[Array, ""] = parameter(1.0)
    l1: Float[Array, ""] = parameter(0.4)
    l2: Float[Array, ""] = parameter(1.2)
    l3: Float[Array, ""] = parameter(1.0)

    def __call__(self, t, q, args):
        arms = jnp.stack([self.l1, self.l2, -self.l3])
        x = jnp.sum(arms * jnp.cos(q)) - self.l0
        return jnp.stack([x, jnp.sum(arms * jnp.sin(q))])


def four_bar(crank_speed: float = 3.0) -> Scene:
    r"""A crank–rocker four-bar linkage (ground 1, crank 0.4, coupler 1.2, rocker 1;
    Grashof: the crank turns fully and the rocker swings), a closed kinematic chain of
    one degree of freedom written as three angles and two closure constraints. From
    the crank upright, $\theta_1 = \pi/2$, turning at `crank_speed`; the other angles
    and velocities close the loop. Time scale $2\pi/$`crank_speed`. Conserves the
    energy."""
    check_positive("four_bar", crank_speed=crank_speed)
    lagrangian = FourBarLagrangian()
    closure = LoopClosure()
    l0, l1, l2, l3 = (
        float(x) for x in (closure.l0, closure.l1, closure.l2, closure.l3)
    )
    a = np.array([0.0, l1])  # the crank's tip at theta_1 = pi/2
    d = np.array([l0, 0.0])  # the rocker's pivot
    dist = np.linalg.norm(d - a)
    along = (l2**2 - l3**2 + dist**2) / (2 * dist)
    across = math.sqrt(l2**2 - along**2)
    unit = (d - a) / dist
    b = a + along * unit + across * np.array([-unit[1], unit[0]])  # the upper joint
    q0 = jnp.array(
        [math.pi / 2, math.atan2(*(b - a)[::-1]), math.atan2(*(b - d)[::-1])]
    )
    jacobian = jax.jacfwd(lambda q: closure(0.0, q, None))(q0)
    rest = jnp.linalg.solve(jacobian[:, 1:], -jacobian[:, 0] * crank_speed)
    v0 = jnp.concatenate([jnp.array([crank_speed]), rest])
    return Scene(
        name="four_bar",
        solvers=GENERAL_SOLVERS,
        lagrangian=lagrangian,
        y0=(q0, momentum(lagrangian, 0.0, q0, v0)),
        period=2 * math.pi / crank_speed,
        invariants=ConstraintResiduals(lagrangian, closure).invariants(),
        constraint=closure,
    )


class ConstraintResiduals(eqx.Module):
    r"""A constrained scene's invariants: the constraint values $g(q)$ and the hidden
    constraint $G(q)\,v(q, p)$, both zero along the exact motion."""

    lagrangian: AbstractQuadraticLagrangian
    constraint: eqx.Module

    def invariants(self) -> dict:
        return {"constraint": self.values, "hidden_constraint": self.hidden}

    def values(self, t, y, args):
        return self.constraint(t, y[0], args)

    def hidden(self, t, y, args):
        q, p = y
        v, _ = inverse_legendre(self.lagrangian, t, (q, p), args, None, promise="nan")
        return jax.jvp(lambda x: self.constraint(t, x, args), (q,), (v,))[1]


class ControlTorque(eqx.Module):
    r"""A bounded torque from a control sequence, and viscous damping:
    $F = u_{\max}\tanh(w_k) - c\,v$ for $t$ in the $k$-th of the `len(w)` equal
    intervals of $[0, T]$, where `args = w` (unbounded control variables, so an
    optimiser needs no constraint)."""

    horizon: Float[Array, ""] = parameter(10.0)
    max_torque: Float[Array, ""] = parameter(0.5)
    damping: Float[Array, ""] = parameter(0.05)

    def __call__(self, t, q, v, args):
        n = args.shape[0]
        k = jnp.clip(jnp.floor(t / self.horizon * n).astype(jnp.int32), 0, n - 1)
        return self.max_torque * jnp.tanh(args[k]) - self.damping * v


def swing_up(controls: int = 20, horizon: float = 10.0) -> Scene:
    r"""A damped pendulum hanging at rest, driven by a torque bounded by half its
    weight (so it must swing to get up; [`diffrax_vi.scenes.ControlTorque`][]) over
    `controls` equal intervals of `[0, horizon]`. `args` is the control sequence
    (zero by default): differentiate a solve with respect to it to find the controls
    that bring the pendulum upright, $q = \pi$, at `horizon` (see
    `examples/swing_up.py`). Time scale $2\pi$."""
    check_count("swing_up", controls=controls)
    check_positive("swing_up", horizon=horizon)
    return Scene(
        name="swing_up",
        lagrangian=PendulumLagrangian(),
        y0=(jnp.array(0.0), jnp.array(0.0)),
        period=2 * math.pi,
        force=ControlTorque(horizon),
        args=jnp.zeros(controls),
    )
