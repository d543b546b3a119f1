"""Gradient time and memory of `diffrax_vi.ReversibleAdjoint` against diffrax's
`RecursiveCheckpointAdjoint` (the default) and `DirectAdjoint`, as ratios from one
run.

For each case: the time of `jax.grad` of a scalar of the final state over the time
of the forward solve alone; for the 4096-mass chain also the peak resident memory of
a process that computes one gradient (`VmHWM`, Linux; the process run afresh for
each adjoint and length). Cases:

- Kepler (e = 0.6, 200 steps per orbit), StormerVerlet, 10^3, 10^4 and 10^5 steps;
- a chain of 256 masses with quartic springs, StormerVerlet, 2*10^4 steps (h = 0.05);
- a chain of 4096 masses, StormerVerlet, 2*10^3 and 2*10^4 steps (memory);
- MidpointVI on the 64-mass chain written as a general Lagrangian (Newton steps),
  2*10^3 steps.

Then the accuracy: the largest relative difference between ReversibleAdjoint's
gradient and RecursiveCheckpointAdjoint's, on Kepler (regular; StormerVerlet, 2*10^3
and 2*10^4 steps; StormerVerlet and MidpointVI under ReversibleController, about
2*10^3 steps), the 64-mass generic chain (MidpointVI, implicit, 2*10^3 steps) and
the double pendulum released from horizontal (chaotic; MidpointVI, h = 0.01, over
growing horizons).

Targets: ReversibleAdjoint <= 0.6x the time of RecursiveCheckpointAdjoint
on the 256-mass chain at 2*10^4 steps, <= 0.2x on Kepler at 10^5 steps; its peak
memory on the 4096-mass chain within 100 MB between 2*10^3 and 2*10^4 steps.

Run: `taskset -c 1 python benchmarks/adjoint.py [--repeats 3] [--xla-default]`.
"""

import argparse
import subprocess
import sys

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402
from step_cost import (  # noqa: E402
    add_xla_option,
    apply_xla_option,
    best_time,
    Chain,
)


class GenericChain(eqx.Module):
    """The same chain as a plain function of (t, q, v, args): Newton's method."""

    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) - Chain().potential(t, q, args)


def kepler_potential(t, q, args):
    return -args / jnp.linalg.norm(q)


KEPLER = dvi.SeparableLagrangian(kepler_potential)


ADJOINTS = {
    "Reversible": dvi.ReversibleAdjoint(),
    "RecursiveCheckpoint": dfx.RecursiveCheckpointAdjoint(),
    "Direct": dfx.DirectAdjoint(),
}


def case(terms, solver, y0, args, h, steps, every=None, controller=None):
    """The forward solve and, per adjoint, the gradient of a scalar of its end
    (`every`: ReversibleAdjoint's `checkpoint_every`). With a `controller`, the
    solve runs to `steps * h` from the step `h` and may take up to `2 * steps`."""
    adjoints = dict(ADJOINTS, Reversible=dvi.ReversibleAdjoint(every))
    fixed = controller is None
    controller = dfx.ConstantStepSize() if fixed else controller

    def final(y0, args, adjoint):
        sol = dfx.diffeqsolve(
            terms,
            solver,
            0.0,
            steps * h,
            h,
            y0,
            args,
            stepsize_controller=controller,
            adjoint=adjoint,
            max_steps=steps if fixed else 2 * steps,
        )
        return jnp.sum(sol.ys[0][-1] ** 2) + jnp.sum(jnp.sin(sol.ys[1][-1]))

    forward = jax.jit(lambda y0, args: final(y0, args, ADJOINTS["Reversible"]))
    grads = {
        name: jax.jit(jax.grad(lambda y0, args, a=adjoint: final(y0, args, a), (0, 1)))
        for name, adjoint in adjoints.items()
    }
    return forward, grads


def measure(label, terms, solver, y0, args, h, steps, repeats, adjoints=ADJOINTS):
    forward, grads = case(terms, solver, y0, args, h, steps)
    t_forward = best_time(forward, y0, args, repeats=repeats)
    row = {}
    for name in adjoints:
        seconds = best_time(grads[name], y0, args, repeats=repeats)
        row[name] = seconds
        print(
            f"  {label:34s} {name:20s} {seconds / t_forward:8.1f}x forward"
            f"  {seconds:9.4f} s",
            flush=True,
        )
    return t_forward, row


def chain_y0(n):
    i = jnp.arange(1.0, n + 1.0)
    return 0.3 * jnp.sin(2.1 * i), jnp.zeros(n)


def peak_memory(adjoint: str, steps: int) -> float:
    """MiB of peak resident memory of a fresh process computing one gradient on the
    4096-mass chain (this script with `--memory`)."""
    out = subprocess.run(
        [sys.executable, __file__, "--memory", adjoint, str(steps)],
        capture_output=True,
        text=True,
        check=True,
    )
    return float(out.stdout.split()[-1])


def one_gradient(adjoint: str, steps: int) -> None:
    _, grads = case(
        dvi.separable_terms(Chain()),
        dvi.StormerVerlet(),
        chain_y0(4096),
        None,
        0.05,
        steps,
    )
    jax.block_until_ready(grads[adjoint](chain_y0(4096), None))
    # VmHWM, not ru_maxrss: the latter keeps the parent's peak across fork and exec.
    with open("/proc/self/status") as status:
        peak_kib = next(int(x.split()[1]) for x in status if x.startswith("VmHWM"))
    print(peak_kib / 1024)


def relative_difference(a, b) -> float:
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return max(float(jnp.max(jnp.abs(x - y)) / jnp.max(jnp.abs(y))) for x, y in pairs)


def accuracy(label, terms, solver, y0, args, h, steps, every=None, controller=None):
    _, grads = case(terms, solver, y0, args, h, steps, every, controller)
    ours = grads["Reversible"](y0, args)
    reference = grads["RecursiveCheckpoint"](y0, args)
    difference = relative_difference(ours, reference)
    print(f"  {label:44s} {difference:9.1e}", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--memory", nargs=2, help=argparse.SUPPRESS)
    add_xla_option(parser)
    args = parser.parse_args()
    if args.memory:
        one_gradient(args.memory[0], int(args.memory[1]))
        return
    print(apply_xla_option(args))
    print(f"jax {jax.__version__}, diffrax {dfx.__version__}, {jax.devices()[0]}")
    print("gradient time over forward time")

    e = 0.6
    kepler_y0 = (
        jnp.array([1 - e, 0.0]),
        jnp.array([0.0, ((1 + e) / (1 - e)) ** 0.5]),
    )
    kepler = dvi.separable_terms(KEPLER)
    sv = dvi.StormerVerlet()
    h = 2 * jnp.pi / 200
    rows = {}
    for steps in (1000, 10_000, 100_000):
        rows["kepler", steps] = measure(
            f"Kepler, {steps} steps", kepler, sv, kepler_y0, 1.0, h, steps, args.repeats
        )

    chain = dvi.separable_terms(Chain())
    rows["chain256"] = measure(
        "chain 256, 2e4 steps",
        chain,
        sv,
        chain_y0(256),
        None,
        0.05,
        20_000,
        args.repeats,
    )
    rows["chain4096"] = measure(
        "chain 4096, 2e3 steps", chain, sv, chain_y0(4096), None, 0.05, 2000, 1
    )
    measure(
        "MidpointVI, generic chain 64, 2e3",
        dvi.LagrangianTerm(GenericChain()),
        dvi.MidpointVI(),
        chain_y0(64),
        None,
        0.05,
        2000,
        args.repeats,
    )

    print("gradient: largest relative difference, Reversible to RecursiveCheckpoint")
    for steps in (2000, 20_000):
        accuracy(
            f"Kepler, StormerVerlet, {steps} steps",
            kepler,
            sv,
            kepler_y0,
            1.0,
            h,
            steps,
        )
    # Steps from h / 4 at perihelion, about 220 per orbit: 2000 steps in 9.1 orbits.
    for solver in (sv, dvi.MidpointVI()):
        accuracy(
            f"Kepler, {type(solver).__name__}, ReversibleController, 9.1 orbits",
            dvi.terms_for(solver, KEPLER),
            solver,
            kepler_y0,
            1.0,
            h / 4,
            round(9.1 * 800),
            controller=dvi.ReversibleController(dvi.PotentialMonitor(KEPLER)),
        )
    accuracy(
        "generic chain 64, MidpointVI, 2000 steps",
        dvi.LagrangianTerm(GenericChain()),
        dvi.MidpointVI(),
        chain_y0(64),
        None,
        0.05,
        2000,
    )
    pendulum = dvi.scenes.double_pendulum()
    for steps, every in (
        (500, None),
        (1000, None),
        (2000, None),
        (4000, None),
        (8000, None),
        (8000, 100),
    ):
        accuracy(
            f"double pendulum, MidpointVI, t = {steps * 0.01:g}"
            + ("" if every is None else f", checkpoint_every={every}"),
            dvi.LagrangianTerm(pendulum.lagrangian),
            dvi.MidpointVI(),
            pendulum.y0,
            None,
            0.01,
            steps,
            every,
        )

    def ratio(key):
        row = rows[key][1]
        return row["Reversible"] / row["RecursiveCheckpoint"]

    print("peak resident memory of one gradient, chain 4096 (MiB)")
    memory = {}
    for name in ADJOINTS:
        for steps in (2000, 20_000):
            memory[name, steps] = peak_memory(name, steps)
            print(f"  {name:20s} {steps:6d} steps  {memory[name, steps]:9.1f}")
    growth = memory["Reversible", 20_000] - memory["Reversible", 2000]
    print("targets")
    print(
        f"  chain 256 at 2e4 steps, Reversible / RecursiveCheckpoint "
        f"{ratio('chain256'):6.2f}x  (<= 0.6)"
    )
    print(
        f"  Kepler at 1e5 steps, Reversible / RecursiveCheckpoint     "
        f"{ratio(('kepler', 100_000)):6.2f}x  (<= 0.2)"
    )
    print(
        f"  chain 4096 peak memory, 2e4 steps minus 2e3 steps        "
        f"{growth:6.1f} MiB  (<= 100 MB)"
    )


if __name__ == "__main__":
    main()
