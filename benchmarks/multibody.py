"""Joined rigid bodies against MuJoCo: the energy error over a long run against the
wall time per simulated second, and the cost of a chain's step as it grows.

The mechanism is `diffrax_vi.scenes.rigid_double_pendulum()`: two boxes of unequal
inertias joined by ball joints, in gravity, no damping, no contact. MuJoCo (the
`mujoco` package, its C engine; the `bench` extra) gets the same model as MJCF, in
its own minimal coordinates (two ball joints: quaternions), from the same state
(checked: the same centres and the same energy to 1e-12), and steps it with
`mujoco.rollout` (its loop in C) at h = 1e-3 with its `Euler`, `implicitfast` and
`RK4` integrators, `--steps` steps (default 10^6: 1000 time units, about 190 swing
periods). This package's `TrapezoidalVI` (RATTLE on the group), `MidpointVI` and
`Composition(MidpointVI(), "yoshida4")` run the scene's maximal coordinates
(12 coordinates, 6 multipliers) over the same span at larger steps, in
`diffrax.diffeqsolve` saving `--samples` states. For each run: the wall time (after
compilation, best of `--repeats`; ours also its trace and compile time), the wall
time per simulated time unit, and the largest energy error over the samples and in
the first and last tenth (MuJoCo's at the same times, from its recorded states).

The per-step cost of `TrapezoidalVI` against a bare `jax.lax.scan` of the same update
written here by hand at its floor (RATTLE on (R^3 x SO(3))^2: the centres' velocities
explicit in the multipliers, Newton on the body velocities and multipliers with an
unrolled elimination, the momenta projected; no LAPACK call or custom fusion in either
loop, checked), timed in turns (target <= 1.5x).

Then `TrapezoidalVI` on `scenes.rigid_chain(links=n)` for each `--links`: its trace
and compile time and its time per step, to show how the constrained step's cost
grows with the chain (dense Jacobians: not linear).

Run: `taskset -c 1 python benchmarks/multibody.py [--steps 1000000] [--links 2,4,8,16]
[--chain-only]`.
"""

import argparse
import importlib.metadata
import time

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402

# SO(3)'s exponential, the package's, with its derivative in closed form: the bare
# update's Newton matrix differentiates it, and Rodrigues' formula differentiated by
# autodiff made the bare step the slower one (17.7 us against 16.3 us).
from diffrax_vi._so3 import _exp as exp  # noqa: E402
from lie_groups import matmul, pull  # noqa: E402


MUJOCO_STEP = 1e-3


def mjcf(scene, half) -> str:
    """The scene's two boxes as MJCF: box 0 hung from the origin by a ball joint at
    its top, box 1 from box 0's bottom by a ball joint at its own top."""
    m = np.asarray(scene.lagrangian.mass).tolist()
    J = np.asarray(scene.lagrangian.inertia).tolist()
    g = float(scene.lagrangian.gravity)
    half = [float(h) for h in half]

    def inertial(i):
        return (
            f'<inertial pos="0 0 0" mass="{m[i]!r}" '
            f'diaginertia="{J[i][0]!r} {J[i][1]!r} {J[i][2]!r}"/>'
        )

    return f"""
<mujoco>
  <option timestep="{MUJOCO_STEP}" gravity="0 0 {-g!r}">
    <flag contact="disable" energy="enable"/>
  </option>
  <worldbody>
    <body pos="0 0 {-half[0]!r}">
      <joint type="ball" pos="0 0 {half[0]!r}"/>
      {inertial(0)}
      <body pos="0 0 {-half[0] - half[1]!r}">
        <joint type="ball" pos="0 0 {half[1]!r}"/>
        {inertial(1)}
      </body>
    </body>
  </worldbody>
</mujoco>"""


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions (w, x, y, z), shape (..., 3, 3)."""
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack(
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1
            ),
            np.stack(
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1
            ),
            np.stack(
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1
            ),
        ],
        -2,
    )


def mujoco_energy(scene, half, qpos, qvel) -> np.ndarray:
    """The scene's energy at MuJoCo states (ball joints: each quaternion relative to
    the parent, each angular velocity in the child's frame relative to the
    parent)."""
    m = np.asarray(scene.lagrangian.mass)
    J = np.asarray(scene.lagrangian.inertia)
    g = float(scene.lagrangian.gravity)
    top = [np.array([0.0, 0.0, h]) for h in half]
    R0 = quaternion_matrix(qpos[:, 0:4])
    relative = quaternion_matrix(qpos[:, 4:8])
    R1 = R0 @ relative
    w0 = qvel[:, 0:3]
    w1 = qvel[:, 3:6] + np.einsum("nji,nj->ni", relative, w0)
    rot = lambda R, v: np.einsum("nij,nj->ni", R, v)
    x0 = -rot(R0, np.broadcast_to(top[0], w0.shape))
    v0 = rot(R0, np.cross(top[0], w0))
    x1 = 2 * x0 - rot(R1, np.broadcast_to(top[1], w1.shape))
    v1 = 2 * v0 + rot(R1, np.cross(top[1], w1))
    kinetic = 0.5 * (
        m[0] * np.sum(v0**2, -1)
        + m[1] * np.sum(v1**2, -1)
        + np.sum(J[0] * w0**2, -1)
        + np.sum(J[1] * w1**2, -1)
    )
    return kinetic + g * (m[0] * x0[:, 2] + m[1] * x1[:, 2])


def mujoco_runs(scene, half, steps, samples, repeats):
    import mujoco
    from mujoco import rollout

    model = mujoco.MjModel.from_xml_string(mjcf(scene, half))
    data = mujoco.MjData(model)
    (x, R), (_, pi) = (
        (np.asarray(a) for a in scene.y0[0]),
        (np.asarray(a) for a in scene.y0[1]),
    )
    omega = pi / np.asarray(scene.lagrangian.inertia)
    relative = R[0].T @ R[1]
    for i, rotation in enumerate((R[0], relative)):
        mujoco.mju_mat2Quat(data.qpos[4 * i : 4 * i + 4], rotation.ravel())
    data.qvel[:3] = omega[0]
    data.qvel[3:6] = omega[1] - relative.T @ omega[0]
    mujoco.mj_forward(model, data)
    e0 = float(scene.energy(0.0, scene.y0, None))
    assert np.max(np.abs(data.xpos[1:] - x)) < 1e-12
    assert abs(sum(data.energy) - e0) < 1e-12
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state0 = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state0, spec)
    rows = []
    for name in ("EULER", "IMPLICITFAST", "RK4"):
        model.opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{name}")
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            states, _ = rollout.rollout(model, data, state0[None], nstep=steps)
            best = min(best, time.perf_counter() - start)
        states = states[0]
        # MuJoCo resets a state whose accelerations blow up to the model's default
        # and goes on ("the simulation is unstable"): its time restarts at 0.
        reset = np.flatnonzero(np.diff(states[:, 0]) < 0)
        label = f"MuJoCo {name.lower()}"
        if reset.size:
            label += f" (unstable at t = {states[reset[0], 0]:.0f})"
            states = states[: reset[0] + 1]
        states = states[steps // samples - 1 :: steps // samples]
        energy = mujoco_energy(scene, half, states[:, 1:9], states[:, 9:15])
        rows.append((label, MUJOCO_STEP, steps, best, None, energy - e0))
    return rows


def our_runs(scene, span, samples, repeats, cases):
    e0 = scene.energy(0.0, scene.y0, None)
    energy = jax.vmap(lambda y: scene.energy(0.0, y, None))
    ts = jnp.linspace(0.0, span, samples + 1)[1:]
    rows = []
    for label, solver, steps_list in cases:

        def solve(y0, dt):
            return dfx.diffeqsolve(
                scene.term(),
                solver,
                0.0,
                span,
                dt,
                y0,
                saveat=dfx.SaveAt(ts=ts),
                max_steps=None,
            )

        start = time.perf_counter()
        lowered = jax.jit(solve).lower(scene.y0, jnp.asarray(span / steps_list[0]))
        compiled = lowered.compile()
        build = time.perf_counter() - start
        for steps in steps_list:
            dt = jnp.asarray(span / steps)
            best = np.inf
            for _ in range(repeats):
                start = time.perf_counter()
                sol = jax.block_until_ready(compiled(scene.y0, dt))
                best = min(best, time.perf_counter() - start)
            assert sol.result == dfx.RESULTS.successful, label
            error = np.asarray(energy(sol.ys) - e0)
            rows.append((label, span / steps, steps, best, build, error))
    return rows


def _mv(a, x):
    return jnp.sum(a * x[..., None, :], axis=-1)


def _solve(A, b, pivot=True):
    """A dense solve by Gaussian elimination, unrolled (no LAPACK call in the
    loop): with partial pivoting, or without it for a symmetric positive definite
    `A`, for which elimination is stable as it is."""
    n = A.shape[0]
    M = jnp.concatenate([A, b[:, None]], axis=1)
    for k in range(n):
        if pivot:
            p = k + jnp.argmax(jnp.abs(M[k:, k]))
            row_k, row_p = M[k], M[p]
            M = M.at[p].set(row_k).at[k].set(row_p)
        factors = M[:, k] / M[k, k]
        factors = jnp.where(jnp.arange(n) > k, factors, 0.0)
        M = M - factors[:, None] * M[k][None, :]
    x = jnp.zeros(n, A.dtype)
    for k in reversed(range(n)):
        x = x.at[k].set((M[k, n] - jnp.sum(M[k, :n] * x)) / M[k, k])
    return x


def bare_rattle(scene, half, h, n):
    """`n` steps of h of TrapezoidalVI on the rigid double pendulum written by hand:
    RATTLE on (R^3 x SO(3))^2 with the exponential map, the centres' velocities
    explicit in the multipliers, Newton on the body velocities and the multipliers
    (12 unknowns, Jacobian by jacfwd, unrolled elimination) to sqrt(eps) of the
    terms and once more, then the momenta projected on the joints' velocity
    constraint (a 6 x 6 symmetric positive definite solve, without pivoting, as
    the library's projection)."""
    m = scene.lagrangian.mass
    J = scene.lagrangian.inertia
    force = -scene.lagrangian.gravity * m[:, None] * jnp.array([0.0, 0.0, 1.0])
    top = jnp.array([[0.0, 0.0, half[0]], [0.0, 0.0, half[1]]])
    bottom0 = jnp.array([0.0, 0.0, -half[0]])
    mass = jnp.broadcast_to(m[:, None], (2, 3))

    def joints(x, R):
        ends = x + _mv(R, top)
        return jnp.concatenate([ends[0], ends[1] - x[0] - _mv(R[0], bottom0)])

    def push(R, lam):
        """G^T lam: the forces on the centres and the body torques."""
        l0, l1 = lam[:3], lam[3:]
        fx = jnp.stack([l0 - l1, l1])
        body = lambda i, v: jnp.sum(R[i] * v[:, None], axis=0)  # R_i^T v
        torque = jnp.stack(
            [
                jnp.cross(top[0], body(0, l0)) - jnp.cross(bottom0, body(0, l1)),
                jnp.cross(top[1], body(1, l1)),
            ]
        )
        return fx, torque

    def jacobian(R):
        eye = jnp.eye(6)
        rows = jax.vmap(lambda e: push(R, e))(eye)
        return jnp.concatenate([rows[0].reshape(6, 6), rows[1].reshape(6, 6)], 1)

    def step(carry, _):
        x, R, px, pi, guess = carry
        kicked = px + 0.5 * h * force

        def residual(u):
            xi, lam = u[:6].reshape(2, 3), u[6:]
            fx, torque = push(R, lam)
            xdot = (kicked + fx) / mass
            w = pi + torque
            r = J * xi - pull(h * xi, w)
            g = joints(x + h * xdot, matmul(R, exp(h * xi)))
            scale = jnp.concatenate(
                [(J * jnp.abs(xi) + jnp.abs(w)).ravel(), jnp.ones_like(g)]
            )
            return jnp.concatenate([r.ravel(), g]), scale

        def newton(state):
            u, _, k = state
            f, scale = residual(u)
            A = jax.jacfwd(lambda v: residual(v)[0])(u)
            return u - _solve(A, f), jnp.max(jnp.abs(f) / scale), k + 1

        def going(state):
            _, size, k = state
            return (size > 1.5e-8) & (k < 16)

        u, _, _ = jax.lax.while_loop(going, newton, (guess, jnp.inf, 0))
        u, _, _ = newton((u, 0.0, 0))
        xi, lam = u[:6].reshape(2, 3), u[6:]
        fx, torque = push(R, lam)
        x1 = x + h * (kicked + fx) / mass
        F = exp(h * xi)
        R1 = matmul(R, F)
        p1 = kicked + fx + 0.5 * h * force
        pi1 = jnp.sum(F * (pi + torque)[:, :, None], axis=-2)  # F^T (pi + torque)
        G1 = jacobian(R1)
        weights = jnp.concatenate([1 / mass.ravel(), 1 / J.ravel()])
        flat = jnp.concatenate([p1.ravel(), pi1.ravel()])
        weighted = G1 * weights
        gram = jnp.sum(weighted[:, None, :] * G1[None, :, :], axis=-1)
        mu = _solve(gram, jnp.sum(weighted * flat, axis=-1), pivot=False)
        flat = flat - jnp.sum(G1 * mu[:, None], axis=0)
        return (x1, R1, flat[:6].reshape(2, 3), flat[6:].reshape(2, 3), u), None

    @jax.jit
    def run(y0):
        (x, R), (px, pi) = y0
        guess = jnp.concatenate([(pi / J).ravel(), jnp.zeros(6)])
        out, _ = jax.lax.scan(step, (x, R, px, pi, guess), None, length=n)
        return (out[0], out[1]), (out[2], out[3])

    return run


def step_ratio(scene, half, repeats, n=20_000, check=200):
    """TrapezoidalVI in `diffeqsolve` against `bare_rattle`, per step, timed in
    turns; the two agree after `check` steps (the motion is chaotic: a longer run
    separates them)."""
    from step_cost import best_times, final_state

    h = scene.period / 100
    ours = final_state(scene.term(), dvi.TrapezoidalVI(), h, n)
    bare = bare_rattle(scene, half, h, n)
    short_ours = final_state(scene.term(), dvi.TrapezoidalVI(), h, check)
    short_bare = bare_rattle(scene, half, h, check)
    gap = max(
        float(jnp.max(jnp.abs(a - b)))
        for a, b in zip(
            jax.tree.leaves(short_ours(scene.y0)), jax.tree.leaves(short_bare(scene.y0))
        )
    )
    breakers = [
        dvi.diagnostics.compiled_loop_breakers(f, scene.y0) for f in (ours, bare)
    ]
    t_ours, t_bare = best_times([ours, bare], scene.y0, repeats=repeats)
    print(
        f"\nrigid_double_pendulum, one step at h = period/100 ({n} steps, best of "
        f"{repeats}, timed in turns): TrapezoidalVI {1e6 * t_ours / n:.2f} us, a bare "
        f"lax.scan of the same update {1e6 * t_bare / n:.2f} us: "
        f"{t_ours / t_bare:.2f}x (target <= 1.5; states agree to {gap:.1e} after "
        f"{check} steps; loop breakers {breakers})"
    )


def chain_costs(links_list, steps=400, per_period=400):
    print(
        f"\nrigid_chain, TrapezoidalVI at h = period/{per_period}: trace + compile, "
        f"and time per step over {steps} steps (best of 3)"
    )
    for links in links_list:
        scene = dvi.scenes.rigid_chain(links=links)
        h = scene.period / per_period

        def solve(y0, t1):
            sol = dfx.diffeqsolve(
                scene.term(),
                dvi.TrapezoidalVI(),
                0.0,
                t1,
                h,
                y0,
                saveat=dfx.SaveAt(t1=True),
                max_steps=None,
                throw=False,
            )
            return sol.ys, sol.result

        start = time.perf_counter()
        compiled = jax.jit(solve).lower(scene.y0, jnp.asarray(h)).compile()
        build = time.perf_counter() - start
        breakers = dvi.diagnostics.loop_breakers(compiled.as_text())
        kinds = sorted({b.split(" (")[1].split(")")[0] for b in breakers})
        n, m = 6 * links, 3 * links
        _, result = compiled(scene.y0, jnp.asarray((steps + 10) * h))
        if result != dfx.RESULTS.successful:
            print(f"  {links:3d} links ({n} coordinates, {m} multipliers): {result}")
            continue
        best = np.inf
        for _ in range(3):
            start = time.perf_counter()
            jax.block_until_ready(compiled(scene.y0, jnp.asarray((steps + 10) * h)))
            long = time.perf_counter() - start
            start = time.perf_counter()
            jax.block_until_ready(compiled(scene.y0, jnp.asarray(10 * h)))
            best = min(best, (long - (time.perf_counter() - start)) / steps)
        print(
            f"  {links:3d} links ({n} coordinates, {m} multipliers): trace + compile "
            f"{build:6.1f} s, {best * 1e6:8.1f} us per step, "
            f"{len(breakers)} loop breakers {kinds}"
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--links", default="2,4,8,16")
    parser.add_argument(
        "--chain-only", action="store_true", help="only the rigid_chain section"
    )
    args = parser.parse_args()
    if args.chain_only:
        chain_costs([int(n) for n in args.links.split(",")])
        return
    versions = ", ".join(
        f"{p} {importlib.metadata.version(p)}" for p in ("jax", "diffrax", "mujoco")
    )
    print(f"{versions}, device {jax.devices()[0]}, float64")
    scene = dvi.scenes.rigid_double_pendulum()
    half = (0.5, 0.4)
    span = args.steps * MUJOCO_STEP
    ours_steps = [int(span / h) for h in (0.05, 0.02, 0.01)]
    cases = [
        ("TrapezoidalVI", dvi.TrapezoidalVI(), ours_steps),
        ("MidpointVI", dvi.MidpointVI(), ours_steps),
        (
            "MidpointVI-Yoshida4",
            dvi.Composition(dvi.MidpointVI(), "yoshida4"),
            [int(span / h) for h in (0.1, 0.05)],
        ),
    ]
    rows = mujoco_runs(scene, half, args.steps, args.samples, args.repeats)
    rows += our_runs(scene, span, args.samples, args.repeats, cases)
    print(
        f"\nrigid_double_pendulum over t = {span:g} (the upper box's small swings: "
        f"period {scene.period:.2f}); energy "
        f"{float(scene.energy(0.0, scene.y0, None)):.6f}; energy error sampled at "
        f"{args.samples} times"
    )
    print(
        f"  {'method':36s} {'h':>7s} {'steps':>8s} {'wall s':>8s} {'s per t':>9s} "
        f"{'max |dE|':>9s} {'first 1/10':>10s} {'last 1/10':>10s}  trace+compile"
    )
    for label, h, steps, wall, build, error in rows:
        tenth = len(error) // 10
        first, last = np.max(np.abs(error[:tenth])), np.max(np.abs(error[-tenth:]))
        compiled = "" if build is None else f"  {build:.1f} s"
        print(
            f"  {label:36s} {h:7.3g} {steps:8d} {wall:8.3f} {wall / span:9.2e} "
            f"{np.max(np.abs(error)):9.2e} {first:10.2e} {last:10.2e}{compiled}"
        )
    print(
        "\nAt equal or lower wall time than each MuJoCo integrator, our lowest "
        "energy error:"
    )
    for label, _, _, wall, _, error in rows[:3]:
        ours = [
            (np.max(np.abs(e)), lab, h) for lab, h, _, w, b, e in rows[3:] if w <= wall
        ]
        mine = np.max(np.abs(error))
        if not ours:
            print(f"  {label}: none of ours runs in {wall:.3f} s")
            continue
        best = min(ours)
        verdict = "below" if best[0] < mine else "NOT below"
        print(
            f"  {label} ({wall:.3f} s, max |dE| {mine:.2e}): {best[1]} at h = "
            f"{best[2]:g}, max |dE| {best[0]:.2e} ({verdict})"
        )
    step_ratio(scene, half, max(args.repeats, 3))
    chain_costs([int(n) for n in args.links.split(",")])


if __name__ == "__main__":
    main()
