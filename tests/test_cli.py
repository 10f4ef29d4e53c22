"""The command line: help, version, mesh generation, info, demo, one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from difftissue import __version__
from difftissue.cli import main
from difftissue.mesh import read_mesh


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert __version__ in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for cmd in ("demo", "fit", "mesh", "info"):
        assert cmd in out
    assert main([]) == 2


def test_python_dash_m_runs():
    r = subprocess.run([sys.executable, "-m", "difftissue", "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and __version__ in r.stdout


def test_mesh_block_and_info(tmp_path, capsys):
    out = tmp_path / "block.msh"
    assert main(["mesh", "block", "--size", "10", "8", "4", "--resolution", "5", "4", "2", "--out", str(out)]) == 0
    mesh = read_mesh(out)
    np.testing.assert_allclose(mesh.bounds()[1], [0.01, 0.008, 0.004], rtol=1e-12)
    assert mesh.n_tets == 6 * 40
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["summary"]["tets"] == 240 and report["summary"]["nodes"] == 6 * 5 * 3
    assert report["summary"]["volume_m3"] == pytest.approx(3.2e-7, rel=1e-12)
    assert report["findings"] == []
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "no problems found" in text and "240" in text


def test_mesh_skin_with_layers_writes_material_fields(tmp_path):
    out = tmp_path / "skin.vtu"
    args = ["mesh", "skin", "--size", "4", "4", "--resolution", "4", "4", "--layer", "epi:0.1:1e6:0.48", "--layer", "derm:1.5:2e5:0.47:3", "--out", str(out)]
    assert main(args) == 0
    mesh = read_mesh(out)
    assert mesh.region_names == ("epi", "derm")
    np.testing.assert_allclose(mesh.bounds()[1][2], 1.6e-3, rtol=1e-12)
    np.testing.assert_array_equal(np.unique(mesh.cell_data["youngs_modulus"][mesh.region_ids == 1]), [2e5])
    np.testing.assert_array_equal(np.unique(mesh.cell_data["poisson_ratio"][mesh.region_ids == 0]), [0.48])


def test_errors_are_one_line_without_traceback(tmp_path, capsys):
    out = tmp_path / "b.vtu"
    assert main(["mesh", "block", "--size", "1", "1", "1", "--resolution", "1", "1", "1", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["mesh", "block", "--size", "1", "1", "1", "--resolution", "1", "1", "1", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("difftissue: error:") and "refusing to overwrite" in err
    assert main(["mesh", "skin", "--layer", "bad:1:1e3:0.5", "--out", str(tmp_path / "s.vtu")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "poisson_ratio" in err and "Traceback" not in err
    assert main(["mesh", "skin", "--layer", "bad", "--out", str(tmp_path / "s.vtu")]) == 2
    assert "expected name:thickness" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing.vtu")]) == 1
    assert "no such mesh file" in capsys.readouterr().err
    with pytest.raises(Exception):
        main(["--debug", "info", str(tmp_path / "missing.vtu")])


def test_info_reports_validation_errors_from_a_foreign_file(tmp_path, capsys):
    skfem = pytest.importorskip("skfem")
    sk = skfem.MeshTet.init_tensor(np.linspace(0, 1, 3), np.linspace(0, 1, 3), np.linspace(0, 2, 3))
    sk.save(str(tmp_path / "sk.vtu"))
    assert main(["info", str(tmp_path / "sk.vtu"), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["summary"] is None
    assert report["findings"][0]["kind"] == "InvertedElementError" and report["findings"][0]["severity"] == "error"
    assert main(["info", str(tmp_path / "sk.vtu"), "--json", "--reorient", "--unit", "mm"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["summary"]["tets"] == sk.t.shape[1]
    assert report["summary"]["volume_m3"] == pytest.approx(2e-9, rel=1e-12)
    assert report["findings"][0]["severity"] == "note"


def test_demo_quick_fits_the_bundled_afm_curve(tmp_path, capsys):
    """`demo --quick` runs the Hertz fit of the bundled Chiaro curve only (the full demo, with the
    Ecoflex compression, is timed by hand: see docs/cli.md)."""
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "E_eff" in text and "demo finished" in text
    rec = json.loads((out / "afm_hertz" / "fit.json").read_text())
    e_eff = rec["parameters"]["youngs_modulus"]["value"]  # nu is fixed at 0: E is E_eff
    assert rec["fixed_parameters"]["poisson_ratio"]["value"] == 0.0 and rec["converged"]
    assert e_eff == pytest.approx(156.0, rel=0.05)  # the instrument's own Hertz fit
    assert rec["parameters"]["youngs_modulus"]["unit"] == "Pa" and rec["parameters"]["youngs_modulus"]["standard_error"] > 0
    assert len(rec["data_files"]) == 1 and len(rec["data_files"][0]["sha256"]) == 64
    for name in ("material.json", "fit.png", "loss.png", "report.md", "config.toml"):
        assert (out / "afm_hertz" / name).is_file()
    assert main(["demo", "--quick", "--out", str(out)]) == 1  # refuses to write into a non-empty folder
    assert "not empty" in capsys.readouterr().err
    assert main(["demo", "--quick", "--out", str(out), "--force"]) == 0


def test_demo_data_and_configs_ship_with_the_package():
    from pathlib import Path

    import difftissue

    pkg = Path(difftissue.__file__).parent / "configs"
    root = Path(__file__).resolve().parents[1] / "data"
    for rel in ("afm/chiaro_AEBP1_indentation_002.txt", "compression/EF10_50T_A1.csv"):
        assert (pkg / "data" / rel).read_bytes() == (root / rel).read_bytes()
    assert (pkg / "data" / "SOURCES.md").is_file()
    assert {p.name for p in pkg.glob("*.toml")} >= {"afm_hertz.toml", "ecoflex_compression.toml"}


def test_mesh_skin_to_medit_keeps_geometry_and_says_so(tmp_path, capsys):
    out = tmp_path / "skin.mesh"
    assert main(["mesh", "skin", "--size", "2", "2", "--resolution", "2", "2", "--out", str(out)]) == 0
    assert "cannot hold the layers' material fields" in capsys.readouterr().out
    assert read_mesh(out).n_tets > 0
    assert main(["mesh", "block", "--size", "1", "0", "1", "--resolution", "1", "1", "1", "--out", str(tmp_path / "b.vtu")]) == 2
    assert "positive lengths in mm" in capsys.readouterr().err
