"""`solve_fixed_steps` against the `diffeqsolve` whose steps it takes, and the drift
study's fixed-step path against diffeqsolve's."""

import diffrax as dfx
import diffrax_vi as dvi
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from diffrax_vi import scenes
from diffrax_vi.study import drift

from .helpers import max_abs_diff


SCENE = scenes.kepler()
H = SCENE.period / 100


def _diffeqsolve_every(terms, solver, y0, steps, every, dtype=jnp.float64):
    sol = dfx.diffeqsolve(
        terms,
        solver,
        jnp.asarray(0.0, dtype),
        jnp.asarray(steps * H, dtype),
        jnp.asarray(H, dtype),
        y0,
        saveat=dfx.SaveAt(steps=True),
        max_steps=steps,
        throw=False,
    )
    return jax.tree.map(lambda x: x[every - 1 :: every], (sol.ts, sol.ys)), sol.result


@pytest.mark.parametrize(
    "solver, tolerance",
    [
        (dvi.StormerVerlet(), 1e-13),
        (dvi.MidpointVI(), 1e-13),
        (dvi.Composition(dvi.StormerVerlet(), "kahan_li6"), 1e-13),
        # A multistep method: its parasitic mode amplifies round-off on Kepler.
        (dvi.LinearizedVI(velocity="centered"), 1e-11),
        (dfx.Tsit5(), 1e-13),
    ],
    ids=["StormerVerlet", "MidpointVI", "KahanLi6", "LinearizedVI", "Tsit5"],
)
def test_same_steps_as_diffeqsolve(solver, tolerance):
    # The same steps at the same times: equal to round-off (XLA may contract the
    # unrolled loop's arithmetic differently, e.g. into fused multiply-adds).
    terms = dvi.terms_for(solver, SCENE.lagrangian)
    (ts, ys), result = _diffeqsolve_every(terms, solver, SCENE.y0, 120, 40)
    sol = jax.jit(
        lambda y0: dvi.solve_fixed_steps(
            terms, solver, 0.0, 120 * H, H, y0, n_save=3, unroll=4
        )
    )(SCENE.y0)
    assert result == dfx.RESULTS.successful == sol.result
    assert (
        max_abs_diff(
            sol.ys,
            jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), SCENE.y0, ys),
        )
        < tolerance
    )
    assert jnp.array_equal(sol.ts[1:], ts) and sol.ts[0] == 0
    assert sol.t_reached == ts[-1] and sol.num_steps == 120


def test_vmapped_ensemble_and_float32_times():
    solver = dvi.StormerVerlet()
    terms = dvi.terms_for(solver, SCENE.lagrangian)
    y0s = SCENE.perturbed(jax.random.key(1), 3)
    (_, ys), _ = jax.vmap(lambda y0: _diffeqsolve_every(terms, solver, y0, 50, 50))(y0s)
    sol = jax.vmap(lambda y0: dvi.solve_fixed_steps(terms, solver, 0.0, 50 * H, H, y0))(
        y0s
    )
    assert (
        max_abs_diff(
            jax.tree.map(lambda x: x[:, -1], sol.ys),
            jax.tree.map(lambda x: x[:, -1], ys),
        )
        < 1e-13
    )
    y32 = jax.tree.map(lambda x: x.astype(jnp.float32), SCENE.y0)
    t1 = jnp.asarray(50 * H, jnp.float32)
    sol = dvi.solve_fixed_steps(terms, solver, jnp.float32(0), t1, jnp.float32(H), y32)
    (_, ys), _ = _diffeqsolve_every(terms, solver, y32, 50, 50, jnp.float32)
    assert sol.ts.dtype == jnp.float32 and sol.ys[0].dtype == jnp.float32
    # Round-off as in float64 above (1e-13 is some 450 float64 eps), in float32's
    # eps: XLA may contract the two loops' arithmetic differently (it does when
    # both are compiled whole: 2 eps apart after 50 steps).
    bound = 1e-13 / jnp.finfo(jnp.float64).eps * jnp.finfo(jnp.float32).eps
    assert (
        max_abs_diff(
            jax.tree.map(lambda x: x[-1], sol.ys), jax.tree.map(lambda x: x[-1], ys)
        )
        < bound
    )


def test_failure_is_reported_as_diffeqsolve_reports_it():
    # One Newton iteration cannot converge: the first step fails.
    solver = dvi.MidpointVI(root_finder=dvi.Newton(), root_find_max_steps=1)
    terms = dvi.terms_for(solver, SCENE.lagrangian)
    _, result = _diffeqsolve_every(terms, solver, SCENE.y0, 10, 10)
    sol = dvi.solve_fixed_steps(terms, solver, 0.0, 10 * H, H, SCENE.y0, n_save=2)
    assert result != dfx.RESULTS.successful
    assert sol.result == result
    assert sol.num_steps == 0 and sol.t_reached == 0.0


def test_bad_times_raise():
    solver = dvi.StormerVerlet()
    terms = dvi.terms_for(solver, SCENE.lagrangian)
    y0 = SCENE.y0
    with pytest.raises(ValueError, match="forwards"):
        dvi.solve_fixed_steps(terms, solver, 1.0, 0.0, 0.1, y0)
    with pytest.raises(ValueError, match="divides"):
        dvi.solve_fixed_steps(terms, solver, 0.0, 1.0, 0.1, y0, n_save=3)  # 10 steps
    with pytest.raises(ValueError, match="finite"):
        dvi.solve_fixed_steps(terms, solver, 0.0, np.inf, 0.1, y0)
    with pytest.raises(ValueError, match="known when it is traced"):
        jax.jit(lambda t1: dvi.solve_fixed_steps(terms, solver, 0.0, t1, 0.1, y0))(1.0)


@pytest.mark.parametrize(
    "solver",
    [
        dvi.StormerVerlet(),
        dvi.MidpointVI(),
        dvi.Composition(dvi.StormerVerlet(), "yoshida4"),
        dvi.LinearizedVI(),
    ],
    ids=["StormerVerlet", "MidpointVI", "Yoshida4", "LinearizedVI"],
)
def test_fixed_step_programs_hold_no_host_callback(solver):
    """JAX's persistent compilation cache stores no program that holds a host
    callback. solve_fixed_steps knows its times when traced, so the start's check of
    them is made then, and a variational solve of a vector-space Lagrangian holds
    none: a repeated run reads it from the cache. So does diffeqsolve from Python
    floats, which it computes its first times from (`known_value`); from arrays it
    checks them at run time. All raise for NaN times."""
    terms = dvi.terms_for(solver, SCENE.lagrangian)

    def text(solve):
        return jax.jit(solve).lower(SCENE.y0).as_text()

    def general(*times):
        return text(
            lambda y0: dfx.diffeqsolve(terms, solver, *times, y0, throw=False).ys
        )

    fixed = text(lambda y0: dvi.solve_fixed_steps(terms, solver, 0.0, 1.0, 0.1, y0))
    assert "callback" not in fixed
    assert "callback" not in general(0.0, 1.0, 0.1)
    assert "callback" in general(*map(jnp.asarray, (0.0, 1.0, 0.1)))
    # The trace-time check itself, on a first step whose end is NaN.
    with pytest.raises(ValueError, match="NaN or infinite"):
        solver.init(terms, jnp.asarray(0.0), jnp.asarray(jnp.nan), SCENE.y0, None)


@pytest.mark.parametrize(
    "solver, owner",
    [
        (dvi.MidpointVI(), dvi.AbstractVariationalSolver),
        (dvi.Composition(dvi.StormerVerlet(), "yoshida4"), dvi.Composition),
    ],
    ids=["MidpointVI", "Yoshida4"],
)
def test_diffeqsolve_reuses_the_step_the_scan_traced(solver, owner, monkeypatch):
    """solve_fixed_steps hands the solver the terms that diffeqsolve hands it (in
    diffrax's WrapTerm), so a step traced once per program (a variational solver's,
    a composition's) for one is reused by the other in the same process: a study
    traces each method's step once for its tracked solve (the scan) and its timed
    one (diffeqsolve)."""
    traced = []
    step = owner._fractional_step

    def counted(self, *args, **kwargs):
        traced.append(type(self).__name__)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(owner, "_fractional_step", counted)
    # A Lagrangian of its own, whose step no other test has traced.
    lagrangian = dvi.SeparableLagrangian(lambda t, q, args: -1 / jnp.linalg.norm(q))
    terms = dvi.terms_for(solver, lagrangian)
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0]))
    once = [type(solver).__name__]
    jax.make_jaxpr(lambda y: dvi.solve_fixed_steps(terms, solver, 0, 1, 0.1, y).ys)(y0)
    assert traced == once
    jax.make_jaxpr(lambda y: dfx.diffeqsolve(terms, solver, 0, 1, 0.1, y).ys)(y0)
    assert traced == once


def test_study_fixed_step_path_equals_diffeqsolve_path():
    # Without a progress meter the study runs fixed steps in the scan; with one, in
    # diffeqsolve. The recorded errors are the same to round-off. (MidpointVI's
    # steps in the scan: test_same_steps_as_diffeqsolve.)
    kwargs = dict(periods=2, steps_per_period=50, n_save=4, ensemble=2)
    methods = ["StormerVerlet"]
    fast = drift(SCENE, methods, **kwargs)
    slow = drift(SCENE, methods, progress=True, **kwargs)
    for a, b in zip(fast.runs, slow.runs):
        assert a.steps == b.steps
        for name in a.errors:
            np.testing.assert_allclose(
                a.errors[name], b.errors[name], rtol=1e-9, atol=1e-14
            )


def test_uneven_step_count_as_constant_step_size_takes_it():
    # (t1 - t0) / dt0 = 3.33: ConstantStepSize takes 4 steps, the first of dt0 and
    # the others ending at fractions of the interval; so does solve_fixed_steps.
    solver = dvi.MidpointVI()
    terms = dvi.terms_for(solver, SCENE.lagrangian)
    sol = dfx.diffeqsolve(
        terms, solver, 0.0, 0.1, 0.03, SCENE.y0, saveat=dfx.SaveAt(steps=True)
    )
    fast = dvi.solve_fixed_steps(terms, solver, 0.0, 0.1, 0.03, SCENE.y0, n_save=4)
    assert fast.num_steps == 4
    np.testing.assert_array_equal(fast.ts[1:], sol.ts[:4])
    assert (
        max_abs_diff(
            jax.tree.map(lambda x: x[1:], fast.ys),
            jax.tree.map(lambda x: x[:4], sol.ys),
        )
        < 1e-14
    )
