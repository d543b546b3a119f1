"""What a user waits for before the first number: the command line's start-up and the
main job (`diffrax-vi drift`, the default energy-drift study) on a cold and a warm
compilation cache.

Every time is the wall time of a fresh process, as a user starts it:

- `import diffrax`, the reference for start-up;
- `diffrax-vi --help` and two refused options (`--scene nope`, and an `--out`
  folder that holds a file), which the entry point answers without importing JAX;
- the main job with `--no-cache`, then on an empty cache (cold), then again on that
  cache (warm): the cache keeps each solve as XLA compiled it (its executable),
  and the warm run loads it instead of tracing, lowering and compiling (not for
  programs that hold a host callback, which no cache keeps), and the size of the
  programs the cold run kept;
- a second warm run, which also records the span in which the study readies its
  solves (`prepare` and `track`: loading or compiling, the untimed tracked runs,
  from the first start to the last end, on both cores), and the rest of the run
  (start-up, imports, the timed runs, the tables and figures);
- the default studies of other scenes (`--scenes`: a rigid body, a mechanism and an
  articulated body), cold then warm on an empty cache, one round each, and how many
  of the solves they trace are kept.

Each time of the main job is the fastest of `--rounds` (3), each round on empty
caches, as a fresh process's time moves by a second from one run of the main job to
the next on this machine (as in `first_call.py`).

Each process may write Python's bytecode cache, as on a user's machine, where the
package's modules are compiled once (at installation, or at the first import of an
editable install); an environment that sets `PYTHONDONTWRITEBYTECODE` (this
machine's does) would otherwise have every process compile diffrax_vi's source
again, 0.1 s of each run.

Run: `python benchmarks/startup.py [--rounds 3] [--scenes a,b]` (recorded:
`results/startup_cpu.txt`).
"""

import argparse
import collections
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time


BIN = pathlib.Path(sys.executable).parent


# The main job, recording the span in which the study readies its solves (traces
# or reads back, compiles, and runs the tracked solves, which are not timed).
PHASES = """
import sys, time
from _diffrax_vi_cli import exit_now, main
from diffrax_vi.study import _run

spans = []


def timed(f):
    def g(*args, **kwargs):
        start = time.perf_counter()
        out = f(*args, **kwargs)
        spans.append((start, time.perf_counter()))
        return out
    return g


_run.prepare, _run.track = timed(_run.prepare), timed(_run.track)
code = main(sys.argv[1:], own_process=True)  # As the console script runs it,
print(max(e for _, e in spans) - min(s for s, _ in spans))
exit_now(code)  # and ends.
"""


def seconds(
    command: list[str], env: dict | None = None, cwd=None, out=None, code: int = 0
) -> float:
    """A fresh process's wall time, checked to exit with `code`; the last line of
    its output, a number, is appended to `out` if given."""
    start = time.perf_counter()
    done = subprocess.run(
        command,
        capture_output=True,
        text=True,
        env={
            **{k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"},
            **(env or {}),
        },
        cwd=cwd,
    )
    elapsed = time.perf_counter() - start
    assert done.returncode == code, done.stderr[-2000:]
    if out is not None:
        out.append(float(done.stdout.strip().splitlines()[-1]))
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--scenes",
        default="free_rigid_body,four_bar,rigid_double_pendulum",
        help="scenes whose default study runs cold and warm once each ('' for none)",
    )
    options = parser.parse_args()
    rounds = options.rounds
    cli = str(BIN / "diffrax-vi")
    job = [cli, "drift", "--out"]
    times = collections.defaultdict(list)
    prepared = []
    for _ in range(rounds):
        with tempfile.TemporaryDirectory() as work:
            cache = {"XDG_CACHE_HOME": str(pathlib.Path(work) / "cache")}
            times["import"].append(seconds([sys.executable, "-c", "import diffrax"]))
            times["help"].append(seconds([cli, "--help"]))
            times["refused"].append(seconds([cli, "drift", "--scene", "nope"], code=2))
            full = pathlib.Path(work) / "full"
            full.mkdir()
            (full / "notes.txt").write_text("mine")
            times["full"].append(seconds([*job, str(full)], code=2))
            times["uncached"].append(
                seconds([*job, "no-cache", "--no-cache"], cache, work)
            )
            times["cold"].append(seconds([*job, "cold"], cache, work))
            programs = pathlib.Path(cache["XDG_CACHE_HOME"]) / "diffrax-vi" / "programs"
            kept = list(programs.iterdir())
            folder = (len(kept), sum(path.stat().st_size for path in kept))
            times["warm"].append(seconds([*job, "warm"], cache, work))
            times["warm_again"].append(
                seconds(
                    [sys.executable, "-c", PHASES, "drift", "--out", "phases"],
                    cache,
                    work,
                    prepared,
                )
            )
    scenes = {}
    for scene in filter(None, options.scenes.split(",")):
        with tempfile.TemporaryDirectory() as work:
            cache = {"XDG_CACHE_HOME": str(pathlib.Path(work) / "cache")}
            study = [cli, "drift", "--scene", scene, "--out"]
            cold_ = seconds([*study, "cold"], cache, work)
            programs = pathlib.Path(cache["XDG_CACHE_HOME"]) / "diffrax-vi" / "programs"
            kept = len(list(programs.iterdir()))
            solves = len(
                json.loads((pathlib.Path(work) / "cold" / "drift.json").read_text())[
                    "summary"
                ]
            )
            scenes[scene] = (
                cold_,
                seconds([*study, "warm"], cache, work),
                kept,
                2 * solves,
            )
    from diffrax_vi.study._programs import MAX_BYTES

    import_diffrax, help_, refused, full, uncached, cold, warm = (
        min(times[k])
        for k in ("import", "help", "refused", "full", "uncached", "cold", "warm")
    )
    # The fastest second warm run, and the span within it.
    warm_again, span = min(zip(times["warm_again"], prepared))
    floor = warm_again - span
    print(
        "Start-up and the main job (`diffrax-vi drift`), fresh processes, seconds; "
        f"each the fastest of {rounds} rounds on empty caches"
    )
    print(f"import diffrax                      {import_diffrax:7.2f}")
    print(
        f"diffrax-vi --help                   {help_:7.2f}"
        f"   {help_ / import_diffrax:.2f}x import diffrax"
    )
    print(
        f"diffrax-vi drift --scene nope       {refused:7.2f}"
        f"   {refused / import_diffrax:.2f}x import diffrax"
    )
    print(
        f"diffrax-vi drift --out <not empty>  {full:7.2f}"
        f"   {full / import_diffrax:.2f}x import diffrax"
    )
    print(f"main job, --no-cache                {uncached:7.2f}")
    print(f"main job, cold cache                {cold:7.2f}")
    print(
        f"main job, warm cache                {warm:7.2f}"
        f"   {warm / cold:.2f}x the cold run"
    )
    print(
        "  each round, cold and warm: "
        + ", ".join(f"{c:.2f} {w:.2f}" for c, w in zip(times["cold"], times["warm"]))
    )
    print(
        f"  kept programs after it: {folder[0]} files, {folder[1] / 2**20:.1f} MiB; "
        f"the folder's bound ({MAX_BYTES / 2**20:.0f} MiB) holds "
        f"{MAX_BYTES // folder[1]} such runs"
    )
    print(f"a second warm run                   {warm_again:7.2f}")
    print(f"  readying the solves               {span:7.2f}")
    print(
        f"  the rest: start-up, timed runs, output {floor:4.2f}"
        f"   {floor / cold:.2f}x the cold run"
    )
    if scenes:
        print(
            "other scenes' default studies (diffrax-vi drift --scene ...), one round "
            "each on an empty cache: cold, warm, and the programs kept of those traced"
        )
    for scene, (cold_, warm_, kept, solves) in scenes.items():
        print(
            f"  {scene:22s} cold {cold_:6.2f}  warm {warm_:6.2f}  "
            f"{warm_ / cold_:.2f}x  kept {kept} of {solves}"
        )
    print(
        "targets: --help and refused options <= 0.5x import diffrax; the main "
        "job <= 10 s cold, a warm run <= 0.35x the cold run"
    )


if __name__ == "__main__":
    main()
