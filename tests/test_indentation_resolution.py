"""The automatic indentation specimen: the resolution rule and the config's default.

The convergence study behind the rule's constants (minutes of CPU) is
``experiments/indentation_resolution.py`` with its table in docs/experiments.md; here the
rule's geometry, its refusals and the config's use of it are checked, without a solve.
"""

import math

import numpy as np
import pytest

from difftissue.errors import ConfigError
from difftissue.scenarios import (CELL_GROWTH, CELLS_PER_CONTACT_RADIUS, CONTACT_CORE, HALF_SPACE_EXTENT, INDENTATION_FORCE_ERROR,
                                  indentation_specimen_for)

R, D = 1e-3, 2e-5  # a sphere of 1 mm to 20 um: a = sqrt(R d) = 141.4 um


def test_sphere_rule_gives_the_documented_block():
    s = indentation_specimen_for("sphere", radius=R, max_depth=D, cells_per_contact_radius=4)
    a = math.sqrt(R * D)
    assert s.contact_radius == pytest.approx(a, rel=1e-12)
    assert s.refine == pytest.approx(a / 4, rel=1e-12) and s.core == pytest.approx(1.5 * a, rel=1e-12)
    assert s.symmetry == "quarter" and not s.thickness_given
    assert s.size == pytest.approx((400 * a, 400 * a, 200 * a), rel=1e-12)
    # 6 core cells, then ceil(log(1 + 198.5 a * 0.3 / (a/4)) / log 1.3) = 21 graded ones
    assert s.cells == (27, 27, 27)
    C, p = INDENTATION_FORCE_ERROR["sphere"]
    assert s.force_error == pytest.approx(C * 4.0 ** (-p), rel=1e-12)
    mesh = s.block()
    pts = np.asarray(mesh.points)
    for axis, length in ((0, 200 * a), (2, 200 * a)):
        x = np.unique(pts[:, axis])
        h = np.diff(x) if axis == 0 else np.diff(x)[::-1]  # z: finest under the top surface
        np.testing.assert_allclose(h[:6], a / 4, rtol=1e-9)  # the uniform contact core
        assert np.max(h[1:] / h[:-1]) <= CELL_GROWTH * (1 + 1e-9)  # growth outside it
        assert x[-1] - x[0] == pytest.approx(length, rel=1e-12)


def test_default_resolution_and_cone_contact_radius():
    s = indentation_specimen_for("sphere", radius=R, max_depth=D)
    assert s.cells_per_contact_radius == CELLS_PER_CONTACT_RADIUS
    assert s.core == pytest.approx(CONTACT_CORE * s.contact_radius) and s.size[0] == pytest.approx(2 * HALF_SPACE_EXTENT * s.contact_radius)
    theta = math.radians(70.0)
    c = indentation_specimen_for("cone", half_angle=theta, max_depth=1e-4, cells_per_contact_radius=3)
    assert c.contact_radius == pytest.approx(2e-4 * math.tan(theta) / math.pi, rel=1e-12)
    assert c.refine == pytest.approx(c.contact_radius / 3, rel=1e-12)
    assert c.force_error is None  # not measured for a cone: no number rather than the sphere's


@pytest.mark.parametrize("indenter, kw, thickness", [("sphere", {"radius": R}, None), ("cone", {"half_angle": math.radians(70.0)}, 3e-3)])
def test_coarser_is_the_same_rule_at_half_the_resolution(indenter, kw, thickness):
    """The discretisation check's coarser block differs from the chosen one in resolution only:
    the rule itself at m / 2 (same size and core, first cells exactly doubled, far field graded
    by the same growth), so the Richardson pair has cell size ratio 2."""
    d = D if indenter == "sphere" else 1e-4
    fine = indentation_specimen_for(indenter, max_depth=d, thickness=thickness, cells_per_contact_radius=4, **kw)
    coarse = fine.coarser()
    same = indentation_specimen_for(indenter, max_depth=d, thickness=thickness, cells_per_contact_radius=2, **kw)
    assert coarse.cells == same.cells and coarse.size == fine.size == same.size and coarse.core == fine.core
    assert coarse.refine == pytest.approx(same.refine, rel=1e-14) and coarse.refine / fine.refine == 2.0
    assert coarse.cells_per_contact_radius == 2.0 and coarse.force_error == same.force_error
    assert coarse.indenter == indenter and coarse.thickness_given == (thickness is not None)
    pts_c, pts_s = np.asarray(coarse.block().points), np.asarray(same.block().points)
    np.testing.assert_allclose(pts_c, pts_s, rtol=0, atol=1e-12 * fine.size[0])
    h = np.diff(np.unique(pts_c[:, 0]))
    np.testing.assert_allclose(h[:3], 2 * fine.refine, rtol=1e-9)  # core 1.5 a = 3 cells of a/2
    assert np.max(h[1:] / h[:-1]) <= CELL_GROWTH * (1 + 1e-9)
    with pytest.raises(ConfigError, match="fewer than one"):
        coarse.coarser(3.0)
    with pytest.raises(ConfigError, match="factor must be > 1"):
        fine.coarser(1.0)


def test_given_thickness_is_the_specimens_own():
    s = indentation_specimen_for("sphere", radius=R, max_depth=D, thickness=2e-3, cells_per_contact_radius=4)
    assert s.thickness_given and s.size[2] == 2e-3 and s.size[0] == pytest.approx(400 * math.sqrt(R * D))
    assert np.unique(np.asarray(s.block().points)[:, 2])[-1] == pytest.approx(2e-3)
    with pytest.raises(ConfigError, match="no room below the contact core"):
        indentation_specimen_for("sphere", radius=R, max_depth=D, thickness=1.5 * math.sqrt(R * D))


@pytest.mark.parametrize("kw, match", [
    ({"indenter": "flat_punch", "radius": R}, "flat punch"),
    ({"indenter": "sphere"}, "positive radius"),
    ({"indenter": "cone", "half_angle": 2.0}, "half-angle"),
    ({"indenter": "sphere", "radius": R, "model": "springs_volume"}, "springs_volume"),
    ({"indenter": "sphere", "radius": R, "cells_per_contact_radius": 0.5}, "cells_per_contact_radius"),
])
def test_rule_refuses_what_it_cannot_choose(kw, match):
    kw = dict(kw)
    ind = kw.pop("indenter")
    with pytest.raises(ConfigError, match=match):
        indentation_specimen_for(ind, max_depth=D, **kw)


_TOML = """
[material]
youngs_modulus = 1e4
poisson_ratio = 0.45
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "sphere"
scenario = "indentation"
{model}
data = {{ format = "table", path = "curve.csv", columns = {{ depth = "depth (um)", force = "force (uN)" }} }}
indenter = {{ shape = "{shape}", {size} length_unit = "mm" }}
length_unit = "um"
{extra}
"""


@pytest.fixture(scope="module")
def curve_dir(tmp_path_factory):
    from difftissue import analytic

    d = np.linspace(2e-6, D, 5)
    f = np.asarray(analytic.hertz_force(d, 1e4, 0.45, R))
    path = tmp_path_factory.mktemp("curve") / "curve.csv"
    path.write_text("depth (um),force (uN)\n" + "\n".join(f"{a * 1e6:.6f},{b * 1e6:.10f}" for a, b in zip(d, f)) + "\n")
    return path.parent


def test_config_3d_automatic_specimen_builds_the_chosen_block(curve_dir):
    from difftissue.config import load_config

    (curve_dir / "auto.toml").write_text(_TOML.format(model='model = "fem_linear"', shape="sphere", size="radius = 1.0,",
                                                      extra='specimen = { geometry = "3d" }'))
    exp = load_config(curve_dir / "auto.toml").experiments[0]
    chosen = indentation_specimen_for("sphere", radius=R, max_depth=D)
    sc = getattr(exp.scenario, "scenario", exp.scenario)
    np.testing.assert_allclose(np.asarray(sc.model.rest_points), np.asarray(chosen.block().points), rtol=0, atol=1e-15)
    assert sc.symmetry == "quarter" and sc.force_multiplier == 4
    assert any("specimen chosen automatically" in n and f"cells {list(chosen.cells)}" in n for n in exp.notes)
    # the discretisation check's coarser block carries the rule's record into the estimate
    # (the rule at half the cells per contact radius, cell size ratio exactly 2)
    coarse_sc, info = exp.coarsen()
    assert info["specimen"] == chosen.record() and info["fine_cells"] == list(chosen.cells)
    assert info["coarse_cells"] == list(chosen.coarser().cells) and info["refinement_ratio"] == 2.0
    coarse_sc = getattr(coarse_sc, "scenario", coarse_sc)
    np.testing.assert_allclose(np.asarray(coarse_sc.model.rest_points), np.asarray(chosen.coarser().block().points), rtol=0, atol=1e-15)


@pytest.mark.parametrize("model, shape, size, match", [
    ("", "sphere", "radius = 1.0,", "springs_volume"),  # the scenario's default model
    ('model = "fem_linear"', "flat_punch", "radius = 0.5,", "flat punch"),
])
def test_config_without_specimen_refuses_with_the_key(curve_dir, model, shape, size, match):
    from difftissue.config import load_config

    (curve_dir / "bad.toml").write_text(_TOML.format(model=model, shape=shape, size=size, extra=""))
    with pytest.raises(ConfigError, match=match) as err:
        load_config(curve_dir / "bad.toml")
    assert "specimen" in str(err.value)


@pytest.mark.parametrize("model", ["fem_neo_hookean", "stable_neo_hookean"])
def test_config_without_specimen_is_axisymmetric_for_a_continuum_sphere(curve_dir, model):
    """The default for a sphere or a cone with a continuum model (FEM or stable neo-Hookean):
    the axisymmetric specimen of axisymmetric_specimen_for; its discretisation check's coarser
    meshes every cell times sqrt(2) and 2 (refined(1 / sqrt(2)), refined(0.5)), the order
    observed on the three levels."""
    from difftissue.config import load_config
    from difftissue.scenarios import AxisymmetricIndentation, axisymmetric_specimen_for

    (curve_dir / "axi.toml").write_text(_TOML.format(model=f'model = "{model}"', shape="sphere", size="radius = 1.0,", extra=""))
    exp = load_config(curve_dir / "axi.toml").experiments[0]
    sc = exp.scenario
    chosen = axisymmetric_specimen_for("sphere", radius=R, max_depth=D)
    assert isinstance(sc, AxisymmetricIndentation) and sc.specimen == chosen and exp.model == model
    assert sc.model.base.kind == model
    assert sc.record()["geometry"] == "axisymmetric"
    assert any("specimen chosen automatically" in n and "axisymmetric, 8 cells per contact radius" in n for n in exp.notes)
    coarse_sc, info = exp.coarsen()
    expected = chosen.refined(2 ** -0.5)
    assert coarse_sc.specimen.first == pytest.approx(expected.first, rel=1e-12) and coarse_sc.specimen.growth == pytest.approx(expected.growth, rel=1e-12)
    assert coarse_sc.specimen.height == chosen.height and info["refinement_ratio"] == pytest.approx(2 ** 0.5, rel=1e-12)
    assert "order" not in info and info["specimen"] == chosen.record()
    coarser_sc, coarser_cells = info["coarser"]()
    assert coarser_sc.specimen == chosen.refined(0.5) and coarser_sc.specimen.first / coarse_sc.specimen.first == pytest.approx(2 ** 0.5, rel=1e-12)
    assert info["fine_cells"] == "axisymmetric, 8 cells per contact radius" and info["coarse_cells"] == "axisymmetric, 5.65685 cells per contact radius"
    assert coarser_cells == "axisymmetric, 4 cells per contact radius"
    np.testing.assert_allclose(exp.provenance["resolution"]["cells_per_contact_radius_range"][1], 8.0, rtol=1e-6)


def test_config_cells_per_contact_radius_sets_the_automatic_resolution(curve_dir):
    from difftissue.config import load_config

    (curve_dir / "axi12.toml").write_text(_TOML.format(model='model = "fem_linear"', shape="sphere", size="radius = 1.0,",
                                                       extra='specimen = { geometry = "axisymmetric", cells_per_contact_radius = 12 }'))
    sc = load_config(curve_dir / "axi12.toml").experiments[0].scenario
    assert sc.specimen.cells_per_contact_radius == 12.0


@pytest.mark.parametrize("model, extra, material", [
    ('model = "stable_neo_hookean"', "", "pre_stretch = 1.05"),  # pre-tension: 3-D
    ('model = "fem_linear"', 'specimen = { geometry = "3d" }', ""),
    ('model = "fem_linear"', "", "pre_stretch = 1.1"),  # pre-tension: 3-D
])
def test_config_without_axisymmetric_form_keeps_the_3d_block(curve_dir, model, extra, material):
    from difftissue.config import load_config
    from difftissue.scenarios import Indentation

    text = _TOML.format(model=model, shape="sphere", size="radius = 1.0,", extra=extra).replace("poisson_ratio = 0.45", "poisson_ratio = 0.45\n" + material)
    (curve_dir / "three.toml").write_text(text)
    exp = load_config(curve_dir / "three.toml").experiments[0]
    sc = getattr(exp.scenario, "scenario", exp.scenario)
    assert isinstance(sc, Indentation) and sc.symmetry == "quarter"
    note = next(n for n in exp.notes if "specimen chosen automatically" in n)
    assert ("not axisymmetric" in note) == (extra == "")  # the fallback says why


@pytest.mark.parametrize("model, shape, size, extra, match", [
    ('model = "springs_volume"', "sphere", "radius = 1.0,", 'specimen = { geometry = "axisymmetric" }', "model 'springs_volume'"),
    ('model = "fem_linear"', "flat_punch", "radius = 0.5,", 'specimen = { geometry = "axisymmetric" }', "a flat_punch indenter"),
    ('model = "fem_linear"', "sphere", "radius = 1.0,", 'specimen = { geometry = "axisymmetric", size = [2, 2, 1] }', r"specimen\.size: not used"),
    ('model = "fem_linear"', "sphere", "radius = 1.0,", 'specimen = { geometry = "2d" }', r"specimen\.geometry"),
    ('model = "fem_linear"', "sphere", "radius = 1.0,", 'specimen = { size = [2, 2, 1], cells_per_contact_radius = 8 }', "cells_per_contact_radius"),
    ('model = "fem_linear"', "sphere", "radius = 1.0,", 'specimen = { geometry = "axisymmetric" }\nrollers = ["x-min"]', "rollers"),
])
def test_config_axisymmetric_refuses_what_it_cannot_simulate(curve_dir, model, shape, size, extra, match):
    from difftissue.config import load_config

    (curve_dir / "badaxi.toml").write_text(_TOML.format(model=model, shape=shape, size=size, extra=extra))
    with pytest.raises(ConfigError, match=match) as err:
        load_config(curve_dir / "badaxi.toml")
    assert "specimen" in str(err.value) or "rollers" in str(err.value)


def test_config_axisymmetric_refuses_a_fitted_pre_stretch(curve_dir):
    from difftissue.config import load_config

    text = _TOML.format(model='model = "fem_linear"', shape="sphere", size="radius = 1.0,", extra='specimen = { geometry = "axisymmetric" }')
    text = text.replace('parameters = ["youngs_modulus"]', 'parameters = ["youngs_modulus", "pre_stretch"]\nbounds = { pre_stretch = [0.9, 1.5] }')
    (curve_dir / "prestretch.toml").write_text(text)
    with pytest.raises(ConfigError, match=r"specimen\.geometry.*pre-stretch \(pre_stretch set or fitted"):
        load_config(curve_dir / "prestretch.toml")
