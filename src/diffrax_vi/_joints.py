r"""Joints between rigid bodies, as holonomic constraints on `q = (x, R)`.

Bodies are the $n$ bodies of an [`diffrax_vi.AbstractMultibodyLagrangian`][]:
centres of mass `x`, shape `(n, 3)`, and attitudes `R`, shape `(n, 3, 3)`. A joint
is a callable `g(t, q, args)` that returns the values it holds at zero, so it is a
`constraint` for [`diffrax_vi.LagrangianTerm`][], and [`diffrax_vi.joints`][]
joins several into the constraint of a mechanism.

A ball joint holds a point $a_i$ of body $i$ (its frame) at a point $a_j$ of body
$j$, $x_i + R_i a_i - x_j - R_j a_j = 0$, or at a fixed point of space. Along the
left-trivialised directions its Jacobian is $[I,\ -R_i\hat a_i,\ -I,\ R_j\hat a_j]$,
so a multiplier $\lambda$ acts as the force $\lambda$ on body $i$ at $a_i$ and its
body torque $a_i \times R_i^\top\lambda$ (Lee, Leok & McClamroch (2005);
Leyendecker, Marsden & Ortiz (2008)). A hinge adds that an axis $n_i$ of body $i$
stays along an axis $n_j$ of body $j$ (or a fixed axis): two more values, the
components of $R_j n_j$ along two body-$i$ directions normal to $n_i$.

Small products are written as sums (`_so3.matvec`) and the joined bodies are taken
by static slices (`_rows`), so that a solve's compiled loop holds no matrix-product
kernel and no scatter (`diagnostics.loop_breakers`).
"""

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._custom_types import Args, Q, RealScalarLike
from ._so3 import matvec


# A point or an axis: an array, or a sequence of three numbers.
Point = ArrayLike | Sequence[float] | Sequence[Sequence[float]]


def _indices(name: str, value) -> tuple[int, ...]:
    values = (value,) if isinstance(value, int | np.integer) else tuple(value)
    if not values or not all(
        isinstance(i, int | np.integer) and not isinstance(i, bool) and i >= 0
        for i in values
    ):
        raise ValueError(
            f"A joint's `{name}` is a body index (an integer >= 0) or a sequence of "
            f"them; got {value!r}."
        )
    return tuple(int(i) for i in values)


def _points(name: str, value, k: int) -> Float[Array, "k 3"]:
    points = jnp.asarray(value, float)
    if points.shape == (3,):
        points = jnp.broadcast_to(points, (k, 3))
    if points.shape != (k, 3):
        raise ValueError(
            f"A joint's `{name}` is a point (shape (3,)) or one per joint (shape "
            f"({k}, 3)); got shape {points.shape}."
        )
    return points


def _bodies(q: Q, joint: str) -> tuple[Array, Array]:
    if not (isinstance(q, tuple) and len(q) == 2 and jnp.ndim(q[1]) == 3):
        raise ValueError(
            f"{joint} constrains the bodies of an AbstractMultibodyLagrangian: "
            "q = (x, R) with x of shape (n, 3) and R of shape (n, 3, 3); got a "
            "position of another structure."
        )
    x, R = q
    return x, R


def _rows(a: Array, indices: tuple[int, ...]) -> Array:
    """`a[np.asarray(indices)]` by static slices: a range (the links of a chain) is
    one strided slice, other indices are single rows joined. An index array would
    be a gather, whose derivative (the constraint forces `G^T lambda`) is a scatter,
    and XLA on CPU runs a loop holding a scatter as kernels one by one (a 4-link
    chain's step took 20 times a 2-link one's)."""
    start, *rest = indices
    step = rest[0] - start if rest else 1
    if step > 0 and indices == tuple(range(start, indices[-1] + 1, step)):
        return a[start : indices[-1] + 1 : step]
    return jnp.concatenate([a[i : i + 1] for i in indices])


def _check_range(joint: str, indices: tuple[int, ...], n: int) -> None:
    if max(indices) >= n:
        raise ValueError(
            f"{joint} joins body {max(indices)}, and the mechanism has {n} bodies "
            f"(indices 0 to {n - 1})."
        )


class BallJoint(eqx.Module):
    r"""Ball (spherical) joints: point `point` of body `body` (in its frame) held at
    point `other_point` of body `other` (in its frame), or, with `other=None`, at the
    fixed point `other_point` of space (the ground). Three values per joint,
    $x_i + R_i a_i - (x_j + R_j a_j)$.

    `body` and `other` may be sequences of indices, with one point per joint
    (shape `(k, 3)`): `k` joints evaluated together, which keeps a long chain's
    constraint one vectorised expression.

    **Arguments:**

    - `body`: the index of body $i$, or a sequence of them.
    - `point`: $a_i$ in body $i$'s frame, shape `(3,)` or `(k, 3)`.
    - `other`: the index of body $j$, a sequence of them, or `None` for the ground.
    - `other_point`: $a_j$ in body $j$'s frame, or the fixed point in space for the
        ground (default: the origin).
    """

    body: tuple[int, ...] = eqx.field(static=True)
    point: Float[Array, "k 3"]
    other: tuple[int, ...] | None = eqx.field(static=True)
    other_point: Float[Array, "k 3"]

    def __init__(
        self,
        body: int | tuple[int, ...],
        point: Point,
        other: int | tuple[int, ...] | None = None,
        other_point: Point = (0.0, 0.0, 0.0),
    ):
        self.body = _indices("body", body)
        k = len(self.body)
        self.point = _points("point", point, k)
        self.other = None if other is None else _indices("other", other)
        if self.other is not None and len(self.other) != k:
            raise ValueError(
                f"A joint's `body` and `other` need as many indices; got {k} and "
                f"{len(self.other)}."
            )
        self.other_point = _points("other_point", other_point, k)

    def attachment(self, q: Q) -> tuple[Array, Array]:
        """Where each joint's two points are in space, each `(k, 3)`."""
        x, R = _bodies(q, "BallJoint")
        _check_range("BallJoint", self.body + (self.other or ()), x.shape[0])
        i = self.body
        here = _rows(x, i) + matvec(_rows(R, i), self.point.astype(R.dtype))
        if self.other is None:
            return here, self.other_point.astype(x.dtype)
        j = self.other
        return here, _rows(x, j) + matvec(_rows(R, j), self.other_point.astype(R.dtype))

    def __call__(self, t: RealScalarLike, q: Q, args: Args) -> Float[Array, " m"]:
        here, there = self.attachment(q)
        return jnp.ravel(here - there)


def _normals(axis: Float[Array, "k 3"]) -> tuple[Array, Array]:
    """Two unit vectors normal to each axis and to each other (fixed, concrete)."""
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    helper = np.where(
        np.abs(axis[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), [[0.0, 1.0, 0.0]]
    )
    u = np.cross(axis, helper)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    return jnp.asarray(u), jnp.asarray(np.cross(axis, u))


class HingeJoint(eqx.Module):
    r"""Hinge (revolute) joints: a [`diffrax_vi.BallJoint`][] whose bodies also keep
    the axis `axis` of body `body` (its frame) along the axis `other_axis` of body
    `other` (its frame), or of space for the ground. Five values per joint: the ball
    joint's three, and the components of $R_j n_j$ along two directions of body $i$
    normal to $n_i$.

    **Arguments:**

    - `body`, `point`, `other`, `other_point`: as for [`diffrax_vi.BallJoint`][].
    - `axis`: the hinge axis $n_i$ in body $i$'s frame, shape `(3,)` or `(k, 3)`
        (any length but zero).
    - `other_axis`: the same axis $n_j$ in body $j$'s frame, or in space for the
        ground.
    """

    ball: BallJoint
    normals: tuple[Float[Array, "k 3"], Float[Array, "k 3"]]
    other_axis: Float[Array, "k 3"]

    def __init__(
        self,
        body: int | tuple[int, ...],
        point: Point,
        axis: Point,
        other: int | tuple[int, ...] | None = None,
        other_point: Point = (0.0, 0.0, 0.0),
        other_axis: Point | None = None,
    ):
        self.ball = BallJoint(body, point, other, other_point)
        k = len(self.ball.body)
        axis = _points("axis", axis, k)
        other_axis = (
            axis if other_axis is None else _points("other_axis", other_axis, k)
        )
        for name, a in (("axis", axis), ("other_axis", other_axis)):
            if not np.all(np.linalg.norm(np.asarray(a), axis=-1) > 0):
                raise ValueError(f"A hinge's `{name}` must not be zero; got {a}.")
        self.normals = _normals(axis)
        self.other_axis = jnp.asarray(
            np.asarray(other_axis)
            / np.linalg.norm(np.asarray(other_axis), axis=-1, keepdims=True)
        )

    def __call__(self, t: RealScalarLike, q: Q, args: Args) -> Float[Array, " m"]:
        x, R = _bodies(q, "HingeJoint")
        body = _rows(R, self.ball.body)
        if self.ball.other is None:
            axis = self.other_axis.astype(R.dtype)
        else:
            axis = matvec(_rows(R, self.ball.other), self.other_axis.astype(R.dtype))
        u, w = (matvec(body, n.astype(R.dtype)) for n in self.normals)
        aligned = jnp.stack(
            [jnp.sum(u * axis, axis=-1), jnp.sum(w * axis, axis=-1)], axis=-1
        )
        return jnp.concatenate([self.ball(t, q, args), jnp.ravel(aligned)])


class Joints(eqx.Module):
    """Several joints as one constraint: their values, concatenated."""

    joints: tuple[eqx.Module, ...]

    def __call__(self, t: RealScalarLike, q: Q, args: Args) -> Array:
        return jnp.concatenate([jnp.ravel(j(t, q, args)) for j in self.joints])


def joints(*parts: BallJoint | HingeJoint) -> Joints:
    """The constraint of a mechanism: its joints' values, concatenated, for
    `LagrangianTerm(lagrangian, constraint=joints(...))`.

    !!! example

        ```python
        # Body 0 hangs from the origin by its point (0, 0, 0.5); body 1's point
        # (0, 0, 0.4) is held at body 0's point (0, 0, -0.5).
        constraint = diffrax_vi.joints(
            diffrax_vi.BallJoint(0, (0.0, 0.0, 0.5)),
            diffrax_vi.BallJoint(1, (0.0, 0.0, 0.4), 0, (0.0, 0.0, -0.5)),
        )
        ```
    """
    if not parts or not all(isinstance(j, BallJoint | HingeJoint) for j in parts):
        raise ValueError(
            "diffrax_vi.joints(...) takes one or more BallJoint or HingeJoint; got "
            f"{parts!r}."
        )
    return Joints(tuple(parts))
