"""The public surface: differentiable scenes, no import-time side effects, the command
line as a public module, and the private diffrax API this package relies on."""

import inspect
import os
import subprocess
import sys
import textwrap

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
from diffrax_vi import scenes
from diffrax_vi._private_api import (
    AdjointTerm,
    assert_term_compatible,
    backends_are_initialized,
    clip_to_end,
    is_subsaveat,
    known_value,
    NoForwardingSolverMeta,
    nondiff_solver_controller_state,
    only_transpose_ys,
    persistent_cache_min_time,
    promote_result,
    save_y,
    unvmap_any,
    use_stepsize_tol,
    WrapTerm,
)


def _make_scene(name):
    """The scene `name`, the learned one untrained and small. Built by the test
    that takes it, not when the suite is collected: building every scene took each
    worker 2.4 s of its collection, half of them for tests the default suite
    deselects."""
    if name != "learned":
        return scenes.SCENES[name]()
    return scenes.Scene(
        name="learned",
        lagrangian=scenes.LearnedLagrangian(jr.key(0), width=4, depth=1),
        y0=(jnp.array(1.5), jnp.array(0.0)),
        period=7.0,
    )


def _final_sum(lagrangian, scene):
    # TrapezoidalVI: explicit for the separable scenes, Newton for the double pendulum.
    h = scene.period / 50
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(lagrangian),
        dvi.TrapezoidalVI(),
        0.0,
        10 * h,
        h,
        scene.y0,
        max_steps=10,
    )
    return sum(jnp.sum(y[-1]) for y in jax.tree.leaves(sol.ys))


# The two largest scenes take most of the time; run them with `-m slow`. The rigid
# bodies' gradients are checked in tests/test_lie.py.
SLOW_SCENES = (
    "double_pendulum",
    "outer_solar_system",
    "bead_wire",
    "free_rigid_body",
    "heavy_top",
    "pendulum_3d",
    "satellite",
)


# Unconstrained here, their implicit steps have 32 and 24 unknowns: Newton's method
# solves them matrix-free, and optimistix's ImplicitAdjoint differentiates them
# with lineax's LU, a LAPACK call (docs/gradients.md, "Implicit steps").
MATRIX_FREE = ("bead_wire", "rigid_chain")


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.slow) if n in SLOW_SCENES else n
        for n in scenes.SCENES
    ],
)
def test_scene_parameters_are_differentiable(name, getkey):
    """The gradient with respect to each parameter against central differences; and
    its program's loops compile whole (`loop_breakers`) where Newton's method
    solves densely: every step is differentiated by an elimination, not by
    lineax's LU, whose LAPACK call and host-callback checks would break a backward
    loop into kernels (tests/test_adjoint.py checks the joined bodies' constrained
    steps). One program gives the value and the gradient."""
    scene = _make_scene(name)
    params, static = eqx.partition(scene.lagrangian, eqx.is_inexact_array)
    leaves, treedef = jax.tree.flatten(params)
    assert leaves, f"{name} has no differentiable parameter"
    value_and_grad = jax.jit(
        jax.value_and_grad(lambda p: _final_sum(eqx.combine(p, static), scene))
    )
    compiled = value_and_grad.lower(params).compile()
    if name not in MATRIX_FREE:
        assert dvi.diagnostics.loop_breakers(compiled.as_text()) == []
    f = lambda p: compiled(p)[0]
    grads = jax.tree.leaves(compiled(params)[1])
    for i, (leaf, grad) in enumerate(zip(leaves, grads)):
        # The derivative along a random direction of this parameter alone, relative
        # to each entry's size (the solar masses span 1 to 1e-8).
        noise = jr.normal(getkey(), jnp.shape(leaf), jnp.result_type(leaf))
        direction = noise * jnp.where(leaf == 0, 1.0, jnp.abs(leaf))
        eps = 1e-6

        def shifted(s):
            moved = list(leaves)
            moved[i] = leaf + s * eps * direction
            return f(jax.tree.unflatten(treedef, moved))

        fd = (shifted(1.0) - shifted(-1.0)) / (2 * eps)
        exact = jnp.sum(grad * direction)
        assert jnp.allclose(exact, fd, rtol=1e-5, atol=1e-9 * (1 + abs(fd))), (
            name,
            i,
            exact,
            fd,
        )


def test_scene_parameters_vmap_and_cast():
    # vmap over a parameter, and a dtype cast that reaches it.
    def final_q(omega):
        lagrangian = scenes.OscillatorLagrangian(omega=omega)
        sol = dfx.diffeqsolve(
            dvi.LagrangianTerm(lagrangian),
            dvi.MidpointVI(),
            0.0,
            1.0,
            0.01,
            (jnp.array(1.0), jnp.array(0.0)),
        )
        return sol.ys[0][-1]

    omegas = jnp.array([0.5, 1.0, 2.0])
    qs = jax.vmap(final_q)(omegas)
    assert np.allclose(qs, np.cos(np.asarray(omegas)), atol=1e-4)
    from diffrax_vi.study._run import cast_scene

    cast = cast_scene(scenes.kepler(), jnp.float32)
    assert all(
        x.dtype == jnp.float32
        for x in jax.tree.leaves(eqx.filter(cast, eqx.is_inexact_array))
    )


def _run(code: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
    )


def test_the_users_matplotlib_backend_is_untouched(tmp_path):
    out = _run(
        f"""
        import sys
        import matplotlib
        matplotlib.use("svg")
        import jax
        jax.config.update("jax_enable_x64", True)
        import diffrax_vi
        from diffrax_vi import scenes, study, thesis, cli
        from diffrax_vi.study import _plot
        s = study.drift(scenes.oscillator(), ["StormerVerlet"], periods=1,
                        steps_per_period=10, n_save=5)
        s.write({str(tmp_path)!r})
        assert matplotlib.get_backend() == "svg", matplotlib.get_backend()
        assert "matplotlib.pyplot" not in sys.modules
        print("ok")
        """
    )
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "drift_energy.png").read_bytes()[:4] == b"\x89PNG"


def test_import_leaves_jaxlie_until_a_group_needs_it():
    """`import diffrax_vi` does not import jaxlie, whose jax_dataclasses imports
    flax where it is installed (0.27 against 0.15 s for the import); the first
    logarithm of an attitude does, and inverts the retraction."""
    out = _run(
        """
        import sys
        import jax
        import jax.numpy as jnp
        import diffrax_vi
        assert "jaxlie" not in sys.modules and "flax" not in sys.modules
        group, eye = diffrax_vi.SO3(), jnp.eye(3)
        x = jnp.array([0.3, -0.2, 0.5])
        y = jax.jit(lambda x: group.difference(eye, group.retract(eye, x)))(x)
        print(float(jnp.max(jnp.abs(y - x))))
        assert "jaxlie" in sys.modules
        """
    )
    assert out.returncode == 0, out.stderr
    assert float(out.stdout) < 1e-6


SMALL_LOOP_PROGRAM = """
    import re, jax, jax.numpy as jnp, diffrax as dfx
    jax.config.update("jax_enable_x64", True)
    import diffrax_vi as dvi
    {before}
    term = dvi.LagrangianTerm(
        dvi.SeparableLagrangian(lambda t, q, a: -1 / jnp.sqrt(jnp.sum(q**2)))
    )
    solver = dvi.Composition(dvi.MidpointVI(), "yoshida4")
    solve = lambda y0: dfx.diffeqsolve(
        term, solver, 0.0, 1.0, 0.01, y0, saveat=dfx.SaveAt(t1=True)
    ).ys
    y0 = (jnp.array([0.4, 0.0]), jnp.array([0.0, 2.0]))
    text = jax.jit(solve).lower(y0).compile().as_text()
    # Loops compiled as one function are called as a "small call".
    print(len(re.findall('xla_cpu_small_call="true"', text)))
    {after}
"""


def _small_loops(before: str = "", after: str = "", **env) -> int:
    """How many loops `SMALL_LOOP_PROGRAM` compiles whole, run in a fresh process."""
    out = _run(SMALL_LOOP_PROGRAM.format(before=before, after=after), **env)
    assert out.returncode == 0, out.stderr
    return int(out.stdout)


def test_import_compiles_small_loops_whole_unless_opted_out():
    """`import diffrax_vi` raises XLA's small-loop threshold: the composition's
    time-stepping loop and its loop over the substeps (over 1 kB) are compiled as one
    function, and not with `DIFFRAX_VI_XLA_DEFAULT=1` or after `keep_xla_default()`;
    a threshold in the user's `XLA_FLAGS` stands; changing the setting after JAX
    has started is an error, not silently ignored."""
    plain = _small_loops(XLA_FLAGS="", DIFFRAX_VI_XLA_DEFAULT="1")
    too_late = """for change in ["keep_xla_default", "compile_small_loops_whole"]:
        try:
            getattr(dvi, change)()
        except RuntimeError as e:
            assert "before JAX starts" in str(e)
        else:
            raise AssertionError("no error after the backend started")"""
    # The root finds' loops are small either way; the time stepping and the loop
    # over the substeps only with the threshold raised.
    assert _small_loops(after=too_late, XLA_FLAGS="") > plain
    undo = "assert dvi.keep_xla_default()\n    assert not dvi.keep_xla_default()"
    assert _small_loops(undo, XLA_FLAGS="") == plain
    # Not even the small loops: the user's zero stands.
    keep = (
        "assert not dvi.compile_small_loops_whole()\n"
        "    assert not dvi.keep_xla_default()"
    )
    zero = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"
    assert _small_loops(keep, XLA_FLAGS=zero) < plain
    for bad in (-1, True):
        with pytest.raises(ValueError, match="non-negative integer"):
            dvi.compile_small_loops_whole(bad)


def test_xla_setting_changes_only_its_own_entry():
    """Flags the user sets after `import diffrax_vi` survive a change or undo of the
    package's threshold, and take effect (four host devices)."""
    out = _run(
        """
        import os
        import diffrax_vi as dvi
        device_count = "--xla_force_host_platform_device_count=4"
        os.environ["XLA_FLAGS"] = os.environ["XLA_FLAGS"] + " " + device_count
        assert dvi.compile_small_loops_whole(1 << 20)
        flags = os.environ["XLA_FLAGS"]
        assert device_count in flags and flags.count("byte_threshold") == 1, flags
        assert dvi.keep_xla_default()
        flags = os.environ["XLA_FLAGS"]
        assert device_count in flags and "byte_threshold" not in flags, flags
        import jax
        assert len(jax.devices()) == 4, jax.devices()
        print("ok")
        """,
        XLA_FLAGS="--xla_backend_extra_options=xla_cpu_use_thunk_runtime=true",
    )
    assert out.stdout.strip() == "ok", out.stderr


def test_import_after_jax_started_warns_once():
    out = _run(
        """
        import warnings
        import jax.numpy as jnp
        jnp.zeros(1)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            import diffrax_vi
            import diffrax_vi.cli
        messages = [str(w.message) for w in caught]
        assert len(messages) == 1 and "cannot apply" in messages[0], messages
        assert "DIFFRAX_VI_XLA_DEFAULT=1" in messages[0]
        print("ok")
        """,
        XLA_FLAGS="",
    )
    assert out.stdout.strip() == "ok", out.stderr


def test_python_dash_m_runs_the_command_line():
    out = subprocess.run(
        [sys.executable, "-m", "diffrax_vi", "drift", "--help"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    assert "--steps-per-period" in out.stdout


def test_private_api_assumptions():
    """Fails loudly if a diffrax or equinox upgrade changes what `_private_api`
    relies on."""
    # diffeqsolve hands the solver a WrapTerm with `term` and `direction`.
    seen = []

    class Spy(dvi.StormerVerlet):
        def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
            seen.append(terms)
            return super().step(terms, t0, t1, y0, args, solver_state, made_jump)

    pair = dvi.terms_for(
        dvi.StormerVerlet(), dvi.SeparableLagrangian(lambda t, q, a: q)
    )
    dfx.diffeqsolve(pair, Spy(), 1.0, 0.0, -0.5, (jnp.array(0.0), jnp.array(1.0)))
    wrapped = seen[0][0]
    assert isinstance(wrapped, WrapTerm) and isinstance(wrapped.term, dfx.ODETerm)
    # (Its fields are traced inside diffeqsolve: compare what the term is.)
    assert type(wrapped.term.vector_field) is type(pair[0].vector_field)
    # known_value: diffeqsolve computes a solve's first times from Python floats by
    # operations on constants, which it evaluates; from a traced argument it cannot.
    times = []

    class Times(dvi.StormerVerlet):
        def init(self, terms, t0, t1, y0, args):
            times.append((known_value(t0), known_value(t1)))
            return super().init(terms, t0, t1, y0, args)

    y0 = (jnp.array(0.0), jnp.array(1.0))
    solve = lambda t1: dfx.diffeqsolve(pair, Times(), 0.0, t1, 0.25, y0).ys
    jax.jit(lambda: solve(1.0)).lower()
    jax.jit(solve).lower(1.0)
    assert times[0] == (0.0, 0.25) and times[1][1] is None
    # `direction` is the sign of t1 - t0, and the control is signed with it.
    direct = WrapTerm(pair[0], -1)
    assert direct.direction == -1 and float(direct.contr(-1.0, -0.5)) == -0.5
    # diffrax's metaclass forwards isinstance through wrapped solvers; our markers'
    # metaclass must be a subclass of it that does not.
    assert isinstance(dfx.HalfSolver(dfx.Tsit5()), dfx.Tsit5)
    assert issubclass(NoForwardingSolverMeta, type(dfx.AbstractSolver))
    assert type(dvi.AbstractSymplecticSolver) is NoForwardingSolverMeta
    # JAX's backends_are_initialized: true once anything has run (it has, above).
    assert backends_are_initialized()
    # equinox's unvmap_any: the `any` over a batch, seen as one value inside vmap.
    out = jax.vmap(lambda x: unvmap_any(x > 0))(jnp.array([-1.0, 2.0]))
    assert out.shape == (2,) and bool(jnp.all(out))
    # diffeqsolve's own check of terms against the solver: a ValueError.
    term = dfx.ODETerm(lambda t, y, args: -y)
    tsit5, pair = dfx.Tsit5(), dfx.SemiImplicitEuler()
    assert_term_compatible(
        0.0,
        jnp.array(1.0),
        None,
        term,
        tsit5.term_structure,
        tsit5.term_compatible_contr_kwargs,
    )
    with pytest.raises(ValueError, match="not compatible"):
        assert_term_compatible(
            0.0,
            (jnp.array(1.0),) * 2,
            None,
            term,
            pair.term_structure,
            pair.term_compatible_contr_kwargs,
        )
    # diffrax's results promote optimistix's and lineax's, and optimistix's
    # lineax's: promote_result is equinox's promotion, item for item.
    for cls, results in [
        (dfx.RESULTS, optx.RESULTS),
        (dfx.RESULTS, lx.RESULTS),
        (optx.RESULTS, lx.RESULTS),
    ]:
        for name in results._name_to_item:
            item = getattr(results, name)
            assert promote_result(cls, item) == cls.promote(item)
            assert promote_result(cls, item) == getattr(cls, name)
    # JAX's shortest compilation its persistent cache keeps, read when it writes an
    # entry: a `with` block sets it in its thread alone.
    import threading

    before, inside, other = persistent_cache_min_time.value, [], []
    with persistent_cache_min_time(before + 7.0):
        inside.append(persistent_cache_min_time.value)
        thread = threading.Thread(
            target=lambda: other.append(persistent_cache_min_time.value)
        )
        thread.start()
        thread.join()
    assert inside == [before + 7.0] and other == [before]
    assert persistent_cache_min_time.value == before
    assert jax.config.jax_persistent_cache_min_compile_time_secs == before
    # An implicit solver's root finder leaves its tolerances to the controller.
    assert dfx.Kvaerno5().root_finder.rtol is use_stepsize_tol
    # BacksolveAdjoint's backward solve hands the solver an AdjointTerm.
    assert issubclass(AdjointTerm, dfx.AbstractTerm)
    # What ReversibleAdjoint shares with diffrax's adjoints: the loop's clipping of
    # a step to t1 (to t1 within 100 ulp, else unchanged), the default save
    # function, the SaveAt leaf test, and the two state helpers' signatures.
    assert float(clip_to_end(0.0, 1.0 - 1e-15, 1.0, 1.0 - 1e-14, True)) == 1.0
    assert float(clip_to_end(0.0, 0.5, 1.0, 1.0 - 1e-14, True)) == 0.5
    assert save_y(0.0, 3.0, None) == 3.0 and dfx.SaveAt(t1=True).subs.fn is save_y
    assert is_subsaveat(dfx.SaveAt(t1=True).subs)
    params = inspect.signature(nondiff_solver_controller_state).parameters
    assert list(params) == [
        "adjoint",
        "init_state",
        "passed_solver_state",
        "passed_controller_state",
    ]
    assert list(inspect.signature(only_transpose_ys).parameters) == ["final_state"]


def test_public_names_are_the_packages_own():
    """Every public name of `diffrax_vi` is defined by the package (or is one of its
    modules): no standard-library module leaks in (`diffrax_vi.importlib`). In a
    fresh process, as a user imports it (the suite's jaxtyping hook adds a name)."""
    out = _run(
        """
        import types
        import diffrax_vi as dvi
        for name in dir(dvi):
            if name.startswith("_"):
                continue
            obj = getattr(dvi, name)
            module = isinstance(obj, types.ModuleType)
            where = obj.__name__ if module else obj.__module__
            assert where.startswith("diffrax_vi"), (name, where)
        print("ok")
        """
    )
    assert out.stdout.strip() == "ok", out.stderr
