import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lagrangian import AbstractQuadraticLagrangian
from ._one_dof import parameter
from ._scene import check_count, GENERAL_SOLVERS, Scene


class BeadWireLagrangian(AbstractQuadraticLagrangian):
    r"""$N$ beads of mass $m$ threaded on a corrugated wire $y(x) = -a\cos(kx)$,
    $k = 2\pi/\ell$, in uniform gravity $g$, each joined to its neighbours by a spring
    of stiffness $\kappa$ and rest length $\ell$ (the distance in the plane); the end
    springs are tied to fixed points of the wire at $x = 0$ and $x = (N + 1)\ell$. At
    rest each bead sits in a trough, $x_i = i\ell$; the coordinates `q` (any length
    $N$) are the beads' displacements from their troughs, $u_i = x_i - i\ell$:

    $$L = \sum_{i=1}^N \tfrac12 m \big(1 + y'(u_i)^2\big) v_i^2
    - \sum_{i=1}^N m g\, y(u_i)
    - \sum_{i=0}^{N} \tfrac12 \kappa \big(d_i - \ell\big)^2,\qquad
    d_i = \big\lVert \big(\ell + u_{i+1} - u_i,\ y(u_{i+1}) - y(u_i)\big)
    \big\rVert,$$

    with $u_0 = u_{N+1} = 0$ ($y$ has period $\ell$, so $y(x_i) = y(u_i)$).
    Displacements keep every coordinate of the order of the motion, so round-off
    does not grow with $N$: the abscissae themselves grow to $N\ell$, and their
    rounding and that of $\cos(k x_i)$ keep an implicit step's residual from
    converging for tens of thousands of beads.

    Not separable: the kinetic energy depends on the configuration (a bead on a
    steep part of the wire moves more of its path vertically), and the springs couple
    neighbours only, so the Newton matrix of an implicit step is tridiagonal and
    matrix-free Krylov solves cost O(N). Defaults: $m = g = \kappa = \ell = 1$,
    $a = 0.2$."""

    mass: Float[Array, ""] = parameter(1.0)
    amplitude: Float[Array, ""] = parameter(0.2)
    spacing: Float[Array, ""] = parameter(1.0)
    stiffness: Float[Array, ""] = parameter(1.0)
    g: Float[Array, ""] = parameter(1.0)

    def height(self, x):
        return -self.amplitude * jnp.cos(2 * jnp.pi * x / self.spacing)

    def slope(self, x):
        k = 2 * jnp.pi / self.spacing
        return self.amplitude * k * jnp.sin(k * x)

    def __call__(self, t, q, v, args):
        kinetic = 0.5 * self.mass * jnp.sum((1 + self.slope(q) ** 2) * v**2)
        fixed = jnp.zeros(1, q.dtype)
        u = jnp.concatenate([fixed, q, fixed])
        y = self.height(u)
        d = jnp.sqrt((self.spacing + jnp.diff(u)) ** 2 + jnp.diff(y) ** 2)
        potential = self.mass * self.g * jnp.sum(y[1:-1]) + 0.5 * self.stiffness * (
            jnp.sum((d - self.spacing) ** 2)
        )
        return kinetic - potential


def bead_wire(n: int = 32, displacement: float = 0.2) -> Scene:
    r"""[`diffrax_vi.scenes.BeadWireLagrangian`][] with `n` beads released from rest,
    displaced from their troughs by `displacement` $\cdot\,\ell\sin(3\pi i/(n+1))$:
    far enough up the corrugations that both the springs and the kinetic energy are
    nonlinear. A large non-separable system for any `n` (the scaling benchmark runs
    it to 4096 on a CPU). Its time scale is the period of the fastest small
    oscillation, $2\pi/\sqrt{g a k^2 + 4\kappa/m}$ (1.82 with the defaults); the
    energy is conserved."""
    check_count("bead_wire", n=n)
    if not 0 <= displacement < 0.5:
        raise ValueError(
            "bead_wire needs n >= 1 beads and a displacement in [0, 0.5) spacings "
            f"(beyond half a spacing a bead leaves its trough); got n={n}, "
            f"displacement={displacement}."
        )
    lagrangian = BeadWireLagrangian()
    i = jnp.arange(1.0, n + 1.0)
    q0 = displacement * jnp.sin(3 * jnp.pi * i / (n + 1))
    k = 2 * math.pi
    omega = math.sqrt(0.2 * k**2 + 4.0)
    return Scene(
        name="bead_wire",
        solvers=GENERAL_SOLVERS,
        lagrangian=lagrangian,
        y0=(q0, jnp.zeros(n)),
        period=2 * math.pi / omega,
    )
