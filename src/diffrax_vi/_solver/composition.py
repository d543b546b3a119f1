r"""Symmetric compositions: a scheme is its coefficients, its order and its citation.

A composition $\Psi_h = \Phi_{\gamma_m h}\circ\dots\circ\Phi_{\gamma_1 h}$ of a
symmetric method $\Phi$ of order $p$ with symmetric $\gamma$
($\gamma_k = \gamma_{m+1-k}$) and $\sum_k\gamma_k = 1$ is symmetric and of order at
least $p$; with also $\sum_k \gamma_k^{p+1} = 0$ its order is $p + 2$ (Hairer,
Lubich & Wanner (2006), II.4 and V.3). The composition of variational integrators is
the variational integrator of the composed discrete Lagrangian, so it is symplectic.
"""

import dataclasses
import functools
from collections.abc import Sequence
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, PyTree

from .._custom_types import Args, RealScalarLike
from .._misc import at_trace_time, has_loop
from .._tolerance import COEFFICIENT_ATOL, PALINDROME_ATOL, PRODUCT_TOL
from .._xla import small_loops_compiled_whole
from .base import (
    AbstractComposableSolver,
    AbstractSymplecticSolver,
    AbstractTracedOnce,
    is_symmetric,
    step_control,
    Substep,
)


@dataclasses.dataclass(frozen=True, eq=False)
class CompositionScheme:
    r"""The step fractions $\gamma_1, \dots, \gamma_m$ of a symmetric composition (not
    a pytree), validated when built: symmetric, finite, summing to 1.

    **Fields:**

    - `coefficients`: the fractions $\gamma_k$ (some may be negative).
    - `order`: the order of the composition of a symmetric method of order
        `base_order`; `None` to infer it from the order conditions (order $p + 2$ if
        $\sum_k \gamma_k^{p+1} = 0$ for the base's order $p$, else $p$).
    - `base_order`: the order of the base method the coefficients were designed for.
    - `reference`: where the coefficients come from.

    The order of a composition of a base of order $p \ge$ `base_order` is then
    $\max(\text{order}, p)$; of a base of lower order, only $p$ is claimed.
    """

    coefficients: np.ndarray
    order: int | None = None
    base_order: int = 2
    reference: str = ""

    def __post_init__(self):
        gammas = np.asarray(self.coefficients, dtype=np.float64)
        object.__setattr__(self, "coefficients", gammas)
        if gammas.ndim != 1 or gammas.size == 0 or not np.all(np.isfinite(gammas)):
            raise ValueError(
                "A composition scheme needs a non-empty sequence of finite step "
                f"fractions; got {self.coefficients!r}."
            )
        if np.any(gammas == 0):
            raise ValueError("A composition scheme's step fractions must be non-zero.")
        if not np.allclose(gammas, gammas[::-1], rtol=0, atol=PALINDROME_ATOL):
            raise ValueError(
                "A composition scheme must be symmetric (gamma_k = gamma_{m+1-k}), so "
                f"that the composition is symmetric; got {gammas.tolist()}."
            )
        if abs(gammas.sum() - 1) > COEFFICIENT_ATOL:
            raise ValueError(
                "A composition scheme's step fractions must sum to 1, so that a step "
                f"of the composition is a step of size h; they sum to {gammas.sum()!r}."
            )
        if self.order is not None:
            # Necessary conditions: sum gamma^k = 0 for odd k from the base's order + 1
            # up to the claimed order - 1. The fitted orders in the tests check the
            # rest.
            for k in range(self.base_order + 1, self.order, 2):
                defect = abs(np.sum(gammas**k)) / np.sum(np.abs(gammas) ** k)
                if defect > PRODUCT_TOL:
                    raise ValueError(
                        f"A composition scheme of order {self.order} for a base of "
                        f"order {self.base_order} needs sum gamma^{k} = 0; it is "
                        f"{np.sum(gammas**k):.3e}."
                    )

    def order_for(self, base_order: int | None) -> int | None:
        """The order of the composition of a symmetric method of order `base_order`."""
        if base_order is None:
            return None
        if self.order is None:
            k = base_order + 1
            gammas = self.coefficients
            if abs(np.sum(gammas**k)) <= PRODUCT_TOL * np.sum(np.abs(gammas) ** k):
                return base_order + 2
            return base_order
        if base_order < self.base_order:
            return base_order
        return max(self.order, base_order)

    def _key(self):
        return (self.coefficients.tobytes(), self.order, self.base_order)

    def __eq__(self, other):
        return isinstance(other, CompositionScheme) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())


def _symmetric(half: list[float]) -> np.ndarray:
    """`(g_1, ..., g_m, ..., g_1)` from its first half and middle."""
    return np.array(half + half[-2::-1])


def triple_jump(base_order: int) -> CompositionScheme:
    r"""The triple jump $(\gamma, 1 - 2\gamma, \gamma)$,
    $\gamma = 1/(2 - 2^{1/(p+1)})$: raises a symmetric method of order $p$ to order
    $p + 2$. Nested, it reaches any even order (Yoshida 1990)."""
    g = 1 / (2 - 2 ** (1 / (base_order + 1)))
    return CompositionScheme(
        np.array([g, 1 - 2 * g, g]),
        order=base_order + 2,
        base_order=base_order,
        reference="Creutz & Gocksch (1989); Suzuki (1990); Yoshida (1990)",
    )


def suzuki_fractal(base_order: int) -> CompositionScheme:
    r"""Suzuki's five-stage fractal $(\gamma, \gamma, 1 - 4\gamma, \gamma, \gamma)$,
    $\gamma = 1/(4 - 4^{1/(p+1)})$: order $p + 2$ with a smaller error constant than
    the triple jump."""
    g = 1 / (4 - 4 ** (1 / (base_order + 1)))
    return CompositionScheme(
        np.array([g, g, 1 - 4 * g, g, g]),
        order=base_order + 2,
        base_order=base_order,
        reference="Suzuki (1990)",
    )


# Named schemes, each a function of the base method's order. The fixed ones are for
# a second-order base; the recursive ones raise any even order by two.
SCHEMES = {
    "yoshida4": lambda p: triple_jump(2),
    "suzuki4": lambda p: suzuki_fractal(2),
    "kahan_li6": lambda p: CompositionScheme(
        _symmetric(
            [
                0.39216144400731413927925056,
                0.33259913678935943859974864,
                -0.70624617255763935980996482,
                0.08221359629355080023149045,
                0.79854399093482996339895035,
            ]
        ),
        order=6,
        reference="Kahan & Li (1997), s9odr6a; Hairer, Lubich & Wanner (2006), V.3.2",
    ),
    "kahan_li8": lambda p: CompositionScheme(
        _symmetric(
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
        ),
        order=8,
        reference="Kahan & Li (1997), s17odr8a; Hairer, Lubich & Wanner (2006), V.3.2",
    ),
    "triple_jump": triple_jump,
    "suzuki_fractal": suzuki_fractal,
}


@functools.cache
def named_scheme(name: str, base_order: int) -> CompositionScheme:
    """The scheme `name` of `SCHEMES` for a base of order `base_order`."""
    if name not in SCHEMES:
        raise ValueError(
            f"Unknown composition scheme {name!r}. Choose from: {', '.join(SCHEMES)}, "
            "or pass the step fractions (a symmetric sequence summing to 1) or a "
            "`diffrax_vi.CompositionScheme`."
        )
    return SCHEMES[name](base_order)


def _as_scheme(
    scheme: "str | Sequence[float] | CompositionScheme", base_order: int
) -> CompositionScheme:
    if isinstance(scheme, CompositionScheme):
        return scheme
    if isinstance(scheme, str):
        return named_scheme(scheme, base_order)
    return CompositionScheme(np.asarray(scheme, dtype=np.float64))


class Composition(
    AbstractTracedOnce, AbstractSymplecticSolver, AbstractComposableSolver
):
    r"""Symmetric composition of a symmetric variational integrator: each step of
    size $h$ is the base method's steps of sizes $\gamma_1 h, \dots, \gamma_m h$
    (some negative).

    The composition of variational integrators is the variational integrator of the
    composed discrete Lagrangian, so it is symplectic, and symmetric because the
    $\gamma_k$ are. It is itself composable, so compositions nest: a triple jump over
    an order-4 composition has order 6. Explicit if the base is. Fixed step sizes
    only. Cubic Hermite interpolation for dense output.

    Named schemes:

    - `"yoshida4"`: the triple jump, 3 stages, order 4 from a second-order base.
    - `"suzuki4"`: Suzuki's 5-stage fractal, order 4 (smaller error constant).
    - `"kahan_li6"`: Kahan & Li's 9 stages, order 6.
    - `"kahan_li8"`: Kahan & Li's 17 stages, order 8.
    - `"triple_jump"`, `"suzuki_fractal"`: the same constructions for a base of any
        order $p$, raising it to $p + 2$.

    !!! example

        ```python
        solver = diffrax_vi.Composition(diffrax_vi.StormerVerlet(), "kahan_li8")
        order6 = diffrax_vi.Composition(
            diffrax_vi.Composition(diffrax_vi.MidpointVI(), "triple_jump"),
            "triple_jump",
        )
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
    scheme: CompositionScheme = eqx.field(static=True)

    interpolation_cls: ClassVar = dfx.ThirdOrderHermitePolynomialInterpolation
    # A symmetric composition of a symmetric base (its scheme is a palindrome).
    symmetric: ClassVar[bool] = True

    def __init__(
        self,
        base: dfx.AbstractSolver,
        scheme: "str | Sequence[float] | CompositionScheme" = "yoshida4",
    ):
        if not isinstance(base, AbstractComposableSolver):
            raise ValueError(
                f"Composition raises the order of a symmetric method only; "
                f"{type(base).__name__} is not one. Use MidpointVI, TrapezoidalVI, "
                "StormerVerlet, GaussVPRK, LobattoVPRK or a Composition as the base "
                "(a wrapper such as diffrax.HalfSolver is not symmetric)."
            )
        if not is_symmetric(base):
            raise ValueError(
                "Composition needs a symmetric base, but this VPRK tableau is not "
                "symmetric (a_ij + a_{s+1-i, s+1-j} = b_j fails)."
            )
        base_order = base.order(None)
        if base_order is None or base_order % 2:
            raise ValueError(
                f"Composition needs the base's (even) order; "
                f"{type(base).__name__}.order() is {base_order}."
            )
        self.base = base
        self.scheme = _as_scheme(scheme, base_order)

    @property
    def term_structure(self):
        return self.base.term_structure

    def order(self, terms):
        return self.scheme.order_for(self.base.order(terms))

    def init(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
    ) -> PyTree:
        return self.base.init(terms, t0, self._first_end(t0, t1), y0, args)

    def resume(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
    ) -> PyTree:
        return self.base.resume(
            terms, t0, self._first_end(t0, t1), y0, args, solver_state
        )

    def trace_settings(self) -> object:
        # Whether explicit substeps are unrolled (`_fractional_step`).
        return _loops_compiled_whole()

    def _first_end(self, t0: RealScalarLike, t1: RealScalarLike) -> RealScalarLike:
        """The end of the first substep of a step from `t0` to `t1`. Python floats
        are weakly typed: they keep float32 times float32. Times known at trace time
        stay known, for the base's check of them."""
        first = float(self.scheme.coefficients[0])
        return at_trace_time(lambda a, b: a + first * (b - a), t0, t1)

    def _fractional_step(
        self,
        terms: PyTree[dfx.AbstractTerm],
        t0: RealScalarLike,
        t1: RealScalarLike,
        y0: PyTree,
        args: Args,
        solver_state: PyTree,
        made_jump: bool | Bool[ArrayLike, ""],
        substep: Substep,
        dense: bool = True,
    ):
        gammas = self.scheme.coefficients
        ends = np.cumsum(gammas)
        starts = np.concatenate([[0.0], ends[:-1]])
        dtype = jnp.result_type(t0, t1)
        m = len(gammas)
        xs = (
            jnp.asarray(gammas, dtype),
            jnp.asarray(starts, dtype),
            jnp.asarray(ends, dtype),
            jnp.arange(m),
        )

        def substep_k(carry, x):
            y, state, result = carry
            gamma, start, end, k = x
            # The last substep ends exactly at t1, not at the rounded cumulative sum.
            ta = t0 + start * (t1 - t0)
            tb = jnp.where(k == m - 1, t1, t0 + end * (t1 - t0))
            y, _, _, state, sub_result = self.base.fractional_step(
                terms,
                ta,
                tb,
                y,
                args,
                state,
                # Kept static where diffrax knows there is no jump (`after_jump`).
                made_jump if made_jump is False else jnp.logical_and(made_jump, k == 0),
                Substep(substep.fraction * gamma, substep.t0, substep.t1),
                dense=False,
            )
            result = dfx.RESULTS.where(
                result == dfx.RESULTS.successful, sub_result, result
            )
            return (y, state, result), None

        init = (y0, solver_state, dfx.RESULTS.successful)
        # The substeps run as an inner scan over the scheme's fractions, unrolled
        # where a substep holds no loop of its own (an explicit step) and XLA on CPU
        # compiles the time-stepping loop as one function (`_xla.py`): XLA then
        # fuses across substeps, and a compensated sum costs no copy of the state
        # carried from one iteration to the next (Kepler, yoshida4 of
        # Stormer-Verlet: 95 -> 69 ns compensated; kahan_li8 542 -> 373 ns, compiled
        # in 0.52 against 0.24 s). At XLA's default threshold the unrolled substeps
        # would run kernel by kernel where the small inner loop runs as one function
        # (yoshida4 1.5x, kahan_li8 3.4x slower). An implicit substep's root find
        # stays in the loop: unrolled, kahan_li8 of MidpointVI compiled in 18.5
        # against 0.55 s and stepped 2.4 times slower. Not measured on GPUs, where
        # the loop stays.
        first = jax.tree.map(lambda x: x[0], xs)
        unroll = _loops_compiled_whole() and not has_loop(
            jax.make_jaxpr(substep_k)(init, first).jaxpr
        )
        (y, state, result), _ = lax.scan(substep_k, init, xs, unroll=unroll)
        if not dense:
            return y, None, None, state, result
        f0 = self.base.func(terms, t0, y0, args)
        f1 = self.base.func(terms, t1, y, args)
        dense_info = dict(
            y0=y0,
            y1=y,
            k0=_scaled(terms, substep, f0),
            k1=_scaled(terms, substep, f1),
        )
        return y, None, dense_info, state, result

    def func(self, terms, t0, y0, args):
        return self.base.func(terms, t0, y0, args)


def _loops_compiled_whole() -> bool:
    """Whether XLA compiles the time-stepping loop as one function here (on CPU, at
    the small-loop threshold `import diffrax_vi` sets), where a composition unrolls
    its explicit substeps: what its trace reads beyond its arguments."""
    return jax.default_backend() == "cpu" and small_loops_compiled_whole()


def _scaled(terms, substep: Substep, f):
    """`f` times each term's control over the step: the Hermite slopes."""
    if isinstance(terms, tuple):
        return tuple(
            term.prod(fi, step_control(term, substep)) for term, fi in zip(terms, f)
        )
    return terms.prod(f, step_control(terms, substep))


Composition.__init__.__doc__ = """**Arguments:**

- `base`: a symmetric solver: [`diffrax_vi.MidpointVI`][],
    [`diffrax_vi.TrapezoidalVI`][], [`diffrax_vi.StormerVerlet`][],
    [`diffrax_vi.GaussVPRK`][], [`diffrax_vi.LobattoVPRK`][], a [`diffrax_vi.VPRK`][]
    with a symmetric tableau, or a `Composition`.
- `scheme`: a name (`"yoshida4"`, the default; `"suzuki4"`, `"kahan_li6"`,
    `"kahan_li8"`, `"triple_jump"`, `"suzuki_fractal"`), a symmetric sequence of step
    fractions summing to 1, or a [`diffrax_vi.CompositionScheme`][].
"""
