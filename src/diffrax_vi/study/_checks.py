"""Validation of a study's settings, before any work starts."""

import math
from collections.abc import Sequence


def positive(name: str, value: int | float) -> float:
    """`value` as a float, if finite and positive; else a `ValueError` naming it."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}.") from None
    if not (math.isfinite(x) and x > 0):
        raise ValueError(f"{name} must be finite and positive, got {value!r}.")
    return x


def positive_int(name: str, value: int | float) -> int:
    if isinstance(value, bool) or int(value) != value or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def tolerance(value: int | float) -> float:
    """A relative tolerance: finite, in (0, 1)."""
    x = positive("rtol", value)
    if x >= 1:
        raise ValueError(f"rtol must be below 1 (a relative tolerance), got {x!r}.")
    return x


def step_count(periods: int | float, steps_per_period: int | float) -> int:
    """The number of fixed steps `periods * steps_per_period`, which must be a whole
    number: the study never silently rounds the horizon or the step."""
    periods = positive("periods", periods)
    steps_per_period = positive_int("steps_per_period", steps_per_period)
    exact = periods * steps_per_period
    n = round(exact)
    if n < 1 or abs(exact - n) > 1e-9 * max(1.0, exact):
        raise ValueError(
            f"periods * steps_per_period = {periods:g} * {steps_per_period} = "
            f"{exact:g} is not a whole number of steps. Choose periods that are a "
            f"multiple of 1/{steps_per_period}, e.g. periods="
            f"{max(1, n) / steps_per_period:g}."
        )
    return n


def non_empty(name: str, values: Sequence) -> list:
    values = list(values)
    if not values:
        raise ValueError(f"{name} is empty: name at least one.")
    return values


def memory_available() -> int | None:
    """Bytes of memory on the devices an ensemble runs on: the accelerators' limit,
    or the host's physical memory on CPU; `None` where neither is known."""
    import os

    import jax

    devices = jax.devices()
    stats = devices[0].memory_stats() if hasattr(devices[0], "memory_stats") else None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"]) * len(devices)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def ensemble_fits(members: int, per_member: int) -> None:
    """A `ValueError` if `members` runs of `per_member` bytes each would take more
    than half the memory available, instead of an allocation failure after
    compilation."""
    available = memory_available()
    if available is not None and members * per_member > available // 2:
        raise ValueError(
            f"An ensemble of {members} members needs about "
            f"{members * per_member / 2**30:.3g} GiB (the state, the solver's state "
            f"and the recorded errors of each member), more than half the "
            f"{available / 2**30:.3g} GiB available: use at most "
            f"{max(1, available // 2 // per_member)} members, or fewer save "
            "intervals."
        )
