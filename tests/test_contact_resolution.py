"""Resolution of the contact zone at each depth of a simulated indentation: the contact radius
formulas, the cell size under the indenter, the named warning for depths below the threshold,
and the config's ``min_cells_per_contact_radius`` / ``under_resolved`` options. Small meshes,
no solve except the one CLI fit."""

import json
import math
import warnings

import jax
import numpy as np
import pytest

from difftissue import analytic
from difftissue.errors import ConfigError, UnderResolvedContactWarning
from difftissue.scenarios import (MIN_CELLS_PER_CONTACT_RADIUS, Indentation, indentation_block, indentation_contact_radius,
                                  indentation_specimen_for)

THETA = math.radians(70.0)


@pytest.mark.parametrize("indenter, kw, force", [
    ("sphere", {"radius": 1e-3}, lambda d, E, nu: analytic.hertz_force(d, E, nu, 1e-3)),
    ("cone", {"half_angle": THETA}, lambda d, E, nu: analytic.cone_force(d, E, nu, THETA)),
    ("flat_punch", {"radius": 0.5e-3}, lambda d, E, nu: analytic.flat_punch_force(d, E, nu, 0.5e-3)),
])
def test_contact_radius_is_the_analytic_one_and_gives_the_contact_stiffness(indenter, kw, force):
    """Against the closed forms, and independently through the half-space relation every
    axisymmetric frictionless indenter obeys: the contact stiffness dF/dd = 2 E* a."""
    d = np.array([1e-6, 5e-6, 2e-5, 1e-4])
    a = indentation_contact_radius(indenter, d, **kw)
    closed = {"sphere": np.sqrt(1e-3 * d), "cone": 2 * d * math.tan(THETA) / math.pi, "flat_punch": np.full_like(d, 0.5e-3)}[indenter]
    np.testing.assert_allclose(a, closed, rtol=1e-12)
    ref = {"sphere": analytic.hertz_contact_radius, "cone": analytic.cone_contact_radius, "flat_punch": analytic.flat_punch_contact_radius}[indenter]
    np.testing.assert_allclose(a, np.asarray(ref(d, next(iter(kw.values())))), rtol=1e-12)
    E, nu = 1e4, 0.45
    stiffness = np.asarray(jax.vmap(jax.grad(lambda x: force(x, E, nu)))(d))
    np.testing.assert_allclose(stiffness, 2 * analytic.indentation_modulus(E, nu) * a, rtol=1e-10)


def test_contact_radius_refuses_unknown_or_incomplete_indenters():
    with pytest.raises(ConfigError, match="indenter must be"):
        indentation_contact_radius("wedge", [1e-6])
    with pytest.raises(ConfigError, match="half_angle"):
        indentation_contact_radius("cone", [1e-6])


def _cone_on_block(depths, size=(2e-3, 2e-3, 1e-3), symmetry="quarter"):
    # 0.25 mm cubes: a quarter's cells span its half-width
    mesh = indentation_block(size, (4, 4, 4) if symmetry == "quarter" else (8, 8, 4), symmetry=symmetry)
    return Indentation(mesh, depths, model="fem_linear", indenter="cone", half_angle=THETA, symmetry=symmetry)


@pytest.mark.parametrize("symmetry", ["quarter", "none"])
def test_cell_size_under_the_indenter_of_a_uniform_block(symmetry):
    sc = _cone_on_block([1e-4, 2e-4], symmetry=symmetry)
    r = sc.resolution()
    assert r.cell_size == pytest.approx(0.25e-3, rel=1e-9)
    np.testing.assert_allclose(r.cells_per_contact_radius, 2 * np.array([1e-4, 2e-4]) * math.tan(THETA) / math.pi / 0.25e-3, rtol=1e-9)


def test_cell_size_of_the_automatic_specimen_is_its_first_cell():
    s = indentation_specimen_for("cone", half_angle=THETA, max_depth=1e-4, extent=8.0)
    sc = Indentation(s.block(), [1e-5, 1e-4], model="fem_linear", indenter="cone", half_angle=THETA, symmetry="quarter")
    r = sc.resolution()
    assert r.cell_size == pytest.approx(s.refine, rel=1e-9)
    np.testing.assert_allclose(r.cells_per_contact_radius, [0.4, 4.0], rtol=1e-6)  # a / refine = 4 at the deepest point


def test_cell_size_on_a_curved_surface():
    """surface="boundary": the surface spacing along the dome near the placed indenter's axis
    (0.25 mm cells, a 2 mm dome: slightly more than 0.25 mm along the slope)."""
    from difftissue.mesh import block, curved_top

    dome = curved_top(block((2e-3, 2e-3, 1e-3), (8, 8, 4), origin=(-1e-3, -1e-3, 0.0)), 2e-3)
    r = Indentation(dome, [2e-6, 2e-5, 1e-4], model="fem_linear", indenter="sphere", radius=1e-3, surface="boundary").resolution()
    assert r.cell_size == pytest.approx(0.25e-3, rel=0.01)
    np.testing.assert_allclose(r.cells_per_contact_radius, np.sqrt(1e-3 * np.array([2e-6, 2e-5, 1e-4])) / r.cell_size, rtol=1e-12)
    assert list(r.flagged) == [0, 1]


def test_warning_fires_for_a_shallow_cone_depth_only():
    """The automatic specimen's 4 cells per contact radius at the deepest point leave 0.4 cells
    at a tenth of the depth: flagged and named; the deepest point alone is not."""
    s = indentation_specimen_for("cone", half_angle=THETA, max_depth=1e-4, extent=8.0)
    mesh = s.block()
    sc = Indentation(mesh, [1e-5, 5e-5, 1e-4], model="fem_linear", indenter="cone", half_angle=THETA, symmetry="quarter", name="tip")
    r = sc.resolution()
    assert list(r.flagged) == [0] and list(r.keep) == [False, True, True]
    with pytest.warns(UnderResolvedContactWarning) as rec:
        msg = r.warn()
    assert msg == str(rec[0].message)
    assert "tip: 1 of 3 depths" in msg and "1e-05 m (0.4)" in msg and "under_resolved" in msg
    assert r.record()["flagged"] == [{"index": 0, "depth": 1e-5, "contact_radius": pytest.approx(2e-5 * math.tan(THETA) / math.pi),
                                       "cells_per_contact_radius": pytest.approx(0.4, rel=1e-6)}]
    deep = Indentation(mesh, [5e-5, 1e-4], model="fem_linear", indenter="cone", half_angle=THETA, symmetry="quarter").resolution()
    assert deep.flagged.size == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert deep.warn() is None
    # a stricter threshold flags the 2-cell depth too
    assert list(sc.resolution(2.5).flagged) == [0, 1]
    with pytest.raises(ConfigError, match="min_cells_per_contact_radius"):
        sc.resolution(0.0)


def test_flat_punch_has_its_radius_at_every_depth():
    mesh = indentation_block((2e-3, 2e-3, 1e-3), (4, 4, 4), symmetry="quarter")
    r = Indentation(mesh, [1e-5, 1e-4], model="fem_linear", indenter="flat_punch", radius=0.6e-3, symmetry="quarter").resolution()
    np.testing.assert_allclose(r.cells_per_contact_radius, [2.4, 2.4], rtol=1e-9)
    assert r.flagged.size == 0 and MIN_CELLS_PER_CONTACT_RADIUS == 1.0


_TOML = """title = "cone resolution"
[material]
youngs_modulus = 1e4
poisson_ratio = 0.45
[fit]
parameters = ["youngs_modulus"]
discretisation_check = false
[[experiment]]
name = "cone"
scenario = "indentation"
model = "fem_linear"
data = {{ format = "table", path = "curve.csv", columns = {{ depth = "depth (um)", force = "force (uN)" }} }}
indenter = {{ shape = "cone", half_angle_deg = 70.0 }}
specimen = {{ size = [2.0, 2.0, 1.0], cells = [4, 4, 4], symmetry = "quarter", length_unit = "mm" }}
length_unit = "um"
{extra}
"""
DEPTHS = np.linspace(0.05e-3, 0.5e-3, 5)  # a / h = 0.35, 1.14, 1.92, 2.71, 3.50 on 0.25 mm cells


@pytest.fixture(scope="module")
def curve_dir(tmp_path_factory):
    f = np.asarray(analytic.cone_force(DEPTHS, 1e4, 0.45, THETA))
    path = tmp_path_factory.mktemp("cone") / "curve.csv"
    path.write_text("depth (um),force (uN)\n" + "\n".join(f"{a * 1e6:.6f},{b * 1e6:.10f}" for a, b in zip(DEPTHS, f)) + "\n")
    return path.parent


def _load(curve_dir, extra=""):
    from difftissue.config import load_config

    (curve_dir / "fit.toml").write_text(_TOML.format(extra=extra))
    return load_config(curve_dir / "fit.toml")


def test_config_warns_by_default_and_keeps_the_depths(curve_dir):
    with pytest.warns(UnderResolvedContactWarning, match=r"1 of 5 depths.*5e-05 m \(0.35\)"):
        cfg = _load(curve_dir)
    exp = cfg.experiments[0]
    sc = getattr(exp.scenario, "scenario", exp.scenario)
    assert np.asarray(sc.abscissa).size == 5  # the data are the user's: nothing dropped by default
    assert any("a contact radius of less than 1 mesh cells" in w for w in cfg.data_warnings)
    res = exp.provenance["resolution"]
    assert res["under_resolved"] == "warn" and res["cell_size"] == pytest.approx(0.25e-3)
    assert [(f["row"], round(f["cells_per_contact_radius"], 2)) for f in res["flagged"]] == [(exp.provenance["used"][0], 0.35)]


def test_config_drop_leaves_the_flagged_depths_out_and_says_so(curve_dir):
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnderResolvedContactWarning)
        cfg = _load(curve_dir, 'under_resolved = "drop"\nmin_cells_per_contact_radius = 2.5')
    exp = cfg.experiments[0]
    sc = getattr(exp.scenario, "scenario", exp.scenario)
    np.testing.assert_allclose(np.asarray(sc.abscissa), DEPTHS[3:], rtol=1e-9)
    assert np.asarray(sc.observed).size == 2 and not cfg.data_warnings
    prov = exp.provenance
    assert prov["rows_used"] == 2 and len(prov["used"]) == 2
    step = prov["steps"][-1]
    assert step["action"] == "left out" and len(step["rows"]) == 3 and "less than 2.5 mesh cells" in step["reason"]
    assert [f["row"] for f in prov["resolution"]["flagged"]] == step["rows"]
    assert any("the fit uses 2 of the 5 rows" in n for n in exp.notes)
    coarse, _ = exp.coarsen()
    assert np.asarray(getattr(coarse, "scenario", coarse).abscissa).size == 2


@pytest.mark.parametrize("extra, match", [
    ('under_resolved = "ignore"', "under_resolved"),
    ("min_cells_per_contact_radius = -1", "min_cells_per_contact_radius"),
    ('under_resolved = "drop"\nmin_cells_per_contact_radius = 10', "nothing is left to fit"),
])
def test_config_refuses_bad_options(curve_dir, extra, match):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnderResolvedContactWarning)
        with pytest.raises(ConfigError, match=match):
            _load(curve_dir, extra)


def test_cli_fit_lists_the_flagged_depths_in_fit_json_and_report(curve_dir, tmp_path):
    """A real (small) fit: the warning reaches the console, fit.json (data_warnings, and the
    flagged depths under data_rows[].resolution) and report.md's Warnings."""
    from difftissue.cli import main

    (curve_dir / "fit.toml").write_text(_TOML.format(extra=""))
    out = tmp_path / "out"
    assert main(["fit", str(curve_dir / "fit.toml"), "--out", str(out)]) == 0
    rec = json.loads((out / "fit.json").read_text())
    flagged = rec["data_rows"][0]["resolution"]["flagged"]
    assert len(flagged) == 1 and flagged[0]["depth"] == pytest.approx(DEPTHS[0]) and flagged[0]["cells_per_contact_radius"] == pytest.approx(0.35, abs=0.005)
    assert any("1 of 5 depths" in w for w in rec["data_warnings"])
    report = (out / "report.md").read_text()
    assert "1 of 5 depths have a contact radius of less than 1 mesh cells" in report and "5e-05 m (0.35)" in report
