"""How XLA compiles the time-stepping loop on CPU, which decides the speed of small
systems.

XLA's CPU compiler (JAX >= 0.7) runs a `while` loop either as one compiled function
or as a sequence of separately dispatched kernels, one per fused operation. It takes
the first only for a loop whose body accesses fewer than
`xla_cpu_small_while_loop_byte_threshold` bytes, 1 kB by default. The loop of a
`diffeqsolve` on a few degrees of freedom is usually just above that: its solver
state, a save buffer, compensated summation or a Newton fallback take it over, and
each step then pays a dispatch for each of tens of kernels, which on a small system
costs several times the step's arithmetic (`benchmarks/step_cost.py` and
`benchmarks/study_cost.py` measure both settings).

The threshold is read once, when JAX starts its CPU backend, from the environment
variable `XLA_FLAGS`; it cannot be set per compilation.
"""

import os
import re

from ._private_api import backends_are_initialized


# Bytes a loop body may access and still be compiled as one function. 4 MiB covers
# the Newton and Krylov loops of the implicit solvers up to about a thousand degrees
# of freedom (64 KiB stopped at about 60), and leaves the loops of 4096-mass chains,
# whose kernels are large enough to pay for their dispatch, as they were (a far
# larger threshold made them slower); `benchmarks/scaling.py` measures both.
SMALL_LOOP_BYTES = 1 << 22

_OPTION = "xla_cpu_small_while_loop_byte_threshold"


def small_loop_flag(threshold_bytes: int) -> str:
    """The `XLA_FLAGS` entry that sets the threshold."""
    return f"--xla_backend_extra_options={_OPTION}={threshold_bytes}"


def compile_small_loops_whole(threshold_bytes: int = SMALL_LOOP_BYTES) -> bool:
    """Let XLA compile every CPU loop whose body accesses fewer than
    `threshold_bytes` bytes as one function: faster steps on systems of a few
    degrees of freedom, and faster implicit steps on 64 to 1024 degrees of freedom,
    whose Newton and Krylov loops cross XLA's threshold (the ratios are on the
    [Benchmarks](../benchmarks.md) page). No effect on GPUs.

    Call it before JAX runs anything (the first array created or computation run
    starts the backend, which reads the setting once); `import jax` and
    `import diffrax_vi` are fine. The `diffrax-vi` command line calls it itself.

    Returns `False` and changes nothing if `XLA_FLAGS` already sets the threshold
    (the user's choice stands); `True` once set.

    **Raises:** `RuntimeError` if JAX's backend has already started, as the setting
    would then be silently ignored.
    """
    if not isinstance(threshold_bytes, int) or threshold_bytes < 0:
        raise ValueError(
            f"threshold_bytes must be a non-negative integer; got {threshold_bytes!r}."
        )
    flags = os.environ.get("XLA_FLAGS", "")
    if re.search(rf"\b{_OPTION}=", flags):
        return False
    if backends_are_initialized():
        raise RuntimeError(
            "compile_small_loops_whole() must be called before JAX starts its "
            "backend (before the first array is created or computation run): XLA "
            "reads XLA_FLAGS only then. Call it right after the imports, or set "
            f"the environment variable XLA_FLAGS={small_loop_flag(threshold_bytes)} "
            "before starting Python."
        )
    os.environ["XLA_FLAGS"] = f"{flags} {small_loop_flag(threshold_bytes)}".strip()
    return True
