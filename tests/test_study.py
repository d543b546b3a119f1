import csv
import dataclasses
import json
import os
import pathlib
import re
import subprocess
import sys
import textwrap

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import matplotlib.image
import numpy as np
import pytest
from diffrax_vi import scenes
from diffrax_vi.cli import main
from diffrax_vi.scenes import kepler
from diffrax_vi.study import _programs, drift, Method, work_precision
from diffrax_vi.study._track import TrackWorstError

from .helpers import max_abs_diff, scene as make_scene, untrained_learned_scene


ROOT = pathlib.Path(__file__).parent.parent
ARGS = ["--periods", "2", "--steps-per-period", "50", "--save", "10"]


def test_drift_errors_match_a_hand_computed_solve():
    scene = kepler()
    study = drift(scene, ["MidpointVI"], periods=2, steps_per_period=50, n_save=10)
    run = study.runs[0]
    assert run.steps == 100 and run.result == "successful"
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(scene.lagrangian),
        dvi.MidpointVI(),
        0.0,
        4 * np.pi,
        4 * np.pi / 100,
        scene.y0,
        saveat=dfx.SaveAt(steps=True),
        max_steps=100,
    )
    q, p = sol.ys
    e = 0.5 * jnp.sum(p**2, axis=1) - 1 / jnp.linalg.norm(q, axis=1)
    # The largest error over each tenth of the steps, not a sample every tenth step.
    per_interval = np.abs(np.asarray(e) - (-0.5)).reshape(10, 10).max(axis=1)
    assert np.allclose(run.errors["energy"][1:], per_interval, atol=1e-14)
    sampled = np.abs(np.asarray(e[9::10]) - (-0.5))
    assert np.all(per_interval >= sampled) and np.any(per_interval > 2 * sampled)
    # The energy of the initial state is exactly -1/2 for this scene.
    assert run.errors["energy"][0] == 0


def test_adaptive_errors_are_over_the_accepted_steps():
    # One interval of an adaptive study takes the same steps as a plain diffeqsolve;
    # its largest energy error is over the accepted steps (rejected ones are many).
    scene = kepler()
    study = drift(
        scene, ["Tsit5+PID"], periods=2, steps_per_period=50, n_save=1, rtol=1e-6
    )
    run = study.runs[0]
    sol = dfx.diffeqsolve(
        dfx.ODETerm(lambda t, y, args: (y[1], -y[0] / jnp.sum(y[0] ** 2) ** 1.5)),
        dfx.Tsit5(),
        0.0,
        4 * np.pi,
        None,
        scene.y0,
        saveat=dfx.SaveAt(steps=True),
        stepsize_controller=dfx.PIDController(rtol=1e-6, atol=1e-6),
    )
    accepted = int(sol.stats["num_accepted_steps"])
    assert sol.stats["num_rejected_steps"] > 10
    assert run.steps == sol.stats["num_steps"]
    q, p = (y[:accepted] for y in sol.ys)
    e = 0.5 * jnp.sum(p**2, axis=1) - 1 / jnp.linalg.norm(q, axis=1)
    assert run.errors["energy"][1] == pytest.approx(np.abs(e + 0.5).max(), rel=1e-12)


@pytest.mark.parametrize("n_save", [1, 50])
def test_adaptive_study_takes_the_steps_of_a_plain_solve(n_save):
    # However many save intervals the study records, an adaptive method takes exactly
    # the steps it takes alone, and the recorded maxima are over exactly those steps.
    # (One diffeqsolve per interval took 3900 steps instead of 1535 for Dopri8 on
    # Kepler over 100 periods, and showed a 4x smaller energy error.)
    scene = kepler()
    periods, rtol = 4, 1e-6
    study = drift(
        scene,
        ["Dopri8+PID"],
        periods=periods,
        steps_per_period=50,
        n_save=n_save,
        rtol=rtol,
    )
    run = study.runs[0]
    t1 = scene.period * periods
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(scene.lagrangian),
        dfx.Dopri8(),
        0.0,
        t1,
        None,
        scene.y0,
        saveat=dfx.SaveAt(steps=True),
        stepsize_controller=dfx.PIDController(rtol=rtol, atol=rtol),
        max_steps=4096,
    )
    accepted = int(sol.stats["num_accepted_steps"])
    assert run.steps == int(sol.stats["num_steps"]) and run.result == "successful"
    ts = np.asarray(sol.ts[:accepted])
    q, p = (np.asarray(y[:accepted]) for y in sol.ys)
    e = np.abs(0.5 * np.sum(p**2, axis=1) - 1 / np.linalg.norm(q, axis=1) + 0.5)
    # The same final state, to round-off.
    from diffrax_vi.study import as_method
    from diffrax_vi.study._run import run as run_method

    outcome = run_method(
        scene,
        as_method("Dopri8+PID", rtol),
        t1=t1,
        n_steps=periods * 50,
        n_save=n_save,
        dtype=jnp.float64,
        y0=scene.y0,
    )
    assert outcome.steps == run.steps
    assert max_abs_diff([x[0] for x in outcome.final], [q[-1], p[-1]]) < 1e-13
    # Each interval's maximum is over the accepted steps ending in it; one in
    # which no step ended repeats the previous interval's.
    bounds = run.ts
    expected = 0.0
    for i in range(n_save):
        inside = (ts > bounds[i]) & (ts <= bounds[i + 1] * (1 + 1e-15))
        expected = e[inside].max() if inside.any() else expected
        assert run.errors["energy"][i + 1] == pytest.approx(expected, rel=1e-10)


def test_methods_compiled_together_run_as_each_alone():
    # A study compiles its methods' solves concurrently, then runs them in turn:
    # each method's errors and final state are those of a study of it alone.
    methods = ["MidpointVI", "StormerVerlet"]
    kwargs = dict(periods=2, steps_per_period=50, n_save=10)
    together = drift(kepler(), methods, **kwargs).runs
    for method, run in zip(methods, together):
        _programs._memo.clear()  # Compiled alone, not reused from the study above.
        (alone,) = drift(kepler(), [method], **kwargs).runs
        assert run.solver == alone.solver == method
        assert run.steps == alone.steps and run.result == alone.result
        assert all(np.array_equal(run.errors[k], alone.errors[k]) for k in run.errors)


def test_wall_time_is_of_the_method_alone(monkeypatch):
    # The tracking of errors adds work to every step (on CPU it made Stormer-Verlet on
    # Kepler 25x slower), so a study times a separate plain solve: the solver itself,
    # unwrapped, in a diffeqsolve saving only t1, with the study's step and
    # controller, fixed steps included (solve_fixed_steps's scan runs cheap explicit
    # steps faster than diffeqsolve does). Only the tracked fixed-step solve runs in
    # the scan.
    from diffrax_vi.study import _run

    calls, times = [], {}
    original = dfx.diffeqsolve
    original_fixed = _run.solve_fixed_steps

    def spy(terms, solver, t0, t1, dt0, y0, **kwargs):
        calls.append((solver, dt0, kwargs["saveat"], kwargs["stepsize_controller"]))
        times[type(solver)] = (t0, t1, dt0)
        return original(terms, solver, t0, t1, dt0, y0, **kwargs)

    def spy_fixed(terms, solver, t0, t1, dt0, y0, args, **kwargs):
        calls.append((solver, dt0, None, None))
        return original_fixed(terms, solver, t0, t1, dt0, y0, args, **kwargs)

    monkeypatch.setattr(dfx, "diffeqsolve", spy)
    monkeypatch.setattr(_run, "solve_fixed_steps", spy_fixed)
    study = drift(kepler(), ["StormerVerlet", "Tsit5+PID"], periods=1, n_save=5)
    assert [r.result for r in study.runs] == ["successful"] * 2
    (fixed,) = [c for c in calls if c[2] is None]
    assert isinstance(fixed[0], TrackWorstError)
    assert fixed[1] == pytest.approx(kepler().period / 200)
    plain = [c for c in calls if c[2] == dfx.SaveAt(t1=True)]
    assert [type(c[0]) for c in plain] == [dvi.StormerVerlet, dfx.Tsit5]
    (_, verlet_dt0, _, verlet_control), (_, dt0, _, control) = plain
    assert verlet_dt0 == pytest.approx(kepler().period / 200)
    assert verlet_control == dfx.ConstantStepSize()
    assert dt0 is None and control == dfx.PIDController(rtol=1e-8, atol=1e-8)
    # Fixed steps' times are Python floats, as a user writes them: diffrax then
    # checks their order when traced, and a Runge-Kutta solve holds no host callback
    # (which JAX's persistent cache would not store); from arrays it holds one.
    verlet_times = times[dvi.StormerVerlet]
    assert all(type(t) is float for t in verlet_times)
    term = kepler().term()

    def lowered(*times):
        solve = lambda y0: original(term, dfx.Tsit5(), *times, y0, throw=False).ys
        return jax.jit(solve).lower(kepler().y0).as_text()

    assert "callback" not in lowered(*verlet_times)
    assert "callback" in lowered(*map(jnp.asarray, verlet_times))


DEFAULT = ["MidpointVI", "StormerVerlet", "KahanLi8", "Tsit5", "Dopri8", "Dopri8+PID"]


def test_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "results"
    assert main(["drift", *ARGS, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in DEFAULT:
        assert name in printed
    with open(out / "drift.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["solver"] for r in rows] == DEFAULT
    api = drift(
        kepler(), ["MidpointVI", "Tsit5"], periods=2, steps_per_period=50, n_save=10
    )
    by_name = {r["solver"]: r for r in rows}
    for run in api.runs:
        assert float(by_name[run.solver]["max_energy_error"]) == pytest.approx(
            run.max_error("energy"), rel=1e-12
        )
        assert int(by_name[run.solver]["steps"]) == 100
        # Kepler's separable term checks its mass once: no check in Tsit5's steps.
        assert not run.checked
    assert "vector field" not in api.verdict()
    data = json.loads((out / "drift.json").read_text())
    assert data["scene"] == "kepler" and len(data["series"]["Tsit5"]["energy"]) == 11
    # The step actually taken: two periods of 2 pi in 100 steps.
    assert data["step"] == pytest.approx(4 * np.pi / 100, rel=1e-14)
    assert data["fixed_steps"] == 100
    for name in ("energy", "angular_momentum"):
        png = out / f"drift_{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert matplotlib.image.imread(png).shape[0] > 100
    # The verdict is the table's numbers, in a line.
    verdict = [line for line in printed.splitlines() if line.startswith("Verdict")]
    best = min(rows, key=lambda r: float(r["max_energy_error"]))
    assert (
        len(verdict) == 1 and f"lowest energy error: {best['solver']} (" in (verdict[0])
    )
    assert "non-symplectic energy errors grow" in verdict[0]


SUPERSCRIPT_DIGITS = str.maketrans("⁻⁰¹²³⁴⁵⁶⁷⁸⁹", "-0123456789")


@pytest.mark.parametrize("limits", [(1e-17, 1e-2), (6.0, 6e3), (0.3, 2.0)])
def test_figure_labels_are_matplotlibs_in_unicode(limits):
    """The figures' log axes label the ticks matplotlib's own formatter labels, and
    each label, read back as a number, is its tick's value: spans of 15, 3 and one
    decade (the last with labelled minor ticks, 2×10⁻¹)."""
    from diffrax_vi.study._plot import _log_labels
    from matplotlib.figure import Figure
    from matplotlib.ticker import LogFormatterSciNotation

    ax = Figure().subplots()
    ax.loglog(limits, limits)
    _log_labels(ax)
    labelled = set()
    for axis in (ax.xaxis, ax.yaxis):
        for minor in (False, True):
            ticks = axis.get_minorticklocs() if minor else axis.get_majorticklocs()
            ours = axis.get_minor_formatter() if minor else axis.get_major_formatter()
            reference = LogFormatterSciNotation(labelOnlyBase=not minor)
            reference.set_axis(axis)
            for tick, label, expected in zip(
                ticks, ours.format_ticks(ticks), reference.format_ticks(ticks)
            ):
                assert bool(label) == bool(expected) and "$" not in label
                if label:
                    coefficient, _, power = label.rpartition("10")
                    value = float(coefficient.rstrip("×") or 1) * 10.0 ** int(
                        power.translate(SUPERSCRIPT_DIGITS) or 1
                    )
                    assert value == pytest.approx(tick, rel=1e-12), label
                    labelled.add(minor)
    assert labelled == ({False, True} if limits[1] / limits[0] < 10 else {False})


def test_work_precision_figure_names_every_solver_once_in_one_colour(
    tmp_path, monkeypatch
):
    """The work-precision figure has one legend entry per solver, each drawn in one
    style and no two solvers alike (thirteen solvers, more than matplotlib's ten
    colours), also where a panel has nothing to draw (a chaotic scene's global
    error past its reference's horizon)."""
    from diffrax_vi.study import WorkPrecision
    from diffrax_vi.study._plot import _styles, plot_work_precision
    from matplotlib.figure import Figure

    ours = ["StormerVerlet", "MidpointVI", "Yoshida4", "KahanLi6", "KahanLi8"]
    ours += ["GaussVPRK2", "GaussVPRK3"]
    rk = ["Tsit5", "Dopri5", "Dopri8", "Tsit5+PID", "Dopri5+PID", "Dopri8+PID"]
    styles = _styles(ours + rk)
    assert len({tuple(sorted(style.items())) for style in styles.values()}) == 13
    records = [
        dict(solver=s, wall_time_s=t, max_energy_error=t, global_error=np.nan)
        for s in ours + rk
        for t in (0.1, 0.2)
    ]
    drawn, savefig = [], Figure.savefig
    monkeypatch.setattr(
        Figure,
        "savefig",
        lambda fig, *a, **k: drawn.append(fig) or savefig(fig, *a, **k),
    )
    path = plot_work_precision(
        WorkPrecision("henon_heiles", 10_000, "float64", records), tmp_path / "wp.png"
    )
    assert matplotlib.image.imread(path).shape[0] > 100
    energy, error = drawn[0].axes
    assert not error.lines
    assert [t.get_text() for t in error.get_legend().get_texts()] == ours + rk
    for line, solver in zip(energy.lines, ours + rk, strict=True):
        assert line.get_label() == solver
        assert line.get_color() == styles[solver]["color"]
        assert line.get_linestyle() == styles[solver]["ls"]


@pytest.mark.parametrize(
    "argv,message",
    [
        (["drift", "--rtol", "-1"], "--rtol: a tolerance must be finite, > 0 and < 1"),
        (["drift", "--rtol", "2"], "< 1"),
        (["drift", "--periods", "0"], "--periods: a horizon must be finite, > 0"),
        (["drift", "--periods", "inf"], "finite"),
        (["drift", "--periods", "nan"], "finite"),
        (["drift", "--periods", "-3"], "> 0"),
        (["drift", "--steps-per-period", "2.5"], "must be an integer"),
        (["drift", "--ensemble", "0"], "--ensemble: a count"),
        (["drift", "--ensemble", "-1"], "--ensemble: a count"),
        (["drift", "--ensemble", "10000000000000"], "use at most"),
        (["drift", "--spread", "nan"], "--spread"),
        (["drift", "--save", "7"], "n_save=7 must divide the number of steps 200000"),
        (["drift", "--periods", "0.15", "--steps-per-period", "10"], "whole number"),
        (["drift", "--solvers", ","], "--solvers names no solver"),
        (["drift", "--solvers", "MidpointVI,RK99"], "Unknown solver 'RK99'"),
        (["drift", "--scene", "blackhole"], "invalid choice: 'blackhole'"),
        (["drift", "--solvers", "MidpointVI+PID"], "or MidpointVI+Adaptive"),
        (["drift", "--solvers", "Tsit5+Adaptive"], "need a symmetric one-step"),
        (
            ["drift", "--scene", "pendulum", "--solvers", "StormerVerlet+Adaptive"],
            "the scene 'pendulum' has none. Scenes with one: kepler",
        ),
        (["drift", "--param", "e=0.9"], "a parameter of the scene 'kepler'"),
        (["drift", "--param", "eccentricity=high"], "'high' is not a number"),
        (["drift", "--param", "eccentricity=1.5"], "bounded for eccentricity"),
        (
            ["drift", "--scene", "double_pendulum", "--solvers", "StormerVerlet"],
            "Partitioned terms exist only",
        ),
        (
            ["drift", "--scene", "forced_duffing", "--solvers", "MidpointVI,KahanLi8"],
            "KahanLi8 integrate(s) partitioned terms",
        ),
        # Refused when its first step is traced: before any work, with the names
        # the scene takes.
        (["drift", "--solvers", "LGVI"], "the scene 'kepler' takes MidpointVI"),
        (["work-precision", "--rtols", "tight"], "--rtols: a tolerance must be a"),
        (["work-precision", "--rtols", ""], "names no value"),
        (["work-precision", "--steps-per-period", "10,-5"], "a count must be"),
        (["work-precision", "--periods", "0.5", "--steps-per-period", "5"], "whole"),
    ],
)
def test_cli_rejects_bad_options_before_any_work(argv, message, capsys, tmp_path):
    """One line on stderr, exit code 2, and nothing written."""
    out = tmp_path / "never"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists()


def test_cli_never_overwrites_results(tmp_path, capsys, monkeypatch):
    small = ["--periods", "1", "--steps-per-period", "20", "--save", "2"]
    out = tmp_path / "mine"
    assert main(["drift", *small, "--solvers", "StormerVerlet", "--out", str(out)]) == 0
    assert (out / "drift_angular_momentum.png").exists()
    before = (out / "drift.csv").read_text()
    # The same folder again: refused, and the first results are untouched.
    argv = ["drift", *small, "--scene", "pendulum", "--solvers", "StormerVerlet"]
    assert main([*argv, "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "drift.csv").read_text() == before
    # With --force the new results replace the old, with no stale figure (the
    # pendulum has no angular momentum), and another file there is kept.
    (out / "notes.txt").write_text("mine")
    assert main([*argv, "--out", str(out), "--force"]) == 0
    assert not (out / "drift_angular_momentum.png").exists()
    assert json.loads((out / "drift.json").read_text())["scene"] == "pendulum"
    assert (out / "notes.txt").read_text() == "mine"
    # A file, or a place that cannot be written, is refused before any work.
    assert main([*argv, "--out", str(out / "notes.txt")]) == 2
    assert "is a file" in capsys.readouterr().err
    # Without --out each run writes a new folder.
    monkeypatch.chdir(tmp_path)
    assert main([*argv]) == 0
    assert main([*argv]) == 0
    runs = sorted(p.name for p in (tmp_path / "diffrax-vi-results").iterdir())
    assert runs == ["drift-pendulum-1", "drift-pendulum-2"]


def test_cli_help_and_study_errors(capsys):
    with pytest.raises(ValueError, match="must divide"):
        drift(kepler(), ["MidpointVI"], periods=1, steps_per_period=10, n_save=3)
    with pytest.raises(ValueError, match="solvers is empty"):
        drift(kepler(), [])
    with pytest.raises(ValueError, match="whole number"):
        drift(kepler(), ["MidpointVI"], periods=0.15, steps_per_period=10)
    with pytest.raises(ValueError, match="rtol"):
        drift(kepler(), ["Tsit5+PID"], rtol=-1.0)
    for command, option in [
        ("drift", "--ensemble"),
        ("work-precision", "--rtols"),
        ("seed", "--out"),
    ]:
        assert main([command, "--help"]) == 0
        assert option in capsys.readouterr().out
    assert main([]) == 2


def test_cli_help_and_bad_options_answer_without_jax(tmp_path):
    """`--help` (which lists the scenes), an option argparse refuses and an `--out`
    the command refuses (a folder with files in it, or a file) answer from the
    entry point alone: JAX is never imported."""
    (tmp_path / "notes.txt").write_text("mine")
    code = textwrap.dedent(
        f"""
        import contextlib, io, sys
        import _diffrax_vi_cli as cli
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            codes = [
                cli.main(["drift", "--help"]),
                cli.main(["drift", "--scene", "nope"]),
                cli.main(["work-precision", "--rtols", "tight"]),
                cli.main(["drift", "--out", {str(tmp_path)!r}]),
                cli.main(["seed", "--out", {str(tmp_path / "notes.txt")!r}]),
            ]
        assert codes == [0, 2, 2, 2, 2], codes
        assert "free_rigid_body" in out.getvalue() and "--no-cache" in out.getvalue()
        lines = err.getvalue().splitlines()
        assert "invalid choice: 'nope'" in lines[0], lines
        assert lines[-2].startswith("diffrax-vi drift: error: --out "), lines
        assert "is not empty: pass --force" in lines[-2], lines
        assert lines[-1].endswith("notes.txt is a file, not a folder."), lines
        assert "jax" not in sys.modules
        print("ok")
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False
    )
    assert done.stdout.strip() == "ok", done.stderr


def test_only_the_console_script_freezes_the_heap(monkeypatch):
    """The `diffrax-vi` command (`command`) runs in a process of its own and moves
    what it imported out of the garbage collector's way; `main`, which a user may
    call from their own process, leaves that process's collector as it is."""
    import gc

    import _diffrax_vi_cli as cli
    import diffrax_vi.cli

    frozen, exits = [], []
    monkeypatch.setattr(gc, "freeze", lambda: frozen.append(True))
    monkeypatch.setattr(cli, "exit_now", exits.append)
    monkeypatch.setattr(diffrax_vi.cli, "run", lambda args: 0)
    argv = ["diffrax-vi", "drift", "--scene", "kepler"]
    monkeypatch.setattr(sys, "argv", argv)
    assert cli.main(argv[1:]) == 0 and not frozen and not exits
    assert cli.command() == 0 and frozen == [True] and exits == [0]


def test_console_script_exits_after_its_output_and_exit_handlers():
    """`exit_now` ends the process with the command's code, without Python's
    teardown, but only once what it printed (buffered, into a pipe) is out and its
    `atexit` handlers have run."""
    code = textwrap.dedent(
        """
        import atexit, sys
        import _diffrax_vi_cli as cli
        atexit.register(lambda: print("handler ran"))
        print("table " * 2000)
        print("warning", file=sys.stderr)
        cli.exit_now(3)
        print("after exit_now")
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False
    )
    assert done.returncode == 3, done.stderr
    assert done.stdout == "table " * 2000 + "\nhandler ran\n"
    assert done.stderr == "warning\n"


def test_cli_scene_names_are_the_scenes():
    from _diffrax_vi_cli import SCENE_NAMES

    assert SCENE_NAMES == tuple(scenes.SCENES)


@pytest.mark.parametrize("command", ["drift", "work-precision"])
@pytest.mark.parametrize("name", list(scenes.SCENES))
def test_every_scene_takes_its_default_methods(name, command):
    """With no --solvers, a scene gets the methods it declares (like with like: a
    Lie-group VI against Runge-Kutta on the same term), else the command's list;
    every one of them takes the scene's terms."""
    import argparse

    from diffrax_vi.cli import _methods

    scene = make_scene(name)
    args = argparse.Namespace(command=command, solvers=None)
    methods = _methods(args, 1e-8, scene)
    assert len(methods) >= 5
    if isinstance(scene.lagrangian, dvi.AbstractRigidBodyLagrangian):
        assert methods[0].name == "LGVI"
    # Every scene compares a variational method with Runge-Kutta and an adaptive one.
    assert any(isinstance(m.solver, dvi.AbstractVariationalSolver) for m in methods)
    assert any(isinstance(m.solver, dfx.Tsit5) for m in methods)
    assert any(not m.fixed for m in methods)


def test_cli_names_solvers_a_scene_takes(capsys, tmp_path):
    argv = ["drift", "--scene", "heavy_top", "--solvers", "StormerVerlet"]
    assert main([*argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "--solvers" in err and "LGVI" in err and "MidpointVI" in err, err


def test_cli_records_the_scenes_parameters(tmp_path, capsys):
    argv = ["drift", "--scene", "oscillator", "--param", "omega=2", "--periods", "1"]
    small = ["--steps-per-period", "8", "--solvers", "StormerVerlet"]
    assert main([*argv, *small, "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "drift.json").read_text())["parameters"] == "omega=2"
    # A short run's wall time keeps its significant digits.
    row = [line for line in capsys.readouterr().out.splitlines() if "| Stormer" in line]
    assert "| 0.000 |" not in row[0], row


def test_default_save_intervals_divide_the_steps():
    from diffrax_vi.study import check_drift

    methods = [dvi.study.as_method("StormerVerlet")]
    for periods, per_period, expected in [
        (10, 20, 200),
        (1000, 200, 1000),
        (7, 11, 77),
    ]:
        assert check_drift(kepler(), methods, periods, per_period, None, "float64") == (
            periods * per_period,
            expected,
        )
    study = drift(kepler(), ["StormerVerlet"], periods=3, steps_per_period=7)
    assert len(study.runs[0].ts) == 22


@pytest.mark.slow
@pytest.mark.parametrize("name", list(scenes.SCENES))
def test_every_scene_runs_with_no_flags(name, tmp_path, capsys):
    """The scenes that declare their methods (the others run the main job's) run
    as typed, over one period at the default step; every method succeeds."""
    # The scenes are built here, not when the suite is collected: the learned one
    # trains for half a minute in each worker, and this test is not in the default
    # suite.
    solvers = make_scene(name).solvers
    if not solvers:
        pytest.skip(f"{name} declares no methods: it runs the main job's")
    argv = ["drift", "--scene", name, "--periods", "1"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "drift.json").read_text())["summary"]
    assert [r["solver"] for r in rows] == list(solvers)
    assert all(r["result"] == "successful" for r in rows), rows


def test_verdict_weighs_every_invariant():
    """The heavy top's numbers from a 1000-period study: Tsit5 has the lowest
    energy error but leaves SO(3); the LGVI keeps every invariant, and the verdict
    says so (the factors are ratios, the same in any units)."""
    from diffrax_vi.study import DriftRun, DriftStudy

    def run(name, energy, orthogonality, symplectic):
        ts = np.linspace(0.0, 1.0, 11)
        series = {
            "energy": np.full(11, energy),
            "spin": np.full(11, 1e-15),
            "orthogonality": np.full(11, orthogonality),
        }
        return DriftRun(name, 100, 0.5, "successful", ts, series, symplectic)

    runs = [run("LGVI", 5e-11, 9e-14, True), run("Tsit5", 1.2e-11, 1.6e-8, False)]
    study = DriftStudy("heavy_top", 10, 10, "float64", 1, runs)
    verdict = study.verdict()
    assert "lowest errors on all 3 invariants together: LGVI (each within x4.2" in (
        verdict
    ), verdict
    assert "lowest energy error: Tsit5 (1.2e-11 in 0.5 s), but its orthogonality " in (
        verdict
    ), verdict
    # In other units (energies x1e6) the verdict is the same.
    scaled = [
        dataclasses.replace(r, errors=dict(r.errors, energy=r.errors["energy"] * 1e6))
        for r in runs
    ]
    assert (
        "together: LGVI"
        in DriftStudy("heavy_top", 10, 10, "float64", 1, scaled).verdict()
    )


def test_adaptive_runs_and_failures_are_recorded():
    scene = scenes.pendulum()
    # One Newton iteration cannot solve a step of a quarter period: a failed solve,
    # kept in the table with its message rather than raised.
    starved = Method("starved", dvi.MidpointVI(root_find_max_steps=1))
    study = drift(
        scene,
        ["Tsit5+PID", starved],
        periods=2,
        steps_per_period=4,
        n_save=2,
        rtol=1e-10,
    )
    adaptive, failed = study.runs
    assert adaptive.result == "successful" and adaptive.steps > 8
    assert adaptive.max_error("energy") < 1e-8
    assert "nonlinear solver" in failed.result
    wp = work_precision(
        scene,
        ["Tsit5+PID", starved],
        periods=2,
        steps_per_period=[4],
        rtols=[1e-6, 1e-9],
    )
    pid = [r for r in wp.records if r["solver"] == "Tsit5+PID"]
    assert [r["rtol"] for r in pid] == [1e-6, 1e-9]
    assert pid[1]["global_error"] < pid[0]["global_error"] < 1e-3
    assert pid[1]["steps"] > pid[0]["steps"]
    (bad,) = [r for r in wp.records if r["solver"] == "starved"]
    assert bad["result"] != "successful" and np.isnan(bad["global_error"])


def test_adaptive_steps_between_saves_are_capped():
    # An adaptive run needing more than MAX_ADAPTIVE_STEPS_PER_SAVE steps in one
    # interval fails, saying so, and more intervals fix it.
    from diffrax_vi.study._methods import MAX_ADAPTIVE_STEPS_PER_SAVE

    kwargs = dict(periods=20, steps_per_period=10, rtol=1e-12)
    (few,) = drift(scenes.oscillator(), ["Tsit5+PID"], n_save=1, **kwargs).runs
    assert few.result.startswith("The maximum number of solver steps was reached")
    assert few.steps == MAX_ADAPTIVE_STEPS_PER_SAVE
    (many,) = drift(scenes.oscillator(), ["Tsit5+PID"], n_save=20, **kwargs).runs
    assert many.result == "successful"
    assert many.steps > MAX_ADAPTIVE_STEPS_PER_SAVE
    assert many.max_error("energy") < 1e-10


def test_work_precision_cli_matches_api(tmp_path, capsys):
    out = tmp_path / "wp"
    argv = ["work-precision", "--scene", "oscillator", "--periods", "2"]
    argv += ["--solvers", "MidpointVI,Tsit5+PID", "--steps-per-period", "20,40"]
    assert main([*argv, "--rtols", "1e-8", "--out", str(out)]) == 0
    with open(out / "work_precision.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["solver"], r["steps"]) for r in rows][:2] == [
        ("MidpointVI", "40"),
        ("MidpointVI", "80"),
    ]
    # The oscillator has an exact solution: MidpointVI's global error is second order
    # (its phase error after 2 periods is 2 pi * (2/3) (pi/n)^2... halves twice).
    e20, e40 = (float(r["global_error"]) for r in rows[:2])
    assert 3.8 < e20 / e40 < 4.2
    # Its energy is quadratic, which the midpoint rule conserves to round-off.
    assert float(rows[0]["max_energy_error"]) < 1e-13
    api = work_precision(
        scenes.oscillator(), ["MidpointVI"], periods=2, steps_per_period=[20]
    )
    assert float(rows[0]["global_error"]) == pytest.approx(
        api.records[0]["global_error"], rel=1e-12
    )
    png = out / "work_precision.png"
    assert matplotlib.image.imread(png).shape[0] > 100


def test_ensemble_equals_a_loop_of_single_runs():
    scene = kepler()
    kwargs = dict(periods=2, steps_per_period=50, n_save=10)
    study = drift(scene, ["StormerVerlet"], ensemble=4, spread=1e-2, **kwargs)
    assert study.members == 4
    q, p = scene.perturbed(jr.key(0), 4, 1e-2)
    singles = [
        drift(
            eqx.tree_at(lambda s: s.y0, scene, (q[i], p[i])),
            ["StormerVerlet"],
            **kwargs,
        ).runs[0]
        for i in range(4)
    ]
    for name in ("energy", "angular_momentum"):
        worst = np.max([run.errors[name] for run in singles], axis=0)
        assert np.allclose(study.runs[0].errors[name], worst, rtol=1e-10, atol=1e-15)
    # The members differ, so the worst is not simply the first.
    assert not np.allclose(singles[0].errors["energy"], worst)


SHARDED = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from diffrax_vi.scenes import kepler
    from diffrax_vi.study import drift
    from diffrax_vi.study._run import shard_ensemble

    assert len(jax.devices()) == 4
    y0s = kepler().perturbed(jax.random.key(0), 8)
    placed = shard_ensemble(y0s, 8)
    assert len(placed[0].sharding.device_set) == 4
    kwargs = dict(periods=2, steps_per_period=50, n_save=10, ensemble=8)
    solvers = ["MidpointVI", "StormerVerlet"]
    sharded = drift(kepler(), solvers, shard=True, **kwargs)
    unsharded = drift(kepler(), solvers, shard=False, **kwargs)
    for a, b in zip(sharded.runs, unsharded.runs):
        for k in a.errors:
            np.testing.assert_allclose(a.errors[k], b.errors[k], rtol=1e-12, atol=1e-16)
    try:
        drift(kepler(), solvers, shard=True, **dict(kwargs, ensemble=6))
    except ValueError as e:
        assert "multiple of 4" in str(e)
    else:
        raise AssertionError("6 members over 4 devices should not shard")
    print("ok")
    """
)


def test_sharded_ensemble_equals_unsharded():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    env["JAX_PLATFORMS"] = "cpu"
    result = subprocess.run(
        [sys.executable, "-c", SHARDED], env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok")


@pytest.mark.slow
def test_seed_cli_reproduces_the_thesis_ratios(tmp_path):
    """`diffrax-vi seed`: the error ratios on halving the step from the thesis's
    analytic start are within 0.15 of 4, as in the thesis's Tables 5.1/5.2."""
    out = tmp_path / "seed"
    assert main(["seed", "--out", str(out)]) == 0
    text = (out / "chapter5.md").read_text()
    rows = [line for line in text.splitlines() if "ours, analytic start" in line]
    assert len(rows) == 4
    ratios = [float(x) for row in rows for x in re.findall(r"\d+\.\d{4}", row)]
    assert len(ratios) == 16
    # h = 0.016 does not divide T = 1 (the thesis rounds 62.5 steps to 62), so one
    # ratio per table departs; the rest are within 0.15 of 4.
    close = [abs(r - 4) < 0.15 for r in ratios]
    assert sum(close) >= 14
    for name in ("figure_5_1", "figure_5_2", "figure_5_3", "figure_1_1_1_2"):
        assert (out / f"{name}.png").read_bytes()[:4] == b"\x89PNG"
    # The Seed page includes the command's stored output: the same sections.
    stored = (ROOT / "benchmarks" / "results" / "seed_chapter5.md").read_text()
    headings = [line for line in text.splitlines() if line.startswith("#")]
    assert headings == [line for line in stored.splitlines() if line.startswith("#")]


def test_seed_page_shows_the_commands_results_file():
    """The Seed page's Chapter 5 numbers are the file `diffrax-vi seed` wrote,
    included as written, not retyped; the file holds the thesis's property."""
    page = (ROOT / "docs" / "seed.md").read_text()
    assert "<!-- include: seed_chapter5.md -->" in page
    assert "ours, analytic start" not in page
    stored = (ROOT / "benchmarks" / "results" / "seed_chapter5.md").read_text()
    rows = [line for line in stored.splitlines() if "ours, analytic start" in line]
    ratios = [float(x) for row in rows for x in re.findall(r"\d+\.\d{4}", row)]
    assert len(ratios) == 16 and sum(abs(r - 4) < 0.15 for r in ratios) >= 14


def test_reversible_adaptive_study_is_a_plain_solve_at_the_mean_step():
    # KahanLi8+Adaptive on Kepler at e = 0.9: about the steps asked for, far lower
    # energy error than the fixed step at the same count, and exactly the steps of a
    # plain diffeqsolve at the dt0 the study calibrated.
    from diffrax_vi.study import as_method, reversible_dt0

    scene = kepler(0.9)
    periods, spp = 20, 100
    study = drift(
        scene,
        ["KahanLi8", "KahanLi8+Adaptive"],
        periods=periods,
        steps_per_period=spp,
        n_save=20,
    )
    fixed, adaptive = study.runs
    assert adaptive.reversible and not adaptive.symplectic
    assert abs(adaptive.steps / (periods * spp) - 1) < 0.05
    assert adaptive.max_error("energy") < 1e-6 * fixed.max_error("energy")
    assert adaptive.max_error("angular_momentum") < 1e-14
    method = as_method("KahanLi8+Adaptive")
    t1 = scene.period * periods
    dt0 = reversible_dt0(scene, method, t1, periods * spp, scene.y0, jnp.float64)
    sol = dfx.diffeqsolve(
        method.terms(scene),
        method.solver,
        0.0,
        t1,
        dt0,
        scene.y0,
        stepsize_controller=dvi.ReversibleController(scene.monitor),
        saveat=dfx.SaveAt(steps=True),
        max_steps=10 * periods * spp,
    )
    n = int(sol.stats["num_steps"])
    assert adaptive.steps == n
    q, p = (np.asarray(y[:n]) for y in sol.ys)
    e = np.abs(0.5 * np.sum(p**2, axis=1) - 1 / np.linalg.norm(q, axis=1) + 0.5)
    assert adaptive.max_error("energy") == pytest.approx(e.max(), rel=1e-8)


def test_cli_scene_parameters(tmp_path, capsys):
    out = tmp_path / "e09"
    argv = ["drift", "--param", "eccentricity=0.9", *ARGS, "--out", str(out)]
    assert main([*argv, "--solvers", "StormerVerlet,StormerVerlet+Adaptive"]) == 0
    with open(out / "drift.csv") as f:
        rows = {r["solver"]: r for r in csv.DictReader(f)}
    # e = 0.9: the energy is still -1/2, but the fixed step is far off.
    fixed = float(rows["StormerVerlet"]["max_energy_error"])
    assert float(rows["StormerVerlet+Adaptive"]["max_energy_error"]) < fixed / 10


def test_work_precision_reference_keeps_the_force_and_the_constraint():
    """Without an exact solution the reference is Dopri8 on the scene's own term:
    the Cartesian pendulum stays on its circle and follows the angle pendulum, and
    the forced Duffing oscillator feels its drive (both against scipy at 1e-12)."""
    from diffrax_vi.study import reference_state
    from scipy.integrate import solve_ivp

    t1 = 5.0
    scene = scenes.cartesian_pendulum()
    q, _ = reference_state(scene, t1)
    angle = solve_ivp(
        lambda t, y: [y[1], -np.sin(y[0])], (0, t1), [2.0, 0.0], rtol=1e-12, atol=1e-12
    ).y[0, -1]
    np.testing.assert_allclose(q, [np.sin(angle), -np.cos(angle)], atol=1e-8)

    scene = scenes.forced_duffing()
    q, p = reference_state(scene, t1)
    duffing = solve_ivp(
        lambda t, y: [y[1], -0.3 * y[1] + y[0] - y[0] ** 3 + 0.5 * np.cos(1.2 * t)],
        (0, t1),
        [1.0, 0.0],
        rtol=1e-12,
        atol=1e-12,
    ).y[:, -1]
    np.testing.assert_allclose([q, p], duffing, atol=1e-8)


def _documented_commands() -> list[str]:
    """Every `diffrax-vi` command the README and the docs show: the lines of their
    shell blocks (continuations joined) and their inline code."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    shell = re.compile(r"^```(?:bash|sh)\n(.*?)^```", re.S | re.M)
    commands = []
    for path in files:
        text = path.read_text()
        for block in shell.findall(text):
            for line in block.replace("\\\n", " ").splitlines():
                line = line.split("  #")[0]
                if "diffrax-vi " in line:
                    commands.append("diffrax-vi " + line.split("diffrax-vi ")[-1])
        commands += [
            c for c in re.findall(r"`(diffrax-vi [^`]*)`", text) if "error" not in c
        ]
    return sorted(set(" ".join(c.split()) for c in commands))


def test_every_documented_command_passes_its_checks(capsys):
    """Each command the README and the docs show parses, and passes every check its
    command makes before any work (the scene, its parameters, each method's first
    step, the study's settings), as typed: none would exit 2. The learned scene
    builds its network untrained: the checks read its structure, not its weights."""
    import _diffrax_vi_cli
    from diffrax_vi.cli import checked

    commands = _documented_commands()
    assert len(commands) > 30, commands
    for command in commands:
        argv = command.split()[1:]
        if "--help" in argv:
            assert _diffrax_vi_cli.main(argv) == 0, command
            continue
        args = _diffrax_vi_cli._parser().parse_args(argv)
        with untrained_learned_scene():
            checked(args)


def test_an_interval_without_a_step_holds_the_previous_error():
    """Dopri8+PID takes fewer steps than there are save intervals: an interval in
    which no step ended shows the error of the state held through it, never 0 (a
    log plot's floor, and a first tenth of zeros made the growth meaningless)."""
    study = drift(kepler(), ["Dopri8+PID"], periods=2, steps_per_period=200, n_save=400)
    run = study.runs[0]
    assert run.steps < 400
    errors = run.errors["energy"][1:]
    assert np.all(errors > 0), errors
    # Each interval's value is a step's error: the distinct values are at most the
    # steps taken.
    assert len(np.unique(errors)) <= run.steps
