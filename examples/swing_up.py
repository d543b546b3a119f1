"""Optimal control through a forced variational integrator: swing a damped pendulum up.

The torque is bounded by half the pendulum's weight, so it cannot lift the pendulum
directly: it must pump energy in over several swings. The control sequence (20
piecewise-constant torques over 10 time units, `scenes.swing_up`) is found by BFGS
(optimistix) on a loss computed by `MidpointVI` on the forced `LagrangianTerm`,
differentiated through the solver (the discrete Lagrange–d'Alembert principle).

Run: `python examples/swing_up.py` (about a minute on one core).
"""

import diffrax as dfx
import jax
import jax.numpy as jnp
import optimistix as optx


jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import scenes  # noqa: E402


def final_state(scene, controls, steps=200):
    horizon = scene.force.horizon
    sol = dfx.diffeqsolve(
        scene.term(),
        dvi.MidpointVI(),
        0.0,
        horizon,
        horizon / steps,
        scene.y0,
        args=controls,
        max_steps=steps,
    )
    return sol.ys[0][-1], sol.ys[1][-1]


def loss(controls, scene):
    """Distance from upright at rest at the horizon, plus a little control effort."""
    q, p = final_state(scene, controls)
    return (1 + jnp.cos(q)) + 0.1 * p**2 + 1e-4 * jnp.sum(controls**2)


def swing_up(scene, guess):
    solver = optx.BFGS(rtol=1e-8, atol=1e-8)
    return optx.minimise(loss, solver, guess, args=scene, max_steps=500).value


def main():
    scene = scenes.swing_up()
    # A start that breaks the symmetry: push one way, then the other.
    guess = jnp.where(jnp.arange(scene.args.shape[0]) % 6 < 3, 1.0, -1.0)
    controls = swing_up(scene, guess)
    q, p = final_state(scene, controls)
    torques = float(scene.force.max_torque) * jnp.tanh(controls)
    print(f"loss {float(loss(controls, scene)):.2e}")
    print(f"final angle {float(q):.4f} (upright: pi = {jnp.pi:.4f}), momentum {p:.1e}")
    print("torques:", " ".join(f"{u:+.2f}" for u in torques))


if __name__ == "__main__":
    main()
