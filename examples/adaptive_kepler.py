"""Reversible adaptive steps: Kepler at e = 0.9 over 1000 orbits, kahan_li8 at a fixed
step and stepped by a `ReversibleController` with the same number of steps. The
invariants are measured at every step, and at 101 physical output times, which
diffrax interpolates between steps (cubic Hermite: there the error is the
interpolant's, not the method's).

Run: `python examples/adaptive_kepler.py` (seconds).
"""

import math

import diffrax
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi  # noqa: E402


scene = diffrax_vi.scenes.kepler(eccentricity=0.9)
solver = diffrax_vi.Composition(diffrax_vi.StormerVerlet(), "kahan_li8")
terms = diffrax_vi.terms_for(solver, scene.lagrangian)
t1 = 1000 * 2 * math.pi
saveat = diffrax.SaveAt(
    subs=[
        diffrax.SubSaveAt(steps=True),
        diffrax.SubSaveAt(ts=jnp.linspace(0.0, t1, 101)),
    ]
)
momentum = jax.vmap(scene.invariants["angular_momentum"], (0, 0, None))
energy = jax.vmap(scene.energy, (0, 0, None))


def errors(ts, ys):
    """The largest energy and angular momentum errors over the saved states."""
    keep = jnp.isfinite(ts)  # the unused tail of the steps' buffer is inf
    e = jnp.where(keep, jnp.abs(energy(ts, ys, None) + 0.5), 0)
    m = jnp.where(keep, jnp.abs(momentum(ts, ys, None) - math.sqrt(1 - 0.9**2)), 0)
    return float(e.max()), float(m.max())


def solve(dt0, controller=None):
    return diffrax.diffeqsolve(
        terms,
        solver,
        0.0,
        t1,
        dt0,
        scene.y0,
        saveat=saveat,
        stepsize_controller=controller or diffrax.ConstantStepSize(),
        max_steps=200_000,
    )


# dt0 is the step at pericentre (where the monitor's density is 1): the monitor,
# r^(3/2), lengthens it about 80-fold at apocentre.
adaptive = solve(0.002, diffrax_vi.ReversibleController(scene.monitor))
steps = int(adaptive.stats["num_steps"])
fixed = solve(t1 / steps)
# Landing on the output times: the saved states are the method's own.
times = saveat.subs[1].ts
landing = solve(0.002, diffrax_vi.ReversibleController(scene.monitor, step_ts=times))
print(f"{steps} steps each; largest |E - E0|, |L - L0|:")
runs = [
    ("fixed", fixed),
    ("reversible adaptive", adaptive),
    ("... landing on the 101", landing),
]
for name, sol in runs:
    at_steps, at_times = errors(sol.ts[0], sol.ys[0]), errors(sol.ts[1], sol.ys[1])
    print(
        f"  {name:22s} at the steps {at_steps[0]:.1e}, {at_steps[1]:.1e}; "
        f"at the 101 output times {at_times[0]:.1e}, {at_times[1]:.1e}"
    )
