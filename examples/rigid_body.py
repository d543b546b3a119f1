"""A free rigid body on SO(3): MidpointVI keeps the attitude a rotation and the
Casimir |Pi| to round-off; Tsit5 on the same term drifts off the group.

Run: `python examples/rigid_body.py`.
"""

import diffrax as dfx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402


def main():
    scene = dvi.scenes.free_rigid_body()
    for solver in (dvi.MidpointVI(), dvi.TrapezoidalVI(), dfx.Tsit5()):
        sol = dfx.diffeqsolve(
            scene.term(),
            solver,
            0.0,
            1000.0,
            0.1,
            scene.y0,
            saveat=dfx.SaveAt(t1=True),
            max_steps=10_001,
        )
        y = (sol.ys[0][-1], sol.ys[1][-1])
        drift = {
            name: float(jnp.max(jnp.abs(fn(0.0, y, None) - fn(0.0, scene.y0, None))))
            for name, fn in scene.conserved().items()
        }
        print(
            f"{type(solver).__name__:>14}: "
            + ", ".join(f"{name} {value:.1e}" for name, value in drift.items())
        )


if __name__ == "__main__":
    main()
