r"""The order conditions of a partitioned Runge–Kutta method, by bicoloured trees.

A partitioned method with coefficients $a$ (positions), $\bar a$ (momenta) and one
set of weights $b$ has order $p$ exactly when $b^\top u(t) = 1/\gamma(t)$ for every
rooted tree $t$ of at most $p$ vertices whose non-root vertices are coloured
(Hairer, Lubich & Wanner, *Geometric Numerical Integration*, III.2.1). $u(t)$ is the
stage vector $\prod_c A_c\,u(c)$ over the root's subtrees $c$, with $A_c = a$ for a
subtree rooted at a position vertex and $\bar a$ at a momentum vertex, and $\gamma$
the tree's density. With equal weights for both parts, the root's colour does not
enter, so each condition is checked once per colouring of the other vertices.
"""

import functools
import itertools

import numpy as np

from .._tolerance import ORDER_CONDITION_ATOL


# Checked tree by tree up to this order (9498 conditions at order 8).
TREE_ORDER_MAX = 8


def _partitions(n: int, largest: int):
    """The partitions of `n` into parts of at most `largest`, largest part first."""
    if n == 0:
        yield ()
        return
    for part in range(min(n, largest), 0, -1):
        for rest in _partitions(n - part, part):
            yield (part, *rest)


def _forests(n: int, subtrees: dict[int, list]):
    """Every multiset of subtrees (each a `(u, gamma)` pair) of total order `n`."""
    for partition in _partitions(n, n):
        groups = [
            itertools.combinations_with_replacement(subtrees[size], count)
            for size, count in ((k, partition.count(k)) for k in sorted(set(partition)))
        ]
        for choice in itertools.product(*groups):
            yield [tree for group in choice for tree in group]


@functools.cache
def _order(a: bytes, a_bar: bytes, b: bytes, s: int, claimed: int) -> int:
    matrices = [np.frombuffer(m).reshape(s, s) for m in (a, a_bar)]
    weights = np.frombuffer(b)
    # subtrees[n]: (A u(c), gamma(c)) for every coloured subtree c of order n.
    subtrees: dict[int, list] = {}
    for n in range(1, claimed + 1):
        rooted = []
        for forest in _forests(n - 1, subtrees):
            u = np.prod([stage for stage, _ in forest], axis=0) * np.ones(s)
            gamma = n * np.prod([g for _, g in forest])
            if abs(weights @ u - 1 / gamma) > ORDER_CONDITION_ATOL:
                return n - 1
            rooted.append((u, gamma))
        subtrees[n] = [(m @ u, gamma) for u, gamma in rooted for m in matrices]
    return claimed


def satisfied_order(a: np.ndarray, a_bar: np.ndarray, b: np.ndarray, claimed: int):
    """The largest order up to `claimed` whose conditions the coefficients meet."""
    s = b.shape[0]
    return _order(a.tobytes(), a_bar.tobytes(), b.tobytes(), s, claimed)
