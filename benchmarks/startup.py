"""What a user waits for before the first number: the command line's start-up and the
main job (`diffrax-vi drift`, the default energy-drift study) on a cold and a warm
compilation cache.

Every time is the wall time of a fresh process, as a user starts it:

- `import diffrax`, the reference for start-up;
- `diffrax-vi --help` and a refused option (`--scene nope`), which the entry point
  answers without importing JAX;
- the main job with `--no-cache`, then on an empty cache (cold), then again on that
  cache (warm): the cache keeps what XLA compiled, and the warm run skips those
  compilations (not the tracing, and not programs that hold a host callback, which
  JAX does not store).

Run: `python benchmarks/startup.py` (recorded: `results/startup_cpu.txt`).
"""

import os
import pathlib
import subprocess
import sys
import tempfile
import time


BIN = pathlib.Path(sys.executable).parent


def seconds(command: list[str], env: dict | None = None, cwd=None) -> float:
    start = time.perf_counter()
    done = subprocess.run(
        command,
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        cwd=cwd,
    )
    elapsed = time.perf_counter() - start
    if command[-1] == "nope":
        assert done.returncode == 2, done.stderr
    else:
        assert done.returncode == 0, done.stderr[-2000:]
    return elapsed


def main() -> None:
    cli = str(BIN / "diffrax-vi")
    with tempfile.TemporaryDirectory() as work:
        cache = {"XDG_CACHE_HOME": str(pathlib.Path(work) / "cache")}
        import_diffrax = seconds([sys.executable, "-c", "import diffrax"])
        help_ = seconds([cli, "--help"])
        refused = seconds([cli, "drift", "--scene", "nope"])
        job = [cli, "drift", "--out"]
        uncached = seconds([*job, "no-cache", "--no-cache"], cache, work)
        cold = seconds([*job, "cold"], cache, work)
        warm = seconds([*job, "warm"], cache, work)
    print("Start-up and the main job (`diffrax-vi drift`), fresh processes, seconds")
    print(f"import diffrax                      {import_diffrax:7.2f}")
    print(
        f"diffrax-vi --help                   {help_:7.2f}"
        f"   {help_ / import_diffrax:.2f}x import diffrax"
    )
    print(
        f"diffrax-vi drift --scene nope       {refused:7.2f}"
        f"   {refused / import_diffrax:.2f}x import diffrax"
    )
    print(f"main job, --no-cache                {uncached:7.2f}")
    print(f"main job, cold cache                {cold:7.2f}")
    print(
        f"main job, warm cache                {warm:7.2f}"
        f"   {warm / cold:.2f}x the cold run"
    )
    print(
        "targets: --help and a refused option <= 0.5x import diffrax; the main "
        "job <= 10 s cold, a warm run <= 0.35x the cold run"
    )


if __name__ == "__main__":
    main()
