import dataclasses
import pathlib
import threading
from collections.abc import Sequence

import diffrax as dfx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._solver import AbstractSymplecticSolver
from ..scenes import Scene
from ._checks import (
    ensemble_fits,
    non_empty,
    positive,
    positive_int,
    step_count,
)
from ._methods import as_method, Method, ReversibleSteps
from ._run import cast_scene, run_all, shard_ensemble
from ._table import markdown_table, write_records


@dataclasses.dataclass(frozen=True)
class DriftRun:
    """One method's run in a drift study.

    **Fields:**

    - `solver`: the method's name.
    - `steps`: the number of steps taken (the most taken by any ensemble member).
    - `wall_time`: seconds for a plain `diffeqsolve` of the method saving only
        `t1` (vmapped over the whole ensemble), after compilation.
    - `result`: `"successful"`, diffrax's message for the failure, or how many
        ensemble members failed.
    - `ts`: the start and the ends of the `n_save` intervals.
    - `errors`: invariant name -> the largest `|I(t) - I(0)|` over the steps in the
        interval ending at each of `ts` (0 at the start; the largest component of a
        vector invariant; the worst ensemble member; NaN after a failure). An
        interval in which no step ended (an adaptive step longer than it) repeats
        the previous interval's value, the error of the state held through it.
    - `symplectic`: a symplectic method at the study's fixed step.
    - `reversible`: a symmetric method stepped by a
        [`diffrax_vi.ReversibleController`][] (`+Adaptive`).
    - `checked`: a Runge–Kutta method whose vector field checks every evaluation by
        a host callback (a Lagrangian whose velocity or constraint forces can fail),
        which `wall_time` includes; `EQX_ON_ERROR=nan` times it without (see
        [Failures and errors](../errors.md)).
    """

    solver: str
    steps: int
    wall_time: float
    result: str
    ts: np.ndarray
    errors: dict[str, np.ndarray]
    symplectic: bool = False
    reversible: bool = False
    checked: bool = False

    def max_error(self, name: str) -> float:
        """The largest error of the invariant `name` over the whole run (NaN after a
        failure)."""
        return float(np.max(self.errors[name]))

    def growth(self, name: str = "energy") -> float:
        """The largest error over the last tenth of the saves over that of the first
        tenth: about 1 for a bounded error, 10 for one growing linearly in time, and
        huge for a blow-up (past a stability limit the values stay finite, and the
        solve successful, until they overflow)."""
        err = self.errors[name][1:]
        k = max(1, len(err) // 10)
        # An error that is exactly zero at first (a quadratic energy) is round-off.
        eps = float(np.finfo(np.float64).eps)
        return (float(np.max(err[-k:])) + eps) / (float(np.max(err[:k])) + eps)


@dataclasses.dataclass(frozen=True)
class DriftStudy:
    """The result of [`diffrax_vi.study.drift`][]: one
    [`diffrax_vi.study.DriftRun`][] per method, and `step`, the fixed step actually
    taken (`periods * period / (periods * steps_per_period)`).

    `verdict()` says in one line what the numbers show. `parameters` names the
    scene's parameters set apart from its defaults (`"eccentricity=0.9"`, as the
    command line's `--param`), for titles and `drift.json`."""

    scene: str
    periods: int | float
    steps_per_period: int
    dtype: str
    members: int
    runs: list[DriftRun]
    step: float = float("nan")
    parameters: str = ""

    @property
    def invariants(self) -> list[str]:
        return list(self.runs[0].errors) if self.runs else []

    @property
    def energy(self) -> str:
        """The energy's column: `energy`, or for a forced scene `energy_balance`,
        $|E(t) - E(0) - W(t)|$."""
        return "energy_balance" if "energy_balance" in self.invariants else "energy"

    def rows(self) -> list[dict]:
        """The summary table as a list of records; `energy_growth` is
        [`diffrax_vi.study.DriftRun.growth`][]."""
        return [
            dict(
                solver=run.solver,
                steps=run.steps,
                wall_time_s=run.wall_time,
                result=run.result,
                **{f"max_{k}_error": run.max_error(k) for k in self.invariants},
                energy_growth=run.growth(self.energy),
            )
            for run in self.runs
        ]

    def table(self) -> str:
        """The summary as a Markdown table."""
        return markdown_table(self.rows())

    def verdict(self) -> str:
        """One line computed from the table: where more than one invariant is
        monitored, the run whose errors are closest to the best run's on every one
        (the smallest worst factor over the best, so that a run that keeps the
        energy but leaves SO(3) does not win); the run with the lowest energy error
        (and, if it is not that one, the invariant it does worst on); the one with
        the lowest energy error times wall time (the best error for the work); and
        how the errors of the non-symplectic runs grow from the first to the last
        tenth of the horizon against those of the symplectic runs (and of the
        reversible adaptive runs, `+Adaptive`); and which runs' times include their
        vector field's check of every evaluation (`DriftRun.checked`)."""
        ok = [r for r in self.runs if r.result == "successful"]
        if not ok:
            return "Verdict: every run failed (see the result column)."

        energy = self.energy
        what = "energy" if energy == "energy" else "energy-balance"

        def said(r):
            return f"{r.solver} ({r.max_error(energy):.1e} in {r.wall_time:.2g} s)"

        # Each invariant's lowest non-zero error over the runs; a run's worst factor
        # above it (a ratio of errors: the same in any units).
        lowest = {
            k: min(positive)
            for k in self.invariants
            if (positive := [r.max_error(k) for r in ok if r.max_error(k) > 0])
        }

        def worst(r):
            return max(
                ((max(r.max_error(k), low) / low, k) for k, low in lowest.items()),
                default=(1.0, energy),
            )

        best = min(ok, key=lambda r: r.max_error(energy))
        thrifty = min(ok, key=lambda r: r.max_error(energy) * max(r.wall_time, 1e-6))
        parts = []
        if len(self.invariants) > 1:
            overall = min(ok, key=worst)
            factor, _ = worst(overall)
            parts.append(
                f"lowest errors on all {len(self.invariants)} invariants together: "
                f"{overall.solver} (each within x{factor:.2g} of the best run's)"
            )
        lowest_energy = f"lowest {what} error: {said(best)}"
        factor, invariant = worst(best)
        if invariant != energy and factor > 10:
            lowest_energy += f", but its {invariant} error is x{factor:.2g} the best"
        parts.append(lowest_energy)
        if thrifty is not best:
            parts.append(f"best error for the time: {said(thrifty)}")

        def growth(runs):
            values = [r.growth(energy) for r in runs]
            low, high = min(values), max(values)
            return f"x{low:.2g}" if high < 1.5 * low else f"x{low:.2g} to x{high:.2g}"

        others = [r for r in ok if not (r.symplectic or r.reversible)]
        geometric = [r for r in ok if r.symplectic]
        reversible = [r for r in ok if r.reversible]
        if others:
            phrase = f"non-symplectic {what} errors grow {growth(others)}"
            if geometric:
                phrase += f", symplectic ones {growth(geometric)}"
            if reversible:
                phrase += f", reversible adaptive ones {growth(reversible)}"
            parts.append(phrase + " from the first to the last tenth of the horizon")
        failed = len(self.runs) - len(ok)
        if failed:
            parts.append(f"{failed} run(s) failed")
        checked = [r.solver for r in self.runs if r.checked]
        if checked:
            parts.append(
                f"the times of {', '.join(checked)} include their vector field's "
                "check of every evaluation (EQX_ON_ERROR=nan times them without it)"
            )
        return "Verdict: " + "; ".join(parts) + "."

    def write(self, out: str | pathlib.Path) -> list[pathlib.Path]:
        """Write `drift.csv` (summary), `drift.json` (summary and series) and, if
        matplotlib is installed, `drift_<invariant>.png` into the folder `out`."""
        out = pathlib.Path(out)
        written = write_records(
            out,
            "drift",
            self.rows(),
            scene=self.scene,
            parameters=self.parameters,
            periods=self.periods,
            steps_per_period=self.steps_per_period,
            step=self.step,
            fixed_steps=round(self.periods * self.steps_per_period),
            dtype=self.dtype,
            members=self.members,
            series={
                run.solver: dict(
                    ts=run.ts.tolist(),
                    **{k: v.tolist() for k, v in run.errors.items()},
                )
                for run in self.runs
            },
        )
        try:
            from ._plot import plot_drift
        except ImportError:
            return written
        for name in self.invariants:
            written.append(plot_drift(self, name, out / f"drift_{name}.png"))
        return written


def _import_figures() -> None:
    try:
        from . import _plot  # noqa: F401
    except ImportError:  # Without matplotlib a study writes no figures.
        pass


def check_methods(scene: Scene, methods: list) -> None:
    """A forced scene's energy balance needs the work of the applied force, which a
    solver of partitioned terms (dq/dt = f(p), dp/dt = g(q)) cannot tell apart from
    the rest of g: refuse those, naming the same method on the LagrangianTerm."""
    if scene.force is None:
        return
    partitioned = [
        m.name for m in methods if isinstance(m.solver.term_structure, tuple)
    ]
    if partitioned:
        raise ValueError(
            f"{', '.join(partitioned)} integrate(s) partitioned terms, in which the "
            f"applied force of the forced scene {scene.name!r} is not told apart, so "
            "the energy balance E(t) - E(0) - W(t) cannot be measured. Use "
            "TrapezoidalVI (the same Stormer-Verlet step on the LagrangianTerm), "
            "MidpointVI, GaussVPRK2/3, or compositions of them as Methods."
        )


def check_drift(
    scene: Scene,
    methods: Sequence[Method],
    periods: int | float,
    steps_per_period: int | float,
    n_save: int | float | None,
    dtype,
    ensemble: int | float | None = None,
) -> tuple[int, int]:
    """Check a drift study's methods (as [`diffrax_vi.study.as_method`][] makes them)
    and settings without running anything, raising what
    [`diffrax_vi.study.drift`][] would raise (its **Raises**); returns the number of
    fixed steps and of save intervals (`n_save`, or by default the largest divisor
    of the steps up to 1000). The command line calls it before it creates the
    output folder."""
    check_methods(scene, methods)
    n_steps = step_count(periods, steps_per_period)
    if n_save is None:
        n_save = max(k for k in range(1, min(n_steps, 1000) + 1) if n_steps % k == 0)
    if isinstance(n_save, bool) or int(n_save) != n_save or n_steps % n_save:
        raise ValueError(
            f"n_save={n_save} must divide the number of steps {n_steps} "
            f"({periods:g} periods x {steps_per_period}) so that the invariants are "
            "saved on step boundaries."
        )
    if ensemble is not None:
        positive_int("ensemble", ensemble)
        state = sum(jnp.size(x) for x in jax.tree.leaves(scene.y0))
        recorded = (n_save + 1) * len(scene.conserved())
        ensemble_fits(ensemble, jnp.dtype(dtype).itemsize * (recorded + 32 * state))
    return n_steps, int(n_save)


def drift(
    scene: Scene,
    solvers: Sequence[str | dfx.AbstractSolver | Method],
    *,
    periods: int | float = 1000,
    steps_per_period: int = 200,
    n_save: int | None = None,
    dtype=jnp.float64,
    rtol: float = 1e-8,
    ensemble: int | None = None,
    spread: float = 1e-3,
    seed: int = 0,
    shard: bool = True,
    progress: bool = False,
) -> DriftStudy:
    """Run each method on the same scene over the same horizon, and record the error
    of every conserved quantity against time.

    Fixed-step methods all take the same step, `period / steps_per_period`;
    adaptive methods (`"Tsit5+PID"`) choose their own. The error of every
    conserved quantity is taken after every step, and the study records its largest
    value over each of `n_save` equal intervals (a sample every k-th step would alias
    with the motion). The running maximum is kept in the solver state: memory is
    O(`n_save`), not O(steps).

    **Arguments:**

    - `scene`: a [`diffrax_vi.scenes.Scene`][].
    - `solvers`: names from `diffrax_vi.study.SOLVERS` (with the suffix `+PID` for a
        `PIDController` at tolerance `rtol`, or `+Adaptive` for reversible adaptive
        steps on the scene's monitor), solver instances, or
        [`diffrax_vi.study.Method`][]s.
    - `periods`: horizon, in the scene's periods.
    - `steps_per_period`: fixed steps per period (the mean for `+Adaptive`
        methods).
    - `n_save`: how many intervals to record the largest errors over; must divide
        the number of steps (by default the largest divisor up to 1000). An
        adaptive method may take at most 4096 steps per interval (a step size
        collapsing to nothing then fails the run rather than spinning).
    - `dtype`: the floating dtype of the state, the Lagrangian's parameters and the
        times.
    - `rtol`: the tolerance of `+PID` methods.
    - `ensemble`: if given, run this many initial states near the scene's
        ([`diffrax_vi.scenes.Scene.perturbed`][] with `spread` and `seed`) at once,
        with `jax.vmap`; the errors reported are the worst member's.
    - `shard`: split the ensemble across all devices with `jax.sharding` (on one
        device this does nothing).
    - `progress`: show diffrax's tqdm progress meter (the timed run then includes its
        overhead).

    **Returns:**

    A [`diffrax_vi.study.DriftStudy`][].

    **Raises:**

    `ValueError`, before any work, for no solvers or unknown solver names, a
    horizon or step count that is not positive and finite, `periods *
    steps_per_period` that is not a whole number of steps, an `n_save` that does not
    divide the number of steps, an ensemble size that is not a positive integer, or
    an ensemble that cannot be split evenly across the devices.
    """
    methods = [as_method(spec, rtol) for spec in non_empty("solvers", solvers)]
    n_steps, n_save = check_drift(
        scene, methods, periods, steps_per_period, n_save, dtype, ensemble
    )
    if ensemble is not None and spread != 0:
        positive("spread", spread)
    scene = cast_scene(scene, dtype)
    t1 = scene.period * periods
    if ensemble is None:
        y0 = scene.y0
    else:
        y0 = scene.perturbed(jr.key(seed), ensemble, spread)
        if shard:
            y0 = shard_ensemble(y0, ensemble)
    # The figures' import of matplotlib runs beside the solves' compilation and
    # runs, which leave Python's lock free.
    threading.Thread(target=_import_figures, daemon=True).start()
    outcomes = run_all(
        scene,
        methods,
        t1=t1,
        n_steps=n_steps,
        n_save=n_save,
        dtype=dtype,
        y0=y0,
        ensemble=ensemble is not None,
        progress=progress,
    )
    runs = []
    for method, outcome in zip(methods, outcomes):
        runs.append(
            DriftRun(
                solver=method.name,
                steps=outcome.steps,
                wall_time=outcome.wall_time,
                result=outcome.result,
                ts=np.linspace(0, t1, n_save + 1),
                errors=outcome.errors(),
                symplectic=method.fixed
                and isinstance(method.solver, AbstractSymplecticSolver),
                reversible=isinstance(method.stepping, ReversibleSteps),
                checked=outcome.checked,
            )
        )
    return DriftStudy(
        scene=scene.name,
        periods=periods,
        steps_per_period=steps_per_period,
        dtype=jnp.dtype(dtype).name,
        members=1 if ensemble is None else ensemble,
        runs=runs,
        step=float(t1 / n_steps),
    )
