r"""Rigid bodies on SO(3): the attitude `R` a rotation matrix, the state
`y = (R, Pi)` with `Pi` the body angular momentum."""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lagrangian import AbstractLagrangian, AbstractRigidBodyLagrangian
from .._so3 import matmul, matvec, rmatvec, SO3
from .._space import Euclidean
from ._scene import check_positive, GENERAL_SOLVERS, RIGID_BODY_SOLVERS, Scene


class RigidBodyLagrangian(AbstractRigidBodyLagrangian):
    r"""$L(R, \Omega) = \tfrac12\Omega^\top J\Omega - m g\,e_3\cdot R\chi$: a rigid body
    with principal moments of inertia $J$ (diagonal), in uniform gravity acting at the
    centre of mass $\chi$ (body frame). A body in no field is a
    [`diffrax_vi.scenes.FreeRigidBodyLagrangian`][]."""

    inertia: Float[Array, " 3"]
    centre: Float[Array, " 3"]
    weight: Float[Array, ""]

    def potential(self, t, R, args):
        return self.weight * jnp.sum(R[2] * self.centre)


class FreeRigidBodyLagrangian(AbstractRigidBodyLagrangian):
    r"""$L(\Omega) = \tfrac12\Omega^\top J\Omega$: a rigid body in no field, with
    principal moments of inertia $J$ (diagonal). With no potential, $L$ does not
    read the attitude, so no solver differentiates through it, and its solves
    compile sooner than with a zero weight in
    [`diffrax_vi.scenes.RigidBodyLagrangian`][] (`benchmarks/first_call.py`)."""

    inertia: Float[Array, " 3"]

    def potential(self, t, R, args):
        return jnp.zeros((), R.dtype)


def casimir(t, y, args) -> Array:
    r"""$|\Pi|$, conserved by the free body's Euler equations."""
    return jnp.sqrt(jnp.sum(y[1] ** 2))


def orthogonality(t, y, args) -> Array:
    r"""$\|R^\top R - I\|_{\max}$: zero on SO(3)."""
    R = y[0]
    return jnp.max(jnp.abs(matmul(R.T, R) - jnp.eye(3, dtype=R.dtype)))


def spatial_momentum(t, y, args) -> Array:
    r"""The spatial angular momentum $R\Pi$."""
    return matvec(y[0], y[1])


def free_rigid_body(
    inertia: tuple[float, float, float] = (2.0, 1.0, 2.0 / 3.0),
    angle: float = 1.1,
) -> Scene:
    r"""A free rigid body: Euler's equations $\dot\Pi = \Pi \times J^{-1}\Pi$ with
    $\dot R = R\hat\Omega$, from $R_0 = I$ and $\Pi_0 = (\cos a, 0, \sin a)$ (the data
    of GeometricProblems.jl: $J = (2, 1, 2/3)$, $a = 1.1$). Conserved: the energy, the
    Casimir $|\Pi|$, the spatial angular momentum $R\Pi$; the attitude stays on
    SO(3)."""
    check_positive("free_rigid_body", inertia=inertia)
    lagrangian = FreeRigidBodyLagrangian(jnp.asarray(inertia, float))
    pi0 = jnp.array([jnp.cos(angle), 0.0, jnp.sin(angle)])
    period = 2 * jnp.pi / float(jnp.linalg.norm(pi0 / lagrangian.inertia))
    return Scene(
        name="free_rigid_body",
        solvers=RIGID_BODY_SOLVERS,
        lagrangian=lagrangian,
        y0=(jnp.eye(3), pi0),
        period=float(period),
        invariants=dict(
            casimir=casimir,
            spatial_momentum=spatial_momentum,
            orthogonality=orthogonality,
        ),
    )


def heavy_top(
    inertia: tuple[float, float, float] = (1.0, 1.0, 0.4),
    weight: float = 1.0,
    tilt: float = 0.3,
    spin: float = 10.0,
) -> Scene:
    r"""The Lagrange top: a symmetric body ($J_1 = J_2$) spinning about its axis, its
    fixed point at the origin and its centre of mass on the axis, $\chi = e_3$, under
    the weight $m g$. Starts tilted by `tilt` about $e_1$ with body angular momentum
    $\Pi_0 = (0, 0, J_3\,\text{spin})$. Conserved: the energy, the vertical spatial
    angular momentum $e_3\cdot R\Pi$ (rotations about the vertical) and the spin $\Pi_3$
    (rotations about the axis)."""
    check_positive("heavy_top", inertia=inertia, spin=spin)
    if inertia[0] != inertia[1]:
        # The spin Pi_3 is conserved only for a symmetric body: with J1 != J2 the
        # study would table real physics as every solver's error.
        raise ValueError(
            f"heavy_top(inertia=...) is the Lagrange top, a symmetric body: it needs "
            f"J1 = J2, whose spin Pi_3 it lists as conserved; got {inertia!r}. For "
            "an asymmetric body on a pivot use pendulum_3d(inertia=..., centre=...)."
        )
    lagrangian = RigidBodyLagrangian(
        jnp.asarray(inertia, float), jnp.array([0.0, 0.0, 1.0]), jnp.asarray(weight)
    )
    c, s = jnp.cos(tilt), jnp.sin(tilt)
    R0 = jnp.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    pi0 = jnp.array([0.0, 0.0, inertia[2] * spin])
    return Scene(
        name="heavy_top",
        solvers=RIGID_BODY_SOLVERS,
        lagrangian=lagrangian,
        y0=(R0, pi0),
        period=2 * float(jnp.pi) / spin,
        invariants=dict(
            vertical_momentum=vertical_momentum,
            spin=body_spin,
            orthogonality=orthogonality,
        ),
    )


def body_spin(t, y, args) -> Array:
    r"""$\Pi_3$, the spin about the top's axis: conserved by a symmetric top."""
    return y[1][2]


def body_orthogonality(t, y, args) -> Array:
    """`orthogonality` of the body of a state `((x, R), (p, Pi))` on R^3 x SO(3)."""
    return orthogonality(t, (y[0][1], y[1][1]), args)


def vertical_momentum(t, y, args) -> Array:
    r"""$e_3\cdot R\Pi$, the spatial angular momentum about the vertical: conserved
    when gravity is the only force, as rotations about the vertical are a symmetry."""
    return jnp.sum(y[0][2] * y[1])


def pendulum_3d(
    inertia: tuple[float, float, float] = (1.0, 2.0, 2.5),
    centre: tuple[float, float, float] = (0.3, 0.2, -1.0),
    weight: float = 1.0,
    omega: tuple[float, float, float] = (1.0, 0.5, 2.0),
) -> Scene:
    r"""The 3D pendulum of Lee, Leok & McClamroch (2005): an asymmetric rigid body on
    a fixed frictionless pivot, its centre of mass $\chi$ off every principal axis,
    under the weight $m g$. `inertia` are the principal moments about the pivot.
    Starts at $R_0 = I$, hanging with $\chi$ tilted from the vertical, with body
    angular velocity $\Omega_0$ = `omega`; its motion is chaotic. The parameters are
    this package's choice, not the paper's. Conserved: the energy and the vertical
    spatial angular momentum $e_3\cdot R\Pi$; the attitude stays on SO(3). The
    period is that of small swings about the first principal axis,
    $2\pi\sqrt{J_1/(m g|\chi|)}$."""
    check_positive("pendulum_3d", inertia=inertia, weight=weight)
    if not any(c != 0 for c in centre):
        raise ValueError(
            "pendulum_3d(centre=...) needs a centre of mass off the pivot (its "
            f"period is that of small swings about it); got {centre!r}. A body "
            "supported at its centre of mass is free_rigid_body."
        )
    lagrangian = RigidBodyLagrangian(
        jnp.asarray(inertia, float), jnp.asarray(centre, float), jnp.asarray(weight)
    )
    pi0 = lagrangian.inertia * jnp.asarray(omega, float)
    arm = float(jnp.linalg.norm(lagrangian.centre))
    return Scene(
        name="pendulum_3d",
        solvers=RIGID_BODY_SOLVERS,
        lagrangian=lagrangian,
        y0=(jnp.eye(3), pi0),
        period=2 * float(jnp.pi) * (inertia[0] / (weight * arm)) ** 0.5,
        invariants=dict(
            vertical_momentum=vertical_momentum,
            orthogonality=orthogonality,
        ),
    )


class SatelliteLagrangian(AbstractLagrangian):
    r"""A rigid satellite in a central field on $\mathbb R^3 \times SO(3)$,
    `q = (x, R)`:

    $$L = \tfrac12 m|\dot x|^2 + \tfrac12\Omega^\top J\Omega + \frac{\mu m}{r}
    + \frac{\mu}{2r^3}\big(\mathrm{tr}\,J - 3\,\hat r^\top R J R^\top \hat r\big),$$

    the orbit and the attitude coupled by MacCullagh's gravity-gradient potential
    (principal moments $J$, $\hat r = x/r$)."""

    mass: Float[Array, ""]
    inertia: Float[Array, " 3"]
    mu: Float[Array, ""]
    space = (Euclidean(), SO3())

    def __call__(self, t, q, v, args):
        (x, R), (xdot, omega) = q, v
        r2 = jnp.sum(x**2)
        r = jnp.sqrt(r2)
        body_direction = rmatvec(R, x) / r
        gradient = (
            0.5
            * self.mu
            / (r * r2)
            * (jnp.sum(self.inertia) - 3 * jnp.sum(self.inertia * body_direction**2))
        )
        kinetic = 0.5 * self.mass * jnp.sum(xdot**2) + 0.5 * jnp.sum(
            self.inertia * omega**2
        )
        return kinetic + self.mu * self.mass / r + gradient


def total_angular_momentum(t, y, args) -> Array:
    r"""$x \times p_x + R\Pi$: conserved, as rotating orbit and attitude together is a
    symmetry."""
    (x, R), (p, pi) = y
    return jnp.cross(x, p) + matvec(R, pi)


def satellite(
    inertia: tuple[float, float, float] = (1e-3, 2e-3, 3e-3),
    spin: float = 2.0,
) -> Scene:
    r"""A rigid satellite on a circular orbit of radius 1 ($\mu = m = 1$, period
    $2\pi$), spinning at `spin` about its body axis $e_1$, which lies in the orbit's
    plane, so that the gravity-gradient torque exchanges angular momentum between
    the attitude and the orbit. The moments of inertia are small against $m r^2 = 1$,
    as a satellite's are (at $J \sim 0.1$ the gradient's force is a third of
    gravity's and the orbit falls in). Conserved: the energy and the total angular
    momentum $x \times p_x + R\Pi$; the attitude stays on SO(3)."""
    check_positive("satellite", inertia=inertia)
    lagrangian = SatelliteLagrangian(
        jnp.asarray(1.0), jnp.asarray(inertia, float), jnp.asarray(1.0)
    )
    x0, p0 = jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0])
    pi0 = jnp.array([inertia[0] * spin, 0.0, 0.0])
    c, s = jnp.cos(0.4), jnp.sin(0.4)
    R0 = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Scene(
        name="satellite",
        solvers=GENERAL_SOLVERS,
        lagrangian=lagrangian,
        y0=((x0, R0), (p0, pi0)),
        period=2 * float(jnp.pi),
        invariants=dict(
            angular_momentum=total_angular_momentum,
            orthogonality=body_orthogonality,
        ),
    )


RigidBodyLagrangian.__init__.__doc__ = """**Arguments:**

- `inertia`: the principal moments of inertia $J$, shape `(3,)`.
- `centre`: the centre of mass $\\chi$ in the body frame, shape `(3,)`.
- `weight`: $m g$, a scalar.
"""
