"""The scene gallery: one drift study per scene, with the solvers that suit it.

Writes `docs/gallery.md` (a section per scene: what it models, the study's table and
its energy-error figure) and the figures under `docs/images/gallery/`.
Run: `python examples/gallery.py` (about ten minutes on a 2-core CPU).
"""

import argparse
import inspect
import pathlib

import jax


jax.config.update("jax_enable_x64", True)
import diffrax_vi  # noqa: E402
from diffrax_vi import scenes  # noqa: E402
from diffrax_vi.study import drift  # noqa: E402


# scene -> (solvers, periods, steps per period, ensemble size or None)
STUDIES = {
    "falling_particle": (["MidpointVI", "LinearizedVI", "Tsit5"], 100, 20, None),
    "oscillator": (
        ["MidpointVI", "StormerVerlet", "LinearizedVI", "GaussVPRK2", "Tsit5"],
        1000,
        20,
        None,
    ),
    "duffing": (
        ["MidpointVI", "StormerVerlet", "LinearizedVI", "Tsit5"],
        1000,
        20,
        None,
    ),
    "pendulum": (
        ["MidpointVI", "StormerVerlet", "KahanLi6", "Tsit5", "Dopri8"],
        1000,
        50,
        None,
    ),
    "double_pendulum": (
        ["MidpointVI", "GaussVPRK2", "LinearizedVI", "Tsit5", "Dopri8"],
        200,
        100,
        16,
    ),
    "kepler": (["MidpointVI", "StormerVerlet", "Tsit5", "Dopri8"], 1000, 200, None),
    "henon_heiles": (
        ["StormerVerlet", "MidpointVI", "Yoshida4", "Tsit5", "Dopri8"],
        1000,
        50,
        16,
    ),
    "fpu": (
        ["StormerVerlet", "MidpointVI", "KahanLi6", "Tsit5", "Tsit5+PID"],
        2000,
        10,
        None,
    ),
    "outer_solar_system": (
        ["StormerVerlet", "MidpointVI", "KahanLi6", "Tsit5", "Dopri8"],
        100,
        400,
        None,
    ),
    "pythagorean_three_body": (
        ["KahanLi8", "StormerVerlet+Adaptive", "KahanLi8+Adaptive", "Dopri8+PID"],
        7,
        1000,
        None,
    ),
    "learned": (["MidpointVI", "StormerVerlet", "Tsit5"], 1000, 50, None),
    "bead_wire": (["MidpointVI", "GaussVPRK2", "Tsit5", "Dopri8"], 200, 40, None),
    "forced_duffing": (
        ["MidpointVI", "TrapezoidalVI", "GaussVPRK2", "Tsit5", "Dopri8"],
        100,
        50,
        None,
    ),
    "cartesian_pendulum": (
        ["TrapezoidalVI", "MidpointVI", "Tsit5", "Dopri8"],
        1000,
        50,
        None,
    ),
    # Tsit5 at this step drifts off the loop into a singular configuration, where
    # the index-reduced vector field raises (docs/forces-constraints.md).
    "four_bar": (["MidpointVI", "Dopri8"], 200, 50, None),
    "free_rigid_body": (
        ["MidpointVI", "TrapezoidalVI", "MidpointVI-Yoshida4", "Tsit5", "Dopri8+PID"],
        200,
        50,
        None,
    ),
    "heavy_top": (["TrapezoidalVI", "MidpointVI", "Tsit5"], 200, 50, None),
    "pendulum_3d": (["TrapezoidalVI", "MidpointVI", "Tsit5", "Dopri8"], 100, 100, 16),
    "satellite": (["MidpointVI", "TrapezoidalVI", "Tsit5"], 20, 200, None),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--docs", default="docs")
    parser.add_argument("--only", default=None, help="comma-separated scene names")
    args = parser.parse_args()
    # As the `diffrax-vi drift` commands quoted on the page do.
    diffrax_vi.compile_small_loops_whole()
    docs = pathlib.Path(args.docs)
    images = docs / "images" / "gallery"
    names = args.only.split(",") if args.only else list(STUDIES)
    sections = {}
    for name in names:
        solvers, periods, spp, members = STUDIES[name]
        make = scenes.SCENES[name]
        scene = make()
        study = drift(
            scene,
            solvers,
            periods=periods,
            steps_per_period=spp,
            ensemble=members,
        )
        print(f"## {name}\n{study.table()}", flush=True)
        study.write(images / name)
        ensemble = (
            f" Ensemble of {members} initial states within 1e-3 of the default; "
            "errors are the worst member's."
            if members
            else ""
        )
        # Docstring links are relative to the API pages in docs/api/; this page is
        # one level up.
        doc = inspect.getdoc(make).replace("\n", " ").replace("](../", "](")
        figures = "\n\n".join(
            f"![{name} {k} error](images/gallery/{name}/drift_{k}.png)"
            for k in study.invariants
        )
        sections[name] = (
            f"## {name}\n\n`diffrax_vi.scenes.{make.__name__}()`: {doc}\n\n"
            f"`diffrax-vi drift --scene {name} --solvers {','.join(solvers)} "
            f"--periods {periods} --steps-per-period {spp}"
            + (f" --ensemble {members}" if members else "")
            + f"`: {periods} periods at {spp} steps per period, float64.{ensemble}\n\n"
            f"{study.table()}\n\n{figures}\n"
        )
    page = docs / "gallery.md"
    header = (
        "# Scene gallery\n\nEvery scene in `diffrax_vi.scenes`, with a drift study of "
        "the solvers that suit it, measured on a 2-core CPU (wall times after "
        "compilation, XLA's small-loop threshold raised, as by the command line). "
        "Generated by `examples/gallery.py`.\n"
    )
    if args.only and page.exists():
        old = page.read_text().split("\n## ")
        kept = {s.split("\n", 1)[0]: "## " + s for s in old[1:]}
        kept.update(sections)
        sections = {n: kept[n] for n in STUDIES if n in kept}
    page.write_text(
        header + "\n" + "\n".join(sections[n] for n in STUDIES if n in sections)
    )


if __name__ == "__main__":
    main()
