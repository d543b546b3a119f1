import functools
import math

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import optimistix as optx
from jaxtyping import Array, Float, PRNGKeyArray

from .._lagrangian import AbstractSeparableLagrangian
from .._solver import MidpointVI
from .._term import LagrangianTerm
from ._one_dof import PendulumLagrangian
from ._scene import agm, check_count, Scene


class LearnedLagrangian(AbstractSeparableLagrangian):
    r"""$L = \tfrac12 v^2 - V_\theta(q)$ with the potential $V_\theta$ a small MLP
    (scalar in, scalar out, `tanh`): a Lagrangian by construction, so a variational
    integrator conserves its energy however well or badly it has been trained."""

    net: eqx.nn.MLP
    mass: Float[Array, ""]

    def __init__(
        self, key: PRNGKeyArray, width: int = 16, depth: int = 2, mass: float = 1.0
    ):
        self.net = eqx.nn.MLP("scalar", "scalar", width, depth, jax.nn.tanh, key=key)
        self.mass = jnp.asarray(mass)

    def potential(self, t, q, args):
        return self.net(q)


def _trajectories(lagrangian, solver, y0s, ts):
    """Positions at `ts` from each initial state in `y0s` (a leading batch axis)."""

    # The reference at 1e-12 in float64; in float32 as close as its round-off lets
    # an adaptive solve get (a tolerance below it is never met).
    tol = max(1e-12, 10 * float(jnp.finfo(ts.dtype).eps))

    def one(y0):
        return dfx.diffeqsolve(
            LagrangianTerm(lagrangian),
            solver,
            ts[0],
            ts[-1],
            ts[1] - ts[0],
            y0,
            saveat=dfx.SaveAt(ts=ts),
            stepsize_controller=dfx.PIDController(rtol=tol, atol=tol)
            if isinstance(solver, dfx.Dopri8)
            else dfx.ConstantStepSize(),
            max_steps=100 * len(ts),
        ).ys[0]

    return jax.vmap(one)(y0s)


def fit_potential(
    model: LearnedLagrangian,
    y0s: tuple[Float[Array, " batch"], Float[Array, " batch"]],
    ts: Float[Array, " times"],
    qs: Float[Array, "batch times"],
    max_steps: int = 300,
) -> tuple[LearnedLagrangian, Float[Array, ""]]:
    """Fit the model's parameters so that `MidpointVI` with step `ts[1] - ts[0]`,
    started from `y0s`, reproduces the observed positions `qs` at `ts` (least squares,
    by BFGS through the differentiated solver). Returns the fitted model and its final
    mean squared error."""
    # Only the network is fitted, not the mass.
    params, static = eqx.partition(model.net, eqx.is_inexact_array)

    def with_net(params):
        return eqx.tree_at(lambda m: m.net, model, eqx.combine(params, static))

    def loss(params, _):
        fitted = with_net(params)
        return jnp.mean((_trajectories(fitted, MidpointVI(), y0s, ts) - qs) ** 2)

    sol = optx.minimise(
        loss,
        optx.BFGS(rtol=1e-10, atol=1e-10),
        params,
        max_steps=max_steps,
        throw=False,
    )
    return with_net(sol.value), loss(sol.value, None)


@functools.cache
def _trained(seed: int, max_steps: int) -> LearnedLagrangian:
    amplitudes = jnp.linspace(0.3, 2.0, 8)
    y0s = (amplitudes, jnp.zeros_like(amplitudes))
    ts = jnp.linspace(0.0, 6.0, 61)
    qs = _trajectories(PendulumLagrangian(), dfx.Dopri8(), y0s, ts)
    model, _ = fit_potential(LearnedLagrangian(jr.key(seed)), y0s, ts, qs, max_steps)
    return model


def learned(seed: int = 0, max_steps: int = 300) -> Scene:
    r"""A pendulum learned from data: a [`diffrax_vi.scenes.LearnedLagrangian`][] fitted
    by [`diffrax_vi.scenes.fit_potential`][] to eight pendulum trajectories
    (amplitudes 0.3 to 2, six time units at step 0.1, from Dopri8 at tolerance
    $10^{-12}$ in float64, ten times the round-off in float32), by differentiating
    through `MidpointVI`. Started from rest at amplitude 1.5; the time scale is the
    true pendulum's period at that amplitude. The first call trains (tens of seconds
    on a CPU); later calls reuse the result."""
    check_count("learned", max_steps=max_steps)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"learned(seed=...) needs an integer; got {seed!r}.")
    amplitude = 1.5
    return Scene(
        name="learned",
        lagrangian=_trained(seed, max_steps),
        y0=(jnp.array(amplitude), jnp.array(0.0)),
        period=2 * math.pi / agm(1.0, math.cos(amplitude / 2)),
    )
