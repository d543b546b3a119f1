import concurrent.futures
import contextlib
import dataclasses
import logging
import math
import os
import re
import time
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, PyTree

from .._misc import all_finite
from .._scan import FixedStepSolution, solve_fixed_steps
from .._solver.base import AbstractStepsByFraction
from .._term import nan_on_failure, start_checked
from ..scenes import Scene
from ._methods import Method
from ._programs import compiled, holds_callback, memoised
from ._track import EnergyBalance, TrackWorstError


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What one method's solve of one scene (or one ensemble of it) produced, as
    NumPy arrays with ensemble members along a leading axis (of size 1 for a single
    solve).

    `max_errors[name][m, i]` is member `m`'s largest `|I(t) - I(0)|` of invariant
    `name` (over the components of a vector invariant) over the steps in the `i`-th
    interval between save times; index 0 is the start, where it is 0. After the
    interval in which a solve failed, it is NaN."""

    max_errors: dict[str, np.ndarray]
    final: PyTree[np.ndarray]
    steps: int
    wall_time: float
    results: list[str]
    # Whether the timed solve checks every evaluation of its vector field by a host
    # callback, which its time includes (`checks_every_evaluation`).
    checked: bool = False

    @property
    def result(self) -> str:
        """`"successful"`, diffrax's message, or how many ensemble members failed."""
        failed = [r for r in self.results if r != "successful"]
        if not failed:
            return "successful"
        if len(self.results) == 1:
            return failed[0]
        return f"{len(failed)} of {len(self.results)} members failed: {failed[0]}"

    def errors(self) -> dict[str, np.ndarray]:
        """The largest error of each invariant in each interval between save times,
        over the ensemble members."""
        return {name: err.max(axis=0) for name, err in self.max_errors.items()}


def cast_scene(scene: Scene, dtype) -> Scene:
    """The scene with every floating array (state and Lagrangian parameters) in
    `dtype`, so that nothing promotes the state back to another precision."""
    return jax.tree.map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, scene
    )


def shard_ensemble(y0s: PyTree[Array], members: int) -> PyTree[Array]:
    """Place an ensemble's initial states across all devices along its leading axis
    (a no-op on one device)."""
    devices = jax.devices()
    if len(devices) == 1:
        return y0s
    if members % len(devices):
        raise ValueError(
            f"An ensemble of {members} members cannot be split evenly across "
            f"{len(devices)} devices: choose a multiple of {len(devices)}, or pass "
            "shard=False."
        )
    mesh = Mesh(np.asarray(devices), ("ensemble",))
    return jax.device_put(y0s, NamedSharding(mesh, PartitionSpec("ensemble")))


def columns(scene: Scene) -> list[str]:
    """The invariants a study records for `scene`, the energy's first: the energy
    balance `energy_balance` of a forced scene, then its conserved quantities."""
    names = list(scene.conserved())
    return names if scene.force is None else ["energy_balance", *names]


class _Solves(eqx.Module):
    """One method's solve of one scene, set up as a plain `diffeqsolve` of it runs:
    the tracked solve that records the errors, and the plain one that is timed."""

    terms: PyTree
    solver: dfx.AbstractSolver
    controller: dfx.AbstractStepSizeController
    args: PyTree
    ts: Array
    dt0: Array | None
    # Fixed steps' `(t0, t1, dt0)` as NumPy values, known when traced as
    # `solve_fixed_steps` needs them and `diffeqsolve` checks them (the solves are
    # traced as closures over this object).
    fixed_times: tuple | None
    conserved: dict
    balance_energy: Callable | None
    max_steps: int | None = eqx.field(static=True)
    steps_per_interval: int | None = eqx.field(static=True)
    # The tracked solve of fixed steps runs in `solve_fixed_steps`'s scan, unless a
    # progress meter (which only diffeqsolve drives) is asked for.
    scan: bool = eqx.field(static=True)
    progress: bool = eqx.field(static=True)

    def diffeqsolve(self, solver, y0, saveat, **kwargs):
        # The method's own steps: an adaptive controller picks its own first step,
        # as it does alone. A bounded loop is checkpointed for reverse-mode
        # differentiation, which copied the per-interval maxima at every step:
        # fixed steps need no bound.
        t0, t1, dt0 = self.ts[0], self.ts[-1], self.dt0
        if self.fixed_times is not None and self.ts.dtype == jnp.result_type(float):
            # Fixed steps' times as a user writes them, Python floats: diffrax
            # checks their order when traced, and our solvers check that they are
            # finite then (`known_value`), so the solve holds no host callback and
            # JAX's persistent cache keeps it. (In float32 they stay arrays: floats
            # would make diffrax's times float64.)
            t0, t1, dt0 = (float(x) for x in self.fixed_times)
        return dfx.diffeqsolve(
            self.terms,
            solver,
            t0,
            t1,
            dt0,
            y0,
            args=self.args,
            saveat=saveat,
            stepsize_controller=self.controller,
            max_steps=self.max_steps,
            throw=False,
            **kwargs,
        )

    def fixed_steps(self, solver, y0) -> FixedStepSolution:
        # The same steps, without diffeqsolve's general loop (see
        # `diffrax_vi.solve_fixed_steps`): states equal to a plain diffeqsolve's.
        return solve_fixed_steps(
            self.terms, solver, *self.fixed_times, y0, self.args, n_save=1
        )

    def plain(self, y0) -> PyTree:
        """The final state of the method alone, as a user would run it: a plain
        `diffeqsolve` saving only `t1`. The tracking adds work to every step and,
        on CPU, can push XLA's compiled loop past the size where it runs as one
        function; `solve_fixed_steps`'s scan takes cheap explicit steps in 0.7x a
        `diffeqsolve`'s time, and a vmapped ensemble's in a quarter of it. So the
        wall time is this solve's."""
        return self.diffeqsolve(self.solver, y0, dfx.SaveAt(t1=True)).ys

    def tracked(self, y0):
        """The largest error of each invariant in each interval, the final state,
        the steps taken and how the solve ended."""
        start = self.ts[0]
        balance = None
        if self.balance_energy is not None:
            energy = self.balance_energy
            balance = EnergyBalance(energy, self.terms, energy(start, y0, self.args))
        solver = TrackWorstError(
            self.solver,
            self.conserved,
            {k: f(start, y0, self.args) for k, f in self.conserved.items()},
            self.ts[1:],
            steps_per_interval=self.steps_per_interval,
            balance=balance,
        )
        if self.scan:
            sol = self.fixed_steps(solver, y0)
            t_reached = sol.t_reached
            # The steps up to and including a failed one, where diffeqsolve stops
            # (the scan goes on, and the tracker counts every step it is given).
            failed = sol.result != dfx.RESULTS.successful
            worst = sol.solver_state.worst
            taken = sol.num_steps + failed.astype(jnp.int32)
        else:
            meter = dfx.TqdmProgressMeter() if self.progress else dfx.NoProgressMeter()
            saveat = dfx.SaveAt(t1=True, solver_state=True)
            sol = self.diffeqsolve(solver, y0, saveat, progress_meter=meter)
            t_reached = sol.ts[-1]
            worst = sol.solver_state.worst
            # Steps counted by the wrapper plus the rejected ones: returning
            # diffrax's own step counters made XLA copy the per-interval maxima at
            # every step.
            taken = worst.steps + sol.stats["num_rejected_steps"]

        # An interval in which no step ended (an adaptive step longer than it)
        # holds the error of the state the method held through it: the previous
        # interval's.
        def fill(previous, row):
            row = jnp.where(row == -jnp.inf, previous, row)
            return row, row

        _, errors = jax.lax.scan(fill, jnp.zeros_like(worst.errors[0]), worst.errors)

        final = jax.tree.map(lambda x: x[-1], sol.ys)
        # diffrax's Runge-Kutta solvers do not check fixed steps for NaN: a blow-up
        # would otherwise be tabled as a success.
        result = dfx.RESULTS.where(
            (sol.result == dfx.RESULTS.successful) & ~all_finite((errors, final)),
            dfx.RESULTS.nonfinite,
            sol.result,
        )
        # Intervals the solve did not reach, after a failure, have no errors.
        reached = self.ts[1:] <= t_reached
        ok = result == dfx.RESULTS.successful
        kept = jnp.where((ok | reached)[:, None], errors, jnp.nan)
        kept = jnp.concatenate([jnp.zeros_like(kept[:1]), kept])
        errors = {k: kept[:, i] for i, k in enumerate(solver.names)}
        return errors, final, taken, result


@dataclasses.dataclass(frozen=True)
class Prepared:
    """One method's two solves of one scene, compiled (see `prepare`): the tracked
    one that records the errors and the plain one that is timed."""

    scene: Scene
    y0: PyTree[Array]
    ensemble: bool
    n_save: int
    tracked: Callable | None
    plain: Callable | None
    # The error that the check of the start raised (then no solve is compiled).
    raised: Exception | None = None
    checked: bool = False


def run(
    scene: Scene,
    method: Method,
    *,
    t1: float,
    n_steps: int,
    n_save: int,
    dtype,
    y0: PyTree[Array],
    ensemble: bool = False,
    progress: bool = False,
) -> Outcome:
    """Solve `scene` from `y0` with `method` to `t1`, recording the largest error of
    each conserved quantity over each of `n_save` equal intervals, and the final
    state. Fixed steps take exactly `n_steps` (which `n_save` must divide); adaptive
    ones take the steps they take in a plain `diffeqsolve` with the same controller
    (at most `MAX_ADAPTIVE_STEPS_PER_SAVE * n_save`): reversible ones about
    `n_steps`, from the `dt0` of [`diffrax_vi.study.reversible_dt0`][]. With
    `ensemble=True`, `y0` has a leading axis of members and the solve is vmapped
    over it (and runs on every device `y0` is sharded over).

    The run is one `diffeqsolve`, as a user would write it: splitting it into one
    solve per interval makes an adaptive controller end every interval on its
    boundary and pick its first step afresh, which changes its steps and its
    errors. The errors are taken at every step, not sampled (a sample every k-th
    step aliases with the motion), by wrapping the solver in `TrackWorstError`,
    which keeps each interval's maximum in its solver state: memory is O(`n_save`),
    not O(steps).

    The tracked solve of fixed steps runs in `diffrax_vi.solve_fixed_steps`, which
    calls the solver's own `init` and `step` at the times `diffeqsolve` would, in
    an unrolled scan: a plain `diffeqsolve`'s states to round-off, without the
    overhead of its general loop, unless `progress` asks for diffrax's progress
    meter. The wall time is of a separate plain `diffeqsolve` of the same method
    (vmapped for an ensemble), saving only `t1`: what the method costs a user
    rather than the study: the best of up to three compiled calls, as many as start
    within a second."""
    with _quiet_checks():
        return execute(
            prepare(
                scene,
                method,
                t1=t1,
                n_steps=n_steps,
                n_save=n_save,
                dtype=dtype,
                y0=y0,
                ensemble=ensemble,
                progress=progress,
            )
        )


def run_all(scene: Scene, methods: list[Method], **kwargs) -> list[Outcome]:
    """`run` of each of `methods` on `scene` (same keywords), their solves traced
    and compiled concurrently, one thread per core: XLA compiles and runs without
    Python's lock, so one method's compilation overlaps the next one's tracing.
    Each tracked solve, which is not timed, runs as soon as it is compiled. The
    timed runs then take their turns, alone on the machine, so each wall time is a
    plain solve's."""

    def ready(method: Method) -> tuple[Prepared, tuple | Exception]:
        prepared = prepare(scene, method, **kwargs)
        return prepared, track(prepared)

    workers = max(1, min(len(methods), os.cpu_count() or 1))
    with _quiet_checks():
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            done = list(pool.map(ready, methods))
        return [execute(prepared, tracked) for prepared, tracked in done]


class _CheckFailed(logging.Filter):
    """Drops JAX's log of a host callback that raised ("jax.pure_callback failed",
    with the traceback of equinox's check): a study catches that check's error and
    tables its message (`_raised`), and any other error is raised again, with its
    traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "jax.pure_callback failed"


@contextlib.contextmanager
def _quiet_checks():
    """While a study runs its solves, a check that fails in one of them is that
    method's row, not a traceback on stderr before the table."""
    logger = logging.getLogger("jax._src.callback")
    quiet = _CheckFailed()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


def prepare(
    scene: Scene,
    method: Method,
    *,
    t1: float,
    n_steps: int,
    n_save: int,
    dtype,
    y0: PyTree[Array],
    ensemble: bool = False,
    progress: bool = False,
) -> Prepared:
    """The tracked and the plain solve of `run`, traced and compiled for `y0`."""
    first = jax.tree.map(lambda x: x[0], y0) if ensemble else y0
    fixed = method.fixed
    ts = jnp.linspace(0, t1, n_save + 1, dtype=dtype)
    dt0 = method.stepping.dt0(scene, method, t1, n_steps, first, dtype)
    terms = method.terms(scene)
    # This package's solvers check a start by host callback: the study checks it
    # apart (`_StartCheck`), so that their solves hold none there and a study run
    # again loads them (`compiled`). diffrax's solvers check no start.
    ours = isinstance(method.solver, AbstractStepsByFraction)
    solves = _Solves(
        terms=start_checked(terms) if ours else terms,
        solver=method.solver,
        controller=method.controller(scene),
        args=scene.args,
        ts=ts,
        dt0=dt0,
        # Read on the host: indexing `ts` would compile a program per index.
        fixed_times=tuple(np.asarray(x) for x in (*np.asarray(ts)[[0, -1]], dt0))
        if fixed
        else None,
        conserved=scene.conserved(),
        balance_energy=None if scene.force is None else scene.energy,
        max_steps=method.stepping.max_steps(n_steps, n_save),
        steps_per_interval=n_steps // n_save if fixed else None,
        scan=fixed and not progress,
        progress=progress,
    )
    # The arrays of `solves` are constants of the compiled solves, as a closure's.
    name = f"{method.name}, {t1}, {n_steps}, {n_save}, {dtype}, {ensemble}, {progress}"
    check = _StartCheck(method.solver, terms, solves, ensemble) if ours else None
    # A Runge-Kutta step evaluates the vector field, which raises by host callback
    # where a mechanism's constraint forces or a Legendre map cannot be solved:
    # the tracked solve's makes NaN there instead, so that it compiles its loop
    # whole and is kept, and the timed solve, a user's, raises why (`execute`).
    watched_terms = terms if ours else nan_on_failure(terms)
    watched = (
        solves
        if watched_terms is terms
        else eqx.tree_at(lambda s: s.terms, solves, watched_terms)
    )
    # (The start time read on the host, as `fixed_times` below.)
    checked = watched_terms is not terms and checks_every_evaluation(
        terms, np.asarray(ts)[0], first, scene.args
    )
    try:
        tracked = compiled(
            f"tracked {name}", _tracked, watched, y0, vmapped=ensemble, check=check
        )
        plain = compiled(
            f"plain {name}", _plain, solves, y0, vmapped=ensemble, check=check
        )
    except _CHECKS as error:
        return Prepared(scene, y0, ensemble, n_save, None, None, _raised(error))
    return Prepared(scene, y0, ensemble, n_save, tracked, plain, checked=checked)


def checks_every_evaluation(terms: PyTree, t0, y0: PyTree, args: PyTree) -> bool:
    """Whether the vector field of `terms` at `y0` checks its evaluation by a host
    callback (a `LagrangianTerm` whose velocity or constraint forces can fail), so
    that a Runge-Kutta solve's time includes that check in every stage: not under
    equinox's `EQX_ON_ERROR=nan`, which makes the check a NaN."""
    jaxpr = jax.make_jaxpr(lambda y: terms.vf(t0, y, args))(y0)
    return holds_callback(jaxpr.jaxpr)


@dataclasses.dataclass
class _StartCheck:
    """The checks of a solve's start that `start_checked` leaves out of its
    programs: the solver's `init` on the terms as they are, compiled and run on
    `y0` where it holds any (it raises what a plain `diffeqsolve` would raise
    there), once. The compiled check is kept in the process as the solves are
    (`memoised`)."""

    solver: dfx.AbstractSolver
    terms: PyTree
    solves: _Solves
    vmapped: bool
    done: bool = False

    def __call__(self, y0: PyTree[Array]) -> None:
        if self.done:
            return
        solves = self.solves
        # The times of the first step, as `_Solves.diffeqsolve` passes them.
        if solves.fixed_times is not None:
            t0, t1, dt0 = (float(x) for x in solves.fixed_times)
        else:
            t0, t1, dt0 = solves.ts[0], solves.ts[-1], solves.dt0
        end = t1 if dt0 is None else t0 + dt0
        start = (self.solver, self.terms, t0, end, solves.args, self.vmapped)
        check = memoised("start check", _check_start, start, y0)
        jax.block_until_ready(check(y0))
        self.done = True


def _check_start(start: tuple, y0: PyTree[Array]) -> Callable:
    """`init` of `start = (solver, terms, t0, t1, args, vmapped)` at `y0` (vmapped
    over it if `vmapped`) compiled, where it checks anything by host callback; else
    a function that does nothing."""
    solver, terms, t0, t1, args, vmapped = start

    def init(y):
        return solver.init(terms, t0, t1, y, args)

    traced = jax.jit(jax.vmap(init) if vmapped else init).trace(y0)
    if holds_callback(traced.jaxpr.jaxpr):
        return traced.lower().compile()
    return lambda y: None


def _tracked(solves: _Solves, y0: PyTree[Array]) -> tuple:
    """The tracked solve, returning arrays only: its result as the array of its
    code, which a program kept between runs (`compiled`) needs."""
    *rest, result = solves.tracked(y0)
    return (*rest, jax.tree.leaves(result)[0])


def _plain(solves: _Solves, y0: PyTree[Array]) -> PyTree[Array]:
    return solves.plain(y0)


def _result(code: np.ndarray) -> dfx.RESULTS:
    """The `RESULTS` of a code from `_tracked` (an array, as equinox reads one)."""
    return jax.tree.unflatten(jax.tree.structure(dfx.RESULTS.successful), [code])


def track(prepared: Prepared) -> tuple | Exception:
    """Run the prepared tracked solve: its outputs, or the error it (or the check
    of its start) raised."""
    if prepared.raised is not None:
        return prepared.raised
    try:
        return jax.block_until_ready(prepared.tracked(prepared.y0))
    except _CHECKS as error:
        return _raised(error)


# What a compiled program raises where one of its checks fails: equinox's error, or
# JAX's around it (`_raised` tells them from other runtime errors).
_CHECKS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)


def _raised(error: Exception) -> Exception:
    """`error`, if it is a check's (equinox's, which a compiled program raises
    inside JAX's own); else raised again. A start off its group or its
    constraints, or a vector field that cannot return a RESULTS (a Runge-Kutta
    solve of a LagrangianTerm that left where the Legendre map or the constraint
    forces can be solved): this method's row says why, the others still run."""
    if "EquinoxRuntimeError" not in str(error):
        raise error
    return error


def execute(prepared: Prepared, tracked: tuple | Exception | None = None) -> Outcome:
    """The outcome of the prepared solves: the tracked one's errors (`tracked`,
    from `track`, or run now), and the plain one's time."""
    scene, y0, ensemble, n_save = (
        prepared.scene,
        prepared.y0,
        prepared.ensemble,
        prepared.n_save,
    )
    if tracked is None:
        tracked = track(prepared)
    if isinstance(tracked, Exception):
        return _failed(scene, y0, ensemble, n_save, tracked)
    # On the host, where reading them compiles nothing.
    errors, final, steps, code = jax.tree.map(np.asarray, tracked)
    plain = prepared.plain
    # Compiled already (`prepare`): the best of the calls is the time, with no call
    # to warm up first.
    times = []
    try:
        while len(times) < 3 and sum(times) < 1.0:
            start = time.perf_counter()
            jax.block_until_ready(plain(y0))
            times.append(time.perf_counter() - start)
    except _CHECKS as error:
        # A vector field that raised where the tracked solve's made NaN.
        return _failed(scene, y0, ensemble, n_save, _raised(error))
    wall_time = min(times)
    if not ensemble:
        errors, final, steps, code = jax.tree.map(
            lambda x: np.expand_dims(x, 0), (errors, final, steps, code)
        )
    # diffrax's messages run to paragraphs; a table cell gets the first sentence.
    results = [
        dfx.RESULTS[_result(np.asarray(code[i]))].split(". ")[0] or "successful"
        for i in range(steps.shape[0])
    ]
    return Outcome(
        # In the scene's order (energy first), not the sorted order of a JAX dict.
        max_errors={k: np.asarray(errors[k], np.float64) for k in columns(scene)},
        final=final,
        steps=int(np.max(steps)),
        wall_time=wall_time,
        results=results,
        checked=prepared.checked,
    )


def _failed(
    scene: Scene, y0: PyTree, ensemble: bool, n_save: int, error: Exception
) -> Outcome:
    """The outcome of a solve that raised: no errors, no state, no time, and the
    error's message (its first line, as the table shows) as the result."""
    members = jax.tree.leaves(y0)[0].shape[0] if ensemble else 1
    errors = np.full((members, n_save + 1), np.nan)
    errors[:, 0] = 0.0
    # equinox puts the stack first and its own advice after the message.
    text = str(error)
    found = re.search(r"EquinoxRuntimeError: (.*?)(\n\n|$)", text, re.S)
    message = (found.group(1) if found else text).strip().split("\n")[0]
    lead = () if ensemble else (1,)
    return Outcome(
        max_errors={k: errors.copy() for k in columns(scene)},
        final=jax.tree.map(lambda x: np.full(lead + np.shape(x), np.nan), y0),
        steps=0,
        wall_time=math.nan,
        results=[f"raised: {message}"] * members,
    )
