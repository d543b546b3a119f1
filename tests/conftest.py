import gc
import os
import shutil
import tempfile

import jax
import numpy as np
import pytest


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")
# The command line keeps compiled programs in $XDG_CACHE_HOME: the suite's runs of
# it write into a folder of their own, not the user's cache, removed when the
# process's tests end (`pytest_unconfigure`, in each worker).
_CACHE = tempfile.mkdtemp(prefix="diffrax-vi-test-cache-")
os.environ["XDG_CACHE_HOME"] = _CACHE


def pytest_unconfigure(config):
    shutil.rmtree(_CACHE, ignore_errors=True)


@pytest.fixture(autouse=True)
def _freeze_what_the_test_keeps():
    """After each test, collect its garbage and freeze what it leaves alive (after
    a worker's first test, the imported heap too, as the console script freezes
    its own after its imports, `_diffrax_vi_cli.command`): JAX's caches of traces
    and compiled programs grow through a worker's run. Python's full collections
    walk every object not frozen, so in a worker that kept them all they came to
    cost 52-61 s of its run (the whole suite on 2 workers), and each test that
    traces much paid for the heap of the tests before it. Walked once here, each
    test's objects cost a quarter of that (14-17 s a worker). Four test files in
    one process: 410 -> 334 s, full collections 28 -> 8 s, peak memory 3.20 ->
    3.18 GB. Objects frozen stay until `_release_compiled_programs` unfreezes
    them."""
    yield
    gc.collect()
    gc.freeze()


@pytest.fixture(autouse=True)
def _patched_code_compiles_afresh(request):
    """A study keeps the programs it compiles for the rest of the process, keyed by
    the values they close over, not by the code that traced them
    (`diffrax_vi.study._programs._Memo`): a test that patches the library starts
    without them, so that its patch is traced."""
    if "monkeypatch" in request.fixturenames:
        from diffrax_vi.study import _programs

        _programs._memo.clear()


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test file. Each one holds memory
    mappings, and a worker that keeps hundreds of files' worth reaches the kernel's
    limit (vm.max_map_count, 65530): XLA's compiler then fails to allocate and the
    worker dies with a segmentation fault (test_study.py, the file that adds the
    most, leaves 10 000). Only past 40 000, 25 000 short of the limit, so that files
    keep sharing compiled programs as long as they safely can."""
    yield
    try:
        with open("/proc/self/maps") as maps:
            crowded = sum(1 for _ in maps) > 40_000
    except OSError:
        crowded = True
    if crowded:
        from diffrax_vi.study import _programs

        _programs._memo.clear()
        jax.clear_caches()
        gc.unfreeze()
        gc.collect()


@pytest.fixture
def as_a_user_runs_it():
    """Runtime type checks off, as a user runs the library: the suite adds
    jaxtyping's import hook (`--jaxtyping-packages`), under which a string outside a
    `Literal` option fails its type check before the library's own `ValueError`
    that names the choices."""
    import jaxtyping

    before = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    yield
    jaxtyping.config.update("jaxtyping_disable", before)


@pytest.fixture
def getkey():
    keys = iter(jax.random.split(jax.random.key(5678), 1000))
    return lambda: next(keys)


# The default suite's budget is 15 minutes on CI's two cores (what it takes:
# benchmarks/results/suite_compiles_cpu.txt). These runs repeat, for one more method
# or Lagrangian, a property the default suite already checks for another; they run
# with `-m slow` (test ids, or their prefix before `[` ... `-`).
SLOW = (
    # tests/test_adaptive.py checks the order with Stormer-Verlet, adaptation of
    # implicit solvers with MidpointVI.
    "test_adaptive.py::test_order_in_the_fictive_step[yoshida4",
    "test_adaptive.py::test_implicit_solvers_adapt_too[GaussVPRK2",
    # The guard's no-false-alarm and the relativistic Legendre map: one case each
    # in the default suite.
    "test_failures.py::test_healthy_linearized_runs_pass_the_guard[pendulum",
    "test_failures.py::test_healthy_linearized_runs_pass_the_guard[henon_heiles",
    "test_guards.py::test_relativistic_lagrangian_runs_in_every_solver[LinearizedVI",
    # Checked for MidpointVI and the other solvers in the default suite.
    "test_resume.py::test_jump_discards_a_stale_state[LinearizedVI-solver3",
    "test_properties.py::test_time_reversible[GaussVPRK(2)",
    "test_stability.py::test_float32_end_to_end[LobattoVPRK(3)",
    # The same NBodyLagrangian as outer_solar_system's; one-degree-of-freedom
    # scenes built like the oscillator's and the pendulum's.
    "test_surface.py::test_scene_parameters_are_differentiable[pythagorean_three_body",
    "test_surface.py::test_scene_parameters_are_differentiable[falling_particle",
    "test_surface.py::test_scene_parameters_are_differentiable[duffing",
    # Each Runge-Kutta solver on the general term, and Tsit5 on the quadratic one.
    "test_term.py::test_runge_kutta_solvers_integrate_the_same_term[quadratic-dopri8",
    "test_term.py::test_runge_kutta_solvers_integrate_the_same_term[quadratic-kvaerno5",
    # suzuki4 checks composition under jit/vmap/grad, test_properties Gauss's vmap.
    "test_higher_order.py::test_jit_vmap_grad[gauss2",
    "test_seed.py::test_linearized_backward_vmap_grad",
    "test_seed.py::test_theorem_1_midpoint_on_lift_is_tangent_of_flow[double-pendulum",
    "test_seed.py::test_theorem_2_presymplectic_on_S[double-pendulum",
    "test_higher_order.py::test_compensated_summation_brouwer",
    "test_higher_order.py::test_composition_substeps_do_not_round_with_t[MidpointVI",
    "test_higher_order.py::test_jit_vmap_grad[lobatto3",
    "test_resume.py::test_resume_from_saved_state[yoshida4(MidpointVI)",
    "test_resume.py::test_resume_from_saved_state[GaussVPRK(2)",
    "test_resume.py::test_resume_from_saved_state[LinearizedVI-solver",
    "test_resume.py::test_jump_discards_a_stale_state[yoshida4(MidpointVI)",
    "test_resume.py::test_jump_discards_a_stale_state[GaussVPRK(2)",
    "test_stability.py::test_float32_end_to_end[LinearizedVI",
    "test_stability.py::test_float32_end_to_end[MidpointVI",
    "test_stability.py::test_stability_limit[LinearizedVI(centered, trapezoidal)",
    "test_stability.py::test_double_pendulum_diverges_but_keeps_its_energy",
    "test_stability.py::test_a_million_steps_keep_the_energy_bounded[MidpointVI",
    "test_solvers.py::test_grad_through_args_and_general_lagrangian",
    "test_solvers.py::test_singular_hessian",  # test_guards.py covers it, two units
    "test_resume.py::test_jump_discards_a_stale_state[LinearizedVI-centered",
    # the pendulum's cases check the property in the default suite
    "test_forces_constraints.py::test_symplectic_on_the_constrained_phase_space[four",
    "test_forces_constraints.py::test_constraints_hold_at_every_step_of_1e5[four_bar",
    # GaussVPRK(2) and yoshida4 fit the forced higher orders by default
    "test_forces_constraints.py::test_forced_oscillator_order[GaussVPRK(3)",
    "test_forces_constraints.py::test_forced_oscillator_order[kahan_li6",
    # gradients through forced and constrained solves: test_forces_constraints.py
    "test_surface.py::test_scene_parameters_are_differentiable[four_bar",
    "test_surface.py::test_scene_parameters_are_differentiable[forced_duffing",
    "test_surface.py::test_scene_parameters_are_differentiable[cartesian_pendulum",
    # Krylov against dense: test_large.py::test_krylov_newton_equals_dense.
    "test_large.py::test_symmetric_krylov_equals_dense",
    # Orders 2 and 4 on the groups run by default (the composition is the same code
    # at every order; orders 6 and 8 there cost a minute of compilation).
    "test_lie.py::test_order_on_the_heavy_top_and_the_free_body[heavy_top-1.0-k",
    "test_lie.py::test_order_on_the_heavy_top_and_the_free_body[free_rigid_body-10.0-k",
    # 10^6 steps of it are benchmarks/lie_groups.py's (results in the docs).
    "test_lie.py::test_free_rigid_body_keeps_the_group_the_casimir_and_bounded_energy",
    # An ensemble equals a loop of single runs: test_study.py checks it unsharded.
    "test_study.py::test_sharded_ensemble_equals_unsharded",
    # Centered LinearizedVI: the forward variant runs by default.
    "test_stability.py::test_step_matrix_roots_match_the_characteristic_polynomial[LinearizedVI(c",
    "test_scan.py::test_same_steps_as_diffeqsolve[LinearizedVI",
    "test_failures.py::test_centered_linearized_on_kepler_fails_instead_of_exploding",
    # The reversible adjoint through a constrained step: RATTLE's case runs by
    # default, MidpointVI's unconstrained case on Kepler.
    "test_adjoint.py::test_constrained_gradients_reach_the_term_and_the_constraint[Mid",
    # The compiled loops of every scene: MidpointVI's run by default on each
    # scene, TrapezoidalVI's and Tsit5's on the groups (where the products are).
    *(
        f"test_compiled_loops.py::test_no_loop_is_broken_into_kernels[{scene}-{s}]"
        for scene in (
            "kepler",
            "falling_particle",
            "oscillator",
            "duffing",
            "pendulum",
            "double_pendulum",
            "henon_heiles",
            "fpu",
            "outer_solar_system",
            "pythagorean_three_body",
            "learned",
            "bead_wire",
            "forced_duffing",
            "cartesian_pendulum",
            "four_bar",
        )
        for s in ("TrapezoidalVI", "Tsit5")
    ),
    # The chain is the rigid double pendulum's code with more links, its joints
    # over index ranges (checked scatter-free by test_joints.py): its loops
    # compile for a minute each, and its parameter gradient (49 s) and its
    # invariants under scipy (15 s) repeat the rigid double pendulum's cases.
    "test_surface.py::test_scene_parameters_are_differentiable[rigid_chain",
    "test_scenes.py::test_conserved_quantities_are_conserved_by_solve_ivp[rigid_chain",
    *(
        f"test_compiled_loops.py::test_no_loop_is_broken_into_kernels[rigid_chain-{s}]"
        for s in ("MidpointVI", "TrapezoidalVI", "Tsit5")
    ),
    # Joined bodies converge at second order under MidpointVI and TrapezoidalVI by
    # default; a composition is the same code at every order, and its fourth order
    # on the groups runs in test_lie.py.
    "test_joints.py::test_rigid_double_pendulum_converges_to_minimal_coordinates[yosh",
    # The LGVI's sixth order: its fourth and eighth run by default.
    "test_rigid_body.py::test_lgvi_order_against_scipy[kahan_li6",
    # A composition takes Stormer-Verlet steps, whose reversal runs by default.
    "test_adjoint.py::test_kepler_gradients_equal_checkpointing[yoshida4",
    # A constrained MidpointVI step's multipliers from its inverse step: the
    # Cartesian pendulum's case (rod-forced) runs by default; the four-bar's two
    # adjoints compile for 30 s.
    "test_adjoint.py::test_the_inverse_steps_root_gives_the_checkpointed_gradient[four",
    # Its 18 unknowns, beyond the unrolled elimination's (two gradients compiling
    # for 40 s): test_a_large_constrained_step_is_differentiated_without_lapack
    # checks their programs by default.
    "test_adjoint.py::test_the_inverse_steps_root_gives_the_checkpointed_gradient[joi",
    # The hinged box vmapped, in solve_fixed_steps and in float32 (52 s of
    # compilation): each runs by default on its own, a vmapped constrained solve in
    # test_forces_constraints.py, fixed steps and float32 on the group in
    # test_lie.py, a constrained float32 solve in test_guards.py.
    "test_joints.py::test_joined_bodies_run_under_jax_transformations",
)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.removeprefix("tests/").startswith(SLOW):
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def symplectic_euler_tableau():
    """Symplectic Euler as a VPRK tableau: a valid method that is not symmetric."""
    import diffrax_vi as dvi  # After x64 is enabled above.

    return dvi.VPRKTableau(
        a=np.array([[1.0]]),
        a_bar=np.array([[0.0]]),
        b=np.array([1.0]),
        c=np.array([1.0]),
        order=1,
    )
