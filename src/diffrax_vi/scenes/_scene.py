from collections.abc import Callable

import equinox as eqx
from jaxtyping import Array, PyTree

from .._lagrangian import AbstractLagrangian, energy


class Scene(eqx.Module):
    """A ready system: a Lagrangian, a default initial state, its time scale and the
    quantities its flow conserves.

    **Fields:**

    - `name`: a short name, as used by the command line.
    - `lagrangian`: an [`diffrax_vi.AbstractLagrangian`][].
    - `y0`: the default initial state `(q0, p0)`.
    - `period`: the natural time scale (a period, where the motion is periodic).
    - `invariants`: extra conserved quantities, `name -> fn(t, y, args) -> scalar`;
        the energy is always conserved for a time-independent Lagrangian and is added
        by [`diffrax_vi.scenes.Scene.conserved`][].
    """

    name: str = eqx.field(static=True)
    lagrangian: AbstractLagrangian
    y0: tuple[PyTree[Array], PyTree[Array]]
    period: float = eqx.field(static=True)
    invariants: dict[str, Callable] = eqx.field(static=True, default_factory=dict)

    def conserved(self) -> dict[str, Callable]:
        """Every conserved quantity, energy first, as `fn(t, y, args) -> scalar`."""
        lagrangian = self.lagrangian

        def _energy(t, y, args):
            return energy(lagrangian, t, y[0], y[1], args)

        return {"energy": _energy, **self.invariants}
