"""The fit config's default specimen for a FEM sphere or cone indentation is axisymmetric
(docs/configuration.md, "Specimen of a simulated indentation"): fits of exact Hertz / Sneddon
data (nu fixed) recover E within 2 % on the mesh the config chooses, the discretisation check
runs on the coarser axisymmetric mesh, and fit.json / report.md state the model and its
resolution. Each fit is a few depths on the default mesh (about 20 s of CPU)."""

import json

import numpy as np
import pytest

from difftissue import analytic
from difftissue.cli import main
from difftissue.config import load_config
from difftissue.scenarios import AxisymmetricIndentation

E, NU = 1.0e4, 0.45

_TOML = """[material]
youngs_modulus = 7e3
poisson_ratio = 0.45
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "{name}"
scenario = "indentation"
model = "fem_linear"
data = {{ format = "table", path = "{name}.csv", columns = {{ depth = "depth (um)", force = "force (uN)" }} }}
indenter = {indenter}
length_unit = "um"
"""


def _write(tmp_path, name, depths, forces, indenter):
    (tmp_path / f"{name}.csv").write_text("depth (um),force (uN)\n" + "\n".join(f"{d * 1e6:.9f},{f * 1e6:.12g}" for d, f in zip(depths, forces)) + "\n")
    path = tmp_path / f"{name}.toml"
    path.write_text(_TOML.format(name=name, indenter=indenter))
    return path


def test_sphere_default_specimen_fits_hertz_within_2_percent(tmp_path):
    """Sphere R = 1 mm to 20 um (d/R = 0.02), exact Hertz forces at 3 depths: E within 2 %
    (measured -1.1 %), through `difftissue fit` so fit.json and report.md are checked too."""
    depths = np.array([10e-6, 15e-6, 20e-6])
    path = _write(tmp_path, "sphere", depths, np.asarray(analytic.hertz_force(depths, E, NU, 1e-3)), '{ shape = "sphere", radius = 1.0, length_unit = "mm" }')
    assert isinstance(load_config(path).experiments[0].scenario, AxisymmetricIndentation)
    out = tmp_path / "out"
    assert main(["fit", str(path), "--out", str(out)]) == 0
    rec = json.loads((out / "fit.json").read_text())
    assert rec["parameters"]["youngs_modulus"]["value"] == pytest.approx(E, rel=0.02)
    assert rec["simulation"] == [{"name": "sphere", "model": "fem_linear", "geometry": "axisymmetric", "cells_per_contact_radius": 8.0,
                                  "resolution": "axisymmetric, 8 cells per contact radius"}]
    disc = rec["discretisation"]
    assert disc["status"] == "estimated" and disc["scenarios"]["sphere"]["order"] == 2.0
    assert disc["method"] == "richardson" and disc["order"] == 2.0  # not labelled first order
    assert disc["scenarios"]["sphere"]["coarse_cells"] == "axisymmetric, 4 cells per contact radius"
    # the estimate brings the fitted E closer to the exact one (sphere: order 2 observed)
    corrected = disc["corrected"]["youngs_modulus"]
    assert abs(corrected / E - 1) < abs(rec["parameters"]["youngs_modulus"]["value"] / E - 1)
    report = (out / "report.md").read_text()
    assert "Simulation of sphere: fem_linear, axisymmetric, 8 cells per contact radius." in report
    assert "axisymmetric, 8 cells per contact radius / axisymmetric, 4 cells per contact radius" in report


def test_cone_default_specimen_fits_sneddon_within_2_percent(tmp_path):
    """Cone of half-angle 70 deg to 0.1 mm, exact Sneddon forces at 3 depths: E within 2 %
    (measured +0.9 %)."""
    theta = np.radians(70.0)
    depths = np.array([0.05e-3, 0.075e-3, 0.1e-3])
    path = _write(tmp_path, "cone", depths, np.asarray(analytic.cone_force(depths, E, NU, theta)), '{ shape = "cone", half_angle_deg = 70.0 }')
    cfg = load_config(path)
    assert isinstance(cfg.experiments[0].scenario, AxisymmetricIndentation)
    result = cfg.run(discretisation_check=False)
    assert result.values["youngs_modulus"] == pytest.approx(E, rel=0.02)
