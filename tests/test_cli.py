"""The command line: help, version, mesh generation, info, demo, one-line errors."""

import json
from pathlib import Path
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


# ------------------------------------------------------------- issue 17: fits a user can trust
def test_help_and_version_do_not_import_jax():
    """`difftissue --help` / `--version` parse arguments before any heavy import (no JAX, NumPy)."""
    code = ("import sys\nfrom difftissue.cli import main\n"
            "for argv in (['--help'], ['--version'], ['fit', '--help']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            "print('HEAVY=' + ','.join(sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'numpy', 'equinox', 'rich'))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "HEAVY=\n" in r.stdout, r.stdout[-500:]


_AFM = Path(__file__).resolve().parents[1] / "difftissue" / "configs" / "afm_hertz.toml"


def _raise_interrupt(*a, **k):
    raise KeyboardInterrupt


@pytest.mark.parametrize("command, target", [
    ("fit", "difftissue.config.load_config"),          # while reading the config and data
    ("fit", "difftissue.config.FitConfig.run"),        # while fitting
    ("fit", "difftissue.fit.write_fit_outputs"),       # while writing the outputs
    ("simulate", "difftissue.config.load_config"),
    ("simulate", "difftissue.simulate.simulate_config"),
    ("demo", "difftissue.config.load_config"),
    ("demo", "difftissue.config.FitConfig.run"),
])
def test_ctrl_c_in_any_phase_exits_130_with_one_line(tmp_path, capsys, monkeypatch, command, target):
    module, _, attr = target.rpartition(".")
    if attr == "run":
        from difftissue.config import FitConfig

        monkeypatch.setattr(FitConfig, "run", _raise_interrupt)
    else:
        monkeypatch.setattr(target, _raise_interrupt)
    if attr == "write_fit_outputs":  # the fit itself must not run for seconds here: stop it at once
        from difftissue.config import FitConfig

        monkeypatch.setattr(FitConfig, "run", lambda self, **kw: object())
    out = tmp_path / "out"
    argv = {"fit": ["fit", str(_AFM), "--out", str(out)], "simulate": ["simulate", str(_AFM), "--out", str(out)],
            "demo": ["demo", "--quick", "--out", str(out)]}[command]
    assert main(argv) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("difftissue: interrupted; rerun the same command"), err
    assert "Traceback" not in err
    assert not (out / ".difftissue.lock").exists()  # the lock is released
    if command == "fit":
        assert not (out / "checkpoint" / "fit.npz").exists() and not (out / "checkpoint").exists()


def test_ctrl_c_after_a_checkpoint_says_resume(tmp_path, capsys, monkeypatch):
    from difftissue.config import FitConfig

    def run(self, **kw):
        Path(kw["checkpoint"]).write_bytes(b"state")
        raise KeyboardInterrupt

    monkeypatch.setattr(FitConfig, "run", run)
    out = tmp_path / "out"
    assert main(["fit", str(_AFM), "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "with --resume to continue from" in err and str(out / "checkpoint" / "fit.npz") in err


def test_a_second_run_into_a_locked_out_is_refused_and_a_stale_lock_taken_over(tmp_path, capsys, monkeypatch):
    import os

    from difftissue.cli import LOCK_NAME

    out = tmp_path / "out"
    out.mkdir()
    lock = out / LOCK_NAME
    lock.write_text(f"{os.getpid()}\n")  # a live process holds it (this one)
    assert main(["fit", str(_AFM), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is in use by another difftissue run" in err and f"pid {os.getpid()}" in err
    assert lock.read_text() == f"{os.getpid()}\n"  # not removed by the refused run
    for argv in (["demo", "--quick", "--out", str(out)], ["simulate", str(_AFM), "--out", str(out)]):
        assert main(argv) == 1 and "in use by another difftissue run" in capsys.readouterr().err
    # a dead process's lock is taken over, with a note
    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock.write_text(child.stdout.strip() + "\n")
    from difftissue.config import FitConfig

    seen = {}

    def run(self, **kw):
        seen["lock"] = lock.read_text().split()[0]
        raise KeyboardInterrupt

    monkeypatch.setattr(FitConfig, "run", run)
    assert main(["fit", str(_AFM), "--out", str(out)]) == 130
    assert seen["lock"] == str(os.getpid()) and not lock.exists()


def test_a_fit_that_fails_before_any_step_leaves_nothing_blocking_a_rerun(tmp_path, capsys, monkeypatch):
    from difftissue.config import FitConfig
    from difftissue.errors import FitError

    def run(self, **kw):
        raise FitError("boom")

    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(FitConfig, "run", run)
        assert main(["fit", str(_AFM), "--out", str(out)]) == 1
    assert "boom" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == []
    assert main(["fit", str(_AFM), "--out", str(out)]) == 0  # the rerun is not refused


def test_library_words_become_cli_flags():
    from difftissue.cli import cli_words

    assert cli_words("x exists; refusing to overwrite it (choose another output directory or pass force=True / --force)") \
        .endswith("(choose another output directory or pass --force)")
    assert "--approximate to drop it" in cli_words("b != 0; pass approximate=True (--approximate) to drop it")
    assert "pass --resume" in cli_words("checkpoint c exists; pass resume=True to continue that fit")
    msg = "read it with reorient=True (CLI: --reorient)"
    assert cli_words(msg, "info") == "read it with --reorient"
    assert "reorient = true" in cli_words(msg, "fit") and "=True" not in cli_words(msg, "fit")
