"""Fit configs: every bad key fails with one line naming it; `difftissue fit` end to end
(outputs, refusal to overwrite, resume); the example configs build."""

import copy
import hashlib
import json
from pathlib import Path

import jax
import numpy as np
import pytest

from difftissue import analytic
from difftissue.cli import main
from difftissue.config import SeparatelyCompiled, load_config, parse_config
from difftissue.errors import ConfigError, DifftissueError

ROOT = Path(__file__).resolve().parents[1]
E_TRUE, NU, R = 2.0e3, 0.45, 1.0e-3


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (int, float)):
        return repr(v) if np.isfinite(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(v)


def dump_toml(cfg: dict) -> str:
    """Just enough TOML writing for these tests: top-level scalars and tables, arrays of tables."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in cfg.items() if not isinstance(v, (dict, list)) or (isinstance(v, list) and not all(isinstance(x, dict) for x in v))]
    for k, v in cfg.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                lines += ["", f"[[{k}]]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def hertz_csv(tmp_path_factory):
    """A synthetic Hertz curve (E = 2 kPa, nu = 0.45, R = 1 mm) with 1 % noise, in um and uN."""
    d = np.linspace(5e-6, 100e-6, 30)
    f = np.asarray(analytic.hertz_force(d, E_TRUE, NU, R))
    f = f * (1 + 0.01 * np.random.default_rng(1).standard_normal(d.size))
    path = tmp_path_factory.mktemp("data") / "curve.csv"
    path.write_text("depth (um),force (uN)\n" + "\n".join(f"{a * 1e6:.6f},{b * 1e6:.8f}" for a, b in zip(d, f)) + "\n")
    return path


def base_config(csv: Path) -> dict:
    return {
        "title": "synthetic Hertz",
        "material": {"youngs_modulus": 1.0e3, "poisson_ratio": NU},
        "fit": {"parameters": ["youngs_modulus"]},
        "experiment": [
            {
                "name": "hertz",
                "scenario": "analytic_indentation",
                "data": {"format": "table", "path": csv.name, "columns": {"depth": "depth (um)", "force": "force (uN)"}},
                "indenter": {"shape": "sphere", "radius": 1.0, "length_unit": "mm"},
                "points": "all",
            }
        ],
    }


def _set(cfg: dict, path: str, value):
    """Set ``a.b[0].c`` in a nested config; ``value=DELETE`` removes the key."""
    keys = []
    for part in path.split("."):
        name, _, idx = part.partition("[")
        keys.append(name)
        if idx:
            keys.append(int(idx.rstrip("]")))
    node = cfg
    for k in keys[:-1]:
        node = node[k]
    if value is DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value


DELETE = object()

# (key to change, new value, the start of the expected one-line message)
BAD = [
    ("colour", "red", "config: unknown key 'colour'; allowed:"),
    ("material", DELETE, "material: missing"),
    ("material.youngs_modulus", -5.0, "material.youngs_modulus: must be a positive number in Pa, got -5.0"),
    ("material.youngs_modulus", "1 kPa", "material.youngs_modulus: must be a positive number in Pa, got '1 kPa'"),
    ("material.poisson_ratio", 0.5, "material.poisson_ratio: must be a number in (-1, 0.5)"),
    ("material.poisson_ratio", DELETE, "material.poisson_ratio: missing"),
    ("material.density", 0, "material.density: must be a positive number"),
    ("material.stiffness", 1.0, "material: unknown key 'stiffness'; allowed: youngs_modulus"),
    ("fit.parameters", [], "fit.parameters: must be a non-empty list"),
    ("fit.parameters", ["youngs_modulus", "shear_modulus"], "fit.parameters[1]: unknown material field 'shear_modulus'"),
    ("fit.parameters", ["youngs_modulus", "youngs_modulus"], "fit.parameters[1]: 'youngs_modulus' is listed twice"),
    ("fit.method", "newton", "fit.method: must be one of 'levenberg_marquardt'"),
    ("fit.loss", "cauchy", "fit.loss: must be one of 'linear'"),
    ("fit.starts", 0, "fit.starts: must be an integer >= 1, got 0"),
    ("fit.max_steps", 2.5, "fit.max_steps: must be an integer >= 0, got 2.5"),
    ("fit.rtol", -1.0, "fit.rtol: must be a positive number"),
    ("fit.absolute_sigma", "yes", "fit.absolute_sigma: must be true or false"),
    ("fit.bounds", {"poisson_ratio": [0.0, 0.499]}, "fit.bounds.poisson_ratio: 'poisson_ratio' is not fitted"),
    ("fit.bounds", {"youngs_modulus": [5e3, 1e4]}, "fit.bounds.youngs_modulus: the initial value material.youngs_modulus = 1000 must lie strictly inside [5000, 10000]"),
    ("fit.bounds", {"youngs_modulus": [10.0]}, "fit.bounds.youngs_modulus: must be [lower, upper]"),
    ("fit.bounds", {"youngs_modulus": [-1.0, 1e5]}, "fit.bounds.youngs_modulus: the lower bound of youngs_modulus must be >= 0"),
    ("fit.bounds", {"youngs_modulus": [2e3, 1e2]}, "fit.bounds.youngs_modulus: needs lower < upper"),
    ("fit.bounds", {"youngs_modulus": [float("-inf"), 1e5]}, "fit.bounds.youngs_modulus: the lower bound of youngs_modulus must be >= 0"),
    ("fit.verbose", True, "fit: unknown key 'verbose'; allowed: parameters"),
    ("experiment", [], "experiment: must be one or more [[experiment]] tables"),
    ("experiment[0].scenario", DELETE, "experiment[0].scenario: missing (required); one of analytic_indentation"),
    ("experiment[0].scenario", "tensile", "experiment[0].scenario: must be one of 'analytic_indentation'"),
    ("experiment[0].sise", 3, "experiment[0]: unknown key 'sise'; allowed: name, scenario, data"),
    ("experiment[0].model", "springs_volume", "experiment[0]: unknown key 'model'"),
    ("experiment[0].name", "", "experiment[0].name: must be a non-empty string"),
    ("experiment[0].data", DELETE, "experiment[0].data: missing"),
    ("experiment[0].data", "curve.csv", "experiment[0].data: must be a table"),
    ("experiment[0].data.format", "instron", "experiment[0].data.format: must be one of 'chiaro', 'table'; got 'instron'"),
    ("experiment[0].data.format", DELETE, "experiment[0].data.format: missing (required)"),
    ("experiment[0].data.path", "nosuch.csv", "experiment[0].data.path: file not found:"),
    ("experiment[0].data.path", DELETE, "experiment[0].data.path: missing"),
    ("experiment[0].data.kind", "compression", "experiment[0].data.kind: a analytic_indentation experiment needs a 'force_depth' table"),
    ("experiment[0].data.columns", {"depth": "depth (um)", "force": "load (N)"}, "experiment[0].data:"),
    ("experiment[0].data.columns", {"depth": {"name": "depth (um)", "unit": "m", "override_header_unit": True}, "force": "force (uN)"}, "experiment[0].data:"),
    ("experiment[0].indenter", DELETE, "experiment[0].indenter: missing (required)"),
    ("experiment[0].indenter.radius", -1, "experiment[0].indenter.radius: must be a positive length in mm, got -1"),
    ("experiment[0].indenter.radius", DELETE, "experiment[0].indenter.radius: missing (required for a sphere)"),
    ("experiment[0].indenter.radius", "instrument", "experiment[0].indenter.radius: \"instrument\": the data file records no tip radius"),
    ("experiment[0].indenter.shape", "pyramid", "experiment[0].indenter.shape: must be one of 'sphere', 'flat_punch', 'cone'"),
    ("experiment[0].indenter.length_unit", "inch", "experiment[0].indenter.length_unit: must be one of 'm'"),
    ("experiment[0].indenter.half_angle_deg", 30, "experiment[0].indenter.half_angle_deg: not used by a sphere"),
    ("experiment[0].indenter.bonded", True, "experiment[0].indenter.bonded: only a simulated flat punch"),
    ("experiment[0].indenter.colour", "red", "experiment[0].indenter: unknown key 'colour'; allowed: shape, radius"),
    ("experiment[0].points", 1, "experiment[0].points: must be an integer >= 2, got 1"),
    ("experiment[0].points", "some", "experiment[0].points: must be an integer >= 2, got 'some'"),
    ("experiment[0].max_depth", 0.0, "experiment[0].max_depth: must be a positive length in m, got 0.0"),
    ("experiment[0].max_depth", 1e-9, "experiment[0].max_depth: only 0 usable data point(s) up to max_depth = 1e-09 m"),
    ("experiment[0].sigma", -1.0, "experiment[0].sigma: must be a positive number in N, 'rms' or { relative = r }"),
    ("experiment[0].sigma", {"relative": 0}, "experiment[0].sigma.relative: must be a positive fraction"),
    ("experiment[0].sigma", {"absolute": 1}, "experiment[0].sigma: unknown key 'absolute'"),
    ("experiment[0].solution", "exact_layer", "experiment[0].thickness: missing (required by solution = 'exact_layer')"),
    ("experiment[0].thickness", 1e-3, "experiment[0].thickness: not used by solution = 'half_space'"),
    ("experiment[0].base", "glued", "experiment[0].base: must be one of 'bonded', 'lubricated'"),
]


@pytest.mark.parametrize("key,value,message", BAD, ids=[f"{b[0]}={b[1] if b[1] is not DELETE else 'DELETE'}" for b in BAD])
def test_bad_config_fails_with_one_line_naming_the_key(hertz_csv, key, value, message):
    cfg = base_config(hertz_csv)
    _set(cfg, key, value if value is DELETE else copy.deepcopy(value))
    with pytest.raises(DifftissueError) as e:
        parse_config(cfg, base_dir=hertz_csv.parent)
    text = str(e.value)
    assert "\n" not in text
    assert text.startswith(message), text


def test_duplicate_names_and_scenario_specific_keys(hertz_csv):
    cfg = base_config(hertz_csv)
    cfg["experiment"].append(copy.deepcopy(cfg["experiment"][0]))
    with pytest.raises(ConfigError, match=r"^experiment\[1\]\.name: 'hertz' is used by experiment\[0\] too"):
        parse_config(cfg, base_dir=hertz_csv.parent)
    bad = {
        "scenario": "compression",
        "data": {"format": "instron", "path": str(ROOT / "data/compression/EF10_50T_A1.csv")},
        "max_strain": 1.5,
    }
    cfg = base_config(hertz_csv)
    cfg["experiment"] = [bad]
    with pytest.raises(ConfigError, match=r"^experiment\[0\]\.max_strain: must be a strain in \(0, 1\), got 1\.5$"):
        parse_config(cfg, base_dir=hertz_csv.parent)
    for extra, msg in [
        ({"max_strain": 0.3, "specimen": {"shape": "sphere"}}, r"^experiment\[0\]\.specimen\.shape: must be one of 'block', 'cylinder'"),
        ({"max_strain": 0.3, "specimen": {"cells": [2, 0, 2]}}, r"^experiment\[0\]\.specimen\.cells\[1\]: must be an integer >= 1, got 0"),
        ({"max_strain": 0.3, "specimen": {"size": [1, 1]}}, r"^experiment\[0\]\.specimen\.size: must be 3 positive lengths in m"),
        ({"max_strain": 0.3, "specimen": {"shape": "cylinder"}}, r"^experiment\[0\]\.model: a cylinder mesh has no cube lattice"),
        ({"max_strain": 0.3, "platens": "glued"}, r"^experiment\[0\]\.platens: must be one of 'frictionless', 'bonded'"),
        ({"max_strain": 0.3, "model": "xpbd"}, r"^experiment\[0\]\.model: must be one of 'springs_volume'"),
        ({"max_strain": 0.3, "solver": {"max_steps": 0}}, r"^experiment\[0\]\.solver\.max_steps: must be an integer >= 1"),
        ({"max_strain": 0.3, "solver": {"tol": 1e-3}}, r"^experiment\[0\]\.solver: unknown key 'tol'"),
        ({"max_strain": 0.3, "indenter": {"shape": "sphere"}}, r"^experiment\[0\]: unknown key 'indenter'; allowed: name, scenario, data, sigma, points, length_unit, model, specimen"),
    ]:
        cfg["experiment"] = [{**bad, **extra}]
        with pytest.raises(ConfigError, match=msg):
            parse_config(cfg, base_dir=hertz_csv.parent)
    # springs_volume represents nu in [0.25, 0.5) only
    cfg["experiment"] = [{**bad, "max_strain": 0.3}]
    cfg["fit"] = {"parameters": ["youngs_modulus", "poisson_ratio"]}
    with pytest.raises(ConfigError, match=r"^fit\.bounds\.poisson_ratio: the springs_volume model \(experiment\[0\]\) needs nu in \[0\.25, 0\.5\)"):
        parse_config(cfg, base_dir=hertz_csv.parent)
    cfg["fit"] = {"parameters": ["youngs_modulus"]}
    cfg["material"]["poisson_ratio"] = 0.2
    with pytest.raises(ConfigError, match=r"^material\.poisson_ratio: the springs_volume model"):
        parse_config(cfg, base_dir=hertz_csv.parent)
    cfg["material"]["poisson_ratio"] = NU
    # fem_field and indentation specifics (structure checked before any data is read)
    fem = {"scenario": "fem_field", "data": {"format": "fem", "path": "missing.vtu"}}
    for extra, msg in [
        ({}, r"^experiment\[0\]\.prescribed: missing \(required\)"),
        ({"prescribed": []}, r"^experiment\[0\]\.prescribed: must be a non-empty list"),
        ({"prescribed": [{"components": "z"}]}, r"^experiment\[0\]\.prescribed\[0\]\.set: missing"),
        ({"prescribed": [{"set": "bottom", "components": "xw"}]}, r"^experiment\[0\]\.prescribed\[0\]\.components: must be letters from 'xyz'"),
        ({"prescribed": [{"set": 3}]}, r"^experiment\[0\]\.prescribed\[0\]\.set: must be the name of a point-data node set or a selector table"),
        ({"prescribed": [{"set": {"face": "w-min"}}]}, r"^experiment\[0\]\.prescribed\[0\]\.set: "),
        ({"prescribed": [{"set": "b"}], "reaction": {"set": "p", "force": [1.0], "field": "r"}}, r"^experiment\[0\]\.reaction: give exactly one of 'force'"),
        ({"prescribed": [{"set": "b"}], "reaction": {"set": "p", "components": "xz", "force": [1.0]}}, r"^experiment\[0\]\.reaction\.force: must be 2 number\(s\) in N"),
        ({"prescribed": [{"set": "b"}], "force_sigma": 1e-3}, r"^experiment\[0\]\.force_sigma: needs a 'reaction'"),
        ({"prescribed": [{"set": "b"}]}, r"^experiment\[0\]\.data\.path: file not found: .*missing\.vtu$"),
        ({"prescribed": [{"set": "b"}], "points": 10}, r"^experiment\[0\]: unknown key 'points'"),
    ]:
        cfg["experiment"] = [{**fem, **extra}]
        with pytest.raises(DifftissueError, match=msg):
            parse_config(cfg, base_dir=hertz_csv.parent)
    ind = {**base_config(hertz_csv)["experiment"][0], "scenario": "indentation"}
    ind.pop("points")
    for extra, msg in [
        ({}, r"^experiment\[0\]\.specimen: missing \(required\)"),
        ({"specimen": {"cells": [4, 4, 4]}}, r"^experiment\[0\]\.specimen\.size: missing \(required\)"),
        ({"specimen": {"size": [5, 5, 0.05], "length_unit": "mm"}}, r"^experiment\[0\]\.max_depth: the deepest point"),
        ({"specimen": {"size": [5, 5, 5], "length_unit": "mm", "refine": 0.1}}, r"^experiment\[0\]\.specimen\.refine: graded cells are not cubes"),
        ({"specimen": {"size": [5, 5, 5], "symmetry": "half"}}, r"^experiment\[0\]\.specimen\.symmetry: must be one of 'quarter', 'none'"),
        ({"specimen": {"mesh": "nosuch.vtu", "cells": [2, 2, 2]}}, r"^experiment\[0\]\.specimen\.cells: not used with 'mesh'"),
        ({"specimen": {"mesh": "nosuch.vtu"}}, r"^experiment\[0\]\.specimen\.mesh: file not found"),
        ({"specimen": {"size": [5, 5, 5]}, "indenter": {"shape": "flat_punch", "radius": 1e-3}, "penalty": 10.0}, r"^experiment\[0\]\.penalty: not used by a flat punch"),
    ]:
        cfg["experiment"] = [{**ind, **extra}]
        with pytest.raises(ConfigError, match=msg):
            parse_config(cfg, base_dir=hertz_csv.parent)


def test_bounds_become_transforms(hertz_csv):
    from difftissue.materials import Identity, Log, ScaledLogit

    cfg = base_config(hertz_csv)
    cfg["material"]["cubic_coefficient"] = 0.5
    cfg["fit"] = {
        "parameters": ["youngs_modulus", "poisson_ratio", "cubic_coefficient", "density"],
        "bounds": {"poisson_ratio": [0.0, 0.499], "youngs_modulus": [100.0, float("inf")], "cubic_coefficient": [float("-inf"), float("inf")]},
        "method": "gauss_newton",
        "starts": 3,
        "max_steps": 7,
    }
    c = parse_config(cfg, base_dir=hertz_csv.parent)
    t = dict(zip(c.parameterization.fields, c.parameterization.transforms))
    assert isinstance(t["poisson_ratio"], ScaledLogit) and (t["poisson_ratio"].lower, t["poisson_ratio"].upper) == (0.0, 0.499)
    assert isinstance(t["youngs_modulus"], Log) and t["youngs_modulus"].lower == 100.0
    assert isinstance(t["cubic_coefficient"], Identity)
    assert isinstance(t["density"], Log) and t["density"].scale == 1000.0  # u = 0 at the initial value
    u = np.asarray(c.parameterization.pack(c.material))
    np.testing.assert_allclose(u[[0, 3]], 0.0, atol=1e-12)
    assert c.options == {"method": "gauss_newton", "starts": 3, "max_steps": 7}
    assert c.experiments[0].scenario.abscissa.size == 30 and c.data_files == (hertz_csv,)
    # inf in a TOML file too
    (hertz_csv.parent / "inf.toml").write_text(dump_toml(cfg))
    assert isinstance(dict(zip(c.parameterization.fields, load_config(hertz_csv.parent / "inf.toml").parameterization.transforms))["cubic_coefficient"], Identity)


def test_points_keep_measured_samples_evenly_in_depth(hertz_csv):
    cfg = base_config(hertz_csv)
    cfg["experiment"][0]["points"] = 5
    cfg["experiment"][0]["max_depth"] = 50e-6
    sc = parse_config(cfg, base_dir=hertz_csv.parent).scenarios[0]
    all_d = parse_config(base_config(hertz_csv), base_dir=hertz_csv.parent).scenarios[0].abscissa
    assert sc.abscissa.size == 5 and np.all(np.isin(sc.abscissa, all_d)) and np.all(np.diff(sc.abscissa) > 0)
    assert sc.abscissa.max() <= 50e-6 and sc.abscissa.max() > 45e-6


def test_rows_out_of_order_are_refused_or_sorted_and_every_row_is_accounted_for(hertz_csv, tmp_path):
    """Issue 17: unsorted rows used to leave a fit with the few rows before the deepest one."""
    from difftissue.errors import NonMonotonicError

    rows = hertz_csv.read_text().splitlines()
    order = np.random.default_rng(3).permutation(len(rows) - 1)
    shuffled = tmp_path / "curve.csv"
    shuffled.write_text("\n".join([rows[0]] + [rows[1 + i] for i in order]) + "\n")
    cfg = base_config(shuffled)
    with pytest.raises(NonMonotonicError, match=r"^experiment\[0\]\.data: the depth column is not a loading curve") as err:
        parse_config(cfg, base_dir=tmp_path)
    assert err.value.lines and all(2 <= n <= len(rows) for n in err.value.lines)  # file lines, header = line 1
    cfg["experiment"][0]["data"]["sort"] = True
    fc = parse_config(cfg, base_dir=tmp_path)
    ref = parse_config(base_config(hertz_csv), base_dir=hertz_csv.parent)
    np.testing.assert_array_equal(fc.scenarios[0].abscissa, ref.scenarios[0].abscissa)
    np.testing.assert_array_equal(fc.scenarios[0].observed, ref.scenarios[0].observed)
    prov = fc.data_provenance[0]
    assert prov["experiment"] == "hertz" and prov["rows_loaded"] == prov["rows_used"] == len(rows) - 1
    assert [st["action"] for st in prov["steps"]] == ["reordered"]
    assert prov["steps"][0]["rows"] == [int(2 + i) for i in np.argsort(order)]  # the file lines in depth order
    assert "reordered 30" in fc.experiments[0].notes[-1] and fc.data_warnings == []
    (tmp_path / "ref.vtu").write_text("")  # never read: the sort key is refused first
    fem = {"scenario": "fem_field", "data": {"format": "fem", "path": "ref.vtu", "sort": True}, "prescribed": [{"set": "bottom"}]}
    with pytest.raises(ConfigError, match=r"data\.sort: only force-depth \(indentation\) and compression data can be sorted"):
        parse_config({**cfg, "experiment": [fem]}, base_dir=tmp_path)


def test_depths_that_do_not_fit_the_indenter_warn_with_the_likely_unit_mistake(hertz_csv):
    from difftissue.errors import ImplausibleUnitWarning

    assert parse_config(base_config(hertz_csv), base_dir=hertz_csv.parent).data_warnings == []
    cfg = base_config(hertz_csv)
    cfg["experiment"][0]["indenter"]["length_unit"] = "m"  # radius 1 m: the depths are 1e-4 of it
    with pytest.warns(ImplausibleUnitWarning, match=r"0\.0001 x the indenter radius 1 m .*most likely depths given in mm but declared as um"):
        fc = parse_config(cfg, base_dir=hertz_csv.parent)
    assert len(fc.data_warnings) == 1 and fc.data_warnings[0].startswith("experiment[0]: the deepest point 0.0001 m")


# Compression data get the treatment of indentation data (issue 17): rows kept / left out and
# why, unsorted rows refused or sorted, and plausibility warnings for a likely unit mistake.
_EPS = np.linspace(0.02, 0.4, 20)
_STRESS = 3.0e4 * (_EPS + 0.5 * _EPS**3)  # Pa


def _compression_case(case):
    """(column name -> values as written, column specs, extra data keys)."""
    perm = np.random.default_rng(0).permutation(_EPS.size)
    fraction = {"strain": {"name": "strain", "unit": "-"}, "stress": {"name": "stress", "unit": "Pa"}}
    return {
        "clean": ({"strain": _EPS, "stress": _STRESS}, fraction, {}),
        "unsorted": ({"strain": _EPS[perm], "stress": _STRESS[perm]}, fraction, {}),
        "unsorted_sort_true": ({"strain": _EPS[perm], "stress": _STRESS[perm]}, fraction, {"sort": True}),
        "loading_then_unloading": ({"strain": np.r_[_EPS, _EPS[::-1][1:]], "stress": np.r_[_STRESS, 0.7 * _STRESS[::-1][1:]]}, fraction, {}),
        "precontact_rows": ({"strain": np.r_[-0.01, 0.0, _EPS], "stress": np.r_[0.0, 0.0, _STRESS]}, fraction, {}),
        "strain_in_percent_declared_fraction": ({"strain": 100 * _EPS, "stress": _STRESS}, fraction, {}),
        "fractions_declared_percent": ({"strain": _EPS, "stress": _STRESS}, {**fraction, "strain": {"name": "strain", "unit": "%"}}, {}),
        "strain_beyond_0.9": ({"strain": np.linspace(0.05, 0.95, 20), "stress": _STRESS}, fraction, {}),
        "displacement_beyond_height": ({"displacement": 30 * _EPS, "stress": _STRESS},  # mm; height 10 mm
                                       {"displacement": {"name": "displacement", "unit": "mm"}, "stress": fraction["stress"]}, {"height": "10 mm"}),
        "stress_kPa_declared_Pa_soft_gel": ({"strain": _EPS, "stress": _STRESS / 4e4}, fraction, {}),  # E = 0.75 Pa
    }[case]


# case, error (type, message) or None, text of the row record (provenance note), data warning
COMPRESSION_INPUT = [
    ("clean", None, "the fit uses 20 of the 20 rows loaded from curve.csv (every data row of the file)", None),
    ("unsorted", ("NonMonotonicError", "experiment[0].data: the strain column is not a loading curve (nor loading then unloading): its rows are "
                  "out of order at file lines"), None, None),
    ("unsorted_sort_true", None, "reordered 20 (file lines [", None),
    ("loading_then_unloading", None, "left out 19 (file lines [22, 23, 24, 25, 26, 27, ... (19 in all)]): after the largest strain (file line 21): "
                                     "the unloading segment", None),
    ("precontact_rows", None, "left out 2 (file lines [2, 3]): strain <= 0 (at or before the platen touches; the model needs strain > 0)", None),
    ("strain_in_percent_declared_fraction", ("ImplausibleMagnitudeError", "above the plausible range"), None, None),
    ("fractions_declared_percent", None, "uses 20 of the 20", "declared in % and its largest value is 0.4 % (a strain of 0.004): most likely fractions declared as percent"),
    ("strain_beyond_0.9", None, "uses 20 of the 20", "the largest nominal compressive strain used is 0.95, beyond 0.9"),
    ("displacement_beyond_height", ("ConfigError", "experiment[0].data: the largest nominal compressive strain used is 1.2 (>= 1: the platen would "
                                    "pass through the specimen); the strain is displacement / height (displacement in mm, height 0.01 m)"), None, None),
    ("stress_kPa_declared_Pa_soft_gel", None, "uses 20 of the 20", "outside the 1 Pa .. 1e+09 Pa of soft tissue: check the units of the stress"),
]


@pytest.mark.parametrize("case, error, note, warning", COMPRESSION_INPUT, ids=[c[0] for c in COMPRESSION_INPUT])
def test_compression_rows_are_accounted_for_and_unit_mistakes_named(tmp_path, case, error, note, warning):
    import warnings as _w

    from difftissue.errors import ImplausibleUnitWarning

    cols, specs, extra = _compression_case(case)
    names = list(cols)
    (tmp_path / "curve.csv").write_text(",".join(names) + "\n" + "".join(",".join(f"{cols[k][i]:.9g}" for k in names) + "\n" for i in range(len(cols[names[0]]))))
    cfg = {"material": {"youngs_modulus": 1.0e4, "poisson_ratio": 0.45}, "fit": {"parameters": ["youngs_modulus"]},
           "experiment": [{"name": "phantom", "scenario": "compression", "points": "all",
                           "data": {"format": "table", "path": "curve.csv", "columns": specs, **extra}}]}
    if error is not None:
        with pytest.raises(DifftissueError) as err:
            parse_config(cfg, base_dir=tmp_path)
        assert type(err.value).__name__ == error[0] and error[1] in " ".join(str(err.value).split()), str(err.value)
        return
    with _w.catch_warnings(record=True) as caught:
        _w.simplefilter("always")
        fc = parse_config(cfg, base_dir=tmp_path)
    implausible = [str(w.message) for w in caught if issubclass(w.category, ImplausibleUnitWarning)]
    assert implausible == list(fc.data_warnings)
    assert note in fc.experiments[0].notes[-1], fc.experiments[0].notes
    prov = fc.data_provenance[0]
    assert prov["experiment"] == "phantom" and prov["rows_loaded"] == len(cols[names[0]]) and prov["rows_used"] == len(prov["used"])
    assert prov["rows_used"] + sum(len(st["rows"]) for st in prov["steps"] if st["action"] == "left out") == prov["rows_loaded"]
    sc = fc.scenarios[0]
    assert np.all(np.diff(sc.abscissa) > 0) and np.all(sc.abscissa > 0)
    if warning is None:
        assert fc.data_warnings == []
        np.testing.assert_allclose(sc.abscissa, _EPS, rtol=1e-8)  # every case keeps exactly the loading rows with strain > 0
        np.testing.assert_allclose(sc.observed, _STRESS, rtol=1e-8)
    else:
        assert len(fc.data_warnings) == 1 and warning in fc.data_warnings[0] and fc.data_warnings[0].startswith("experiment[0]: ")


def _write(tmp_path, cfg, name="fit.toml"):
    p = tmp_path / name
    p.write_text(dump_toml(cfg))
    return p


@pytest.fixture()
def workdir(tmp_path, hertz_csv):
    (tmp_path / hertz_csv.name).write_bytes(hertz_csv.read_bytes())
    return tmp_path


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda c: _set(c, "experiment[0].indenter.radius", -1), "experiment[0].indenter.radius: must be a positive length in mm, got -1"),
        (lambda c: _set(c, "experiment[0].sise", 3), "experiment[0]: unknown key 'sise'; allowed:"),
        (lambda c: _set(c, "fit.parameters", ["youngs_modulus", "nu"]), "fit.parameters[1]: unknown material field 'nu'"),
    ],
)
def test_cli_bad_config_exits_1_with_one_line(workdir, capsys, edit, message):
    cfg = base_config(workdir / "curve.csv")
    edit(cfg)
    path = _write(workdir, cfg)
    assert main(["fit", str(path), "--out", str(workdir / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"difftissue: error: {message}"), err
    assert not (workdir / "out").exists()  # nothing written for a bad config


def test_cli_invalid_toml_and_missing_file(workdir, capsys):
    bad = workdir / "bad.toml"
    bad.write_text("[material]\nyoungs_modulus = \n")
    assert main(["fit", str(bad), "--out", str(workdir / "o")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "invalid TOML" in err and "line 2" in err
    assert main(["fit", str(workdir / "nosuch.toml"), "--out", str(workdir / "o")]) == 1
    assert "config file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # --out is required (argparse: exit 2)
        main(["fit", str(bad)])
    assert e.value.code == 2


@pytest.mark.filterwarnings("ignore::difftissue.errors.IdentifiabilityWarning")
def test_cli_fit_writes_outputs_refuses_overwrite_and_resumes(workdir, capsys):
    cfg = base_config(workdir / "curve.csv")
    cfg["experiment"][0]["data"]["path"] = "curve.csv"
    path = _write(workdir, cfg)
    out = workdir / "out"
    assert main(["fit", str(path), "--out", str(out), "--no-progress"]) == 0
    stdout = capsys.readouterr().out
    assert "youngs_modulus" in stdout and "converged" in stdout
    for name in ("fit.json", "fit.png", "loss.png", "report.md", "config.toml", "checkpoint/fit.npz"):
        assert (out / name).is_file(), name
    rec = json.loads((out / "fit.json").read_text())
    p = rec["parameters"]["youngs_modulus"]
    assert p["unit"] == "Pa" and p["value"] == pytest.approx(E_TRUE, rel=0.02)
    assert 0 < p["standard_error"] < 0.02 * E_TRUE
    assert rec["fixed_parameters"]["poisson_ratio"]["value"] == NU and rec["converged"] is True
    assert rec["model"] == "hertz" and [s["name"] for s in rec["scenarios"]] == ["hertz"]
    data = workdir / "curve.csv"
    # no host directories (issue 16): the data path relative to the config, the config by name
    assert rec["data_files"] == [{"path": "curve.csv", "sha256": hashlib.sha256(data.read_bytes()).hexdigest()}]
    assert rec["config"]["path"] == path.name and str(workdir) not in (out / "material.json").read_text()
    assert rec["config"]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest() and rec["config"]["content"]["fit"]["parameters"] == ["youngs_modulus"]
    assert (out / "config.toml").read_bytes() == path.read_bytes()

    # refuses to overwrite
    assert main(["fit", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists; refusing to overwrite" in err and "--force" in err
    # a checkpoint alone (an interrupted run) is refused too, naming --resume
    for name in ("fit.json", "fit.png", "loss.png", "report.md", "config.toml"):
        (out / name).unlink()
    assert main(["fit", str(path), "--out", str(out)]) == 1
    assert "--resume" in capsys.readouterr().err
    assert main(["fit", str(path), "--out", str(out), "--force"]) == 0
    capsys.readouterr()

    # interrupted after 1 step, then resumed: same answer as the uninterrupted fit
    cfg["fit"]["max_steps"] = 1
    short = _write(workdir, cfg, "short.toml")
    out2 = workdir / "out2"
    assert main(["fit", str(short), "--out", str(out2)]) == 3  # not converged: the answer is unusable (exit 3), outputs written
    first = json.loads((out2 / "fit.json").read_text())
    assert first["converged"] is False and first["steps"] == 1 and "max_steps" in first["reason"]
    cfg["fit"]["max_steps"] = 100
    short.write_text(dump_toml(cfg))
    assert main(["fit", str(short), "--out", str(out2), "--resume"]) == 0
    resumed = json.loads((out2 / "fit.json").read_text())
    assert resumed["converged"] is True and resumed["steps"] == rec["steps"]
    assert resumed["parameters"]["youngs_modulus"]["value"] == pytest.approx(p["value"], rel=1e-10)
    capsys.readouterr()
    # a checkpoint of another problem (2 starts) is refused with one line
    assert main(["fit", str(short), "--out", str(out2), "--resume", "--starts", "2"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "number of starts" in err


def test_example_and_demo_configs_build():
    paths = sorted((ROOT / "experiments" / "configs").glob("*.toml")) + sorted((ROOT / "difftissue" / "configs").glob("*.toml"))
    kinds = set()
    for p in paths:
        cfg = load_config(p)
        kinds |= {e.kind for e in cfg.experiments}
        for sc in cfg.scenarios:
            assert sc.observed.size >= 2 and np.all(np.isfinite(sc.sigma))
    assert kinds == {"analytic_indentation", "indentation", "compression", "fem_field", "incision"}


def test_runtime_errors_are_reported_in_one_line():
    from difftissue.cli import _runtime_message

    text = "INTERNAL: CpuCallback error calling callback: Traceback (most recent call last):\n  File \"x.py\", line 1\n_EquinoxRuntimeError: static solve did not converge within max_steps Newton steps\n\n------\nAn error occurred"
    assert _runtime_message(RuntimeError(text)) == "static solve did not converge within max_steps Newton steps"


def test_a_failed_evaluation_is_recorded_as_its_message():
    """SeparatelyCompiled keeps the message of an evaluation that raised inside compiled code
    (equinox's runtime error carries the callback's traceback and a paragraph on filter_jit),
    as the discretisation check's reason reports it; it kept the last 300 characters before,
    traceback included."""
    from dataclasses import dataclass

    import equinox as eqx
    import jax.numpy as jnp

    from difftissue import Material
    from difftissue.config import SeparatelyCompiled

    @dataclass(frozen=True, eq=False)
    class Failing:
        name: str
        abscissa: np.ndarray
        observed: np.ndarray
        sigma: np.ndarray
        x_label: str = "load [N]"
        y_label: str = "displacement [m]"

        def predict(self, material):
            e = jnp.atleast_1d(material.youngs_modulus)
            return eqx.error_if(e, e > 100.0, "the test's solve did not converge (raise max_steps)")

    wrapped = SeparatelyCompiled(Failing("failing", np.array([1.0]), np.zeros(1), np.ones(1)), mode="reverse")
    assert np.all(np.isnan(np.asarray(wrapped.evaluate(Material(1e3, 0.3)))))
    assert wrapped.failures == ["the test's solve did not converge (raise max_steps)"]


def test_separately_compiled_scenario_matches_the_scenario():
    from difftissue import Material
    from difftissue.scenarios import AnalyticIndentation

    d = np.linspace(1e-5, 1e-4, 6)
    sc = AnalyticIndentation(d, np.asarray(analytic.hertz_force(d, 2e3, 0.3, 1e-3)), radius=1e-3, name="h")
    m = Material(2e3, 0.3)
    fields = ("youngs_modulus", "poisson_ratio")

    def fn(s):
        return lambda v: s.predict(m.replace(**dict(zip(fields, v))))

    v = jax.numpy.array([2.5e3, 0.35])
    fwd = SeparatelyCompiled(sc, mode="forward")
    np.testing.assert_allclose(fwd.predict(m), sc.predict(m), rtol=1e-13)
    J = np.asarray(jax.jacfwd(fn(sc))(v))
    np.testing.assert_allclose(jax.jit(jax.jacfwd(fn(fwd)))(v), J, rtol=1e-12)
    np.testing.assert_allclose(jax.jacrev(fn(SeparatelyCompiled(sc, mode="reverse")))(v), J, rtol=1e-12)
    V = jax.numpy.array([[1e3, 0.3], [2e3, 0.4]])  # batched calls (several starts) run one by one
    np.testing.assert_allclose(jax.jit(jax.vmap(fn(fwd)))(V), jax.vmap(fn(sc))(V), rtol=1e-13)
    # Jacobians of several starts at once (the fit's multi-start vmap around jacfwd): the
    # tangents of each start go through one call of the one compiled program.
    JV = np.asarray(jax.vmap(jax.jacfwd(fn(sc)))(V))
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.jacfwd(fn(fwd))))(V), JV, rtol=1e-12)
    # jvp and linearize outside a Jacobian (one tangent at a time)
    y, jt = jax.jvp(fn(fwd), (v,), (jax.numpy.array([1.0, 0.0]),))
    np.testing.assert_allclose(jt, J[:, 0], rtol=1e-12)
    # forward mode gives the prediction with its tangents from one call: jvp and jacfwd, not
    # linearize (the fit linearises through its own forward Jacobian, fit._with_forward_jacobian)
    with pytest.raises(ValueError, match="Linearization failed"):
        jax.linearize(fn(fwd), v)
    two = SeparatelyCompiled(sc, mode="forward", n_tangents=2)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(fn(two)))(v), J, rtol=1e-12)
    np.testing.assert_allclose(two.predict(m), sc.predict(m), rtol=1e-13)
    assert fwd.name == "h" and fwd.observed is sc.observed
