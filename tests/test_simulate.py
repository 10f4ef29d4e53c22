"""`difftissue simulate`: a config's experiments evaluated at one material, without fitting."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import difftissue
from difftissue.analytic import hertz_force
from difftissue.cli import main
from difftissue.config import load_config
from difftissue.errors import OutputExistsError, SimulationError
from difftissue.materials import Material
from difftissue.simulate import simulate_config, write_simulation_outputs

AFM = Path(difftissue.__file__).resolve().parent / "configs" / "afm_hertz.toml"


def test_simulate_afm_matches_hertz_and_writes_outputs(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(AFM), "--out", str(out), "--set", "youngs_modulus=160", "--set", "poisson-ratio=0.3"]) == 0
    text = capsys.readouterr().out
    assert "afm" in text and "relative RMS error" in text
    rec = json.loads((out / "simulation.json").read_text())
    assert rec["schema"] == "difftissue-simulation/1"
    assert rec["material"]["youngs_modulus"] == 160.0 and rec["material"]["poisson_ratio"] == 0.3
    (exp,) = rec["experiments"]
    depth, observed, predicted = (np.asarray(exp[k]) for k in ("abscissa", "observed", "predicted"))
    # independent check: the Hertz force of the 27.5 um sphere read from the instrument file
    np.testing.assert_allclose(predicted, np.asarray(hertz_force(depth, 160.0, 0.3, 27.5e-6)), rtol=1e-12)
    rel = np.sqrt(np.mean((predicted - observed) ** 2)) / np.sqrt(np.mean(observed**2))
    assert exp["relative_rms"] == pytest.approx(rel, rel=1e-12)
    with open(out / exp["csv"], newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][0].startswith("abscissa (") and len(rows) == depth.size + 1
    np.testing.assert_allclose(np.asarray(rows[1:], dtype=float)[:, 2], predicted, rtol=1e-9)
    assert (out / "simulation.png").stat().st_size > 1000


def test_simulate_default_material_is_the_config_material_and_scales_with_E(tmp_path):
    """[material] as written (100 Pa), not the fit's data-driven start (the Hertz slope, 158.5 Pa)."""
    cfg = load_config(AFM)
    mat, (a,) = simulate_config(cfg)
    assert float(mat.youngs_modulus) == float(cfg.config_material.youngs_modulus) == 100.0
    assert float(cfg.material.youngs_modulus) == pytest.approx(158.5, rel=1e-3)
    _, (b,) = simulate_config(cfg, overrides={"youngs_modulus": 3 * float(cfg.config_material.youngs_modulus)})
    np.testing.assert_allclose(b.predicted, 3 * a.predicted, rtol=1e-12)  # Hertz is linear in E


def test_simulate_refuses_overwrite_and_bad_input(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(AFM), "--out", str(out)]) == 0
    before = (out / "simulation.json").read_bytes()
    capsys.readouterr()
    assert main(["simulate", str(AFM), "--out", str(out), "--set", "youngs_modulus=200"]) == 1
    err = capsys.readouterr().err.strip()
    assert "exists" in err and len(err.splitlines()) == 1
    assert (out / "simulation.json").read_bytes() == before
    assert main(["simulate", str(AFM), "--out", str(out), "--set", "youngs_modulus=200", "--force"]) == 0
    assert json.loads((out / "simulation.json").read_text())["material"]["youngs_modulus"] == 200.0
    capsys.readouterr()
    assert main(["simulate", str(AFM), "--out", str(tmp_path / "x"), "--set", "stiffness=3"]) == 1
    assert "unknown material field 'stiffness'" in capsys.readouterr().err
    assert main(["simulate", str(AFM), "--out", str(tmp_path / "x"), "--set", "youngs_modulus"]) == 2
    assert "FIELD=VALUE" in capsys.readouterr().err
    assert main(["simulate", str(AFM), "--out", str(tmp_path / "x"), "--set", "youngs_modulus=-5"]) == 1
    assert "youngs_modulus" in capsys.readouterr().err
    assert not (tmp_path / "x" / "simulation.json").exists()


class _NaNScenario:
    name, observed, sigma, abscissa = "broken", np.ones(3), np.ones(3), np.arange(3.0)
    x_label, y_label = "depth [m]", "force [N]"

    def predict(self, material):
        return np.array([1.0, np.nan, 1.0])


class _Cfg:
    material = Material(1e3, 0.3)

    class experiments_item:
        name, kind, model, scenario = "broken", "indentation", "fem_linear", _NaNScenario()

    experiments = (experiments_item,)


def test_non_finite_prediction_is_an_error_not_a_number(tmp_path):
    with pytest.raises(SimulationError, match="'broken': 1 of 3 predictions are not finite"):
        simulate_config(_Cfg())


def test_write_refuses_existing_csv(tmp_path):
    cfg = load_config(AFM)
    mat, sims = simulate_config(cfg)
    (tmp_path / "afm.csv").write_text("mine")
    with pytest.raises(OutputExistsError, match="afm.csv"):
        write_simulation_outputs(mat, sims, tmp_path)
    assert (tmp_path / "afm.csv").read_text() == "mine"
    assert not (tmp_path / "simulation.json").exists()
