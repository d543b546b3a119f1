"""Drop-in use: the same pendulum under SemiImplicitEuler, StormerVerlet, MidpointVI and
Tsit5, with the energy error of each after 10^4 steps.

Run: `python examples/drop_in.py`.
"""

import functools

import diffrax
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi  # noqa: E402


pendulum = diffrax_vi.SeparableLagrangian(lambda t, q, args: -jnp.cos(q))
y0 = (jnp.array(2.0), jnp.array(0.0))
t1, dt0, n = 1000.0, 0.1, 10_000
saveat = diffrax.SaveAt(
    ts=jnp.linspace(0.0, t1, 101), fn=functools.partial(diffrax_vi.energy, pendulum)
)
solvers = {
    "SemiImplicitEuler": diffrax.SemiImplicitEuler(),
    "StormerVerlet": diffrax_vi.StormerVerlet(),
    "MidpointVI": diffrax_vi.MidpointVI(),
    "Tsit5": diffrax.Tsit5(),
}
for name, solver in solvers.items():
    # The partitioned pair for SemiImplicitEuler and StormerVerlet, the LagrangianTerm
    # for the others.
    terms = diffrax_vi.terms_for(solver, pendulum)
    sol = diffrax.diffeqsolve(
        terms, solver, 0.0, t1, dt0, y0, saveat=saveat, max_steps=n + 1
    )
    error = jnp.abs(sol.ys - sol.ys[0])
    print(
        f"{name:18s} max |E - E0| = {float(error.max()):.2e}, "
        f"at t = {t1:g}: {float(error[-1]):.2e}"
    )
