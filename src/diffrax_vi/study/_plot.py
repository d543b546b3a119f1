"""Figures of the studies, drawn on `matplotlib.figure.Figure` directly: no pyplot,
so the user's backend is never touched."""

import pathlib
import re

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatterSciNotation


# Errors are plotted on log axes; an exact zero (energy of a quadratic Lagrangian
# under a variational integrator) is shown at this floor rather than dropped.
FLOOR = 1e-17

_SUPERSCRIPTS = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


class _UnicodeLogFormatter(LogFormatterSciNotation):
    """matplotlib's labels of a log axis (which ticks get one, and what it says, as
    `LogFormatterSciNotation` decides), written in Unicode superscripts (10⁻¹⁵, 2×10³)
    instead of mathtext: the same labels, without parsing a mathtext expression for
    each, which took 0.1-0.25 s of a process's first figures."""

    def __call__(self, x, pos=None) -> str:
        label = super().__call__(x, pos)
        label = label.removeprefix(r"$\mathdefault{").removesuffix("}$")
        return re.sub(
            r"\^\{(-?\d+)\}",
            lambda m: m.group(1).translate(_SUPERSCRIPTS),
            label.replace(r"\times", "×"),
        )


def _log_labels(ax) -> None:
    """Label both log axes of `ax` with `_UnicodeLogFormatter`, as matplotlib's
    log scale sets up its own (every minor tick may get a label)."""
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(_UnicodeLogFormatter())
        axis.set_minor_formatter(_UnicodeLogFormatter(labelOnlyBase=False))


def _scene(study) -> str:
    return f"{study.scene}({study.parameters})" if study.parameters else study.scene


def plot_drift(study, invariant: str, path: pathlib.Path) -> pathlib.Path:
    """Log–log plot of one invariant's error against time, a line per solver."""
    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.subplots()
    for run in study.runs:
        ts, err = run.ts[1:], run.errors[invariant][1:]
        ax.loglog(ts, err + FLOOR, label=f"{run.solver} ({run.wall_time:.3g} s)")
    _log_labels(ax)
    ax.set_xlabel("time")
    ax.set_ylabel(f"|{invariant}(t) - {invariant}(0)|")
    members = f", worst of {study.members}" if study.members > 1 else ""
    ax.set_title(
        f"{_scene(study)}: {study.steps_per_period} steps per period, "
        f"{study.dtype}{members}"
    )
    ax.grid(True, which="both", alpha=0.3)
    # Beside the axes, where it covers no line.
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.savefig(path, dpi=120)
    return path


def _styles(solvers) -> dict:
    """A line style per solver, the same in every panel of a figure: ours solid with
    round markers, diffrax's Runge–Kutta solvers dashed with square ones, each group
    through matplotlib's ten default colours (a figure's thirteen solvers would
    otherwise share colours)."""
    rk = [s for s in solvers if s.startswith(("Tsit5", "Dopri"))]
    ours = [s for s in solvers if s not in rk]
    styles = {
        s: dict(ls="-", marker="o", color=f"C{i % 10}") for i, s in enumerate(ours)
    }
    styles |= {
        s: dict(ls="--", marker="s", color=f"C{i % 10}") for i, s in enumerate(rk)
    }
    return styles


def plot_work_precision(study, path: pathlib.Path) -> pathlib.Path:
    """Energy error and global error against wall time, a line per solver, one
    legend for both panels."""
    fig = Figure(figsize=(13, 4.5), layout="constrained")
    axes = fig.subplots(1, 2)
    styles = _styles(list(dict.fromkeys(r["solver"] for r in study.records)))
    handles = {}
    for key, ax in zip(("max_energy_error", "global_error"), axes):
        for solver, style in styles.items():
            points = sorted(
                (r["wall_time_s"], r[key] + FLOOR)
                for r in study.records
                if r["solver"] == solver and np.isfinite(r[key])
            )
            if points:
                (line,) = ax.loglog(*zip(*points), ms=3, label=solver, **style)
                handles.setdefault(solver, line)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel(key.replace("_", " "))
        if ax.lines:
            _log_labels(ax)
            ax.grid(True, which="both", alpha=0.3)
        else:  # A chaotic scene's global error past its reference's horizon.
            ax.set_xticks([]), ax.set_yticks([])
            ax.text(0.5, 0.5, "no finite values", ha="center", transform=ax.transAxes)
    labels = [s for s in styles if s in handles]
    axes[1].legend(
        [handles[s] for s in labels],
        labels,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        fontsize=7,
    )
    fig.suptitle(f"{_scene(study)}: {study.periods:g} periods, {study.dtype}")
    fig.savefig(path, dpi=110)
    return path
