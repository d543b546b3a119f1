import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lagrangian import AbstractSeparableLagrangian
from ._one_dof import parameter
from ._scene import check_count, check_positive, Scene


class FPULagrangian(AbstractSeparableLagrangian):
    r"""The Fermi–Pasta–Ulam chain with stiff linear and soft cubic springs (Hairer,
    Lubich and Wanner, *Geometric Numerical Integration*, I.5): $2m$ unit masses
    $q_1, \dots, q_{2m}$ with fixed ends $q_0 = q_{2m+1} = 0$,
    $$V = \frac{\omega^2}{4}\sum_{i=1}^m (q_{2i} - q_{2i-1})^2
    + \sum_{i=0}^m (q_{2i+1} - q_{2i})^4.$$
    The stiff springs oscillate with frequency $\omega$."""

    omega: Float[Array, ""] = parameter(50.0)
    mass: Float[Array, ""] = parameter(1.0)

    def potential(self, t, q, args):
        stiff = q[1::2] - q[0::2]
        padded = jnp.concatenate([jnp.zeros(1, q.dtype), q, jnp.zeros(1, q.dtype)])
        soft = padded[1::2] - padded[0::2]
        return 0.25 * self.omega**2 * jnp.sum(stiff**2) + jnp.sum(soft**4)


def fpu(omega: float = 50.0, m: int = 3) -> Scene:
    r"""The stiff Fermi–Pasta–Ulam chain with Hairer–Lubich–Wanner's initial data: in
    the centre-of-spring coordinates $x_{0,i} = (q_{2i} + q_{2i-1})/\sqrt2$ and spring
    elongations $x_{1,i} = (q_{2i} - q_{2i-1})/\sqrt2$, $x_{0,1} = 1$,
    $\dot x_{0,1} = 1$, $x_{1,1} = \omega^{-1}$, $\dot x_{1,1} = 1$ and all others 0.
    The time scale is the fast period $2\pi/\omega$, so `steps_per_period` sets how
    well a step resolves the stiff springs (a step is stable for explicit methods only
    while $\omega h < 2$)."""
    check_count("fpu", m=m)
    check_positive("fpu", omega=omega)
    s = 1 / math.sqrt(2)
    q0 = jnp.zeros(2 * m).at[0].set(s * (1 - 1 / omega)).at[1].set(s * (1 + 1 / omega))
    p0 = jnp.zeros(2 * m).at[1].set(2 * s)
    return Scene(
        name="fpu",
        lagrangian=FPULagrangian(omega),
        y0=(q0, p0),
        period=2 * math.pi / omega,
    )
