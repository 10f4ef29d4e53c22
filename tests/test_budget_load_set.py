"""Budget calibration over a set of loads (difftissue.budget.calibrate_for_load_set): one card
for depths, indenter shapes and a stiffness range, its validity range, and saturation detection
with a measured budget proposal (docs/budget.md, docs/dev/budget-calibration.md)."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from difftissue.budget import (BudgetLoad, _LoadSet, calibrate_for_budget, calibrate_for_load_set, indentation_load)
from difftissue.errors import (BudgetExtrapolationWarning, BudgetRangeError, BudgetSaturationError, ConfigError)
from difftissue.materials import Material
from difftissue.mesh import block
from difftissue.models import make_model
from difftissue.solvers.static import solve_static
from difftissue.solvers.xpbd import XPBDSettings, xpbd_quasi_static
from program_events import ObtainedPrograms

MATERIAL = Material(youngs_modulus=10e3, poisson_ratio=0.45)
TUNED = XPBDSettings(dt=3e-3, substeps=1, iterations=10, method="gauss_seidel", warm_start=False)  # the tuned case
TWO_SUBSTEPS = XPBDSettings(dt=3e-3, substeps=2, iterations=10, method="gauss_seidel", warm_start=False)


@pytest.fixture(scope="module")
def mesh():
    return block((0.01, 0.01, 0.005), (4, 4, 2))  # 2.5 mm cells, 192 tets (experiments/budget_indentation.py)


def _force(mesh, load, material, settings=None):
    """Reaction on the moved nodes along -z: budgeted XPBD (settings) or the static solve (None)."""
    model = make_model(mesh, "springs_volume")
    if settings is None:
        sol = solve_static(model, material, load.bc)
    else:
        sol = xpbd_quasi_static(model, material, load.bc, settings=settings, tol=1e-10, max_steps=5000)
    moved = np.any(np.asarray(load.bc.fixed) & (np.abs(np.asarray(load.bc.displacement)) > 0), axis=1)
    return -float(np.sum(np.asarray(sol.reaction)[moved, 2]))


def test_indentation_loads(mesh):
    p = np.asarray(mesh.points)
    punch = indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3)
    moved = np.any(np.asarray(punch.bc.displacement) != 0, axis=1)
    assert moved.sum() == 5 and np.allclose(np.asarray(punch.bc.displacement)[moved, 2], -1e-4)
    platen = indentation_load(mesh, "platen", 1e-4)
    assert np.any(np.asarray(platen.bc.displacement) != 0, axis=1).sum() == 25
    sphere = indentation_load(mesh, "sphere", 2e-4, radius=10e-3)  # a = 2 mm: the centre node only
    d = np.asarray(sphere.bc.displacement)
    centre = np.flatnonzero(np.any(d != 0, axis=1))
    assert centre.size == 1 and np.allclose(p[centre, :2], 0.005) and d[centre[0], 2] == pytest.approx(-2e-4)
    deep = indentation_load(mesh, "sphere", 8e-4, radius=10e-3)  # a = 4 mm: the centre, 4 neighbours (2.5 mm), 4 diagonals (3.5 mm)
    d = np.asarray(deep.bc.displacement)
    ring = np.flatnonzero(np.any(d != 0, axis=1))
    assert ring.size == 9
    r = np.hypot(p[ring, 0] - 0.005, p[ring, 1] - 0.005)
    np.testing.assert_allclose(d[ring, 2], -(8e-4 - r**2 / (2 * 10e-3)), rtol=1e-12)  # on the sphere's paraboloid
    with pytest.raises(ConfigError, match="shape"):
        indentation_load(mesh, "cone", 1e-4, radius=1e-3)
    with pytest.raises(ConfigError, match="radius"):
        indentation_load(mesh, "sphere", 1e-4)
    with pytest.raises(ConfigError, match="no top node"):
        indentation_load(block((0.01, 0.01, 0.005), (3, 3, 1)), "flat_punch", 1e-4, radius=1e-3)  # no node at the centre


def test_budget_number_scaling_and_sensitivity_gradient(mesh):
    """Physics of the budget: with velocities zeroed every substep the substep map depends on
    E h^2 only (compliance alpha / h^2), so the budgeted force at (h / 2, 4 E) is 4 times the
    one at (h, E) -- the reason a substep search can run as a dt search. And the sensitivity
    d log F / d log E (forward mode through the XPBD loop) equals a central difference."""
    load = indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3)
    f1 = _force(mesh, load, MATERIAL, TUNED)
    f2 = _force(mesh, load, MATERIAL.replace(youngs_modulus=40e3), XPBDSettings(dt=1.5e-3, substeps=1, iterations=10, warm_start=False))
    assert f2 == pytest.approx(4 * f1, rel=1e-6)
    ls = _LoadSet(mesh, make_model(mesh, "springs_volume"), MATERIAL, [load], 1e-12, 5000)
    F, s, ok = ls.response(ls.youngs, TUNED)
    h = 1e-3
    Fp = np.asarray(ls.forces(ls.youngs * np.exp(h), TUNED)[0])
    Fm = np.asarray(ls.forces(ls.youngs * np.exp(-h), TUNED)[0])
    fd = (np.log(Fp) - np.log(Fm)) / (2 * h)
    print(f"sensitivity {s[0]:.6f}, central difference {fd[0]:.6f}")
    assert ok[0] and F[0] == pytest.approx(f1, rel=1e-6)
    assert s[0] == pytest.approx(fd[0], rel=1e-4)
    assert 0.5 < s[0] < 0.7  # the tuned punch: 0.575 (1 when converged)


def test_saturated_budget_raises_and_the_proposal_unsaturates(mesh):
    """dt = 1/60 s with 10 iterations on 2.5 mm cells (a measured saturated case: d log F / d log E
    ~ 0.03): the load-set calibration refuses with the budget that carries the set, found by a
    measured search; the proposal, re-run, is above the threshold and calibrates."""
    loads = [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3), indentation_load(mesh, "platen", 1e-4)]
    sixty = XPBDSettings(dt=1.0 / 60.0, substeps=1, iterations=10, method="gauss_seidel", warm_start=False)
    with pytest.raises(BudgetSaturationError, match="saturated") as info:
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, loads, sixty, propose=("substeps",))
    err = info.value
    print(err)
    assert max(err.sensitivity) < 0.1
    prop = err.proposal
    assert prop is not None and prop.substeps is not None and prop.substeps_sensitivity >= 0.5
    assert "substeps = " in str(err)
    # the search's record: the count below the proposal was measured and failed
    below = [m for m in prop.measured if m[0] == "substeps" and m[1] == prop.substeps - 1]
    assert below and below[0][2] < 0.5
    # re-run at the proposed settings themselves (prop.substeps substeps per 1/60 s frame; the search ran them as
    # frames of dt / substeps): every load's sensitivity is above the threshold at the true modulus
    ls = _LoadSet(mesh, make_model(mesh, "springs_volume"), MATERIAL, loads, 1e-10, 5000)
    _, s, ok = ls.response(ls.youngs, prop.settings(sixty, "substeps"))
    print(f"at {prop.substeps} substeps: sensitivities {s}")
    assert np.all(ok) and np.min(s) >= 0.5


def test_load_set_card_reproduces_its_set_and_refuses_outside(mesh):
    loads = [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3),
             indentation_load(mesh, "flat_punch", 2e-4, radius=3e-3),
             indentation_load(mesh, "platen", 1e-4),
             indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, youngs_modulus=40e3, name="punch 4x stiffer")]
    cal = calibrate_for_load_set(mesh, "springs_volume", MATERIAL, loads, TWO_SUBSTEPS)
    v = cal.validity
    print(v)
    assert v["shapes"] == ["flat_punch", "platen"] and v["depth_range"] == [1e-4, 2e-4]
    assert v["youngs_modulus_range"] == [10e3, 40e3] and cal.stiffness_nodes == (10e3, 40e3)
    assert 0 < cal.max_error < 0.03  # one card for punch and platen: a compromise, stated per load
    for ld, row in zip(loads, cal.loads):
        # an independent evaluation: the card's material through the public solver, one load at a time
        E = MATERIAL.youngs_modulus if ld.youngs_modulus is None else ld.youngs_modulus
        m = cal.effective_material(shape=ld.shape, depth=ld.depth, youngs_modulus=E, settings=TWO_SUBSTEPS, mesh=mesh)
        ref = _force(mesh, ld, MATERIAL.replace(youngs_modulus=E))
        got = _force(mesh, ld, m, TWO_SUBSTEPS)
        assert row["reference"] == pytest.approx(ref, rel=1e-9)
        assert got / ref - 1.0 == pytest.approx(row["error"], abs=1e-6)
        assert abs(got / ref - 1.0) <= cal.max_error + 1e-6
    card = cal.card()
    assert card["validity"]["max_residual_error"] == cal.max_error and len(card["loads"]) == 4
    import json
    json.dumps(card)
    # outside the range: refused; depth and stiffness may be extrapolated on request, with a named warning
    with pytest.raises(BudgetRangeError, match="depth"):
        cal.effective_material(shape="flat_punch", depth=8e-4)
    with pytest.raises(BudgetRangeError, match="Young's modulus"):
        cal.effective_material(shape="flat_punch", depth=1e-4, youngs_modulus=2.5e3)
    with pytest.warns(BudgetExtrapolationWarning, match="outside its calibrated range"):
        cal.effective_material(shape="flat_punch", depth=8e-4, extrapolate=True)
    with pytest.raises(BudgetRangeError, match="shapes"):
        cal.effective_material(shape="sphere", depth=1e-4, extrapolate=True)
    with pytest.raises(BudgetRangeError, match="setting"):
        cal.effective_material(shape="platen", depth=1e-4, settings=TUNED)
    with pytest.raises(BudgetRangeError, match="mesh"):
        cal.effective_material(shape="platen", depth=1e-4, mesh=block((0.01, 0.01, 0.005), (8, 8, 4)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal.effective_material(shape="platen", depth=1.5e-4, youngs_modulus=20e3)  # inside: no warning


def test_one_load_set_is_the_single_load_calibration(mesh):
    """The single-load API is the one-load special case: the same modulus (1.3531, the tuned
    punch of docs/budget.md) and the same error."""
    load = indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3)
    single = calibrate_for_budget(mesh, "springs_volume", MATERIAL, load.bc, TUNED)
    cal = calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [load], TUNED, max_steps=10)
    print(f"single {single.ratio():.9f}, set {cal.factor:.9f}")
    assert single.ratio() == pytest.approx(1.3531, abs=5e-4)
    assert cal.factor == pytest.approx(single.ratio(), rel=1e-8)
    assert abs(cal.loads[0]["error"]) == pytest.approx(single.calibrated_error, abs=1e-8)
    assert cal.steps == single.steps
    assert cal.effective_material(shape="flat_punch", depth=1e-4).youngs_modulus == pytest.approx(float(single.material.youngs_modulus))


def test_a_load_set_of_other_numbers_compiles_nothing(mesh):
    """The joint fit is compiled once per structure (mesh, loading pattern, budget, number of
    stiffness nodes): a set at another depth, material and dt obtains no program (none compiled,
    none loaded from the persistent cache) and gives its own card."""
    first = calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3)],
                                   TUNED, max_steps=10)
    material = MATERIAL.replace(youngs_modulus=12e3, poisson_ratio=0.4)
    settings = XPBDSettings(dt=2.5e-3, substeps=1, iterations=10, method="gauss_seidel", warm_start=False)
    load = indentation_load(mesh, "flat_punch", 1.5e-4, radius=3e-3)
    with ObtainedPrograms() as got:
        cal = calibrate_for_load_set(mesh, "springs_volume", material, [load], settings, max_steps=10)
    assert got.count == {"compiled": 0, "loaded": 0}, got.count
    assert cal.stiffness_nodes == (12e3,) and cal.setting["dt"] == 2.5e-3 and cal.poisson_ratio == 0.4
    assert cal.loads[0]["reference"] > 1.5 * first.loads[0]["reference"]  # deeper and stiffer: its own reference
    assert abs(cal.loads[0]["error"]) < 1e-3 and cal.factor != first.factor


def test_validation(mesh):
    load = indentation_load(mesh, "platen", 1e-4)
    with pytest.raises(ConfigError, match="empty"):
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [], TUNED)
    with pytest.raises(ConfigError, match="BudgetLoad"):
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [load.bc], TUNED)
    other = block((0.01, 0.01, 0.005), (2, 2, 1))
    with pytest.raises(ConfigError, match="set's mesh"):
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [indentation_load(other, "platen", 1e-4)], TUNED)
    with pytest.raises(ConfigError, match="threshold"):
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [load], TUNED, threshold=1.5)
    with pytest.raises(ConfigError, match="warm_start"):
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [load], XPBDSettings(warm_start=True))
    with pytest.raises(ConfigError, match="depth"):
        calibrate_for_load_set(mesh, "springs_volume", MATERIAL, [BudgetLoad(load.bc, "platen", -1.0)], TUNED)
