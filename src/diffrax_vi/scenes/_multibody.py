r"""Rigid bodies joined by ball joints, in maximal coordinates: `q = (x, R)` with the
centres of mass `x`, shape `(n, 3)`, and the attitudes `R`, shape `(n, 3, 3)`; the
joints are holonomic constraints on `q`."""

import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float

from .._joints import BallJoint, joints
from .._lagrangian import AbstractMultibodyLagrangian
from .._so3 import matvec, rotation_departure
from ._scene import check_count, check_positive, GENERAL_SOLVERS, Scene


class RigidBodiesLagrangian(AbstractMultibodyLagrangian):
    r"""$n$ rigid bodies in uniform gravity $g$ along $-e_3$:
    $L = \sum_i \tfrac12 m_i|\dot x_i|^2 + \tfrac12\Omega_i^\top J_i\Omega_i
    - m_i g\,e_3\cdot x_i$."""

    mass: Float[Array, " n"]
    inertia: Float[Array, "n 3"]
    gravity: Float[Array, ""]

    def potential(self, t, q, args):
        return self.gravity * jnp.sum(self.mass * q[0][:, 2])


def box_inertia(mass: float, size: tuple[float, float, float]) -> np.ndarray:
    """The principal moments of a uniform box of edges `size` about its centre."""
    a, b, c = (s**2 for s in size)
    return mass / 12 * np.array([b + c, a + c, a + b])


def _rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def hanging_chain(
    lagrangian: RigidBodiesLagrangian,
    half: float | np.ndarray,
    attitudes: np.ndarray,
    omega: np.ndarray,
):
    r"""The state of links hung one below the other by ball joints, link $i$'s top
    $(0, 0, h_i)$ held at link $i-1$'s bottom $(0, 0, -h_{i-1})$ and link 0's top at
    the origin, with attitudes `attitudes` and body angular velocities `omega`: the
    centres and their velocities follow from the joints, so the state lies on the
    constraint manifold and its hidden constraint exactly. Returns `(q0, p0)` and
    the joints."""
    n = attitudes.shape[0]
    half = np.broadcast_to(np.asarray(half, float), (n,))
    top = np.stack([np.zeros(n), np.zeros(n), half], axis=-1)
    x, xdot = np.zeros((n, 3)), np.zeros((n, 3))
    joint, joint_velocity = np.zeros(3), np.zeros(3)
    for i in range(n):
        R = attitudes[i]
        x[i] = joint - R @ top[i]
        xdot[i] = joint_velocity - R @ np.cross(omega[i], top[i])
        joint = x[i] - R @ top[i]
        joint_velocity = xdot[i] - R @ np.cross(omega[i], top[i])
    constraint = joints(
        BallJoint(0, top[0]),
        *(
            (BallJoint(tuple(range(1, n)), top[1:], tuple(range(n - 1)), -top[:-1]),)
            if n > 1
            else ()
        ),
    )
    mass = np.asarray(lagrangian.mass)[:, None]
    y0 = (
        (jnp.asarray(x), jnp.asarray(attitudes)),
        (jnp.asarray(mass * xdot), jnp.asarray(np.asarray(lagrangian.inertia) * omega)),
    )
    return y0, constraint


def vertical_momentum(t, y, args) -> Array:
    r"""$e_3\cdot\sum_i (x_i \times p_i + R_i\Pi_i)$, the angular momentum about the
    vertical through the pivot: gravity and the pivot exert no torque about it."""
    (x, R), (p, pi) = y
    return jnp.sum(jnp.cross(x, p)[:, 2] + matvec(R, pi)[:, 2])


def orthogonality(t, y, args) -> Array:
    r"""$\max_i\|R_i^\top R_i - I\|_{\max}$: zero on SO(3)."""
    R = y[0][1]
    return rotation_departure(R)


def _constraint_residual(constraint, t, y, args):
    """$\\max|g(q)|$: zero on the constraint manifold."""
    return jnp.max(jnp.abs(constraint(t, y[0], args)))


def _scene(name, lagrangian, y0, constraint, period) -> Scene:
    return Scene(
        name=name,
        solvers=GENERAL_SOLVERS,
        lagrangian=lagrangian,
        y0=y0,
        period=period,
        constraint=constraint,
        invariants=dict(
            vertical_momentum=vertical_momentum,
            constraint=jtu.Partial(_constraint_residual, constraint),
            orthogonality=orthogonality,
        ),
    )


def _swing_period(lagrangian, half) -> float:
    """The period of small swings of link 0 alone about its pivot (first axis)."""
    m, j = float(lagrangian.mass[0]), float(lagrangian.inertia[0, 0])
    g = float(lagrangian.gravity)
    return float(2 * np.pi * ((j + m * half**2) / (m * g * half)) ** 0.5)


def rigid_double_pendulum(
    masses: tuple[float, float] = (1.0, 0.8),
    gravity: float = 1.0,
) -> Scene:
    r"""Two rigid boxes hung by ball joints, in gravity: box 0 (edges
    $0.3 \times 0.5 \times 1$) from the origin by the centre of its top face, box 1
    (edges $0.2 \times 0.4 \times 0.8$) from the centre of box 0's bottom face by
    the centre of its own top face. Unequal principal moments, so that each box
    also tumbles about its own axis. Starts tilted out of every vertical plane and
    spinning, $\Omega_0 = (0.3, 0.5, 2)$, $\Omega_1 = (-0.4, 0.2, -1)$; the motion
    is chaotic. Conserved: the energy and the angular momentum about the vertical
    through the pivot; the joints and SO(3) are kept exactly (the constraint
    residual and the orthogonality error). The period is that of small swings of
    box 0 alone."""
    check_positive("rigid_double_pendulum", masses=masses, gravity=gravity)
    sizes = ((0.3, 0.5, 1.0), (0.2, 0.4, 0.8))
    lagrangian = RigidBodiesLagrangian(
        jnp.asarray(masses, float),
        jnp.asarray(np.stack([box_inertia(m, s) for m, s in zip(masses, sizes)])),
        jnp.asarray(gravity, float),
    )
    half = np.array([s[2] / 2 for s in sizes])
    attitudes = np.stack(
        [
            _rotation(0, 0.6) @ _rotation(2, 0.3),
            _rotation(1, 0.9) @ _rotation(0, 0.3),
        ]
    )
    omega = np.array([[0.3, 0.5, 2.0], [-0.4, 0.2, -1.0]])
    y0, constraint = hanging_chain(lagrangian, half, attitudes, omega)
    return _scene(
        "rigid_double_pendulum",
        lagrangian,
        y0,
        constraint,
        _swing_period(lagrangian, half[0]),
    )


def rigid_chain(links: int = 4, gravity: float = 1.0) -> Scene:
    r"""`links` identical rigid boxes (edges $0.2 \times 0.3 \times 1$, mass 1) hung
    one below the other by ball joints at the centres of their end faces, the top
    one from the origin: $6n$ coordinates and $3n$ joint constraints, for scaling
    studies. Link $i$ starts tilted by 0.5 about $e_1$ and turned by $0.7i$ about
    the vertical (a helix), spinning at $\Omega = (0.2, -0.1, 1)$. Conserved: the
    energy and the angular momentum about the vertical through the pivot; the
    joints and SO(3) are kept exactly. The period is that of small swings of one
    link alone."""
    check_count("rigid_chain", links=links)
    check_positive("rigid_chain", gravity=gravity)
    inertia = box_inertia(1.0, (0.2, 0.3, 1.0))
    lagrangian = RigidBodiesLagrangian(
        jnp.ones(links),
        jnp.asarray(np.broadcast_to(inertia, (links, 3))),
        jnp.asarray(gravity, float),
    )
    attitudes = np.stack(
        [_rotation(2, 0.7 * i) @ _rotation(0, 0.5) for i in range(links)]
    )
    omega = np.broadcast_to(np.array([0.2, -0.1, 1.0]), (links, 3))
    y0, constraint = hanging_chain(lagrangian, 0.5, attitudes, omega)
    return _scene(
        "rigid_chain", lagrangian, y0, constraint, _swing_period(lagrangian, 0.5)
    )


RigidBodiesLagrangian.__init__.__doc__ = """**Arguments:**

- `mass`: the masses $m_i$, shape `(n,)`.
- `inertia`: the principal moments of inertia $J_i$ about the centres of mass,
    shape `(n, 3)`.
- `gravity`: $g$, a scalar.
"""
