import csv
import json

import diffrax as dfx
import diffrax_vi as dvi
import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest
from diffrax_vi.scenes import kepler
from diffrax_vi.study import drift
from diffrax_vi.study._cli import main


ARGS = ["--periods", "2", "--steps-per-period", "50", "--save", "10"]


def test_drift_errors_match_a_hand_computed_solve():
    scene = kepler()
    study = drift(scene, ["MidpointVI"], periods=2, steps_per_period=50, n_save=10)
    run = study.runs[0]
    assert run.steps == 100 and run.result == "successful"
    sol = dfx.diffeqsolve(
        dvi.LagrangianTerm(scene.lagrangian),
        dvi.MidpointVI(),
        0.0,
        4 * np.pi,
        4 * np.pi / 100,
        scene.y0,
        saveat=dfx.SaveAt(steps=True),
    )
    q, p = sol.ys
    every_tenth = slice(9, 100, 10)
    e = 0.5 * jnp.sum(p[every_tenth] ** 2, axis=1) - 1 / jnp.linalg.norm(
        q[every_tenth], axis=1
    )
    assert np.allclose(run.errors["energy"][1:], np.abs(e - (-0.5)), atol=1e-14)
    # The energy of the initial state is exactly -1/2 for this scene.
    assert run.errors["energy"][0] == 0


def test_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "results"
    assert main(["drift", *ARGS, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in ("MidpointVI", "StormerVerlet", "Tsit5", "Dopri8"):
        assert name in printed
    with open(out / "drift.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["solver"] for r in rows] == [
        "MidpointVI",
        "StormerVerlet",
        "Tsit5",
        "Dopri8",
    ]
    api = drift(
        kepler(), ["MidpointVI", "Tsit5"], periods=2, steps_per_period=50, n_save=10
    )
    by_name = {r["solver"]: r for r in rows}
    for run in api.runs:
        assert float(by_name[run.solver]["max_energy_error"]) == pytest.approx(
            run.max_error("energy"), rel=1e-12
        )
        assert int(by_name[run.solver]["steps"]) == 100
    data = json.loads((out / "drift.json").read_text())
    assert data["scene"] == "kepler" and len(data["series"]["Tsit5"]["energy"]) == 11
    for name in ("energy", "angular_momentum"):
        png = out / f"drift_{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert matplotlib.image.imread(png).shape[0] > 100


def test_cli_errors(capsys):
    with pytest.raises(SystemExit, match="unknown solver"):
        main(["drift", "--solvers", "MidpointVI,RK99"])
    with pytest.raises(SystemExit, match="unknown scene"):
        main(["drift", "--scene", "blackhole"])
    with pytest.raises(ValueError, match="must divide"):
        drift(kepler(), ["MidpointVI"], periods=1, steps_per_period=10, n_save=3)
    with pytest.raises(SystemExit):
        main(["drift", "--help"])
    assert "--steps-per-period" in capsys.readouterr().out
