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
from difftissue.errors import DiscretisationWarning
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
    sc = disc["scenarios"]["sphere"]
    # three levels (8, 5.66, 4 cells per contact radius): the order is observed (3.2 here: the
    # 5.66 level is luckily close) and capped at the linear triangles' 2
    assert disc["status"] == "estimated" and sc["observed_order"] > 2 and sc["order"] == 2.0
    assert sc["order_source"].startswith("observed") and "capped at the element's 2" in sc["order_source"]
    assert disc["method"] == "richardson" and disc["order"] == sc["order"]  # not labelled first order
    assert sc["coarse_cells"] == "axisymmetric, 5.65685 cells per contact radius" and sc["coarser_cells"] == "axisymmetric, 4 cells per contact radius"
    # the estimate brings the fitted E closer to the exact one (sphere: order 2 observed)
    corrected = disc["corrected"]["youngs_modulus"]
    assert abs(corrected / E - 1) < abs(rec["parameters"]["youngs_modulus"]["value"] / E - 1)
    report = (out / "report.md").read_text()
    assert "Simulation of sphere: fem_linear, axisymmetric, 8 cells per contact radius." in report
    assert "axisymmetric, 8 cells per contact radius / axisymmetric, 5.65685 cells per contact radius / axisymmetric, 4 cells per contact radius" in report


def test_cone_default_specimen_fits_sneddon_within_2_percent_and_estimates_its_mesh_error(tmp_path):
    """Cone of half-angle 70 deg to 0.1 mm, exact Sneddon forces at 3 depths: E within 2 %
    (measured +0.9 %). The discretisation check's three levels (8, 5.66, 4 cells per contact
    radius) give an observed order and a mesh-converged E near the converged model's: the fits
    at 8 / 11.3 / 16 cells on 10 exact depths, each corrected by its own three levels, gave
    +1.81 / +1.96 / +1.71 % (docs/dev/axisymmetric-indentation.md); the converged model's force
    is about 1.7 % below Sneddon's (finite deformation under a 70 deg cone), so its E is that
    much above the data's."""
    theta = np.radians(70.0)
    depths = np.array([0.05e-3, 0.075e-3, 0.1e-3])
    path = _write(tmp_path, "cone", depths, np.asarray(analytic.cone_force(depths, E, NU, theta)), '{ shape = "cone", half_angle_deg = 70.0 }')
    cfg = load_config(path)
    assert isinstance(cfg.experiments[0].scenario, AxisymmetricIndentation)
    with pytest.warns(DiscretisationWarning, match=r"youngs_modulus: the mesh's estimated share"):  # 3 exact depths: tiny standard error
        result = cfg.run()
    assert result.values["youngs_modulus"] == pytest.approx(E, rel=0.02)
    disc = result.discretisation
    sc = disc["scenarios"]["cone"]
    assert disc["status"] == "estimated" and sc["order_source"] == "observed (three levels)", disc
    assert 1.0 < sc["order"] < 3.0 and sc["change_ratio"] > 1
    # the 8-cell mesh is stiffer than the converged model, so its E is low against the
    # converged one (estimate < 0) and the correction raises it: fit +0.9 %, corrected within
    # 0.5 pt of the converged model's +1.8 %
    assert disc["estimate"]["youngs_modulus"] < 0
    assert disc["corrected"]["youngs_modulus"] / E - 1 == pytest.approx(0.018, abs=0.005)


_THICK = """specimen = {{ {spec} }}
"""


def _cone_config(tmp_path, spec, name="layer"):
    theta = np.radians(70.0)
    depths = np.array([0.05e-3, 0.1e-3])  # contact radius 0.175 mm at the deepest point
    path = _write(tmp_path, name, depths, np.asarray(analytic.cone_force(depths, E, NU, theta)), '{ shape = "cone", half_angle_deg = 70.0 }')
    path.write_text(path.read_text() + _THICK.format(spec=spec))
    return path


def test_config_thickness_sets_the_axisymmetric_specimens_height(tmp_path):
    """specimen.thickness in the specimen's length_unit: the automatic cylinder's height (a
    layer on the bonded base), same radius and cells; recorded as the specimen's own."""
    from difftissue.scenarios import axisymmetric_specimen_for

    exp = load_config(_cone_config(tmp_path, 'thickness = 2.5, length_unit = "mm"')).experiments[0]
    sc = exp.scenario
    assert isinstance(sc, AxisymmetricIndentation)
    want = axisymmetric_specimen_for("cone", half_angle=np.radians(70.0), max_depth=float(sc.abscissa.max()), thickness=2.5e-3)
    assert sc.specimen == want and sc.specimen.height == pytest.approx(2.5e-3) and sc.specimen.thickness_given
    assert sc.record()["height"] == pytest.approx(2.5e-3, rel=1e-12)
    assert not any("contact radii thick" in w for w in exp.warnings)  # 14 contact radii: not thin
    coarse_sc, info = exp.coarsen()
    assert coarse_sc.specimen.height == pytest.approx(2.5e-3) and info["specimen"]["thickness_given"]
    # metres without a length_unit; with geometry = "3d" the automatic block takes it as its height
    sc_m = load_config(_cone_config(tmp_path, "thickness = 2.5e-3", name="m")).experiments[0].scenario
    assert sc_m.specimen.height == pytest.approx(2.5e-3)
    exp3 = load_config(_cone_config(tmp_path, 'geometry = "3d", thickness = 2.5, length_unit = "mm"', name="three")).experiments[0]
    assert exp3.scenario.model.rest_points[:, 2].max() - exp3.scenario.model.rest_points[:, 2].min() == pytest.approx(2.5e-3, rel=1e-9)


def test_config_thin_thickness_warns_and_too_thin_is_refused(tmp_path):
    from difftissue.errors import ConfigError, ThinSpecimenWarning

    # 1 mm = 5.72 contact radii: simulated (the layer is the model), with a named warning
    with pytest.warns(ThinSpecimenWarning, match=r"specimen.thickness: the specimen is 5.72 contact radii thick"):
        exp = load_config(_cone_config(tmp_path, 'thickness = 1.0, length_unit = "mm"')).experiments[0]
    assert any("5.72 contact radii thick" in w for w in exp.warnings) and exp.scenario.specimen.height == pytest.approx(1e-3)
    # 0.2 mm: less than the contact core (1.5 contact radii and a cell): refused, naming the key
    with pytest.raises(ConfigError, match=r"specimen.thickness.*leaves no room below the contact core"):
        load_config(_cone_config(tmp_path, 'thickness = 0.2, length_unit = "mm"', name="thin"))
    with pytest.raises(ConfigError, match=r"specimen.thickness.*positive length"):
        load_config(_cone_config(tmp_path, "thickness = -1.0", name="neg"))
    with pytest.raises(ConfigError, match=r"specimen.thickness.*not used with size"):
        load_config(_cone_config(tmp_path, 'thickness = 1.0, size = [4, 4, 2], cells = [4, 4, 4], length_unit = "mm"', name="size"))
