"""Chapter 5 (and Figures 1.1/1.2) of Hirani (2000), reproduced: A. N. Hirani,
*Linearization methods for variational integrators and Euler-Lagrange equations*
(Caltech, 2000)."""

import pathlib

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure

from .._discrete import discrete_lagrangian, MidpointRule
from .._lagrangian import SeparableLagrangian
from .._solver import LinearizedVI, MidpointVI
from .._term import LagrangianTerm


RULE = MidpointRule()
OSCILLATOR = SeparableLagrangian(lambda t, q, args: 0.5 * q**2)  # m = K = 1
THESIS_TABLES = {
    1: {
        "DEL (5.26)": [3.9924, 3.9788, 3.9574, 3.9673],
        "linearized (5.27)": [3.9633, 3.9671, 3.9369, 3.9946],
    },
    5: {
        "DEL (5.26)": [4.0025, 3.9991, 3.9982, 3.9935],
        "linearized (5.27)": [4.0053, 4.0026, 4.0060, 3.9999],
    },
}
HS = [0.001 * 2**k for k in range(5)]


def d2_ld(lagrangian, t0, t1, q0, q1):
    return jax.grad(
        lambda b: discrete_lagrangian(RULE, lagrangian, t0, t1, q0, b, None)
    )(q1)


# Room for the longest run (Figure 5.3's 10^4 steps), so that every step size shares
# one compilation per solver.
MAX_STEPS = 10_000


@eqx.filter_jit
def _solve(solver, lagrangian, t0, t1, h, y0, solver_state=None, *, max_steps):
    """Positions at every step from t0 to t1 (padded with inf to `max_steps`)."""
    sol = dfx.diffeqsolve(
        LagrangianTerm(lagrangian),
        solver,
        t0,
        t1,
        h,
        y0,
        saveat=dfx.SaveAt(t0=True, steps=True),
        solver_state=solver_state,
        max_steps=max_steps,
    )
    return sol.ys[0]


def _start(solver, h, thesis_start):
    """Where the oscillator q(0) = 1, qdot(0) = 0 starts for `solver`: the initial
    time, state and solver state, and the positions before it."""
    exact = lambda t: jnp.cos(t)
    h = jnp.asarray(h)
    if not thesis_start:
        return jnp.asarray(0.0), (jnp.array(1.0), jnp.array(0.0)), None, []
    if isinstance(solver, MidpointVI):
        # (5.26) from q0, q1 of the analytic solution.
        y0 = (exact(h), d2_ld(OSCILLATOR, 0.0, h, exact(0.0), exact(h)))
        term = LagrangianTerm(OSCILLATOR)
        return h, y0, solver.init(term, h, 2 * h, y0, None), [exact(0.0)]
    # (5.27) from q0, q1, q2 of the analytic solution.
    y0 = (exact(2 * h), d2_ld(OSCILLATOR, h, 2 * h, exact(h), exact(2 * h)))
    state = solver.init_from_history((exact(h), exact(0.0)), (h, h), y0)
    return 2 * h, y0, state, [exact(0.0), exact(h)]


def oscillator_positions(solver, h, n, thesis_start):
    """Positions q_k, k = 0..n, of the oscillator q(0) = 1, qdot(0) = 0."""
    t0, y0, state, head = _start(solver, h, thesis_start)
    steps = n - len(head)
    h = jnp.asarray(h)
    qs = _solve(
        solver, OSCILLATOR, t0, t0 + steps * h, h, y0, state, max_steps=MAX_STEPS
    )
    return np.concatenate([np.asarray(head), np.asarray(qs)[: steps + 1]])


def global_error(solver, h, T, thesis_start):
    n = round(T / h)  # the thesis's Phi^(T/h); 1/0.016 = 62.5 rounds to 62
    qs = oscillator_positions(solver, h, n, thesis_start)
    return abs(qs[n] - np.cos(n * h))


METHODS = {"DEL (5.26)": MidpointVI(), "linearized (5.27)": LinearizedVI()}


def tables_5_1_and_5_2(out):
    lines, errors = [], {}
    for T in (1, 5):
        lines += [
            f"\n### Table 5.{1 if T == 1 else 2}: ratio of global errors at time {T} "
            "on doubling the step\n",
            "| method | start | "
            + " | ".join(f"e({2 * h:g})/e({h:g})" for h in HS[:-1])
            + " |",
            "|---|---|" + "---|" * 4,
        ]
        for name, solver in METHODS.items():
            lines.append(
                f"| {name} | thesis | "
                + " | ".join(f"{r:.4f}" for r in THESIS_TABLES[T][name])
                + " |"
            )
            for start in ("analytic", "library"):
                e = [global_error(solver, h, T, start == "analytic") for h in HS]
                errors[(T, name, start)] = e
                ratios = [e[i + 1] / e[i] for i in range(4)]
                lines.append(
                    f"| {name} | ours, {start} start | "
                    + " | ".join(f"{r:.4f}" for r in ratios)
                    + " |"
                )
    for T, fig in ((1, "5_1"), (5, "5_2")):
        fig_ = Figure(figsize=(6, 4), layout="constrained")
        ax = fig_.subplots()
        for name in METHODS:
            ax.plot(HS, errors[(T, name, "analytic")], "o-", label=name)
        ax.set_xlabel("step size h")
        ax.set_ylabel(f"|computed - analytic| at time {T}")
        ax.set_title(f"Figure {fig.replace('_', '.')}: global error at time {T}")
        ax.legend()
        fig_.savefig(out / f"figure_{fig}.png", dpi=110)
    return lines


def figure_5_3(out):
    h, n = 0.001, 10_000
    ts = h * np.arange(n + 1)
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    lines = ["\n### Figure 5.3: pointwise error, h = 0.001, on [0, 10]\n"]
    for name, solver in METHODS.items():
        err = oscillator_positions(solver, h, n, True) - np.cos(ts)
        ax.plot(ts, err, label=name)
        lines.append(
            f"- {name}: |error| at t = 1: {abs(err[1000]):.2e}; at t = 5: "
            f"{abs(err[5000]):.2e}; max over [0, 10]: {np.abs(err).max():.2e}"
        )
    ax.set_xlabel("time")
    ax.set_ylabel("computed - analytic")
    ax.set_title("Figure 5.3: pointwise error for h = 0.001")
    ax.legend()
    fig.savefig(out / "figure_5_3.png", dpi=110)
    return lines


def falling_particle():
    g = 9.81
    particle = SeparableLagrangian(lambda t, q, args: g * q)
    y0 = (jnp.array(2.0), jnp.array(3.0))
    h, n = 0.05, 200
    ts = h * np.arange(1, n + 1)
    exact = 2.0 + 3.0 * ts - 0.5 * g * ts**2
    lines = ["\n### Falling particle: both discrete equations are exact\n"]
    for name, solver in METHODS.items():
        sol = dfx.diffeqsolve(
            LagrangianTerm(particle),
            solver,
            0.0,
            h * n,
            h,
            y0,
            saveat=dfx.SaveAt(steps=True),
            max_steps=n,
        )
        err = np.abs(np.asarray(sol.ys[0]) - exact).max()
        lines.append(f"- {name}: max |q_k - q(t_k)| over {n} steps = {err:.1e}")
    return lines


def duffing_orders():
    duffing = SeparableLagrangian(lambda t, q, args: -0.5 * q**2 + 0.25 * q**4)
    y0 = (jnp.array(0.5), jnp.array(0.0))
    lines = [
        "\n### Duffing (L = v²/2 + q²/2 − q⁴/4, q(0) = 0.5): fitted global orders\n",
        "| method | thesis's local error (5.5) | order at T = 1 | order at T = 5 |",
        "|---|---|---|---|",
    ]
    fine = dfx.diffeqsolve(
        LagrangianTerm(duffing),
        dfx.Dopri8(),
        0.0,
        5.0,
        1e-3,
        y0,
        saveat=dfx.SaveAt(ts=jnp.array([1.0, 5.0])),
        stepsize_controller=dfx.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )
    solvers = {
        "DEL (MidpointVI)": (MidpointVI(), "O(h²)"),
        "linearized, forward u": (LinearizedVI(), "O(h)"),
        "linearized, centered u (5.6)": (LinearizedVI(velocity="centered"), "—"),
    }
    for name, (solver, local) in solvers.items():
        orders = []
        for i, T in enumerate((1.0, 5.0)):
            ns = [int(50 * T) * 2**k for k in range(5)]
            errs = [
                abs(
                    _solve(
                        solver,
                        duffing,
                        jnp.asarray(0.0),
                        jnp.asarray(T),
                        jnp.asarray(T / n),
                        y0,
                        max_steps=MAX_STEPS,
                    )[n]
                    - float(fine.ys[0][i])
                )
                for n in ns
            ]
            slope = np.polyfit(np.log([T / n for n in ns]), np.log(errs), 1)[0]
            orders.append(f"{slope:.2f}")
        lines.append(f"| {name} | {local} | {orders[0]} | {orders[1]} |")
    return lines


def smiley(n=400):
    """A face of initial conditions around (q, p) = (1.3, 0): outline, eyes, mouth."""
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    outline = np.stack([1.3 + 0.4 * np.cos(s), 0.4 * np.sin(s)], 1)
    eye = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    eyes = [
        np.stack([1.3 + dx + 0.05 * np.cos(eye), 0.12 + 0.05 * np.sin(eye)], 1)
        for dx in (-0.14, 0.14)
    ]
    m = np.linspace(-0.8, 0.8, 40)
    mouth = np.stack([1.3 + 0.22 * np.sin(m), -0.05 - 0.18 * np.cos(m)], 1)
    return outline, np.concatenate([*eyes, mouth])


def shoelace(points):
    x, y = points[:, 0], points[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def figures_1_1_and_1_2(out):
    pendulum = SeparableLagrangian(lambda t, q, args: -jnp.cos(q))
    outline, features = smiley()
    points = np.concatenate([outline, features])
    times = [0.0, 2.0, 4.0, 6.0]
    h = 0.1
    lines = [
        "\n### Figures 1.1/1.2: a cloud of initial conditions (pendulum, h = 0.1)\n",
        "| method | " + " | ".join(f"area at t = {t:g}" for t in times) + " |",
        "|---|" + "---|" * len(times),
    ]
    fig = Figure(figsize=(11, 4.5), layout="constrained")
    axes = fig.subplots(1, 2)
    for ax, (name, solver) in zip(
        axes, {"forward Euler": dfx.Euler(), "MidpointVI": MidpointVI()}.items()
    ):
        flow = jax.vmap(
            lambda y: (
                dfx.diffeqsolve(
                    LagrangianTerm(pendulum),
                    solver,
                    0.0,
                    times[-1],
                    h,
                    y,
                    saveat=dfx.SaveAt(ts=jnp.array(times)),
                    max_steps=100,
                ).ys
            )
        )
        qs, ps = flow((jnp.asarray(points[:, 0]), jnp.asarray(points[:, 1])))
        qs, ps = np.asarray(qs), np.asarray(ps)
        areas = []
        for k, t in enumerate(times):
            cloud = np.stack([qs[:, k], ps[:, k]], 1)
            areas.append(shoelace(cloud[: len(outline)]))
            ax.plot(cloud[: len(outline), 0], cloud[: len(outline), 1], "-", lw=1)
            ax.plot(cloud[len(outline) :, 0], cloud[len(outline) :, 1], ".", ms=1.5)
            ax.annotate(f"t={t:g}", cloud[0], fontsize=8)
        lines.append(f"| {name} | " + " | ".join(f"{a:.5f}" for a in areas) + " |")
        ax.set_title(f"{name}: area {areas[0]:.4f} → {areas[-1]:.4f}")
        ax.set_xlabel("q")
        ax.set_ylabel("p")
        ax.set_aspect("equal")
    fig.savefig(out / "figure_1_1_1_2.png", dpi=110)
    return lines


def chapter5(out: str | pathlib.Path) -> str:
    """Reproduce Chapter 5 of Hirani (2000): Tables 5.1/5.2, Figures 5.1–5.3, the
    falling particle of §5.1 and the Duffing orders of §5.3 and §5.5, and Figures
    1.1/1.2, beside the thesis's own numbers. Writes `chapter5.md` and PNG figures
    into the folder `out` and returns the Markdown. Needs float64
    (`jax_enable_x64`) and matplotlib; about 15 s on a 2-core CPU."""
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "The thesis's tables resolve errors near 1e-12 and need float64: call "
            '`jax.config.update("jax_enable_x64", True)` first.'
        )
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# Chapter 5 of Hirani (2000), reproduced", ""]
    lines += falling_particle()
    lines += tables_5_1_and_5_2(out)
    lines += figure_5_3(out)
    lines += duffing_orders()
    lines += figures_1_1_and_1_2(out)
    text = "\n".join(lines) + "\n"
    (out / "chapter5.md").write_text(text)
    return text
