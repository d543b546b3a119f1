"""`ReversibleAdjoint`: gradients through solves, computed from states rebuilt by
inverse steps, against diffrax's `RecursiveCheckpointAdjoint` (the derivative of the
same discrete solve, from stored states)."""

import diffrax as dfx
import diffrax_vi as dvi
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest


E = 0.6  # Kepler, eccentricity; period 2 pi
KEPLER_Y0 = (
    jnp.array([1 - E, 0.0]),
    jnp.array([0.0, ((1 + E) / (1 - E)) ** 0.5]),
)
KEPLER = dvi.SeparableLagrangian(lambda t, q, args: -args / jnp.linalg.norm(q))
H = 2 * jnp.pi / 200


def _relative_error(a, b) -> float:
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return max(float(jnp.max(jnp.abs(x - y)) / jnp.max(jnp.abs(y))) for x, y in pairs)


@eqx.filter_jit
@eqx.filter_grad
def _kepler_gradient(inputs, solver, adjoint, steps):
    """d/d(y0, GM) of a scalar of the final state, after `steps` steps (traced, so
    that one compiled solve serves every length up to 2e4)."""
    y0, gm = inputs
    explicit = isinstance(getattr(solver, "base", solver), dvi.StormerVerlet)
    terms = dvi.separable_terms(KEPLER) if explicit else dvi.LagrangianTerm(KEPLER)
    sol = dfx.diffeqsolve(
        terms, solver, 0.0, steps * H, H, y0, gm, adjoint=adjoint, max_steps=20_000
    )
    q, p = sol.ys
    return jnp.sum(q[-1] ** 2) + jnp.sum(jnp.sin(p[-1]))


@pytest.mark.parametrize(
    "solver",
    [dvi.StormerVerlet(), dvi.MidpointVI(), dvi.Composition(dvi.StormerVerlet())],
    ids=["StormerVerlet", "MidpointVI", "yoshida4"],
)
def test_kepler_gradients_equal_checkpointing(solver):
    """Over 2000 steps (ten orbits) to 1e-8; Stormer-Verlet also over 2e4."""
    inputs = (KEPLER_Y0, jnp.asarray(1.0))
    lengths = (2000, 20_000) if isinstance(solver, dvi.StormerVerlet) else (2000,)
    for steps, tolerance in zip(lengths, (1e-8, 1e-6)):
        steps = jnp.asarray(steps)
        ours = _kepler_gradient(inputs, solver, dvi.ReversibleAdjoint(), steps)
        reference = _kepler_gradient(
            inputs, solver, dfx.RecursiveCheckpointAdjoint(), steps
        )
        assert _relative_error(ours, reference) < tolerance, steps


@eqx.filter_jit
@eqx.filter_grad
def _adaptive_kepler_gradient(inputs, solver, adjoint, saveat, step_ts):
    """d/d(y0, GM, initial step density) of a scalar of the saved states, with
    steps that follow the potential (ReversibleController): the step sizes depend
    on the state, and the last step is cut to end on t1."""
    y0, gm, density = inputs
    controller = dvi.ReversibleController(
        dvi.PotentialMonitor(KEPLER), density=density, step_ts=step_ts
    )
    sol = dfx.diffeqsolve(
        dvi.terms_for(solver, KEPLER),
        solver,
        0.0,
        9.1 * 2 * jnp.pi,
        H / 4,
        y0,
        gm,
        stepsize_controller=controller,
        saveat=saveat,
        adjoint=adjoint,
        max_steps=2400,
    )
    q, p = sol.ys
    weights = jnp.linspace(1.0, 2.0, q.shape[0])[:, None]
    return jnp.sum(weights * q**2) + jnp.sum(weights * jnp.sin(p))


SAVE_TS = jnp.linspace(0.0, 9 * 2 * jnp.pi, 23)


@pytest.mark.parametrize(
    "solver, saveat, step_ts",
    [
        (dvi.StormerVerlet(), dfx.SaveAt(ts=SAVE_TS, t1=True), None),
        (dvi.StormerVerlet(), dfx.SaveAt(t0=True, ts=SAVE_TS), SAVE_TS),
        pytest.param(
            dvi.MidpointVI(), dfx.SaveAt(t1=True), None, marks=pytest.mark.slow
        ),
    ],
    ids=["StormerVerlet-interpolated-ts", "StormerVerlet-step-ts", "MidpointVI"],
)
def test_reversible_controller_gradients_equal_checkpointing(solver, saveat, step_ts):
    """Over about 2000 steps sized by the potential monitor (nine orbits), states
    saved at t1, interpolated at ts, or at steps landing on ts: the gradients with
    respect to y0 and GM to 1e-8 relative. The density's is small (about 0.03
    against gradients of about 400, the sum of cancelling contributions through
    every step size) and is held to 1e-8 of the gradient's scale."""
    inputs = (KEPLER_Y0, jnp.asarray(1.0), jnp.asarray(1.0))
    ours = _adaptive_kepler_gradient(
        inputs, solver, dvi.ReversibleAdjoint(), saveat, step_ts
    )
    reference = _adaptive_kepler_gradient(
        inputs, solver, dfx.RecursiveCheckpointAdjoint(), saveat, step_ts
    )
    assert all(float(jnp.max(jnp.abs(g))) > 1e-3 for g in jax.tree.leaves(reference))
    assert _relative_error(ours[:2], reference[:2]) < 1e-8
    scale = max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(reference))
    assert abs(float(ours[2] - reference[2])) < 1e-8 * scale


def test_saves_at_ts_between_fixed_steps():
    """SaveAt(ts=...) between the steps of a fixed grid: the cubic Hermite
    interpolants are differentiated too."""

    @eqx.filter_jit
    @eqx.filter_grad
    def gradient(inputs, adjoint):
        y0, gm = inputs
        sol = dfx.diffeqsolve(
            dvi.separable_terms(KEPLER),
            dvi.StormerVerlet(),
            0.0,
            2 * jnp.pi,
            H,
            y0,
            gm,
            saveat=dfx.SaveAt(t0=True, ts=jnp.linspace(0.01, 2 * jnp.pi - 0.01, 7)),
            adjoint=adjoint,
            max_steps=300,
        )
        q, p = sol.ys
        return jnp.sum(jnp.arange(8.0)[:, None] * (q + jnp.sin(p)))

    inputs = (KEPLER_Y0, jnp.asarray(1.0))
    ours = gradient(inputs, dvi.ReversibleAdjoint())
    reference = gradient(inputs, dfx.RecursiveCheckpointAdjoint())
    assert _relative_error(ours, reference) < 1e-10


def test_checkpoints_re_anchor_the_rebuilt_states():
    inputs, steps = (KEPLER_Y0, jnp.asarray(1.0)), jnp.asarray(2000)
    solver = dvi.StormerVerlet()
    ours = _kepler_gradient(inputs, solver, dvi.ReversibleAdjoint(64), steps)
    reference = _kepler_gradient(
        inputs, solver, dfx.RecursiveCheckpointAdjoint(), steps
    )
    assert _relative_error(ours, reference) < 1e-8
    for every in (0, -3, True):
        with pytest.raises(ValueError, match="checkpoint_every"):
            dvi.ReversibleAdjoint(every)


class _Pendulum(dvi.AbstractSeparableLagrangian):
    gravity: jax.Array
    mass: float = 1.0

    def potential(self, t, q, args):
        return self.gravity * q[1]


@pytest.mark.parametrize("wrt", ["y0", "gm"])
def test_a_gradient_with_respect_to_some_inputs_only(wrt):
    """The backward pass gives cotangents to what is differentiated only: with
    respect to y0 alone (GM and the controller's density arrays held fixed), or GM
    alone (y0 fixed), under ReversibleController, the gradient is checkpointing's
    to 1e-8."""
    controller = dvi.ReversibleController(
        dvi.PotentialMonitor(KEPLER), density=jnp.asarray(1.0)
    )
    solver = dvi.StormerVerlet()

    @eqx.filter_jit
    def gradient(adjoint):
        def final(y0, gm):
            sol = dfx.diffeqsolve(
                dvi.separable_terms(KEPLER),
                solver,
                0.0,
                4 * jnp.pi,
                H / 4,
                y0,
                gm,
                stepsize_controller=controller,
                adjoint=adjoint,
                max_steps=1000,
            )
            return jnp.sum(sol.ys[0] ** 2) + jnp.sum(jnp.sin(sol.ys[1]))

        return jax.grad(final, argnums=0 if wrt == "y0" else 1)(
            KEPLER_Y0, jnp.asarray(1.0)
        )

    ours = gradient(dvi.ReversibleAdjoint())
    reference = gradient(dfx.RecursiveCheckpointAdjoint())
    assert all(float(jnp.max(jnp.abs(g))) > 1e-3 for g in jax.tree.leaves(reference))
    assert _relative_error(ours, reference) < 1e-8


def _circle(t, q, args):
    return jnp.sum(q**2) - args**2


@pytest.mark.parametrize(
    "solver", [dvi.TrapezoidalVI(), dvi.MidpointVI()], ids=["Trapezoidal", "Midpoint"]
)
def test_constrained_gradients_reach_the_term_and_the_constraint(solver):
    """The Cartesian pendulum (RATTLE / constrained midpoint): gradients with
    respect to the Lagrangian's parameter (a leaf of the term), the constraint's
    (`args`, the length) and y0, on an uneven StepTo grid with both ends saved."""
    term = dvi.LagrangianTerm(_Pendulum(jnp.array(9.8)), constraint=_circle)
    angle = 0.3
    y0 = (
        jnp.array([jnp.sin(angle), -jnp.cos(angle)]),
        0.3 * jnp.array([jnp.cos(angle), jnp.sin(angle)]),
    )
    ts = jnp.concatenate([jnp.linspace(0, 1.5, 100), jnp.linspace(1.5, 3, 180)[1:]])

    @eqx.filter_jit
    @eqx.filter_grad
    def gradient(inputs, adjoint):
        term, y0, length = inputs
        sol = dfx.diffeqsolve(
            term,
            solver,
            0.0,
            3.0,
            None,
            y0,
            length,
            stepsize_controller=dfx.StepTo(ts),
            saveat=dfx.SaveAt(t0=True, t1=True),
            adjoint=adjoint,
        )
        return sum(jnp.sum(jnp.sin(x)) for x in jax.tree.leaves(sol.ys))

    inputs = (term, y0, jnp.asarray(1.0))
    ours = gradient(inputs, dvi.ReversibleAdjoint())
    reference = gradient(inputs, dfx.RecursiveCheckpointAdjoint())
    assert abs(float(reference[0].lagrangian.gravity)) > 1e-3
    assert _relative_error(ours, reference) < 1e-8


def test_forward_results_are_the_plain_solve():
    kwargs = dict(args=1.0, max_steps=500)
    terms = dvi.separable_terms(KEPLER)
    plain = dfx.diffeqsolve(
        terms, dvi.StormerVerlet(), 0.0, 400 * H, H, KEPLER_Y0, **kwargs
    )
    ours = dfx.diffeqsolve(
        terms,
        dvi.StormerVerlet(),
        0.0,
        400 * H,
        H,
        KEPLER_Y0,
        adjoint=dvi.ReversibleAdjoint(),
        **kwargs,
    )
    for a, b in zip(jax.tree.leaves(plain.ys), jax.tree.leaves(ours.ys)):
        assert jnp.array_equal(a, b)


def _solve(solver, term=None, **kwargs):
    term = dvi.LagrangianTerm(KEPLER) if term is None else term
    return dfx.diffeqsolve(
        term,
        solver,
        0.0,
        1.0,
        kwargs.pop("dt0", 0.1),
        KEPLER_Y0,
        1.0,
        adjoint=dvi.ReversibleAdjoint(),
        **kwargs,
    )


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: _solve(dvi.LinearizedVI()), "needs a symmetric solver"),
        (lambda: _solve(dfx.Tsit5()), "needs a symmetric solver"),
        (
            lambda: _solve(
                dvi.MidpointVI(),
                stepsize_controller=dfx.PIDController(rtol=1e-6, atol=1e-6),
            ),
            "PIDController",
        ),
        (
            lambda: _solve(dvi.MidpointVI(), saveat=dfx.SaveAt(steps=True)),
            "SaveAt",
        ),
        (
            lambda: _solve(
                dvi.MidpointVI(),
                event=dfx.Event(lambda t, y, args, **kw: y[0][0]),
            ),
            "events",
        ),
        (
            lambda: _solve(
                dvi.MidpointVI(),
                term=dvi.LagrangianTerm(KEPLER, force=lambda t, q, v, args: -0.1 * v),
            ),
            "not time-reversible",
        ),
    ],
    ids=["linearized", "runge-kutta", "pid", "steps", "event", "friction"],
)
def test_what_it_cannot_do_is_refused_when_traced(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_an_asymmetric_tableau_is_refused(symplectic_euler_tableau):
    """A VPRK tableau that is not symmetric (symplectic Euler's) has no inverse
    step with -h."""
    assert not symplectic_euler_tableau.symmetric
    with pytest.raises(ValueError, match="needs a symmetric solver"):
        _solve(dvi.VPRK(symplectic_euler_tableau))


def test_gradients_on_a_lie_group():
    """The free rigid body on SO(3) under the Lie midpoint rule: the gradient with
    respect to its inertia (a leaf of the term) and the initial body momentum, over
    200 steps, against central differences of the forward solve along random
    directions (one compiled forward solve, not a second compiled gradient; they
    agree to about 3e-11 of |gradient| |direction|)."""
    scene = dvi.scenes.free_rigid_body()

    def loss(inputs, adjoint):
        term, p0 = inputs
        sol = dfx.diffeqsolve(
            term,
            dvi.MidpointVI(),
            0.0,
            2.0,
            0.01,
            (scene.y0[0], p0),
            adjoint=adjoint,
            max_steps=200,
        )
        attitude, momentum = sol.ys
        weights = jnp.arange(9.0).reshape(3, 3)
        return jnp.sum(attitude[-1] * weights) + jnp.sum(jnp.sin(momentum[-1]))

    inputs = (dvi.LagrangianTerm(scene.lagrangian), scene.y0[1])
    ours = eqx.filter_jit(eqx.filter_grad(loss))(inputs, dvi.ReversibleAdjoint())
    # The gradient reaches the inertia and the momentum.
    inertia, p0 = ours[0].lagrangian.inertia, ours[1]
    assert jnp.any(inertia != 0) and jnp.any(p0 != 0)
    arrays, static = eqx.partition(inputs, eqx.is_inexact_array)
    forward = eqx.filter_jit(
        lambda x: loss(eqx.combine(x, static), dfx.RecursiveCheckpointAdjoint())
    )
    flat, unflatten = jax.flatten_util.ravel_pytree(arrays)
    gradient = jax.flatten_util.ravel_pytree(eqx.filter(ours, eqx.is_inexact_array))[0]
    eps = 1e-6
    for key in jax.random.split(jax.random.key(0), 2):
        d = jax.random.normal(key, flat.shape)
        change = forward(unflatten(flat + eps * d)) - forward(unflatten(flat - eps * d))
        exact = gradient @ d
        assert abs(change / (2 * eps) - exact) < 1e-9 * jnp.linalg.norm(gradient) * (
            jnp.linalg.norm(d)
        ), (change / (2 * eps), exact)


def _oscillator_sum(t0, t1, dt0, ts, k, adjoint, closure=False):
    args = None if closure else k
    fn = (
        (lambda t, q, v, args: 0.5 * v**2 - 0.5 * k * q**2)
        if closure
        else (lambda t, q, v, args: 0.5 * v**2 - 0.5 * args * q**2)
    )
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(dvi.Lagrangian(fn)),
        dvi.MidpointVI(),
        t0,
        t1,
        dt0,
        (jnp.array(1.0), jnp.array(0.0)),
        args=args,
        saveat=dfx.SaveAt(ts=ts),
        adjoint=adjoint,
        max_steps=64,
    )
    return jnp.sum(sol.ys[0])


@pytest.mark.parametrize(
    "index,name", [(0, "t0"), (1, "t1"), (2, "dt0"), (3, r"SaveAt\(ts=...\)")]
)
def test_a_derivative_it_does_not_take_is_refused_by_name(index, name):
    """A derivative with respect to the time grid is refused when traced, naming the
    argument and the adjoint that takes it (not equinox's 'Unexpected tangent')."""
    inputs = (0.0, 1.0, 0.1, jnp.array([0.5, 1.0]), 2.0)
    with pytest.raises(Exception, match=f"not {name}") as caught:
        jax.grad(_oscillator_sum, argnums=index)(*inputs, dvi.ReversibleAdjoint())
    assert "RecursiveCheckpointAdjoint" in str(caught.value)


def test_a_lagrangian_closing_over_the_parameter_is_differentiated():
    """A Lagrangian written as a lambda that captures the differentiated array (or a
    pair of ODETerms that do): the same gradient as checkpointing."""
    inputs = (0.0, 1.0, 0.1, jnp.array([0.5, 1.0]), 2.0)
    grad = jax.grad(_oscillator_sum, argnums=4)
    checkpointed = grad(*inputs, dfx.RecursiveCheckpointAdjoint(), closure=True)
    reversible = grad(*inputs, dvi.ReversibleAdjoint(), closure=True)
    assert abs(reversible - checkpointed) < 1e-12 * abs(checkpointed)

    def pair(k, adjoint):
        f = dfx.ODETerm(lambda t, p, args: p)
        g = dfx.ODETerm(lambda t, q, args: -k * q)
        y0 = (jnp.array(1.0), jnp.array(0.0))
        solver = dvi.StormerVerlet()
        sol = dfx.diffeqsolve((f, g), solver, 0.0, 1.0, 0.1, y0, adjoint=adjoint)
        return jnp.sum(sol.ys[0])

    checkpointed = jax.grad(pair)(2.0, dfx.RecursiveCheckpointAdjoint())
    reversible = jax.grad(pair)(2.0, dvi.ReversibleAdjoint())
    assert abs(reversible - checkpointed) < 1e-12 * abs(checkpointed)


def test_a_step_with_a_fallback_root_finder_is_differentiated_once():
    """MidpointVI's default policy (the fixed-point iteration, Newton's method where
    it does not contract) differentiates the root it finds once, at the root: a
    gradient's program holds one implicit linear solve, not one per root finder
    (the other would be traced and compiled for a branch a gradient never needs:
    Kepler's gradient program is 8% smaller, CHANGELOG)."""
    gradient = jax.grad(
        lambda y0: jnp.sum(
            dfx.diffeqsolve(
                dvi.LagrangianTerm(KEPLER), dvi.MidpointVI(), 0.0, 1.0, H, y0, 1.0
            ).ys[0]
        )
    )
    assert str(jax.make_jaxpr(gradient)(KEPLER_Y0)).count("custom_linear_solve") == 1


def _kepler_loss(adjoint, solver=None):
    solver = dvi.MidpointVI() if solver is None else solver
    return lambda y0: jnp.sum(
        dfx.diffeqsolve(
            dvi.LagrangianTerm(KEPLER), solver, 0.0, 1.0, H, y0, 1.0, adjoint=adjoint
        ).ys[0]
    )


def test_the_backward_pass_solves_each_step_once():
    """The forward step that each backward step differentiates takes the root of
    the inverse step that has just undone it (`root_of_inverse`): the program holds
    the root solves of the forward solve and of the inverse steps (each the
    fixed-point iteration and its Newton fallback), not a third pair for the
    repeated forward steps, which `checkpoint_every` keeps (its steps from an anchor
    start from the forward solve's state, not the inverse step's)."""

    def root_solves(adjoint):
        program = jax.make_jaxpr(jax.grad(_kepler_loss(adjoint)))(KEPLER_Y0)
        return str(program).count("name=root_find")

    assert root_solves(dvi.ReversibleAdjoint()) == 4
    assert root_solves(dvi.ReversibleAdjoint(checkpoint_every=4)) == 6

    # A constrained step too: its multipliers are the inverse step's projection's.
    rod = dvi.scenes.cartesian_pendulum()

    def rod_solves(adjoint):
        def loss(y0):
            sol = dfx.diffeqsolve(
                rod.term(), dvi.MidpointVI(), 0.0, 1.0, 0.05, y0, adjoint=adjoint
            )
            return jnp.sum(sol.ys[0])

        return str(jax.make_jaxpr(jax.grad(loss))(rod.y0)).count("name=root_find")

    assert rod_solves(dvi.ReversibleAdjoint()) == 4
    assert rod_solves(dvi.ReversibleAdjoint(checkpoint_every=4)) == 6


def test_a_large_constrained_step_is_differentiated_without_lapack():
    """The rigid double pendulum's constrained steps have 18 unknowns, beyond the
    unrolled elimination's 16: Newton's method factorises them densely by the
    elimination rolled into a loop (`constrained_solver`), and so does each step's
    implicit derivative: no LAPACK LU (lineax's, with its host-callback checks) in
    either gradient's program; and the reversible adjoint's repeated forward steps
    take the inverse steps' roots (two root solves for the forward steps, two for
    the inverse steps: the fixed-point iteration and its Newton fallback; eight
    before). Before, both gradients' backward loops were broken into kernels
    (`benchmarks/gradient_loops.py`)."""
    scene = dvi.scenes.rigid_double_pendulum()
    term, solver, h = scene.term(), dvi.TrapezoidalVI(), scene.period / 100
    total = lambda y: sum(jnp.sum(x) for x in jax.tree.leaves(y))

    def one_step(y0):
        # What RecursiveCheckpointAdjoint differentiates, step by step (tracing
        # it in a whole solve's gradient took 10 s).
        state = solver.init(term, 0.0, h, y0, None)
        return total(solver.step(term, 0.0, h, y0, None, state, False)[0])

    def reversible(y0):
        adjoint = dvi.ReversibleAdjoint()
        sol = dfx.diffeqsolve(term, solver, 0.0, 4 * h, h, y0, adjoint=adjoint)
        return total(sol.ys)

    assert " = lu " not in str(jax.make_jaxpr(jax.grad(one_step))(scene.y0))
    program = str(jax.make_jaxpr(jax.grad(reversible))(scene.y0))
    assert " = lu " not in program
    assert program.count("name=root_find") == 4


def _perturbed_leaves(fn, y0) -> list[bool]:
    """Which floating-point leaves of `fn(y0)` carry a derivative (not JAX's
    symbolic zero) when `fn` is linearised at `y0`."""
    seen = []

    @eqx.filter_custom_jvp
    def probe(x):
        return x

    @probe.def_jvp
    def _(primals, tangents):
        given = jax.tree.map(lambda _, t: t is not None, primals[0], tangents[0])
        seen.extend(jax.tree.leaves(given))
        return primals[0], tangents[0]

    linearised = lambda y: jax.linearize(lambda y: probe(fn(y)), y)[0]
    jax.eval_shape(linearised, y0)  # Traced, not run.
    return seen


def _read_leaves(fn, x) -> list[bool]:
    """Which floating-point leaves of `x` (arrays or their shapes) the output of
    `fn(x)` depends on differentiably (their cotangent is not JAX's symbolic
    zero)."""
    seen = []

    @jax.custom_vjp
    def probe(x):
        return x

    def forward(x):
        return jax.tree.map(lambda p: p.value, x), None

    def backward(_, cotangents):
        zero = jax.custom_derivatives.SymbolicZero
        seen.extend(not isinstance(c, zero) for c in jax.tree.leaves(cotangents))
        return (cotangents,)

    probe.defvjp(forward, backward, symbolic_zeros=True)

    def pull_back(x):
        dynamic, static = eqx.partition(x, eqx.is_inexact_array)
        out, vjp = jax.vjp(lambda d: fn(eqx.combine(probe(d), static)), dynamic)
        return vjp(jax.tree.map(jnp.ones_like, out))

    jax.eval_shape(pull_back, x)  # Traced, not run.
    return seen


@pytest.mark.parametrize(
    "scene, solver",
    [
        ("kepler", dvi.MidpointVI()),
        ("kepler", dvi.Composition(dvi.StormerVerlet(), "kahan_li8")),
        ("cartesian_pendulum", dvi.MidpointVI()),
        ("cartesian_pendulum", dvi.TrapezoidalVI()),
        ("heavy_top", dvi.LGVI()),
    ],
    ids=["MidpointVI", "KahanLi8", "constrained", "RATTLE", "LGVI"],
)
def test_a_gradient_carries_what_a_step_reads_from_the_start(scene, solver):
    """The floating-point leaves of a solver's state that carry a derivative are
    the same at the start as after a step, and are those whose derivative the next
    step's `y` reads: the compensation and a step's end force, not the guesses of
    the next root (held without one: a root's derivative is the implicit
    function theorem's). `RecursiveCheckpointAdjoint`'s loop linearises the step
    until the set of differentiated carries stops growing, once more for each leaf
    that a step perturbs but the start does not, and its backward loop linearises
    it again for the carries whose derivative it reads where the two sets differ
    (tracing the rigid double pendulum's gradient made 27% fewer Python calls,
    CHANGELOG)."""
    scene = dvi.scenes.SCENES[scene]()
    term = dvi.terms_for(solver, scene.term())
    h = scene.period / 100
    step = lambda y, state: solver.step(term, 0.0, h, y, scene.args, state, False)
    init = lambda y0: solver.init(term, 0.0, h, y0, scene.args)
    floats = lambda tree: eqx.filter(tree, eqx.is_inexact_array)
    init_shape = jax.eval_shape(init, scene.y0)

    start = _perturbed_leaves(lambda y0: floats(init(y0)), scene.y0)
    after_a_step = _perturbed_leaves(lambda y0: floats(step(y0, init(y0))[3]), scene.y0)
    read = _read_leaves(lambda state: step(scene.y0, state)[0], init_shape)
    assert any(start)
    assert start == after_a_step
    assert [p and r for p, r in zip(start, read)] == start


def test_a_gradient_traces_each_kind_of_step_once():
    """Tracing a reversible gradient runs the solver's step in Python once for each
    kind of step it takes: the forward solve's, the inverse step's (from a jump)
    and the repeated forward step's (with the inverse step's root). JAX traces the
    forward loop twice (a custom VJP's function, then its forward rule); the second
    trace must reuse the first, or it traces the forward step again in a context it
    tells apart (4 calls; the first calls are in `benchmarks/first_call.py`)."""
    calls = []

    class Counted(dvi.MidpointVI):
        def _fractional_step(self, *args, **kwargs):
            calls.append(None)
            return super()._fractional_step(*args, **kwargs)

    jax.jit(jax.grad(_kepler_loss(dvi.ReversibleAdjoint(), Counted()))).trace(KEPLER_Y0)
    assert len(calls) == 3


def test_backward_steps_leave_out_the_dense_output_nothing_interpolates():
    """The backward pass's steps trace the vector field at their ends (their dense
    output) only where `SaveAt(ts=...)` interpolates it: JAX differentiated it
    before XLA removed it (the first calls are in `benchmarks/first_call.py`). The
    forward solve keeps it: diffrax decides what it interpolates."""

    def traced(saveat):
        calls = []

        # A class of its own for each trace, so that no step's trace is reused.
        class Counted(dvi.MidpointVI):
            def _fractional_step(self, *args):
                calls.append(args[-1])  # `dense`
                return super()._fractional_step(*args)

        def loss(y0):
            sol = dfx.diffeqsolve(
                dvi.LagrangianTerm(KEPLER),
                Counted(),
                0.0,
                1.0,
                H,
                y0,
                1.0,
                saveat=saveat,
                adjoint=dvi.ReversibleAdjoint(),
            )
            return jnp.sum(sol.ys[0])

        jax.jit(jax.grad(loss)).trace(KEPLER_Y0)
        return sorted(calls)

    # The forward solve's, the inverse step's and the repeated forward step's.
    assert traced(dfx.SaveAt(t1=True)) == [False, False, True]
    assert traced(dfx.SaveAt(ts=jnp.linspace(0.0, 1.0, 5))) == [False, True, True]


def test_the_backward_pass_checks_the_start_once():
    """The inverse steps start from the forward solve's end, which its steps reached
    from a checked start: `resume` does not check it again. The four-bar's
    reversible gradient holds the start's checks (the extreme eigenvalues of its
    mass matrix, the rank of its constraint Jacobian) once, as its forward solve
    does, not a second time at the end; and `resume` gives the state `init` does
    wherever `init`'s checks pass (implicit steps with and without constraints, a
    composition of them), to round-off of its largest entry."""
    scene = dvi.scenes.four_bar()
    term = scene.term()

    def solve(y0, adjoint):
        return dfx.diffeqsolve(
            term,
            dvi.MidpointVI(),
            0.0,
            1.0,
            0.1,
            y0,
            saveat=dfx.SaveAt(t1=True),
            adjoint=adjoint,
        ).ys

    def lapack(program):
        text = str(program)
        return text.count("eigh["), text.count("svd[")

    forward = jax.make_jaxpr(lambda y0: solve(y0, dfx.RecursiveCheckpointAdjoint()))
    gradient = jax.make_jaxpr(
        jax.grad(lambda y0: jnp.sum(solve(y0, dvi.ReversibleAdjoint())[0]))
    )
    assert lapack(forward(scene.y0)) == lapack(gradient(scene.y0)) == (1, 1)

    rod = dvi.scenes.cartesian_pendulum()
    cases = [
        (term, scene.y0, None, dvi.MidpointVI()),
        (term, scene.y0, None, dvi.Composition(dvi.MidpointVI(), "yoshida4")),
        (dvi.LagrangianTerm(KEPLER), KEPLER_Y0, 1.0, dvi.TrapezoidalVI()),
        (rod.term(), rod.y0, None, dvi.MidpointVI()),
    ]
    for term_, y0, args, solver in cases:

        @jax.jit
        def both(y0):
            state = solver.init(term_, 0.0, 0.1, y0, args)
            return state, solver.resume(term_, 0.0, 0.1, y0, args, state)

        state, resumed = both(y0)
        assert jax.tree.structure(resumed) == jax.tree.structure(state)
        for a, b in zip(jax.tree.leaves(resumed), jax.tree.leaves(state)):
            if not jnp.issubdtype(b.dtype, jnp.floating):
                assert jnp.array_equal(a, b)
                continue
            # The same velocity, solved in another way: `init` by the
            # eigendecomposition that checks d2L/dv2 (the four-bar's), `resume` by
            # an elimination. Both are backward stable and the mass matrices are
            # well conditioned (the four-bar's: 2.2 in units of its diagonal), so
            # they agree to a few ulps of the largest entry.
            size = jnp.max(jnp.abs(jnp.where(jnp.isfinite(b), b, 0)), initial=0)
            eps = jnp.finfo(b.dtype).eps
            np.testing.assert_allclose(a, b, rtol=0, atol=8 * eps * size)


def _final_gradient(scene, solver, adjoint, forced):
    """d/dy0 of a scalar of the scene's final state after 60 steps, with a force of
    time and position where `forced`."""
    force = (lambda t, q, v, args: 0.3 * jnp.cos(t) + 0.1 * q**2) if forced else None
    term = dvi.LagrangianTerm(
        scene.lagrangian, force=force, constraint=scene.constraint
    )

    def loss(y0):
        sol = dfx.diffeqsolve(
            term, solver, 0.0, 3.0, 0.05, y0, args=scene.args, adjoint=adjoint
        )
        return sum(jnp.sum(jnp.sin(x[-1])) for x in sol.ys)

    return jax.jit(jax.grad(loss))(scene.y0)


@pytest.mark.parametrize(
    "scene, solver, forced",
    [
        ("double_pendulum", dvi.GaussVPRK(2), False),
        ("double_pendulum", dvi.TrapezoidalVI(), True),
        ("heavy_top", dvi.LGVI(), False),
        ("four_bar", dvi.MidpointVI(), False),
        ("cartesian_pendulum", dvi.MidpointVI(), True),
        ("cartesian_pendulum", dvi.TrapezoidalVI(), False),
        ("rigid_double_pendulum", dvi.TrapezoidalVI(), False),
    ],
    ids=[
        "GaussVPRK(2)",
        "TrapezoidalVI-forced",
        "LGVI",
        "four-bar",
        "rod-forced",
        "RATTLE",
        "joined-bodies",
    ],
)
def test_the_inverse_steps_root_gives_the_checkpointed_gradient(scene, solver, forced):
    """The root a forward step takes from its inverse step: the same velocities,
    the stages of a two-stage Gauss method in reverse order (taken in their own
    order, the gradient is wrong in the third digit); for the trapezoidal step of a
    general Lagrangian, with a force of time and position, its one velocity; for
    LGVI, whose inverse step's Cayley parameter is -f with -h, the same velocity
    2f/h. A constrained step's multipliers are those of the inverse step's
    momentum projection (the four-bar's loop closure; the Cartesian pendulum's
    rod, forced, and under RATTLE, whose unknowns are the multipliers alone; the
    rigid double pendulum's 18 unknowns, beyond the unrolled elimination's 16). The
    gradients equal checkpointing's to 1e-12 relative."""
    scene = dvi.scenes.SCENES[scene]()
    ours = _final_gradient(scene, solver, dvi.ReversibleAdjoint(), forced)
    reference = _final_gradient(scene, solver, dfx.RecursiveCheckpointAdjoint(), forced)
    assert _relative_error(ours, reference) < 1e-12


@pytest.mark.parametrize("scene", ["fpu", "double_pendulum"])
def test_linearized_gradients_equal_finite_differences(scene):
    """`LinearizedVI` solves one linear system a step: by conjugate gradients where its
    matrix is symmetric and larger than 4 x 4 (FPU, 6 unknowns), by elimination
    where it is not (the double pendulum). Its derivatives are solves of the same
    system, in reverse mode (`RecursiveCheckpointAdjoint`) and forward mode
    (`ForwardMode`): both equal central differences of the solve to 1e-6 along a
    direction of `y0`, and neither loop holds a kernel (lineax's derivative of its
    own solve checks each tangent and transposed solve by a host callback, and the
    elimination's row permutation transposes into a scatter: 12-14x slower gradient
    steps)."""
    from diffrax_vi.diagnostics import loop_breakers

    scene = dvi.scenes.SCENES[scene]()
    direction = jax.tree.map(
        lambda x: jnp.cos(jnp.arange(1.0, x.size + 1.0)).reshape(x.shape), scene.y0
    )

    def loss(y0, adjoint):
        sol = dfx.diffeqsolve(
            scene.term(),
            dvi.LinearizedVI(),
            0.0,
            scene.period * 0.6,
            scene.period / 100,
            y0,
            scene.args,
            adjoint=adjoint,
            max_steps=64,
        )
        return sum(jnp.sum(jnp.sin(x[-1])) for x in jax.tree.leaves(sol.ys))

    def along(y0, eps):
        return jax.tree.map(lambda x, d: x + eps * d, y0, direction)

    def reverse(y0):
        grad = jax.grad(loss)(y0, dfx.RecursiveCheckpointAdjoint())
        return sum(
            jnp.vdot(g, d) for g, d in zip(*map(jax.tree.leaves, (grad, direction)))
        )

    def forward(y0):
        return jax.jvp(
            lambda e: loss(along(y0, e), dfx.ForwardMode()),
            (jnp.asarray(0.0),),
            (jnp.asarray(1.0),),
        )[1]

    eps = 1e-6
    plain = lambda e: loss(along(scene.y0, e), dfx.RecursiveCheckpointAdjoint())
    reference = (plain(eps) - plain(-eps)) / (2 * eps)
    for derivative in (reverse, forward):
        compiled = jax.jit(derivative).lower(scene.y0).compile()
        assert loop_breakers(compiled.as_text()) == [], derivative.__name__
        value = compiled(scene.y0)
        assert jnp.allclose(value, reference, rtol=1e-6), (derivative, value, reference)
