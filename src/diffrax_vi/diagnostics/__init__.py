"""Diagnostics of the geometry of a solver or a solution: the discrete Euler–Lagrange
residuals and 2-forms of Hirani (2000), the symplecticity of a step, and linear
stability on the harmonic oscillator."""

from .._discrete import del_residual as del_residual
from ._forms import (
    del_residuals as del_residuals,
    presymplectic_form as presymplectic_form,
    tangent_discrete_lagrangian as tangent_discrete_lagrangian,
    tangent_symplectic_form as tangent_symplectic_form,
)
from ._loops import (
    compiled_loop_breakers as compiled_loop_breakers,
    loop_breakers as loop_breakers,
)
from ._stability import (
    oscillator_step_matrix as oscillator_step_matrix,
    spectral_radius as spectral_radius,
    stability_limit as stability_limit,
)
from ._symplectic import (
    step_jacobian as step_jacobian,
    symplecticity_defect as symplecticity_defect,
)
