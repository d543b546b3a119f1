from typing import Any, TypeAlias

from jaxtyping import Array, ArrayLike, Float, PyTree, Shaped


Args: TypeAlias = PyTree[Any]
Scalar: TypeAlias = Shaped[Array, ""]
RealScalarLike: TypeAlias = float | int | Float[ArrayLike, ""]
# Positions, velocities and momenta: any PyTree of floating arrays, the same structure
# for all three.
Q: TypeAlias = PyTree[Float[ArrayLike, "..."]]
V: TypeAlias = PyTree[Float[ArrayLike, "..."]]
P: TypeAlias = PyTree[Float[ArrayLike, "..."]]
