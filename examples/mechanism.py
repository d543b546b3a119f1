"""Rigid bodies joined at joints: a door on a vertical hinge with a small body
hanging from its far corner by a ball joint.

The bodies live on (R^3 x SO(3))^2, the joints are holonomic constraints on them
(`diffrax_vi.HingeJoint`, `diffrax_vi.BallJoint`), and the start is put on the joints
with `diffrax_vi.project_onto_constraints`. TrapezoidalVI (RATTLE on the group) keeps
the joints and the attitudes to round-off and the energy bounded; Tsit5 on the same
term integrates the index-reduced equations and leaves the joints.

Run: `python examples/mechanism.py`.
"""

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402


class Bodies(dvi.AbstractMultibodyLagrangian):
    """Bodies in unit gravity along -e3."""

    mass: jax.Array
    inertia: jax.Array

    def potential(self, t, q, args):
        return jnp.sum(self.mass * q[0][:, 2])


def main():
    bodies = Bodies(
        jnp.array([2.0, 0.5]), jnp.array([[0.2, 0.3, 0.1], [0.02, 0.02, 0.01]])
    )
    constraint = dvi.joints(
        # The door's edge point (-0.5, 0, 0.5) on the vertical axis through the origin.
        dvi.HingeJoint(0, (-0.5, 0.0, 0.5), (0.0, 0.0, 1.0)),
        # The small body's top held at the door's far lower corner.
        dvi.BallJoint(1, (0.0, 0.0, 0.2), 0, (0.5, 0.0, -0.5)),
    )
    term = dvi.LagrangianTerm(bodies, constraint=constraint)
    x0 = jnp.array([[0.5, 0.0, -0.5], [1.0, 0.0, -1.2]])
    R0 = jnp.stack([jnp.eye(3), jnp.eye(3)])
    push = (jnp.array([[0.0, 0.2, 0.0], [0.1, 0.0, 0.0]]), jnp.zeros((2, 3)))
    y0, result = dvi.project_onto_constraints(term, 0.0, ((x0, R0), push))
    assert result == dfx.RESULTS.successful
    e0 = dvi.energy(bodies, 0.0, y0)
    for solver in (dvi.TrapezoidalVI(), dvi.MidpointVI(), dfx.Tsit5()):
        sol = dfx.diffeqsolve(
            term,
            solver,
            0.0,
            20.0,
            0.01,
            y0,
            saveat=dfx.SaveAt(ts=jnp.linspace(0.0, 20.0, 201)),
        )
        joints = jax.vmap(lambda q: jnp.max(jnp.abs(constraint(0.0, q, None))))(
            sol.ys[0]
        )
        energy = jax.vmap(lambda y: dvi.energy(bodies, 0.0, y))(sol.ys)
        print(
            f"{type(solver).__name__:>14}: joints {float(jnp.max(joints)):.1e}, "
            f"energy error {float(jnp.max(jnp.abs(energy - e0))):.1e}"
        )


if __name__ == "__main__":
    main()
