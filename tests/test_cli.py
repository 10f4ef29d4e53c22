"""The command line: help, version, mesh generation, info, demo, one-line errors."""

import json
import os
from pathlib import Path
import subprocess
import sys
import warnings

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
    # the +-5 sigma residual waves of the Hertz fit are named, not "Warnings: None" (issue 17)
    q = rec["quality"]
    assert q["verdict"] == "warnings" and [f["name"] for f in q["flags"]] == ["systematic_residuals"]
    assert q["scenarios"]["afm"]["rms"] == pytest.approx(2.13, abs=0.01) and q["scenarios"]["afm"]["lag1_autocorrelation"] > 0.5
    assert "quality: warnings: systematic_residuals (afm)" in " ".join(text.split())
    assert "## Quality" in (out / "afm_hertz" / "report.md").read_text()
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


@pytest.mark.parametrize("given", [None, "3"])
def test_the_command_line_runs_one_openblas_thread_unless_told(given):
    """`main` sets ``OPENBLAS_NUM_THREADS=1`` before NumPy (and with it OpenBLAS, which reads
    it once) is loaded, and keeps a value the user set."""
    code = ("import os, sys\nfrom difftissue.cli import main\n"
            "try:\n    main(['--version'])\nexcept SystemExit:\n    pass\n"
            "print('THREADS=' + os.environ.get('OPENBLAS_NUM_THREADS', 'unset'), 'numpy' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr
    assert f"THREADS={given or '1'} False" in r.stdout, r.stdout[-500:]


_AFM = Path(__file__).resolve().parents[1] / "difftissue" / "configs" / "afm_hertz.toml"


def _raise_interrupt(*a, **k):
    raise KeyboardInterrupt


@pytest.mark.parametrize("command, target", [
    ("fit", "difftissue.config.load_config"),          # while reading the config and data
    ("fit", "difftissue.config.FitConfig.run"),        # while fitting
    ("fit", "difftissue.report.write_fit_outputs"),    # while writing the outputs
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
    else:  # the folder may hold this run's files: the rerun needs --force
        assert f"(add --force if {out} holds files of this run)" in err


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


# Bad input (docs/fitting.md, "Bad input"): what a user sees for each case. A Hertz curve of
# E = 5 kPa, nu = 0.45, sphere radius 2 mm, 30 rows, depths 0.02 .. 0.6 mm.
_E, _NU, _R = 5.0e3, 0.45, 2.0e-3


def _hertz_rows(depth_m):
    d = np.asarray(depth_m, dtype=float)
    return 4.0 / 3.0 * _E / (1 - _NU**2) * np.sqrt(_R) * np.clip(d, 0, None) ** 1.5


def _curve(case):
    """(depth values as written, force values as written, depth unit, force unit, data extra)."""
    d = np.linspace(0.02e-3, 0.6e-3, 30)
    f = _hertz_rows(d)
    perm = np.random.default_rng(0).permutation(30)
    return {
        "unsorted": (d[perm] * 1e3, f[perm], "mm", "N", ""),
        "unsorted_sort_true": (d[perm] * 1e3, f[perm], "mm", "N", ", sort = true"),
        "loading_then_unloading": (np.r_[d, d[::-1][1:]] * 1e3, np.r_[f, 0.8 * f[::-1][1:]], "mm", "N", ""),
        "precontact_rows": (np.r_[-0.1e-3, -0.05e-3, 0.0, d] * 1e3, np.r_[0.0, 0.0, 0.0, f], "mm", "N", ""),
        "depth_m_declared_mm": (d, f, "mm", "N", ""),
        "depth_um_declared_mm": (d * 1e6, f, "mm", "N", ""),  # 0.6 m: beyond the loader's 'macro' range
        "depth_30x_radius": (d * 1e5, f, "mm", "N", ""),  # 0.06 m: in range, but 30 x the radius
        "force_uN_declared_N": (d * 1e3, f * 1e6, "mm", "N", ""),
    }[case]


def _write_case(tmp_path, case):
    depth, force, du, fu, extra = _curve(case)
    (tmp_path / "curve.csv").write_text("depth,force\n" + "".join(f"{a:.9g},{b:.9g}\n" for a, b in zip(depth, force)))
    (tmp_path / "fit.toml").write_text(f'''
[material]
youngs_modulus = 1e3
poisson_ratio = 0.45
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "curve"
scenario = "analytic_indentation"
data = {{ format = "table", path = "curve.csv", columns = {{ depth = {{ name = "depth", unit = "{du}" }}, force = {{ name = "force", unit = "{fu}" }} }}{extra} }}
indenter = {{ shape = "sphere", radius = 2, length_unit = "mm" }}
''')
    return tmp_path / "fit.toml"


# case, exit status, text the user sees (stderr on errors, stdout otherwise), fitted E [Pa] or None
BAD_INPUT = [
    ("unsorted", 1, "rows are out of order at file lines", None),
    ("unsorted_sort_true", 0, "reordered 30 (file lines", _E),
    ("loading_then_unloading", 0, "left out 29 (file lines [32, 33", _E),
    ("precontact_rows", 0, "depth <= 0 (at or before the contact point", _E),
    ("depth_m_declared_mm", 0, "warning: experiment[0]: the deepest point 6e-07 m is 0.0003 x the indenter radius", None),
    ("depth_um_declared_mm", 1, "above the plausible range [1e-07, 2e-01] m for 'macro' data; the values would be plausible in 'um' or 'nm'. "
     "Check the unit, or set plausible = { depth = [lo, hi] } (SI) in the experiment's data table", None),
    ("depth_30x_radius", 0, "most likely depths given in um but declared as mm", None),
    # E = 5e9 Pa: the data warning, and now the quality gate too (implausible_value, exit 3)
    ("force_uN_declared_N", 3, "implies an effective modulus of", None),
]


@pytest.mark.filterwarnings("ignore::difftissue.errors.IdentifiabilityWarning")
@pytest.mark.parametrize("case, status, seen, modulus", BAD_INPUT, ids=[b[0] for b in BAD_INPUT])
def test_bad_input_is_never_a_silent_wrong_modulus(tmp_path, capsys, case, status, seen, modulus):
    out = tmp_path / "out"
    assert main(["fit", str(_write_case(tmp_path, case)), "--out", str(out)]) == status
    cap = capsys.readouterr()
    text = " ".join((cap.err if status == 1 else cap.out).split())
    assert seen in text, text[-2000:]
    if status == 3:
        assert "answer is unusable (implausible_value (youngs_modulus))" in cap.err
    if status == 1:
        assert cap.err.count("\n") == 1 and "Traceback" not in cap.err and not (out / "fit.json").exists()
        return
    rec = json.loads((out / "fit.json").read_text())
    report = (out / "report.md").read_text()
    rows = rec["data_rows"][0]
    assert rows["rows_used"] == len(rows["used"]) and rows["rows_loaded"] == len(_curve(case)[0])
    assert rows["rows_used"] + sum(len(st["rows"]) for st in rows["steps"] if st["action"] == "left out") == rows["rows_loaded"]
    assert "## Data rows" in report and f"| curve | `curve.csv` | {rows['rows_used']} |" in report
    if modulus is not None:  # the rows were handled correctly: the true modulus comes back
        assert rec["parameters"]["youngs_modulus"]["value"] == pytest.approx(modulus, rel=1e-6)
        assert rec["data_warnings"] == []
    else:  # a likely unit mistake: named in the output, fit.json and report.md
        assert len(rec["data_warnings"]) >= 1 and "ImplausibleUnitWarning" not in text
        assert all(f"- data: {w}" in report for w in rec["data_warnings"])


def _punch_reference(tmp_path):
    """A tiny fem_field reference (2 x 2 x 1 cubes, punch of 4 top nodes pressed down 1 % of the height)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from difftissue import Material, block, write_mesh
    from difftissue.boundary import BoundaryConditions
    from difftissue.models import make_model
    from difftissue.solvers.host import HostStaticSolver

    mesh = block((0.002, 0.002, 0.001), (2, 2, 1))
    p = np.asarray(mesh.points)
    bottom, top = np.isclose(p[:, 2], 0.0), np.isclose(p[:, 2], 0.001)
    punch = top & (np.hypot(p[:, 0] - 0.001, p[:, 1] - 0.001) <= 0.0011)
    bc = BoundaryConditions.free(mesh).fix(mesh, np.flatnonzero(bottom)).fix(mesh, np.flatnonzero(punch), "z", (0, 0, -1e-5))
    # solve_static's Newton iteration on the host (18 nodes; equal to it to round-off): only the
    # model's derivatives are compiled, not a solve program for the reference alone
    host = HostStaticSolver(make_model(mesh, "fem_linear"), bc.fixed)
    sol = host.solve(host.checked(Material(12e3, 0.42)), np.asarray(bc.displacement), np.zeros((mesh.n_nodes, 3)))
    assert sol.converged
    write_mesh(tmp_path / "ref.vtu", mesh, point_data={"displacement": np.asarray(sol.displacement), "reaction": np.asarray(sol.reaction),
                                                       "bottom": bottom.astype(np.int32), "punch": punch.astype(np.int32)})
    return float(np.asarray(sol.reaction)[punch, 2].sum())


@pytest.mark.filterwarnings("ignore::difftissue.errors.IdentifiabilityWarning")
def test_fem_field_force_of_the_wrong_sign_is_refused(tmp_path, capsys):
    """The reaction on the prescribed punch nodes is negative (pressed down in -z); the docs'
    old comment suggested a positive force, which drove E to 2e-41 Pa with converged: true."""
    F = _punch_reference(tmp_path)
    assert F < 0
    for force, status in ((-F, 1), (F, 0)):
        (tmp_path / "fit.toml").write_text(f'''
[material]
youngs_modulus = 5e3
poisson_ratio = 0.42
[fit]
parameters = ["youngs_modulus"]
max_steps = 30
[[experiment]]
name = "punch"
scenario = "fem_field"
data = {{ format = "fem", path = "ref.vtu", field = "displacement" }}
prescribed = [{{ set = "bottom" }}, {{ set = "punch", components = "z" }}]
reaction = {{ set = "punch", components = "z", force = [{force!r}] }}
''')
        rc = main(["fit", str(tmp_path / "fit.toml"), "--out", str(tmp_path / f"out{status}")])
        cap = capsys.readouterr()
        assert rc == status, cap.err
        if status:
            err = " ".join(cap.err.split())
            assert "ReactionSign" not in err and "opposite sign of the model's reaction" in err and f"force = [{F:.6g}]" in err
            assert "negative along an axis the nodes are pushed into the specimen" in err
        else:
            rec = json.loads((tmp_path / "out0" / "fit.json").read_text())
            assert rec["parameters"]["youngs_modulus"]["value"] == pytest.approx(12e3, rel=1e-6)
            # the plot: a displacement profile and a separate force panel (not one axis vs observation index)
            import matplotlib.image

            img = matplotlib.image.imread(tmp_path / "out0" / "fit.png")
            assert img.shape[1] > 1.5 * img.shape[0]


def test_an_unusable_fit_writes_its_outputs_and_exits_3(tmp_path, capsys):
    """Not converged (max_steps = 1 from the config's E = 100 Pa, far from the data) or E outside
    fit.plausible: the answer is unusable."""
    base = _AFM.read_text().replace('path = "data/', f'path = "{_AFM.parent}/data/')
    for extra, flag in (("max_steps = 1\nstart = \"material\"", "not_converged"), ("plausible = { youngs_modulus = [1e3, 1e9] }", "implausible_value")):
        cfg = tmp_path / f"{flag}.toml"
        cfg.write_text(base.replace('method = "levenberg_marquardt"', 'method = "levenberg_marquardt"\n' + extra))
        rc = main(["fit", str(cfg), "--out", str(tmp_path / flag)])
        cap = capsys.readouterr()
        assert rc == 3, cap.err
        assert "answer is unusable" in cap.err and flag in cap.err and f"error: " in cap.out
        rec = json.loads((tmp_path / flag / "fit.json").read_text())
        assert rec["quality"]["usable"] is False and flag in [f["name"] for f in rec["quality"]["flags"] if f["severity"] == "error"]
        assert "UNUSABLE" in (tmp_path / flag / "report.md").read_text()


def test_a_fitted_modulus_outside_the_stated_tissue_range_is_a_warning(tmp_path, capsys):
    """fit.tissue states the material class: the AFM demo's E (~158 Pa effective) is outside
    'skin' (1 kPa-100 MPa), a warning named in the CLI, fit.json and the report (exit 0), and
    inside 'cell'; an unknown class is a config error naming the choices."""
    base = _AFM.read_text().replace('path = "data/', f'path = "{_AFM.parent}/data/')
    for tissue, flagged in (("skin", True), ("cell", False)):
        cfg = tmp_path / f"{tissue}.toml"
        cfg.write_text(base.replace('method = "levenberg_marquardt"', f'method = "levenberg_marquardt"\ntissue = "{tissue}"'))
        rc = main(["fit", str(cfg), "--out", str(tmp_path / tissue)])
        cap = capsys.readouterr()
        assert rc == 0, cap.err
        names = [f["name"] for f in json.loads((tmp_path / tissue / "fit.json").read_text())["quality"]["flags"]]
        assert ("outside_tissue_range" in names) == flagged
        assert ("outside_tissue_range" in cap.out + cap.err) == flagged
        assert ("fit.tissue = 'skin'" in (tmp_path / tissue / "report.md").read_text()) == flagged
    bad = tmp_path / "bad.toml"
    bad.write_text(base.replace('method = "levenberg_marquardt"', 'method = "levenberg_marquardt"\ntissue = "bone"'))
    assert main(["fit", str(bad), "--out", str(tmp_path / "bad")]) != 0
    assert "fit.tissue" in capsys.readouterr().err


# Data-driven starts (issue 17): the shipped configs converge whatever the stiffness.
_SHIPPED = Path(__file__).resolve().parents[1] / "difftissue" / "configs"


@pytest.mark.parametrize("E", [1e3, 1e5])
def test_hertz_fit_starts_from_the_data_over_100x_in_E(tmp_path, E):
    """Synthetic Hertz curves (1 mm sphere, nu = 0, 1 % noise) of E = 1 kPa and 100 kPa with
    the shipped AFM config's [material] (E = 100 Pa): the start is the data's Hertz slope."""
    from difftissue.config import load_config

    d = np.linspace(5e-6, 100e-6, 40)
    f = 4.0 / 3.0 * E * np.sqrt(1e-3) * d**1.5
    f = f + 0.01 * f.max() * np.random.default_rng(1).normal(size=d.size)
    (tmp_path / "curve.csv").write_text("depth,force\n" + "".join(f"{a:.9g},{b:.9g}\n" for a, b in zip(d, f)))
    text = _AFM.read_text().split("[[experiment]]")[0] + '''[[experiment]]
name = "afm"
scenario = "analytic_indentation"
data = { format = "table", path = "curve.csv", columns = { depth = { name = "depth", unit = "m" }, force = { name = "force", unit = "N" } } }
indenter = { shape = "sphere", radius = 1e-3 }
sigma = { relative = 0.01 }
'''
    (tmp_path / "fit.toml").write_text(text)
    cfg = load_config(tmp_path / "fit.toml")
    assert cfg.start["youngs_modulus"]["config_value"] == 100.0
    assert cfg.start["youngs_modulus"]["value"] == pytest.approx(E, rel=0.02) == cfg.material.youngs_modulus
    assert main(["fit", str(tmp_path / "fit.toml"), "--out", str(tmp_path / "out")]) == 0
    rec = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert rec["parameters"]["youngs_modulus"]["value"] == pytest.approx(E, rel=0.02) and rec["quality"]["usable"]
    assert rec["start"]["youngs_modulus"]["value"] == pytest.approx(E, rel=0.02)
    (tmp_path / "pinned.toml").write_text(text.replace("[fit]\n", '[fit]\nstart = "material"\n'))
    pinned = load_config(tmp_path / "pinned.toml")
    assert pinned.start is None and pinned.material.youngs_modulus == 100.0


def test_shipped_compression_config_fits_a_10x_stiffer_silicone(tmp_path, capsys):
    """The bundled Ecoflex curve with forces and stresses x 10 (a stiff silicone, ~160 kPa):
    the shipped config (start E = 10 kPa) used to stop with a NaN linear solve after 3
    Gauss-Newton steps at E = 5.2e10 Pa; from the data's small-strain slope, with LM, it
    converges to 10 x the bundled fit's E and the same b."""
    src = _SHIPPED / "data" / "compression" / "EF10_50T_A1.csv"
    lines = src.read_text().splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("Time"))
    rows = []
    for ln in lines[head + 1:]:
        v = ln.split(",")
        for j in (2, 4, 6):  # load [N], engineering stress [kPa], true stress [kPa]
            v[j] = f"{10.0 * float(v[j]):.6f}"
        rows.append(",".join(v))
    (tmp_path / "stiff.csv").write_text("\n".join(lines[: head + 1] + rows) + "\n")
    cfg = _SHIPPED.joinpath("ecoflex_compression.toml").read_text().replace('path = "data/compression/EF10_50T_A1.csv"', 'path = "stiff.csv"')
    (tmp_path / "stiff.toml").write_text(cfg)
    assert main(["fit", str(tmp_path / "stiff.toml"), "--out", str(tmp_path / "out")]) == 0, capsys.readouterr().err
    rec = json.loads((tmp_path / "out" / "fit.json").read_text())
    # one cube: no coarser mesh, and the summary and fit.json say so (issue 17)
    assert "discretisation error: not estimated (ecoflex: the specimen has one cell in each direction" in " ".join(capsys.readouterr().out.split())
    assert rec["discretisation"]["status"] == "not estimated"
    assert rec["method"] == "levenberg_marquardt" and rec["converged"] and rec["quality"]["usable"]
    assert rec["parameters"]["youngs_modulus"]["value"] == pytest.approx(158403, rel=0.01)  # bundled curve: 15.84 kPa
    assert rec["parameters"]["cubic_coefficient"]["value"] == pytest.approx(-1.643, abs=0.01)


_B_TRUE = 1.5


def _compression_config(tmp_path, E, b=_B_TRUE, extra_fit="", bounds="[-3.0, 5.0]"):
    """A curve of the springs_volume cube itself (nu = 0.49, cubic coefficient ``b``, 0.5 % noise)
    to 40 % strain, and the shipped compression config's [material] and [fit] for it (start
    E = 10 kPa, b = 0, bounds b in [-3, 5])."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from difftissue import Material, block
    from difftissue.scenarios import Compression

    eps = np.linspace(0.02, 0.4, 20)
    # solved on the host (equal to predict to round-off): only the model's derivatives are
    # compiled, the ones the CLI fit of this one-cube config uses (not a protocol of its own)
    stress, _ = Compression(block((0.01,) * 3, (1, 1, 1)), eps).solve_on_host(Material(E, 0.49, cubic_coefficient=b))
    stress = stress * (1.0 + 0.005 * np.random.default_rng(2).normal(size=eps.size))
    (tmp_path / "curve.csv").write_text("strain,stress\n" + "".join(f"{a:.9g},{s:.9g}\n" for a, s in zip(eps, stress)))
    head = _SHIPPED.joinpath("ecoflex_compression.toml").read_text().split("[[experiment]]")[0]
    assert "cubic_coefficient = 0.0" in head and "youngs_modulus = 1.0e4" in head
    head = head.replace("bounds = { cubic_coefficient = [-3.0, 5.0] }", f"bounds = {{ cubic_coefficient = {bounds} }}")
    (tmp_path / "fit.toml").write_text(head.replace("[fit]\n", "[fit]\n" + extra_fit) + '''[[experiment]]
name = "phantom"
scenario = "compression"
data = { format = "table", path = "curve.csv", columns = { strain = { name = "strain", unit = "-" }, stress = { name = "stress", unit = "Pa" } } }
points = "all"
sigma = { relative = 0.01 }
specimen = { size = [0.01, 0.01, 0.01], cells = [1, 1, 1] }
''')
    return tmp_path / "fit.toml"


@pytest.mark.parametrize("E", [3e3, 3e5])
def test_cubic_coefficient_starts_from_the_data_over_100x_in_E(tmp_path, capsys, E):
    """Issue 17: b starts from the data (the model's curve at the data's E with the config's b
    and b + 1, matched to the measured curve), within 0.3 of the b that made the curve, for a
    soft and a stiff specimen 100 x apart; the fit converges to it; fit.json, the CLI note and
    report.md say where the start came from."""
    from difftissue.config import load_config

    cfg = load_config(_compression_config(tmp_path, E))
    assert cfg.start["youngs_modulus"]["value"] == pytest.approx(E, rel=0.2)
    rec = cfg.start_cubic_coefficient()
    assert rec["value"] == pytest.approx(_B_TRUE, abs=0.3) == cfg.material.cubic_coefficient and rec["config_value"] == 0.0
    assert cfg.config_material.cubic_coefficient == 0.0 and cfg.start_cubic_coefficient() is None  # once
    assert main(["fit", str(tmp_path / "fit.toml"), "--out", str(tmp_path / "out")]) == 0, capsys.readouterr().err
    out = " ".join(capsys.readouterr().out.split())
    assert "note: start: cubic_coefficient = " in out and "the config's material.cubic_coefficient = 0 is not the start" in out
    fj = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert fj["converged"] and fj["quality"]["usable"]
    for f, true in (("cubic_coefficient", _B_TRUE), ("youngs_modulus", E)):  # the truth within 3 standard errors (0.5 % noise)
        p = fj["parameters"][f]
        assert abs(p["value"] - true) < 3 * p["standard_error"] and p["standard_error"] < 0.05 * abs(true), (f, p)
    assert fj["start"]["cubic_coefficient"]["value"] == pytest.approx(_B_TRUE, abs=0.3)
    report = (tmp_path / "out" / "report.md").read_text()
    assert "| cubic_coefficient | " in report.split("## Starting values")[1]
    # compression rows are accounted for as indentation rows are: CLI note, fit.json, report.md
    assert "note: experiment[0]: the fit uses 20 of the 20 rows loaded from curve.csv" in out
    assert fj["data_rows"][0]["rows_used"] == 20 and fj["data_rows"][0]["used"] == list(range(2, 22)) and fj["data_warnings"] == []
    assert "| phantom | `curve.csv` | 20 | 20 (every data row of the file) | - |" in report


def test_a_pinned_or_bounded_cubic_start_is_respected(tmp_path):
    """fit.start = "material" keeps the config's b (no model evaluation); an estimate outside
    fit.bounds.cubic_coefficient starts 5 % of the range inside the bound."""
    from difftissue.config import load_config

    cfg = load_config(_compression_config(tmp_path, 3e4, extra_fit='start = "material"\n'))
    assert cfg.start is None and cfg.start_cubic_coefficient() is None and cfg.material.cubic_coefficient == 0.0
    cfg = load_config(_compression_config(tmp_path, 3e4, b=4.0, bounds="[-1.0, 3.0]"))
    rec = cfg.start_cubic_coefficient()
    assert rec["value"] == pytest.approx(3.0 - 0.05 * 4.0) and "kept inside fit.bounds.cubic_coefficient = [-1, 3]" in rec["from"]


def test_progress_lines_off_a_terminal_for_fit_and_simulate(tmp_path, capsys, monkeypatch):
    """stderr is not a terminal under pytest: plain 'difftissue: [t s] phase' lines every
    PROGRESS_EVERY seconds (10 s by default; shortened here), for fit and simulate; none with --no-progress."""
    import difftissue.cli as cli

    monkeypatch.setattr(cli, "PROGRESS_EVERY", 0.02)
    assert main(["fit", str(_AFM), "--out", str(tmp_path / "fit")]) == 0
    err = capsys.readouterr().err
    # Which phases a tick lands in depends on timing (in a full run the fit's programs are
    # already compiled and the fit takes milliseconds): every line names its phase.
    lines = [ln for ln in err.splitlines() if ln.startswith("difftissue: [")]
    assert lines and all(any(p in ln for p in ("starting", "loading", "compiling the model", "fitting: step", "writing", "done")) for ln in lines), err
    assert main(["simulate", str(_AFM), "--out", str(tmp_path / "sim")]) == 0
    err = capsys.readouterr().err
    assert "simulating experiment 1/1 (afm" in err or "writing simulation.json" in err or "loading" in err, err
    assert main(["fit", str(_AFM), "--out", str(tmp_path / "quiet"), "--no-progress"]) == 0
    assert capsys.readouterr().err == ""


def test_data_start_stays_inside_the_bounds_of_E(tmp_path):
    """A data estimate outside fit.bounds.youngs_modulus starts at the bounds' geometric mean."""
    from difftissue.config import load_config

    text = _AFM.read_text().replace('path = "data/', f'path = "{_AFM.parent}/data/').replace(
        'method = "levenberg_marquardt"', 'method = "levenberg_marquardt"\nbounds = { youngs_modulus = [10.0, 40.0] }').replace("youngs_modulus = 100.0", "youngs_modulus = 20.0")
    (tmp_path / "b.toml").write_text(text)
    cfg = load_config(tmp_path / "b.toml")  # the Hertz slope, 158.5 Pa, lies above the bounds
    assert cfg.material.youngs_modulus == pytest.approx(20.0) and cfg.start["youngs_modulus"]["config_value"] == 20.0


def test_cubic_coefficient_start_of_a_simulated_indentation_states_when_the_curve_cannot_give_it(tmp_path):
    """The b start also serves simulated indentation, where b's effect on a force-depth curve
    is nearly a change of scale (traded off against E): on a springs_volume sphere indentation
    made with b = 1.5 (quarter block of 4 x 4 x 4 cubes of 0.5 mm, 1 % noise) the estimate's
    standard error exceeds CUBIC_START_MAX_SE, so the config's b stays the start and the
    record says why (a start from noise was 4.6, at the bound, before this check)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from difftissue import Material
    from difftissue.config import load_config
    from difftissue.errors import UnderResolvedContactWarning

    size, cells, R = (4e-3, 4e-3, 2e-3), (4, 4, 4), 2e-3
    depths = np.linspace(0.05, 0.5, 10) * 1e-3
    config = lambda start: f'''[material]
youngs_modulus = 1.0e3
poisson_ratio = 0.45
cubic_coefficient = 0.0

[fit]
parameters = ["youngs_modulus", "cubic_coefficient"]
bounds = {{ cubic_coefficient = [-3.0, 5.0] }}
start = "{start}"

[[experiment]]
name = "sphere"
scenario = "indentation"
model = "springs_volume"
data = {{ format = "table", path = "curve.csv", columns = {{ depth = {{ name = "depth", unit = "m" }}, force = {{ name = "force", unit = "N" }} }} }}
points = "all"
indenter = {{ shape = "sphere", radius = {R} }}
specimen = {{ size = [{size[0]}, {size[1]}, {size[2]}], cells = [{cells[0]}, {cells[1]}, {cells[2]}], symmetry = "quarter" }}
'''
    # The curve: the config's own scenario (the quarter block and sphere above) at b = 1.5, through
    # the program the b start then evaluates (measured data are arguments of the compiled
    # program, so the placeholder curve of this first load does not enter it).
    (tmp_path / "curve.csv").write_text("depth,force\n" + "".join(f"{a:.9g},{a:.9g}\n" for a in depths))
    (tmp_path / "fit.toml").write_text(config("material"))
    with warnings.catch_warnings():  # the depths' resolution warning: stated by the load below
        warnings.simplefilter("ignore", UnderResolvedContactWarning)
        (sc,) = load_config(tmp_path / "fit.toml").fit_scenarios()
    assert sc.inner.model.n_nodes == 125 and not sc.solves_on_host  # the 4 x 4 x 4 quarter block, a compiled protocol
    force = np.asarray(sc.evaluate(Material(8e3, 0.45, cubic_coefficient=1.5)))
    assert force.shape == depths.shape and np.all(np.diff(force) > 0)
    force = force * (1.0 + 0.01 * np.random.default_rng(3).normal(size=force.size))
    (tmp_path / "curve.csv").write_text("depth,force\n" + "".join(f"{a:.9g},{f:.9g}\n" for a, f in zip(depths, force)))
    (tmp_path / "fit.toml").write_text(config("data"))
    cfg = load_config(tmp_path / "fit.toml")
    assert cfg.start_cubic_coefficient() is None and cfg.material.cubic_coefficient == 0.0
    rec = cfg.start["cubic_coefficient"]
    assert rec["value"] == 0.0 and "sphere: the curve's shape does not determine b" in rec["no_estimate"], rec
