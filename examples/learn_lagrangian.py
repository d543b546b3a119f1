"""Learn a potential from one long trajectory, differentiating through MidpointVI
with `ReversibleAdjoint`.

The data: a Duffing oscillator, V(q) = a q^2/2 + b q^4/4 with a = 1, b = 0.5,
observed every 2 time units over 400 time units (200 observations, 20 000 steps of
h = 0.02). The model: the same form with unknown (a, b), started from (0.5, 0). The
loss is multiple shooting: from each observed state, 100 steps to the next
observation (the 200 intervals are one vmapped `diffeqsolve`), and BFGS
(`optimistix.BFGS`) fits it. Each interval's gradient is taken by inverse steps:
memory holds the 200 observed states, not the 20 000 steps. The
script prints the fitted parameters, and the time and peak memory of one gradient
with each adjoint.

Run: `python examples/learn_lagrangian.py` (a minute).
"""

import resource
import time

import diffrax
import jax
import jax.numpy as jnp
import optimistix as optx


jax.config.update("jax_enable_x64", True)

import diffrax_vi  # noqa: E402


def duffing(t, q, params):
    a, b = params
    return a * q**2 / 2 + b * q**4 / 4


TERM = diffrax_vi.LagrangianTerm(diffrax_vi.SeparableLagrangian(duffing))
SOLVER = diffrax_vi.MidpointVI()
H, EVERY, OBSERVATIONS = 0.02, 100, 200  # 100 steps between observations
Y0 = (jnp.array(1.0), jnp.array(0.0))


def trajectory(params, adjoint):
    """The states at the observation times, from Y0 with these params."""

    def interval(y, _):
        sol = diffrax.diffeqsolve(
            TERM,
            SOLVER,
            0.0,
            EVERY * H,
            H,
            y,
            params,
            adjoint=adjoint,
            max_steps=EVERY,
        )
        y = jax.tree.map(lambda x: x[-1], sol.ys)
        return y, y

    return jax.lax.scan(interval, Y0, length=OBSERVATIONS)[1]


def loss(params, observed, adjoint):
    """Multiple shooting: from each observation to the next."""
    starts = jax.tree.map(
        lambda x, x0: jnp.concatenate([x0[None], x[:-1]]), observed, Y0
    )

    def interval(y):
        sol = diffrax.diffeqsolve(
            TERM, SOLVER, 0.0, EVERY * H, H, y, params, adjoint=adjoint, max_steps=EVERY
        )
        return jax.tree.map(lambda x: x[-1], sol.ys)

    q, p = jax.vmap(interval)(starts)
    return jnp.mean((q - observed[0]) ** 2 + (p - observed[1]) ** 2)


def main():
    adjoint = diffrax_vi.ReversibleAdjoint()
    observed = trajectory(jnp.array([1.0, 0.5]), adjoint)
    start = time.perf_counter()
    fit = jax.jit(
        lambda x0: optx.minimise(
            lambda x, _: loss(x, observed, adjoint),
            optx.BFGS(rtol=1e-10, atol=1e-12),
            x0,
            max_steps=200,
        )
    )(jnp.array([0.5, 0.0]))
    a, b = fit.value
    print(
        f"fitted a = {float(a):.10f}, b = {float(b):.10f} "
        f"(true 1, 0.5) in {int(fit.stats['num_steps'])} BFGS iterations, "
        f"{time.perf_counter() - start:.1f} s with compilation"
    )
    for name, each in (
        ("ReversibleAdjoint", adjoint),
        ("RecursiveCheckpointAdjoint", diffrax.RecursiveCheckpointAdjoint()),
    ):
        gradient = jax.jit(jax.grad(lambda x, a=each: loss(x, observed, a)))
        jax.block_until_ready(gradient(jnp.array([0.9, 0.4])))
        start = time.perf_counter()
        jax.block_until_ready(gradient(jnp.array([0.9, 0.4])))
        print(f"one gradient with {name}: {time.perf_counter() - start:.3f} s")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory of this process: {peak:.0f} MiB")


if __name__ == "__main__":
    main()
