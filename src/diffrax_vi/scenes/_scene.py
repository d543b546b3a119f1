import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, PRNGKeyArray, PyTree

from .._constraint import project_onto_constraints
from .._lagrangian import AbstractLagrangian, energy_value
from .._space import is_euclidean, retract
from .._term import LagrangianTerm


def _energy_in_loop(lagrangian, t, y, args):
    return energy_value(lagrangian, t, y, args, promise="nan")


class Scene(eqx.Module):
    """A ready system: a Lagrangian, a default initial state, its time scale, the
    quantities its flow conserves and, where one is known, its exact solution.

    **Fields:**

    - `name`: a short name, as used by the command line.
    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][].
    - `y0`: the default initial state `(q0, p0)`.
    - `period`: the natural time scale (the period, where the motion is periodic). A
        study's step is `period / steps_per_period`.
    - `invariants`: extra conserved quantities, `name -> fn(t, y, args) -> array`;
        the energy is always conserved for a time-independent Lagrangian and is added
        by [`diffrax_vi.scenes.Scene.conserved`][].
    - `exact`: the exact solution from `y0`, `fn(t) -> (q, p)`, or `None` where none
        is known in closed form.
    - `force`: the applied force `force(t, q, v, args)`, or `None`.
    - `constraint`: the holonomic constraints `constraint(t, q, args)`, or `None`.
    - `args`: the default `args` of a solve (a control sequence, say), or `None`.
    - `monitor`: a step-size monitor `monitor(t, y, args) -> scalar` for reversible
        adaptive steps ([`diffrax_vi.ReversibleController`][]; the study's
        `+Adaptive` methods), or `None` where fixed steps suit the motion.
    - `solvers`: the names (in `diffrax_vi.study.SOLVERS`, with the suffixes `+PID`
        and `+Adaptive`) of the methods its default study compares, like with like,
        where the command line's general default does not fit the scene (a general
        Lagrangian, a constraint or a group, which `StormerVerlet` cannot take, or
        an applied force, whose work its partitioned terms cannot tell apart);
        `None` for the general default.
    """

    name: str = eqx.field(static=True)
    lagrangian: AbstractLagrangian
    y0: tuple[PyTree[Array], PyTree[Array]]
    period: float = eqx.field(static=True)
    invariants: dict[str, Callable] = eqx.field(default_factory=dict)
    exact: Callable | None = eqx.field(static=True, default=None)
    force: Callable | None = None
    constraint: Callable | None = None
    args: PyTree = None
    monitor: Callable | None = None
    solvers: tuple[str, ...] | None = eqx.field(static=True, default=None)

    def term(self) -> LagrangianTerm:
        """The scene's [`diffrax_vi.LagrangianTerm`][], with its force and
        constraint."""
        return LagrangianTerm(self.lagrangian, self.force, self.constraint)

    @property
    def energy(self) -> Callable:
        r"""The energy $E = p\cdot v - L$ as `fn(t, y, args) -> array`
        ([`diffrax_vi.energy`][]), traced into the caller's program: a study tracks
        it in every step. NaN where the Legendre map cannot be inverted, and where
        a Lagrangian marked quadratic in `v` is not (which `diffrax_vi.energy`
        raises, by a host callback that would break a time-stepping loop into
        kernels). It carries the Lagrangian alone, not the scene (whose exact
        solution is a new function for each scene built), so two equal scenes give
        a study equal programs to compile, which it then shares."""
        return jtu.Partial(_energy_in_loop, self.lagrangian)

    def conserved(self) -> dict[str, Callable]:
        """Every conserved quantity, energy first, as `fn(t, y, args) -> array`. With
        an applied force the energy is not conserved, and only `invariants` are
        listed (the drift study checks the energy balance instead)."""
        if self.force is not None:
            return dict(self.invariants)
        return {"energy": self.energy, **self.invariants}

    def perturbed(
        self, key: PRNGKeyArray, n: int, spread: float = 1e-3
    ) -> tuple[PyTree[Array], PyTree[Array]]:
        """`n` initial states near `y0`, for ensembles: each leaf of `y0` plus
        Gaussian noise of standard deviation `spread * (1 + |leaf|)`. The first member
        is `y0` itself. Returns `y0`'s structure with a leading axis of size `n`. On a
        group the positions move along it, `q0` moved by a tangent increment of
        standard deviation `spread`. With a constraint, each member is then moved
        onto it ([`diffrax_vi.project_onto_constraints`][]), where a constrained
        solve must start."""
        return self._on_constraints(self._spread(key, n, spread))

    def _on_constraints(self, y):
        if self.constraint is None:
            return y
        term = self.term()
        project = lambda y: project_onto_constraints(term, 0.0, y, self.args)[0]
        return jax.vmap(project)(y)

    def _spread(self, key, n, spread):

        def perturb(k, x):
            x = jnp.asarray(x)
            noise = (
                jr.normal(k, (n, *x.shape), x.dtype) * (spread * (1 + jnp.abs(x)))[None]
            )
            return (x[None] + noise).at[0].set(x)

        space = self.lagrangian.space
        if not is_euclidean(space):
            # On a group the positions move along it, by a tangent increment.
            q0, p0 = self.y0
            key_q, key_p = jr.split(key)
            p_leaves, p_def = jtu.tree_flatten(p0)
            dq = jtu.tree_unflatten(
                p_def,
                [
                    (spread * jr.normal(k, (n, *jnp.shape(x)), x.dtype)).at[0].set(0.0)
                    for k, x in zip(jr.split(key_q, len(p_leaves)), p_leaves)
                ],
            )
            q = jax.vmap(lambda x: retract(space, q0, x))(dq)
            keys = jr.split(key_p, len(p_leaves))
            p = jtu.tree_unflatten(p_def, list(map(perturb, keys, p_leaves)))
            return q, p
        leaves, treedef = jtu.tree_flatten(self.y0)
        keys = jr.split(key, len(leaves))

        return jtu.tree_unflatten(treedef, list(map(perturb, keys, leaves)))


# The methods a scene's default study compares where StormerVerlet and its
# compositions do not apply (or, under a force, cannot be measured): variational
# solvers of a LagrangianTerm against
# diffrax's Runge-Kutta solvers on the same term, at equal steps and adaptive.
GENERAL_SOLVERS = (
    "MidpointVI",
    "TrapezoidalVI",
    "MidpointVI-Yoshida4",
    "Tsit5",
    "Dopri8",
    "Dopri8+PID",
)
# A rigid body with constant inertia (an AbstractRigidBodyLagrangian) adds the LGVI.
RIGID_BODY_SOLVERS = ("LGVI", *GENERAL_SOLVERS)


def entries(x: Array) -> tuple[Array, ...]:
    """The entries of a vector `x`, each as its sum against a unit vector rather than
    as `x[i]`: reverse mode transposes an entry picked out into a pad of the whole
    vector, and an implicit step differentiates a general Lagrangian (and a
    constraint) twice over, into dozens of pad fusions. With this and whole-vector
    sums the four-bar's and the double pendulum's first calls, gradients and steps
    take less time (the figures are in the CHANGELOG; the first calls in
    `benchmarks/first_call.py`). A separable potential, whose steps take first
    derivatives only, gains nothing (its steps took longer so), and Hénon–Heiles
    keeps `q[0]`. An infinite entry makes every entry NaN (0 * inf), which no step
    takes for a finite state."""
    units = np.eye(x.shape[-1], dtype=x.dtype)
    return tuple(jnp.sum(unit * x, axis=-1) for unit in units)


def agm(a: float, b: float) -> float:
    """The arithmetic–geometric mean, for the closed-form periods
    (`K(k) = pi / (2 agm(1, sqrt(1 - k^2)))`)."""
    for _ in range(60):
        a, b = (a + b) / 2, (a * b) ** 0.5
    return a


def check_positive(scene: str, **values) -> None:
    """A `ValueError` naming the scene and the parameter unless every value (a number,
    or a sequence of them) is finite and positive."""
    for name, value in values.items():
        entries = value if isinstance(value, tuple | list) else (value,)
        if not all(
            isinstance(x, int | float) and math.isfinite(x) and x > 0 for x in entries
        ):
            what = (
                "finite positive values"
                if len(entries) > 1
                else "a finite positive value"
            )
            raise ValueError(f"{scene}({name}=...) needs {what}; got {value!r}.")


def check_count(scene: str, **values) -> None:
    """A `ValueError` naming the scene and the parameter unless every value is an
    integer of at least 1 (not a float with an integer value: it would make shapes)."""
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(
                f"{scene}({name}=...) needs an integer of at least 1; got {value!r}."
            )
