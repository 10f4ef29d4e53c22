"""Incisions in a skin with an anisotropic pre-stretch (``Material.pre_stretch_y``): the cut
opens across the direction of higher tension, by symmetry exactly as the swapped case, and a
fit of two cuts recovers both pre-stretches.

One square skin (6 x 6 mm, 1 mm cells: a 1 mm dermis, fitted, on 1 mm of fat without
pre-stretch; lateral faces held, base clamped) with a 2 mm
cut along x and one along y, springs_volume (its cube lattice is symmetric under x <-> y, so
the swapped problems are the same problem up to the node order).
"""

import jax
import numpy as np
import pytest

from difftissue.config import SeparatelyCompiled
from difftissue.cutting import ScalpelPath, cut_specimen
from difftissue.fit import fit
from difftissue.incision import Incision, IncisionOptions
from difftissue.materials import Material, MaterialParameterization
from difftissue.mesh import layered_skin

MM = 1e-3
SKIN, FAT = Material(2e5, 0.45), Material(5e3, 0.45)
OPTS = IncisionOptions(scalpel_steps=1, rtol=1e-11)


def _incision(path):
    spec = layered_skin([("dermis", 1 * MM, SKIN, 1), ("fat", 1 * MM, FAT, 1)], size=(6 * MM, 6 * MM), resolution=(6, 6))
    cut = cut_specimen(spec, ScalpelPath(path, depth=1 * MM))
    return Incision(cut, model="springs_volume", fitted_regions=("dermis",), options=OPTS, quantity="surface_width", name="cut")


@pytest.fixture(scope="module")
def along_x():
    return _incision([(2 * MM, 3 * MM), (4 * MM, 3 * MM)])


@pytest.fixture(scope="module")
def along_y():
    return _incision([(3 * MM, 2 * MM), (3 * MM, 4 * MM)])


@pytest.fixture(scope="module")
def compiled(along_x, along_y):
    return [SeparatelyCompiled(s, pre_stretch_y=True, n_tangents=2) for s in (along_x, along_y)]


def test_cut_opens_across_the_higher_tension_and_the_swap_is_exact(along_x, along_y, compiled):
    """A cut along y under (lx, 1) opens exactly as a cut along x under (1, ly) with lx = ly
    (x <-> y symmetry, 1e-8 relative); and wider than a cut along x under the same (lx, 1)."""
    high = 1.08
    w_y = compiled[1].evaluate(SKIN.replace(pre_stretch=high, pre_stretch_y=1.0))
    w_x = compiled[0].evaluate(SKIN.replace(pre_stretch=1.0, pre_stretch_y=high))
    assert np.all(np.isfinite(w_x)) and np.max(w_y) > 0.05 * MM
    np.testing.assert_allclose(w_x, w_y, rtol=1e-8, atol=1e-8 * np.max(w_y))
    w_x_low = compiled[0].evaluate(SKIN.replace(pre_stretch=high, pre_stretch_y=1.0))
    assert np.max(w_y) > 2.0 * np.max(w_x_low)  # measured ratio in docs/dev/anisotropic-pre-stretch.md
    print(f"max width: cut along y under (1.08, 1): {np.max(w_y) / MM:.5f} mm, cut along x: {np.max(w_x_low) / MM:.5f} mm")


def test_opening_gradients_in_both_pre_stretches_match_central_differences(compiled):
    """d(surface widths)/d(lambda_x, lambda_y) by implicit differentiation vs central
    differences (float64, rtol 1e-5). The cut along y's program of the module (its JVP pushes two
    tangents: one jacfwd over both pre-stretches; a primal call runs it with zero tangents), not a
    second compilation of the same scenario."""

    def widths(q):
        return compiled[1].predict(SKIN.replace(pre_stretch=q[0], pre_stretch_y=q[1])) / MM

    q0 = np.array([1.07, 1.03])
    jac = np.asarray(jax.jacfwd(widths)(q0))
    assert np.all(jac[:, 0] > 0)  # the stretch across the cut drives its opening
    h = 1e-5
    for i in range(2):
        dq = np.zeros(2)
        dq[i] = h
        fd = (np.asarray(widths(q0 + dq)) - np.asarray(widths(q0 - dq))) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-5, atol=1e-7 * np.max(np.abs(jac)))


def test_two_cuts_recover_both_pre_stretches(compiled):
    """Synthetic widths of a cut along x and one along y at (lambda_x, lambda_y) = (1.08, 1.03)
    (same model); fitted from (1.05, 1.05): both recovered to 1e-6."""
    true = SKIN.replace(pre_stretch=1.08, pre_stretch_y=1.03)
    scen = []
    for c, name in zip(compiled, ("cut_x", "cut_y")):
        data = np.asarray(c.evaluate(true))
        scen.append(_Data(c, data, name))
    param = MaterialParameterization(("pre_stretch", "pre_stretch_y"))
    res = fit(scen, param, SKIN.replace(pre_stretch=1.05), max_steps=30)
    print(f"fit: {res.values}, {res.steps} steps, standard errors {res.standard_errors}, jacobian {np.asarray(res.jacobian).tolist()}, loss {res.loss}")
    assert res.converged
    assert res.values["pre_stretch"] == pytest.approx(1.08, rel=1e-6)
    assert res.values["pre_stretch_y"] == pytest.approx(1.03, rel=1e-6)


class _Data:
    """A compiled scenario with other observed data (the fit protocol)."""

    def __init__(self, model, observed, name):
        self.name = name
        self.observed = np.asarray(observed, dtype=float)
        self.sigma = np.full(self.observed.size, float(np.sqrt(np.mean(self.observed**2))))
        self.abscissa = np.arange(self.observed.size, dtype=float)
        self.x_label, self.y_label = "pair", "width [m]"
        self.predict = model.predict


def test_config_takes_pre_stretch_y():
    """[material] pre_stretch_y and fit.parameters = ["pre_stretch", "pre_stretch_y"]: the scenarios
    are compiled with the sixth leaf; a bad value names the key."""
    from difftissue.config import parse_config
    from difftissue.errors import ConfigError

    exp = {"name": "wound", "scenario": "incision", "length_unit": "mm",
           "data": {"quantity": "surface_width", "positions": [0.5, 1.0, 1.5], "widths": [0.2, 0.3, 0.2]},
           "specimen": {"size": [6, 6], "cells": [6, 6], "layers": [{"name": "dermis", "thickness": 1, "cells": 1, "fitted": True},
                                                                  {"name": "fat", "thickness": 1, "cells": 1, "youngs_modulus": 5e3, "poisson_ratio": 0.45}]},
           "cut": {"path": [[2, 3], [4, 3]], "depth": 1}}
    doc = {"material": {"youngs_modulus": 2e5, "poisson_ratio": 0.45, "pre_stretch": 1.05, "pre_stretch_y": 1.02},
           "fit": {"parameters": ["pre_stretch", "pre_stretch_y"]}, "experiment": [exp]}
    cfg = parse_config(doc)
    assert float(cfg.material.pre_stretch_y) == 1.02 and cfg.parameterization.fields == ("pre_stretch", "pre_stretch_y")
    assert cfg.anisotropic_pre_stretch
    (sc,) = cfg.fit_scenarios()
    assert sc._leaves[-1] == "pre_stretch_y"
    with pytest.raises(ConfigError, match="pre_stretch_y"):
        parse_config({**doc, "material": {**doc["material"], "pre_stretch_y": -1.0}})
    with pytest.raises(ConfigError, match="was compiled without one"):
        SeparatelyCompiled(cfg.experiments[0].scenario).predict(cfg.material)
