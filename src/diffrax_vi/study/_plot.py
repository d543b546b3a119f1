"""Figures of the studies, drawn on `matplotlib.figure.Figure` directly: no pyplot,
so the user's backend is never touched."""

import pathlib

import numpy as np
from matplotlib.figure import Figure


# Errors are plotted on log axes; an exact zero (energy of a quadratic Lagrangian
# under a variational integrator) is shown at this floor rather than dropped.
FLOOR = 1e-17


def _scene(study) -> str:
    return f"{study.scene}({study.parameters})" if study.parameters else study.scene


def plot_drift(study, invariant: str, path: pathlib.Path) -> pathlib.Path:
    """Log–log plot of one invariant's error against time, a line per solver."""
    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.subplots()
    for run in study.runs:
        ts, err = run.ts[1:], run.errors[invariant][1:]
        ax.loglog(ts, err + FLOOR, label=f"{run.solver} ({run.wall_time:.3g} s)")
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


def plot_work_precision(study, path: pathlib.Path) -> pathlib.Path:
    """Energy error and global error against wall time, a line per solver."""
    fig = Figure(figsize=(13, 4.5), layout="constrained")
    axes = fig.subplots(1, 2)
    for key, ax in zip(("max_energy_error", "global_error"), axes):
        for solver in dict.fromkeys(r["solver"] for r in study.records):
            points = sorted(
                (r["wall_time_s"], r[key] + FLOOR)
                for r in study.records
                if r["solver"] == solver and np.isfinite(r[key])
            )
            if points:
                style = "--" if solver.startswith(("Tsit5", "Dopri")) else "-"
                ax.loglog(*zip(*points), style + "o", ms=3, label=solver)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel(key.replace("_", " "))
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    fig.suptitle(f"{_scene(study)}: {study.periods:g} periods, {study.dtype}")
    fig.savefig(path, dpi=110)
    return path
