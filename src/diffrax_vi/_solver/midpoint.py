from typing import ClassVar

import optimistix as optx

from .implicit import IMPLICIT_ARGS_DOC
from .vprk import AbstractVPRK, gauss_tableau, VPRKTableau


class MidpointVI(AbstractVPRK):
    r"""Midpoint variational integrator.

    2nd order symmetric symplectic variational integrator. One nonlinear solve per step
    (Newton, from a second-order extrapolated guess). Fixed step sizes only. Cubic
    Hermite interpolation for dense output.

    Discrete Lagrangian (Hirani (2000), eq. (3.3)):

    $$L_d(q_0, q_1) = h\,L\Big(t_0 + \tfrac h2, \tfrac{q_0 + q_1}2,
    \tfrac{q_1 - q_0}h\Big),$$

    stepped in position–momentum form on $y = (q, p)$: solve
    $p_0 = -D_1 L_d(q_0, q_1)$ for $q_1$, then $p_1 = D_2 L_d(q_0, q_1)$ (the discrete
    Legendre transforms, Hirani (2000), eq. (3.4)). It is the one-stage Gauss
    [`diffrax_vi.VPRK`][], `GaussVPRK(1)`. It conserves every quadratic first integral
    and, by the discrete Noether theorem, the momentum of every symmetry of $L$.

    ??? cite "References"

        ```bibtex
        @mastersthesis{hirani2000linearization,
            title={Linearization methods for variational integrators and
                   {E}uler--{L}agrange equations},
            author={Hirani, Anil N.},
            school={California Institute of Technology},
            year={2000},
        }
        @article{marsden2001discrete,
            title={Discrete mechanics and variational integrators},
            author={Marsden, Jerrold E. and West, Matthew},
            journal={Acta Numerica},
            volume={10},
            pages={357--514},
            year={2001},
        }
        ```
    """

    tableau: ClassVar[VPRKTableau] = gauss_tableau(1)

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 16
    compensated: bool = True


MidpointVI.__init__.__doc__ = "**Arguments:**\n\n" + IMPLICIT_ARGS_DOC
