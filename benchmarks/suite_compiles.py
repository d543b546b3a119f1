"""Where the test suite's time goes: for each test, JAX's tracing, lowering and XLA
compilation, and the programs compiled more than once in one worker.

Runs the README's test command (`python -m pytest`, two workers on this machine)
with this file as a pytest plugin, which records in each worker:

- per test, its wall time and JAX's own durations of tracing, lowering and XLA's
  compilation (`jax.monitoring` events; a nested trace counts inside its parent's
  too);
- per compilation, its time and two fingerprints of the program XLA receives: the
  module's text without source locations, and that text with every constant
  replaced, which equal for two programs that differ only in a value (a time, a
  step, a parameter given as a Python number, which `jax.jit` and `eqx.filter_jit`
  treat as static).

A test that runs a fresh process (the docs pages' code, the command line's
subprocesses) shows its wall time alone: the plugin records the workers.

A program compiled again in a worker that already compiled it is a compilation the
suite could share (the same function, or the same values passed as arrays). The
summary (`results/suite_compiles_cpu.txt`) sums the durations, counts the repeated
programs and lists the tests that take longest and the repeats that cost most.

Run: `python benchmarks/suite_compiles.py` (the whole default suite, about 20
minutes here), or `python benchmarks/suite_compiles.py --summarise DIR [--wall S]`
for the records of an earlier run (`S`: the wall time pytest printed).
"""

import argparse
import collections
import hashlib
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time


RESULTS = pathlib.Path(__file__).parent / "results" / "suite_compiles_cpu.txt"
EVENTS = {
    "trace": "/jax/core/compile/jaxpr_trace_duration",
    "lower": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "compile": "/jax/core/compile/backend_compile_duration",
}
_LOCATION = re.compile(r"loc\([^)]*\)|#loc\d*( = loc.*)?")
_CONSTANT = re.compile(r"dense<[^>]*>")


# --- The plugin (loaded in each pytest worker by `-p suite_compiles`) --------------

_test = {"id": None}
_durations: dict = {}
_compiles: list = []


def _listen(event, duration, **_):
    if _test["id"] is not None:
        record = _durations.setdefault(_test["id"], {})
        record[event] = record.get(event, 0.0) + duration


def _fingerprint(text: str) -> str:
    return hashlib.md5(text.encode()).hexdigest()[:16]


def pytest_configure(config):
    import jax
    from jax._src import compiler

    jax.monitoring.register_event_duration_secs_listener(_listen)
    compile_or_get_cached = compiler.compile_or_get_cached

    def recorded(backend, computation, *args, **kwargs):
        text = _LOCATION.sub("", str(computation))
        start = time.perf_counter()
        executable = compile_or_get_cached(backend, computation, *args, **kwargs)
        _compiles.append(
            dict(
                test=_test["id"],
                program=_fingerprint(text),
                up_to_constants=_fingerprint(_CONSTANT.sub("C", text)),
                seconds=time.perf_counter() - start,
            )
        )
        return executable

    compiler.compile_or_get_cached = recorded


def pytest_runtest_protocol(item, nextitem):
    _test["id"] = item.nodeid
    _durations.setdefault(item.nodeid, {})["start"] = time.perf_counter()


def pytest_runtest_logfinish(nodeid, location):
    # Under xdist the controller hears of every test but runs none.
    record = _durations.get(nodeid, {})
    if "start" in record:
        record["wall"] = time.perf_counter() - record.pop("start")
    _test["id"] = None


def pytest_unconfigure(config):
    folder = os.environ.get("SUITE_COMPILES_DIR")
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        path = pathlib.Path(folder) / f"{worker}.json"
        path.write_text(json.dumps(dict(durations=_durations, compiles=_compiles)))


# --- The summary -------------------------------------------------------------------


def _repeats(compiles, key):
    """Compilations of a program that the same worker compiled before: their count,
    seconds, and seconds by (test that repeated it, test that compiled it first)."""
    first, count, seconds = {}, 0, 0.0
    by_pair = collections.Counter()
    for c in compiles:
        k = (c["worker"], c[key])
        if k in first:
            count += 1
            seconds += c["seconds"]
            by_pair[(c["test"], first[k])] += c["seconds"]
        else:
            first[k] = c["test"]
    return count, seconds, by_pair


def summarise(folder: pathlib.Path, wall: float | None) -> str:
    durations, compiles = {}, []
    for path in sorted(folder.glob("*.json")):
        record = json.loads(path.read_text())
        durations.update(
            (k, v) for k, v in record["durations"].items() if v.get("wall", 0) > 0
        )
        compiles += [dict(c, worker=path.stem) for c in record["compiles"]]
    total = collections.Counter()
    for record in durations.values():
        total["wall"] += record.get("wall", 0.0)
        for name, event in EVENTS.items():
            total[name] += record.get(event, 0.0)
    lines = []
    if wall is not None:
        lines.append(f"pytest's wall time: {wall:.0f} s")
    lines += [
        f"tests: {len(durations)}; their wall times summed over the workers: "
        f"{total['wall']:.0f} s",
        f"  XLA compilation {total['compile']:.0f} s "
        f"({total['compile'] / total['wall']:.0%}), lowering {total['lower']:.0f} s, "
        f"tracing {total['trace']:.0f} s (nested traces counted twice)",
        f"compilations: {len(compiles)}, {sum(c['seconds'] for c in compiles):.0f} s",
    ]
    for key, what in (
        ("program", "the same program"),
        ("up_to_constants", "a program differing only in its constants"),
    ):
        count, seconds, by_pair = _repeats(compiles, key)
        lines.append(
            f"  of {what} compiled before in the same worker: {count}, "
            f"{seconds:.0f} s; the costliest (seconds, the repeat's test <- the "
            "first's):"
        )
        for (test, first), s in by_pair.most_common(8):
            pair = test if test == first else f"{test} <- {first}"
            lines.append(f"    {s:5.1f}  {pair}")
    lines.append("the longest tests: wall, trace, lower, compile (seconds), test")
    rows = sorted(
        durations.items(), key=lambda item: item[1].get("wall", 0.0), reverse=True
    )
    for test, record in rows[:25]:
        times = [record.get("wall", 0.0)] + [
            record.get(e, 0.0) for e in EVENTS.values()
        ]
        lines.append("  " + " ".join(f"{t:6.1f}" for t in times) + f"  {test}")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--summarise", type=pathlib.Path, default=None)
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS)
    parser.add_argument("--wall", type=float, default=None, help="pytest's seconds")
    options = parser.parse_args()
    wall = options.wall
    folder = options.summarise
    if folder is None:
        folder = pathlib.Path(tempfile.mkdtemp(prefix="suite-compiles-"))
        root = pathlib.Path(__file__).parent.parent
        env = dict(
            os.environ,
            SUITE_COMPILES_DIR=str(folder),
            PYTHONPATH=os.pathsep.join(
                [str(pathlib.Path(__file__).parent), os.environ.get("PYTHONPATH", "")]
            ),
        )
        start = time.perf_counter()
        command = [sys.executable, "-m", "pytest", "-q", "-p", "suite_compiles"]
        subprocess.run(command, cwd=root, env=env, check=True)
        wall = time.perf_counter() - start
    text = summarise(folder, wall)
    print(text, end="")
    options.out.write_text(text)


if __name__ == "__main__":
    main()
