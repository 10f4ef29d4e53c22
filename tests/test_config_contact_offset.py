"""`contact_offset = "fit"` in a config: an analytic indentation's contact offset fitted with E
by `difftissue fit` (fit.json / report.md show it, the material card does not); the refusals."""

import json
import warnings

import jax
import numpy as np
import pytest

from difftissue import analytic
from difftissue.cli import main
from difftissue.config import parse_config
from difftissue.errors import ConfigError

from test_config import dump_toml

jax.config.update("jax_enable_x64", True)

E_TRUE, NU, R, OFFSET = 2.0e3, 0.45, 1.0e-3, 1.0e-5


@pytest.fixture()
def late_contact(tmp_path):
    """An exact Hertz curve whose contact point was picked 10 um too late, in um and uN."""
    d = np.linspace(0.0, 100e-6, 30)
    f = np.asarray(analytic.hertz_force(d + OFFSET, E_TRUE, NU, R))
    path = tmp_path / "curve.csv"
    path.write_text("depth (um),force (uN)\n" + "\n".join(f"{a * 1e6:.9f},{b * 1e6:.12e}" for a, b in zip(d, f)) + "\n")
    return path


def config(csv, **extra) -> dict:
    return {
        "material": {"youngs_modulus": 1.0e3, "poisson_ratio": NU},
        "fit": {"parameters": ["youngs_modulus"]},
        "experiment": [{"name": "hertz", "scenario": "analytic_indentation", "points": "all",
                        "data": {"format": "table", "path": csv.name, "columns": {"depth": "depth (um)", "force": "force (uN)"}},
                        "indenter": {"shape": "sphere", "radius": 1.0, "length_unit": "mm"}, **extra}],
    }


def test_config_fits_the_contact_offset_of_an_analytic_indentation(late_contact, capsys):
    work = late_contact.parent
    path = work / "fit.toml"
    path.write_text(dump_toml(config(late_contact, contact_offset="fit")))
    out = work / "out"
    assert main(["fit", str(path), "--out", str(out), "--no-progress"]) == 0
    assert "hertz.contact_offset" in capsys.readouterr().out
    rec = json.loads((out / "fit.json").read_text())
    p = rec["parameters"]["hertz.contact_offset"]
    assert p["unit"] == "m" and abs(p["value"] - OFFSET) < 1e-9 and np.isfinite(p["standard_error"])
    assert rec["parameters"]["youngs_modulus"]["value"] == pytest.approx(E_TRUE, rel=1e-6)
    assert "| hertz.contact_offset |" in (out / "report.md").read_text()
    assert "contact_offset" not in (out / "material.json").read_text()
    # without it the same data give a biased E
    path.write_text(dump_toml(config(late_contact)))
    c = parse_config(config(late_contact), base_dir=work)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = c.run(progress=False)
    assert plain.values["youngs_modulus"] / E_TRUE - 1 > 0.1


def test_contact_offset_refusals(late_contact):
    work = late_contact.parent
    with pytest.raises(ConfigError, match=r'^experiment\[0\]\.contact_offset: must be "fit"'):
        parse_config(config(late_contact, contact_offset=1e-5), base_dir=work)
    cfg = config(late_contact, contact_offset="fit")
    cfg["experiment"][0].update(scenario="indentation", specimen={"size": [5, 5, 5], "cells": [2, 2, 4], "length_unit": "mm"})
    cfg["experiment"][0].pop("points")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the coarse mesh under-resolves the contact: not solved here
        c = parse_config(cfg, base_dir=work)
    with pytest.raises(ConfigError, match=r"^experiment 'hertz': contact_offset = \"fit\" on a simulated indentation needs fit\.separate_compilation = false"):
        c.fit_scenarios()
    assert c.fit_scenarios(separate_compilation=False)[0] is c.experiments[0].scenario
