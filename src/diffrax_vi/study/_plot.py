import pathlib

import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt


def plot_drift(study, invariant: str, path: str | pathlib.Path) -> None:
    """Log–log plot of one invariant's error against time, a line per solver."""
    fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
    floor = 1e-17
    for run in study.runs:
        ts, err = run.ts[1:], run.errors[invariant][1:]
        ax.loglog(ts, err + floor, label=f"{run.solver} ({run.wall_time:.2f} s)")
    ax.set_xlabel("time")
    ax.set_ylabel(f"|{invariant}(t) - {invariant}(0)|")
    ax.set_title(
        f"{study.scene}: {study.steps_per_period} steps per period, {study.dtype}"
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.savefig(path, dpi=120)
    plt.close(fig)
