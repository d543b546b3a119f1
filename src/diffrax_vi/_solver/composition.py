import functools
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike
from .base import AbstractSymmetricSolver, AbstractSymplecticSolver


def _symmetric(half: list[float]) -> np.ndarray:
    """`(g_1, ..., g_m, ..., g_1)` from its first half and middle."""
    return np.array(half + half[-2::-1])


@functools.cache
def composition_coefficients(scheme: str) -> tuple[np.ndarray, int]:
    """The step fractions `gamma_k` of a symmetric composition, and its order when
    the base method is symmetric of order 2."""
    if scheme == "yoshida4":
        # Triple jump: Creutz & Gocksch (1989), Suzuki (1990), Yoshida (1990).
        g = 1 / (2 - 2 ** (1 / 3))
        return np.array([g, 1 - 2 * g, g]), 4
    if scheme == "suzuki4":
        # Suzuki (1990), five stages.
        g = 1 / (4 - 4 ** (1 / 3))
        return np.array([g, g, 1 - 4 * g, g, g]), 4
    if scheme == "kahan_li6":
        # Kahan & Li (1997), s9odr6a; Hairer, Lubich & Wanner (2006), V.3.2.
        return _symmetric(
            [
                0.39216144400731413927925056,
                0.33259913678935943859974864,
                -0.70624617255763935980996482,
                0.08221359629355080023149045,
                0.79854399093482996339895035,
            ]
        ), 6
    if scheme == "kahan_li8":
        # Kahan & Li (1997), s17odr8a; Hairer, Lubich & Wanner (2006), V.3.2.
        return _symmetric(
            [
                0.13020248308889008087881763,
                0.56116298177510838456196441,
                -0.38947496264484728640807860,
                0.15884190655515560089621075,
                -0.39590389413323757733623154,
                0.18453964097831570709183254,
                0.25837438768632204729397911,
                0.29501172360931029887096624,
                -0.60550853383003451169892108,
            ]
        ), 8
    raise ValueError(
        f"Unknown composition scheme {scheme!r}. Choose from: {', '.join(SCHEMES)}."
    )


SCHEMES = ("yoshida4", "suzuki4", "kahan_li6", "kahan_li8")


def _scaled_increments(terms, t0, t1, f):
    """`f` times each term's control over `[t0, t1]`: the Hermite slopes."""
    if isinstance(terms, tuple):
        return tuple(term.prod(fi, term.contr(t0, t1)) for term, fi in zip(terms, f))
    return terms.prod(f, terms.contr(t0, t1))


class Composition(AbstractSymplecticSolver, AbstractSymmetricSolver):
    r"""Symmetric composition of a symmetric variational integrator: each step of
    size $h$ is the base method's steps of sizes $\gamma_1 h, \dots, \gamma_m h$
    (some negative).

    The composition of variational integrators is the variational integrator of the
    composed discrete Lagrangian, so it is symplectic, and symmetric because the
    $\gamma_k$ are. Its order is that of the scheme (4, 6 or 8) for a second-order
    base. Explicit if the base is. Fixed step sizes only. Cubic Hermite interpolation
    for dense output.

    Schemes:

    - `"yoshida4"`: the triple jump, 3 stages, order 4.
    - `"suzuki4"`: Suzuki's 5-stage fractal, order 4 (smaller error constant).
    - `"kahan_li6"`: Kahan & Li's 9 stages, order 6.
    - `"kahan_li8"`: Kahan & Li's 17 stages, order 8.

    !!! example

        ```python
        solver = diffrax_vi.Composition(diffrax_vi.StormerVerlet(), "kahan_li8")
        ```

    ??? cite "References"

        ```bibtex
        @article{yoshida1990construction,
            title={Construction of higher order symplectic integrators},
            author={Yoshida, Haruo},
            journal={Physics Letters A},
            volume={150},
            number={5--7},
            pages={262--268},
            year={1990},
        }
        @article{suzuki1990fractal,
            title={Fractal decomposition of exponential operators with applications
                   to many-body theories and {M}onte {C}arlo simulations},
            author={Suzuki, Masuo},
            journal={Physics Letters A},
            volume={146},
            number={6},
            pages={319--323},
            year={1990},
        }
        @article{kahan1997composition,
            title={Composition constants for raising the orders of unconventional
                   schemes for ordinary differential equations},
            author={Kahan, William and Li, Ren-Cang},
            journal={Mathematics of Computation},
            volume={66},
            number={219},
            pages={1089--1099},
            year={1997},
        }
        ```
    """

    base: dfx.AbstractSolver
    scheme: str = eqx.field(static=True, default="yoshida4")

    interpolation_cls: ClassVar = dfx.ThirdOrderHermitePolynomialInterpolation

    def __check_init__(self):
        if not isinstance(self.base, AbstractSymmetricSolver):
            raise ValueError(
                f"Composition raises the order of a symmetric method only; "
                f"{type(self.base).__name__} is not symmetric. Use MidpointVI, "
                "TrapezoidalVI, StormerVerlet or GaussVPRK as the base."
            )
        composition_coefficients(self.scheme)

    @property
    def term_structure(self):
        return self.base.term_structure

    def order(self, terms):
        return composition_coefficients(self.scheme)[1]

    def init(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
    ) -> PyTree:
        gammas, _ = composition_coefficients(self.scheme)
        # Python floats are weakly typed: they keep float32 times float32.
        return self.base.init(terms, t0, t0 + float(gammas[0]) * (t1 - t0), y0, args)

    def step(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
    ):
        gammas, _ = composition_coefficients(self.scheme)
        fractions = np.concatenate([[0.0], np.cumsum(gammas)])
        ts = [t0 + float(f) * (t1 - t0) for f in fractions]
        ts[-1] = t1  # exactly, not up to the rounding of the cumulative sum
        y, state, result = y0, solver_state, dfx.RESULTS.successful
        for k in range(len(gammas)):
            y, _, _, state, sub_result = self.base.step(
                terms,
                ts[k],
                ts[k + 1],
                y,
                args,
                state,
                made_jump if k == 0 else False,
                # The substep's size from the whole step's, not from ts[k + 1] - ts[k].
                substep=(float(gammas[k]), t0, t1),
            )
            result = dfx.RESULTS.where(
                result == dfx.RESULTS.successful, sub_result, result
            )
        f0 = self.base.func(terms, t0, y0, args)
        f1 = self.base.func(terms, t1, y, args)
        dense_info = dict(
            y0=y0,
            y1=y,
            k0=_scaled_increments(terms, t0, t1, f0),
            k1=_scaled_increments(terms, t0, t1, f1),
        )
        return y, None, dense_info, state, result

    def func(self, terms, t0, y0, args):
        return self.base.func(terms, t0, y0, args)


Composition.__init__.__doc__ = """**Arguments:**

- `base`: a symmetric solver of this package: [`diffrax_vi.MidpointVI`][],
    [`diffrax_vi.TrapezoidalVI`][], [`diffrax_vi.StormerVerlet`][],
    [`diffrax_vi.GaussVPRK`][] or [`diffrax_vi.LobattoVPRK`][].
- `scheme`: `"yoshida4"` (default), `"suzuki4"`, `"kahan_li6"` or `"kahan_li8"`.
"""
