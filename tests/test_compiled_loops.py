"""The structure of the compiled program: every scene's default solves compile their
time-stepping and Newton loops with no custom call, no custom fusion and no scatter,
which on CPU
would break each loop into separately dispatched kernels (a rigid-body step ran at a
hundred times its arithmetic that way). A structural test, not a timed one."""

import functools
import math

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import numpy as np
import pytest
from diffrax_vi._lagrangian import constant_mass
from diffrax_vi._linear import dense_jacobian, holds_product
from diffrax_vi.diagnostics import compiled_loop_breakers, loop_breakers
from diffrax_vi.diagnostics._loops import kernels_outside_loops

from .helpers import scene as make_scene


SOLVERS = {
    "MidpointVI": dvi.MidpointVI,
    "TrapezoidalVI": dvi.TrapezoidalVI,
    "Tsit5": dfx.Tsit5,
}


# Multi-stage methods: one scene where the fixed-point iteration falls back to
# Newton's method (separable), one where Newton's method solves every step.
MULTI_STAGE = {
    "GaussVPRK(2)": lambda: dvi.GaussVPRK(2),
    "LobattoVPRK(3)": lambda: dvi.LobattoVPRK(3),
}


def _make(solver):
    if solver == "LGVI":
        return dvi.LGVI()
    if solver == "LinearizedVI":
        return dvi.LinearizedVI(velocity="centered")
    return {**SOLVERS, **MULTI_STAGE}[solver]()


def _solve(scene, solver, adjoint=None):
    term = dvi.terms_for(solver, scene.term())
    h = scene.period / 50
    adjoint = dfx.RecursiveCheckpointAdjoint() if adjoint is None else adjoint

    def run(y0):
        return dfx.diffeqsolve(
            term,
            solver,
            0.0,
            8 * h,
            h,
            y0,
            args=scene.args,
            saveat=dfx.SaveAt(t1=True),
            adjoint=adjoint,
            max_steps=8,
        ).ys

    return run


# A Runge-Kutta solver on a term whose velocity map can fail at a state (a general
# Lagrangian, a constraint) keeps its documented per-evaluation check, a host
# callback, and nothing else: the term's `mass_checked` says which terms.
# The stage equations' sums over stages, batched by Newton's Jacobian, were custom
# fusions in every multi-stage solve of Kepler, the double pendulum, Henon-Heiles,
# the n-body scenes and the bead (GaussVPRK(2) on the double pendulum 4x slower).
# LinearizedVI on a general Lagrangian solved its step by lineax's LU (LAPACK) and
# re-checked the Lagrangian (an eigensolver, host callbacks) in the branch that
# re-anchors its past: 14x slower than MidpointVI.
CASES = (
    [(scene, solver) for scene in dvi.scenes.SCENES for solver in SOLVERS]
    + [(scene, "LGVI") for scene in ("free_rigid_body", "heavy_top", "pendulum_3d")]
    + [("kepler", "GaussVPRK(2)"), ("double_pendulum", "LobattoVPRK(3)")]
    + [("double_pendulum", "LinearizedVI")]
)


@functools.cache
def _compiled(scene: str, solver: str) -> str:
    """The optimised HLO text of `solver`'s solve of `scene`, compiled once per
    process for the tests that read it."""
    scene = make_scene(scene)
    return jax.jit(_solve(scene, _make(solver))).lower(scene.y0).compile().as_text()


@pytest.mark.parametrize("scene,solver", CASES)
def test_no_loop_is_broken_into_kernels(scene, solver):
    """Also: an unconstrained scene of declared constant mass (separable, rigid
    bodies) holds no LAPACK call anywhere, its start included: its check of the
    mass reads the diagonal, where an eigensolver's call (the first in a process
    imports SciPy's linalg to lower it) cost a free body's first call 0.12 s."""
    text = _compiled(scene, solver)
    scene = make_scene(scene)
    breakers = loop_breakers(text)
    if solver == "Tsit5" and not scene.term().mass_checked:
        assert breakers and all("python_cpu_callback" in b for b in breakers)
    else:
        assert breakers == []
    lagrangian = scene.lagrangian
    if scene.constraint is None and constant_mass(lagrangian, scene.y0[1]) is not None:
        assert "lapack" not in text


@pytest.mark.parametrize(
    "solver",
    [dvi.MidpointVI(), dvi.Composition(dvi.MidpointVI(), "yoshida4")],
    ids=["MidpointVI", "composition"],
)
def test_a_solve_that_interpolates_compiles_its_loop_whole(solver):
    """Saving at times interpolates each step's dense output: Hamilton's equations at
    both of its ends. For the double pendulum's Lagrangian, marked quadratic in
    `v`, they check that marker in `LagrangianTerm.vf` alone (a Runge-Kutta
    solve's vector field, which must raise: `test_false_quadratic_marker_is_caught`),
    not in a variational step's dense output, where the solve's start has checked
    it: with that check's host callback the loop was broken into kernels (the
    `MidpointVI` step 5.8 against 0.9 us). A composition's dense output takes them
    from its method's `func` (its yoshida4 of `MidpointVI`: 5.8 against 1.8 us)."""
    scene = make_scene("double_pendulum")
    h = scene.period / 50

    def run(y0):
        return dfx.diffeqsolve(
            scene.term(),
            solver,
            0.0,
            8 * h,
            h,
            y0,
            saveat=dfx.SaveAt(ts=np.linspace(0.0, 8 * h, 5)),
            max_steps=8,
        ).ys

    text = jax.jit(run).lower(scene.y0).compile().as_text()
    assert loop_breakers(text) == []


# Tsit5 on the Cartesian pendulum's term, whose vector field solves the constraint
# force and checks it: the final state of `_solve`'s 8 steps of a 50th of a swing,
# and the result of `solve_fixed_steps` at 5 steps a swing, where the solution
# leaves the rod.
_CHECK_CASE = """
import json
import diffrax as dfx
import jax
import numpy as np
jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi
from diffrax_vi.diagnostics import loop_breakers

scene = dvi.scenes.cartesian_pendulum()
term = scene.term()


def run(y0):
    h = scene.period / 50
    return dfx.diffeqsolve(
        term, dfx.Tsit5(), 0.0, 8 * h, h, y0,
        args=scene.args, saveat=dfx.SaveAt(t1=True), max_steps=8,
    ).ys


compiled = jax.jit(run).lower(scene.y0).compile()
coarse = dvi.solve_fixed_steps(
    term, dfx.Tsit5(), 0.0, 20 * scene.period, scene.period / 5, scene.y0, scene.args
)
body = dvi.scenes.free_rigid_body()
R0, p0 = body.y0
off_group = dfx.diffeqsolve(
    body.term(), dvi.MidpointVI(), 0.0, body.period, body.period / 20,
    (1.1 * R0, p0), body.args, saveat=dfx.SaveAt(t1=True), throw=False,
)
print(json.dumps(dict(
    breakers=loop_breakers(compiled.as_text()),
    final=[np.asarray(x).tolist() for x in jax.tree.leaves(compiled(scene.y0))],
    coarse=str(coarse.result == dfx.RESULTS.nonfinite),
    off_group=str(off_group.result == dfx.RESULTS.nonfinite),
)))
"""


def test_eqx_on_error_nan_compiles_a_checked_vector_fields_loop_whole():
    """The switch the errors page gives for timing Runge-Kutta steps without the
    vector field's check: under `EQX_ON_ERROR=nan` (read when equinox is imported,
    so in a fresh process) the check of a mechanism's constraint forces is no host
    callback, Tsit5's loop holds no loop breaker, and its solution is the checked
    solve's; `solve_fixed_steps` still reports the failure of a solve that leaves
    the rod as `RESULTS.nonfinite` (the checked one raises), and so does a
    variational solve from a start off its group (equinox's NaN fills only the
    check's floating leaves: in the whole state, the start's `RESULTS` read as no
    outcome at all)."""
    import json
    import os
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", _CHECK_CASE],
        capture_output=True,
        text=True,
        env={**os.environ, "EQX_ON_ERROR": "nan"},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["breakers"] == []
    assert out["coarse"] == "True" and out["off_group"] == "True"
    scene = make_scene("cartesian_pendulum")
    checked = jax.jit(_solve(scene, dfx.Tsit5())).lower(scene.y0).compile()
    assert loop_breakers(checked.as_text())
    for ours, theirs in zip(jax.tree.leaves(checked(scene.y0)), out["final"]):
        np.testing.assert_allclose(np.asarray(ours), theirs, rtol=1e-12, atol=1e-14)


def test_a_studys_tracked_solve_compiles_its_loop_whole():
    """A study evaluates every conserved quantity at every step of its tracked
    solve. The double pendulum's energy inverts the Legendre map of a Lagrangian
    marked quadratic in `v`, and a mechanism's hidden constraint (the four-bar's)
    does too: neither checks that marker by a host callback there (the solve's
    start has checked it; `Scene.energy`), which broke the tracked loop into
    kernels (the double pendulum's tracked `TrapezoidalVI` solve of 2 x 10^5 steps
    took 0.97-1.19 against 0.18-0.19 s)."""
    from diffrax_vi.study import _methods, _run

    scene = make_scene("double_pendulum")
    prepared = _run.prepare(
        scene,
        _methods.as_method("TrapezoidalVI"),
        t1=scene.period,
        n_steps=20,
        n_save=2,
        dtype=np.float64,
        y0=scene.y0,
    )
    assert loop_breakers(prepared.tracked.as_text()) == []
    four_bar = make_scene("four_bar")
    hidden = four_bar.invariants["hidden_constraint"]
    assert "callback" not in str(jax.make_jaxpr(hidden)(0.0, four_bar.y0, None))


@pytest.mark.parametrize(
    "scene,solver,reference",
    [("kepler", "MidpointVI", "Tsit5"), ("free_rigid_body", "MidpointVI", "LGVI")],
)
def test_the_start_of_a_constant_mass_compiles_no_kernels_of_its_own(
    scene, solver, reference
):
    """The start of an implicit solve of a declared constant mass takes v0 = p0 / m
    and leaves its finiteness to the first step's check: its checks of v0 compiled
    to reductions and selects outside the loop, three kernels of their own on Kepler
    (0.03 s of its 0.36 s compile). Outside its loops the solve then holds no more
    kernels than Tsit5's of the same term, or, on a group, than LGVI's (whose start
    checks the attitude as MidpointVI's does)."""
    ours = kernels_outside_loops(_compiled(scene, solver))
    assert ours <= kernels_outside_loops(_compiled(scene, reference))


def test_the_exponential_s_series_are_computed_once():
    """The free body's `MidpointVI` step differentiates the exponential map only in
    its Newton matrix, and each series of a coefficient's derivative (below the
    threshold where its closed form cancels) is computed once there: XLA copied a
    series into each of the four fused loops of the matrix's cofactor solve that
    read it (three copies in the program; the step took 0.321 against 0.288 us).
    Counted by the series' first coefficient in Horner's order, -7/(14 + m)! for
    the coefficient c_m."""
    text = _compiled("free_rigid_body", "MidpointVI")
    for m in (2, 3):
        assert text.count(f"constant({-7 / math.factorial(14 + m)!r})") == 1


ADJOINTS = {
    "checkpoint": dfx.RecursiveCheckpointAdjoint,
    "reversible": dvi.ReversibleAdjoint,
}


@pytest.mark.parametrize(
    "scene,solver,adjoint",
    [
        ("kepler", "MidpointVI", "checkpoint"),
        ("kepler", "MidpointVI", "reversible"),
        ("heavy_top", "LGVI", "checkpoint"),
        pytest.param("four_bar", "MidpointVI", "checkpoint", marks=pytest.mark.slow),
        pytest.param(
            "free_rigid_body", "TrapezoidalVI", "reversible", marks=pytest.mark.slow
        ),
    ],
)
def test_no_loop_of_a_gradient_is_broken_into_kernels(scene, solver, adjoint):
    """The backward pass differentiates each implicit step by the implicit function
    theorem: its linear solve is the forward's unrolled elimination, not lineax's
    LU, whose LAPACK calls and host-callback checks broke the backward loops into
    kernels (a heavy top's gradient ran 12x slower)."""
    scene = dvi.scenes.SCENES[scene]()
    solve = _solve(scene, _make(solver), ADJOINTS[adjoint]())
    loss = lambda y0: sum(jax.numpy.sum(x) for x in jax.tree.leaves(solve(y0)))
    assert compiled_loop_breakers(jax.grad(loss), scene.y0) == []


class _NeuralLagrangian(dvi.AbstractLagrangian):
    """A Lagrangian neural network's kind of Lagrangian: an MLP (`equinox.nn.Linear`
    layers, matrix-vector products) of the positions and the velocities, on top of
    a regular kinetic term, on two degrees of freedom."""

    net: eqx.nn.MLP

    def __init__(self):
        self.net = eqx.nn.MLP(4, "scalar", 8, 2, jax.nn.tanh, key=jax.random.key(0))

    def __call__(self, t, q, v, args):
        jnp = jax.numpy
        kinetic = 0.5 * jnp.sum(v**2) - 0.5 * jnp.sum(q**2)
        return kinetic + 0.05 * self.net(jnp.concatenate([q, v]))


class _NeuralPotential(dvi.AbstractSeparableLagrangian):
    """A learned potential of two degrees of freedom (the `learned` scene's kind, on
    two): its steps solve by the fixed-point iteration with a Newton fallback."""

    net: eqx.nn.MLP
    mass: float = eqx.field(static=True, default=1.0)

    def __init__(self):
        self.net = eqx.nn.MLP(2, "scalar", 8, 2, jax.nn.tanh, key=jax.random.key(0))

    def potential(self, t, q, args):
        return self.net(q) + 0.5 * jax.numpy.sum(q**2)


@pytest.mark.parametrize(
    "lagrangian,solver,gradient",
    [
        (_NeuralLagrangian, "MidpointVI", False),
        (_NeuralLagrangian, "GaussVPRK(2)", False),
        (_NeuralLagrangian, "Tsit5", False),
        (_NeuralLagrangian, "LinearizedVI", False),
        (_NeuralPotential, "MidpointVI", False),
        (_NeuralPotential, "MidpointVI", True),
    ],
)
def test_no_loop_of_a_neural_lagrangian_is_broken_into_kernels(
    lagrangian, solver, gradient
):
    """A dense Jacobian taken by `vmap` over its directions (Newton's, the implicit
    function theorem's, the Legendre map's in a Runge-Kutta vector field) turns a
    user's matrix-vector products into matrix products, which XLA on CPU makes
    YNNPACK fusions: 4 to 12 of them broke these loops into kernels (`MidpointVI` on
    the two-degree-of-freedom potential 4.5 against 2.3 us a step). Such Jacobians
    are taken column by column; Tsit5 keeps its documented check alone."""
    y0 = (jax.numpy.array([0.1, 0.5]), jax.numpy.array([0.0, 0.2]))
    scene = dvi.scenes.Scene(
        name="neural", lagrangian=lagrangian(), y0=y0, period=2 * np.pi
    )
    solve = _solve(scene, _make(solver))
    loss = lambda y0: sum(jax.numpy.sum(x) for x in jax.tree.leaves(solve(y0)))
    breakers = compiled_loop_breakers(jax.grad(loss) if gradient else solve, y0)
    if solver == "Tsit5":
        assert breakers and all("python_cpu_callback" in b for b in breakers)
    else:
        assert breakers == []


def test_a_jacobian_through_matrix_vector_products_is_taken_column_by_column():
    """The column-by-column Jacobian is `jax.jacfwd`'s to round-off, and is taken
    only where a product sums more than one term: a one-stage tableau's contraction
    (a scaling) and a single column keep `vmap`."""
    jnp = jax.numpy
    net = eqx.nn.MLP(3, 3, 8, 2, jax.nn.tanh, key=jax.random.key(1))
    x = jnp.array([0.3, -0.2, 0.5])
    assert holds_product(net, x)
    np.testing.assert_allclose(
        dense_jacobian(net, x), jax.jacfwd(net)(x), rtol=1e-13, atol=1e-15
    )
    one_stage = lambda v: jnp.tensordot(jnp.ones((1, 1)), v[None], axes=1)[0]
    assert not holds_product(one_stage, x)
    assert not holds_product(lambda v: jnp.sin(v) * v, x)
    assert not holds_product(lambda v: net(jnp.concatenate([v, v, v])), x[:1])


class _Springs(dvi.AbstractSeparableLagrangian):
    """Unit masses joined by linear springs: a force with no reduction in it, so
    that any reduction in the loop is the solver's own."""

    mass: float = eqx.field(static=True, default=1.0)

    def potential(self, t, q, args):
        return 0.5 * jax.numpy.sum(jax.numpy.diff(q) ** 2)


def _verlet_final(y0):
    return dfx.diffeqsolve(
        dvi.separable_terms(_Springs()),
        dvi.StormerVerlet(),
        0.0,
        0.08,
        0.02,
        y0,
        saveat=dfx.SaveAt(t1=True),
    ).ys


@pytest.mark.parametrize("shape", [(4096,), (4096, 2)], ids=["4096 masses", "vmap"])
def test_no_loop_of_a_large_state_is_broken_into_kernels(shape):
    """XLA on CPU hands a floating-point reduction of 4096 or more elements to
    YNNPACK as a custom fusion: the step's finiteness check, a sum over the state,
    did so for a 4096-mass chain and for an ensemble of 4096 two-mass systems. The
    check counts finite entries in an integer sum instead, of 32 bits: in 64 (the
    default sum of 32-bit integers under x64) the loop converted each flag twice
    and summed twice the bytes, and the 4096-mass chain's Stormer-Verlet step took
    1.22-1.27x its bare scan against 1.20x (`benchmarks/step_cost.py`)."""
    y0 = (jax.numpy.linspace(0.0, 1.0, np.prod(shape)).reshape(shape),) * 2
    solve = jax.vmap(_verlet_final) if len(shape) == 2 else _verlet_final
    program = jax.jit(solve).lower(y0).compile().as_text()
    assert loop_breakers(program) == []
    assert f"s64[{','.join(map(str, shape))}]" not in program


def test_the_check_finds_a_small_matrix_product_in_a_loop():
    # A batched 3 x 9 product: what a Jacobian makes of a small `R @ x`.
    def loop(a, b):
        body = lambda c, _: (jax.numpy.tanh(c @ b)[:, :3] + c, None)
        return jax.lax.scan(body, a, None, length=4)[0]

    a, b = jax.numpy.ones((3, 3)), jax.numpy.ones((3, 9))
    found = compiled_loop_breakers(loop, a, b)
    assert len(found) == 1 and "__ynn_fusion" in found[0]
    assert loop_breakers(jax.jit(loop).lower(a, b[:, :3]).compile().as_text()) == []


def test_the_check_finds_a_scatter_in_a_loop():
    # Rows taken by an index array: a gather, whose derivative is a scatter; XLA on
    # CPU then runs the loop kernel by kernel (no `xla_cpu_small_call`).
    rows = np.array([0, 2])

    def loop(x, take):
        def body(c, _):
            force = jax.grad(lambda y: jax.numpy.sum(jax.numpy.sin(take(y))))(c)
            return c + force, None

        return jax.lax.scan(body, x, None, length=4)[0]

    x = jax.numpy.ones((4, 3))
    by_array = lambda y: y[rows]
    by_slices = lambda y: y[0:3:2]
    text = jax.jit(lambda x: loop(x, by_array)).lower(x).compile().as_text()
    found = loop_breakers(text)
    assert found and all("(scatter)" in b for b in found)
    assert "xla_cpu_small_call" not in text
    text = jax.jit(lambda x: loop(x, by_slices)).lower(x).compile().as_text()
    assert loop_breakers(text) == [] and "xla_cpu_small_call" in text
