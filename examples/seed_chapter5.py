"""Reproduce Chapter 5 (and Figures 1.1/1.2) of Hirani (2000): A. N. Hirani,
*Linearization methods for variational integrators and Euler-Lagrange equations*
(Caltech, 2000). The same as `diffrax-vi seed`.

Writes `chapter5.md` (the tables, beside the thesis's numbers) and PNG figures into
`--out` (default `seed-results`). Run: `python examples/seed_chapter5.py`.
"""

import argparse

import jax


jax.config.update("jax_enable_x64", True)
from diffrax_vi.thesis import chapter5  # noqa: E402


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="seed-results")
    print(chapter5(parser.parse_args().out))
