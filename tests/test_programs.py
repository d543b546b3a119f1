"""The programs a study compiles, kept within a process and, for the command line,
between runs (`study._programs`): a program read back computes what tracing it again
would, a changed key traces again, what cannot be kept is traced every time, and the
folder keeps within its bound the programs used last."""

import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from diffrax_vi.cli import main, programs_dir
from diffrax_vi.study import _programs, _run


def _counted(calls: list):
    def f(_, x):
        calls.append(None)  # Once per trace.
        return {"sum": jnp.sum(jnp.sin(x)), "x": (x * 2,)}

    return f


def test_a_kept_program_is_read_back_instead_of_traced(tmp_path):
    calls = []
    x = jnp.linspace(0.0, 1.0, 5)
    expected = _counted([])(None, x)
    with _programs.keep_programs(tmp_path, "context"):
        first = _programs.compiled("f", _counted(calls), None, x)(x)
        again = _programs.compiled("f", _counted(calls), None, x)(x)
    assert len(calls) == 1 and len(list(tmp_path.iterdir())) == 1
    for out in (first, again):
        assert jax.tree.structure(out) == jax.tree.structure(expected)
        assert all(
            np.array_equal(a, b)
            for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(expected))
        )


@pytest.mark.parametrize(
    "change",
    ["context", "name", "shape", "dtype"],
)
def test_a_program_is_traced_again_when_its_key_changes(tmp_path, change):
    calls = []
    x = jnp.zeros(3)
    with _programs.keep_programs(tmp_path, "a"):
        _programs.compiled("f", _counted(calls), None, x)
    context, name, y = "a", "f", x
    if change == "context":
        context = "b"
    elif change == "name":
        name = "g"
    elif change == "shape":
        y = jnp.zeros(4)
    else:
        y = jnp.zeros(3, jnp.float32)
    with _programs.keep_programs(tmp_path, context):
        _programs.compiled(name, _counted(calls), None, y)
    assert len(calls) == 2 and len(list(tmp_path.iterdir())) == 2


def test_the_key_follows_the_code(tmp_path, monkeypatch):
    """An edited source file of a package the programs are traced through (here a
    stand-in package) changes every key."""
    package = tmp_path / "stand_in"
    package.mkdir()
    (package / "__init__.py").write_text("x = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(_programs, "_PACKAGES", ("stand_in",))
    programs = _programs._Programs(tmp_path, "g")
    paths = []
    for text in ("x = 1\n", "x = 22\n"):
        (package / "__init__.py").write_text(text)
        _programs._code.cache_clear()
        paths.append(programs.path("f", (jnp.zeros(2),)))
    _programs._code.cache_clear()
    assert paths[0] != paths[1]


def test_a_program_holding_a_host_callback_is_traced_every_time(tmp_path):
    calls = []

    def make():
        def f(_, x):
            calls.append(None)
            y = jax.pure_callback(np.cos, jax.ShapeDtypeStruct(x.shape, x.dtype), x)
            return y + 1

        return f

    x = jnp.ones(2)
    with _programs.keep_programs(tmp_path, "c"):
        outs = [_programs.compiled("f", make(), None, x)(x) for _ in range(2)]
    assert len(calls) == 2 and not any(tmp_path.iterdir())
    assert all(np.allclose(out, np.cos(1.0) + 1) for out in outs)


def test_a_kept_eigensolver_runs_in_a_process_that_lowered_none(tmp_path):
    """An eigensolver (a start's check of d2L/dv2) is a call into LAPACK, whose
    kernels jaxlib points at SciPy's LAPACK when it lowers one. A process that
    loads the kept program has lowered none: it must set them up itself (it
    crashed, calling a null pointer)."""
    script = f"""
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from diffrax_vi.study import _programs
a = jnp.array([[2.0, 1.0], [1.0, 3.0]])
with _programs.keep_programs({str(tmp_path)!r}, "eigh"):
    program = _programs.compiled("eigh", lambda _, a: jnp.linalg.eigvalsh(a), None, a)
print(np.asarray(program(a)).tolist())
"""
    runs = [
        subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
        for _ in range(2)  # Kept, then loaded.
    ]
    assert [run.returncode for run in runs] == [0, 0], runs[-1].stderr[-2000:]
    assert len(list(tmp_path.iterdir())) == 1
    exact = [(5 - np.sqrt(5)) / 2, (5 + np.sqrt(5)) / 2]
    for run in runs:
        assert np.allclose(json.loads(run.stdout), exact, rtol=1e-14, atol=0)


def test_a_damaged_file_is_replaced(tmp_path):
    calls = []
    x = jnp.arange(3.0)
    with _programs.keep_programs(tmp_path, "d"):
        _programs.compiled("f", _counted(calls), None, x)
        (path,) = tmp_path.iterdir()
        path.write_bytes(path.read_bytes()[:100])
        out = _programs.compiled("f", _counted(calls), None, x)(x)
        assert len(calls) == 2 and np.allclose(out["sum"], jnp.sum(jnp.sin(x)))
        _programs.compiled("f", _counted(calls), None, x)
    assert len(calls) == 2


def test_a_folder_it_cannot_write_is_a_warning_not_a_failure(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("")  # A file where the folder would be.
    x = jnp.arange(2.0)
    with _programs.keep_programs(blocked / "programs", "f"):
        with pytest.warns(RuntimeWarning, match="cannot keep the solves"):
            out = _programs.compiled("f", _counted([]), None, x)(x)
    assert np.allclose(out["sum"], jnp.sum(jnp.sin(x)))


def test_the_folder_keeps_the_programs_used_last_within_its_bound(tmp_path):
    """After a program is kept, the folder is cut to its bound, the files least
    recently written or read going first: a program read back counts as used, an
    earlier version's file (`.jaxexport`) as a kept program, and a file that a run
    stopped before it finished writing goes after an hour."""
    now = time.time()

    def age(path, hours: float):
        os.utime(path, (now - 3600 * hours, now - 3600 * hours))
        return path

    def aged(name: str, size: int, hours: float):
        (tmp_path / name).write_bytes(b"x" * size)
        return age(tmp_path / name, hours)

    oldest = aged("a.jaxexport", 1000, 30)
    old = aged("b.xla", 1000, 20)
    recent = aged("c.xla", 1000, 2)
    abandoned = aged("d.part", 10, 2)
    writing = aged("e.part", 10, 0.1)
    x = jnp.arange(3.0)
    with _programs.keep_programs(tmp_path, "c"):
        _programs.compiled("f", _counted([]), None, x)
    assert not abandoned.exists() and oldest.exists()  # Within 512 MiB.
    (kept,) = set(tmp_path.glob("*.xla")) - {old, recent}
    size = kept.stat().st_size
    age(kept, 40)  # The oldest, were it not read below.
    calls = []
    # Room for two programs and 1500 bytes: of the three 1000-byte files, the two
    # oldest go.
    with _programs.keep_programs(tmp_path, "c", max_bytes=2 * size + 1500):
        _programs.compiled("f", _counted(calls), None, x)  # Read back: used now.
        assert not calls and oldest.exists()  # A read sweeps nothing.
        _programs.compiled("g", _counted(calls), None, x)  # Another program.
    (new,) = set(tmp_path.glob("*.xla")) - {old, recent, kept}
    assert len(calls) == 1 and abs(new.stat().st_size - size) < 400
    assert set(tmp_path.iterdir()) == {recent, kept, new, writing}


def test_outside_keep_programs_nothing_is_kept(tmp_path):
    calls = []
    x = jnp.ones(2)
    for _ in range(2):
        _programs.compiled("f", _counted(calls), None, x)
    assert len(calls) == 2


def test_a_repeated_study_reads_its_programs_back(tmp_path, monkeypatch):
    """Each command keeps what it compiles in $XDG_CACHE_HOME/diffrax-vi/jax and the
    solves it traces in .../programs, and leaves the process's JAX settings as they
    were: its second run traces none of its solves and tables the same numbers.
    `--no-cache` reads and writes neither."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    traced = []
    tracked = _run._Solves.tracked

    def counting(self, y0):
        traced.append(None)
        return tracked(self, y0)

    monkeypatch.setattr(_run._Solves, "tracked", counting)
    argv = ["drift", "--periods", "2", "--steps-per-period", "10"]
    argv += ["--solvers", "StormerVerlet,Tsit5"]
    rows = []
    for out in ("a", "b"):
        _programs._memo.clear()  # Each run as a fresh process does it.
        assert main([*argv, "--out", str(tmp_path / out)]) == 0
        summary = json.loads((tmp_path / out / "drift.json").read_text())["summary"]
        for row in summary:
            del row["wall_time_s"]
        rows.append(summary)
    assert len(traced) == 2  # Both methods, in the first run only.
    assert rows[0] == rows[1]
    assert len(list(programs_dir().iterdir())) == 4  # Tracked and plain, each.
    assert any((programs_dir().parent / "jax").iterdir())
    assert jax.config.jax_compilation_cache_dir is None
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "off"))
    assert main([*argv, "--no-cache", "--out", str(tmp_path / "c")]) == 0
    assert len(traced) == 4 and not (tmp_path / "off").exists()


def test_a_study_on_a_group_keeps_its_solves_and_still_checks_its_start(
    tmp_path, monkeypatch
):
    """A variational solve checks that its start lies on its group by host callback,
    which a kept program cannot hold: the study checks the start apart (the
    solver's `init` as a plain solve runs it) and compiles its solves without that
    check, so a repeated study of a rigid body reads them back. A start off its
    group is still the row's error: in the process, where another start of the
    same shape reuses the same programs and the same compiled check, and under
    `keep_programs`, which then keeps nothing."""
    import equinox as eqx
    from diffrax_vi.scenes import free_rigid_body
    from diffrax_vi.study import drift

    scene = free_rigid_body()
    rotation, momentum = scene.y0
    off = eqx.tree_at(lambda s: s.y0, scene, (1.01 * rotation, momentum))
    traced = []
    tracked = _run._Solves.tracked

    def counting(self, y0):
        traced.append(None)
        return tracked(self, y0)

    def result(scene):
        (run,) = drift(scene, ["LGVI"], periods=2, steps_per_period=10).runs
        return run.result

    checks = []
    check_start = _run._check_start

    def compiling(*args):
        checks.append(None)
        return check_start(*args)

    monkeypatch.setattr(_run._Solves, "tracked", counting)
    monkeypatch.setattr(_run, "_check_start", compiling)
    message = "raised: The initial position is not on its group"
    _programs._memo.clear()
    assert result(off).startswith(message)
    assert result(scene) == "successful"
    # The same programs, and the same compiled check, run again.
    assert result(off).startswith(message)
    assert len(traced) == 1 and len(checks) == 1
    with _programs.keep_programs(tmp_path, "off"):
        assert result(off).startswith(message)
    assert not any(tmp_path.iterdir())
    for _ in range(2):  # Kept, then read back.
        _programs._memo.clear()
        with _programs.keep_programs(tmp_path, "on"):
            assert result(scene) == "successful"
    assert len(traced) == 2 and len(list(tmp_path.iterdir())) == 2


def test_a_study_run_again_in_the_process_reuses_its_programs(monkeypatch):
    """A notebook's cell rerun: a study of a new but equal scene compiles none of its
    solves and tables the same errors. Another start is an argument of the same
    programs; another value of a parameter the solves close over compiles them
    again."""
    import equinox as eqx
    from diffrax_vi.scenes import kepler
    from diffrax_vi.study import drift

    compiles = []
    original = _programs._compile

    def counting(*args):
        compiles.append(None)
        return original(*args)

    monkeypatch.setattr(_programs, "_compile", counting)
    heavier = eqx.tree_at(lambda s: s.lagrangian.mu, kepler(), jnp.asarray(1.2))
    studies, compiled = [], []
    for scene in (kepler(), kepler(), kepler(0.5), heavier):
        before = len(compiles)
        studies.append(
            drift(scene, ["MidpointVI", "Tsit5"], periods=2, steps_per_period=50)
        )
        compiled.append(len(compiles) - before)
    assert compiled == [4, 0, 0, 4]
    assert all(run.result == "successful" for study in studies for run in study.runs)
    for first, again, *others in zip(*(study.runs for study in studies)):
        assert np.array_equal(first.errors["energy"], again.errors["energy"])
        for other in others:
            assert not np.allclose(
                first.errors["energy"][1:], other.errors["energy"][1:]
            )


def test_the_process_key_is_the_value_of_what_a_program_closes_over():
    key = _programs._Memo.key

    def f(constants, x):
        return x

    x = jnp.zeros(2)
    same = dict(a=jnp.arange(3.0), b=1.0, g=jnp.sin)
    assert key("f", f, same, (x,), False) == key("f", f, dict(same), (x,), False)
    for other in [
        dict(same, a=jnp.array([0.0, 1.0, 2.0 + 1e-12])),
        dict(same, a=jnp.arange(3.0, dtype=jnp.float32)),
        dict(same, b=2.0),
        dict(same, b=1),  # An int traces otherwise than a float.
        dict(same, g=jnp.cos),
        dict(same, c=None),  # Another structure.
    ]:
        assert key("f", f, other, (x,), False) != key("f", f, same, (x,), False)
    assert key("f", f, same, (jnp.zeros(3),), False) != key("f", f, same, (x,), False)
    assert key("f", f, same, (x,), True) != key("f", f, same, (x,), False)
    assert key("g", f, same, (x,), False) != key("f", f, same, (x,), False)
    # JAX's settings are part of a trace.
    before = key("f", f, same, (x,), False)
    setting = jax.config.jax_numpy_rank_promotion
    jax.config.update(
        "jax_numpy_rank_promotion", "warn" if setting != "warn" else "allow"
    )
    try:
        assert key("f", f, same, (x,), False) != before
    finally:
        jax.config.update("jax_numpy_rank_promotion", setting)
    # A leaf that cannot be hashed has no key: its program is compiled every time.
    assert key("f", f, dict(same, d=bytearray(b"x")), (x,), False) is None


def test_the_process_keeps_only_the_latest_programs():
    memo = _programs._Memo(size=2)
    programs = {k: (lambda: k) for k in "abcd"}
    for k in "abc":
        memo.put(k, programs[k])
    assert memo.get("a") is None and memo.get("b") is programs["b"]
    memo.put("d", programs["d"])  # "b" was used last: "c" goes.
    assert memo.get("c") is None
    assert memo.get("b") is programs["b"] and memo.get("d") is programs["d"]


def test_a_kept_solve_is_its_traces_program_compiled_apart_from_jaxs_cache(
    tmp_path, monkeypatch
):
    """The study times the kept program: loaded in a later run, it is the program
    XLA makes of the solve traced in the process, instruction for instruction, and
    computes the same numbers. An executable that JAX loads from its persistent
    cache, serialised again, lacks some of its kernels (XLA's "Function ... not
    found" when run): a kept program is compiled by XLA even where JAX's cache holds
    the same program, and is not written to that cache."""
    import collections
    import logging
    import re

    from diffrax_vi.cli import compilation_cache
    from diffrax_vi.scenes import kepler
    from diffrax_vi.study import as_method

    hits = []  # The programs JAX loads from its persistent cache, by name.

    class Hits(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Persistent compilation cache hit"):
                hits.append(record.args[0])

    logger, handler = logging.getLogger("jax._src.compiler"), Hits(logging.DEBUG)

    def solves_in(folder):
        names = (f.name for f in folder.iterdir())
        return sorted(n for n in names if n.startswith(("jit__tracked", "jit__plain")))

    def instructions(compiled):
        text = compiled.as_text()
        return collections.Counter(re.findall(r" = \S+ ([\w-]+)\(", text))

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    jax_cache = tmp_path / "cache" / "diffrax-vi" / "jax"
    scene, method = kepler(), as_method("MidpointVI")
    settings = dict(t1=scene.period, n_steps=100, n_save=2, dtype=jnp.float64)
    level = logger.level
    logger.setLevel(logging.DEBUG)
    logger.addHandler(handler)
    try:
        with compilation_cache():
            direct = _run.prepare(scene, method, y0=scene.y0, **settings)
            before = solves_in(jax_cache)  # The direct ones.
            for _ in range(2):  # Kept, then loaded.
                jax.clear_caches()  # As a new process: JAX's cache on disk.
                _programs._memo.clear()
                with _programs.keep_programs(tmp_path / "programs", "h"):
                    kept = _run.prepare(scene, method, y0=scene.y0, **settings)
            assert solves_in(jax_cache) == before and len(before) == 2
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    # The kept solves, compiled, then loaded: never from JAX's cache.
    assert not [h for h in hits if "_tracked" in h or "_plain" in h]
    assert len(list((tmp_path / "programs").iterdir())) == 2
    for a, b in [(direct.plain, kept.plain), (direct.tracked, kept.tracked)]:
        assert a is not b
        assert instructions(a) == instructions(b) and sum(instructions(a).values())
        outputs = [jax.tree.leaves(f(scene.y0)) for f in (a, b)]
        assert all(np.all(np.isfinite(x)) for x in outputs[0])
        assert all(np.array_equal(x, y) for x, y in zip(*outputs))


def test_a_study_keeps_the_tracked_runge_kutta_solve_of_a_mechanism(tmp_path):
    """A Runge-Kutta step evaluates a constrained term's vector field, which raises
    by host callback where the constraint forces cannot be solved. The study's
    tracked solve makes NaN there instead: it holds no callback and is kept (the
    timed solve, as a user runs it, holds the check and is not), and its errors
    are those of the user's solve at every step. Where the vector field fails, the
    timed solve raises why (at 5 steps a swing, Tsit5 leaves the rod and grows
    without bound within 3 swings), and that is the row, kept or not. The run and
    the verdict say that its time includes the check (`DriftRun.checked`;
    tests/test_study.py::test_cli_end_to_end: a separable scene's does not)."""
    import diffrax as dfx
    from diffrax_vi.scenes import cartesian_pendulum
    from diffrax_vi.study import drift

    scene = cartesian_pendulum()

    def study(periods, steps_per_period):
        result = drift(
            scene,
            ["Tsit5"],
            periods=periods,
            steps_per_period=steps_per_period,
            n_save=2,
        )
        return result.runs[0], result.verdict()

    _programs._memo.clear()
    with _programs.keep_programs(tmp_path, "rk"):
        run, verdict = study(2, 50)
    assert run.result == "successful" and len(list(tmp_path.iterdir())) == 1
    assert run.checked and "times of Tsit5 include their vector field's" in verdict
    sol = dfx.diffeqsolve(
        scene.term(),
        dfx.Tsit5(),
        0.0,
        2 * scene.period,
        scene.period / 50,
        scene.y0,
        scene.args,
        saveat=dfx.SaveAt(steps=True),
        max_steps=100,
    )
    energy = jax.vmap(lambda y: scene.energy(0.0, y, scene.args))(sol.ys)
    drift_ = np.abs(np.asarray(energy - scene.energy(0.0, scene.y0, scene.args)))
    halves = drift_.reshape(2, 50).max(axis=1)
    assert np.allclose(run.errors["energy"][1:], halves, rtol=1e-9, atol=0)
    assert np.all(halves > 1e-8)
    for _ in range(2):  # Compiled, then the tracked solve read back.
        _programs._memo.clear()
        with _programs.keep_programs(tmp_path, "rk, unstable"):
            failed, _ = study(10, 5)
        assert failed.result.startswith("raised: The constraint forces cannot")
    assert len(list(tmp_path.iterdir())) == 2
