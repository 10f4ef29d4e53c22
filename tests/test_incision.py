"""Incision (difftissue.incision): the opening of a cut in a pre-tensioned skin, its gradients,
the progressive (seed 002) reference, fits, pictures and the config.

One small two-layer skin (8 x 8 mm, 1 mm cells; dermis 1 mm pre-stretched on 2 mm of soft
fat; lateral faces held, base clamped) and one 4 mm cut serve every test, so each model's
incision is compiled once. Slow: the whole file took 31 min on the loaded 2-core machine (load
~10; the joint fit 19 min with 24 LM steps from a farther start, the gradient test 8 min,
mostly compilation); the joint fit alone, from the present start, 15.5 min (13 steps, with
the compilation of the model and its JVP); the config and refusal tests (`-k "config or
bad_input or example"`) ~30 s.
"""


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue.config import SeparatelyCompiled
from difftissue.cutting import ScalpelPath, cut_specimen
from difftissue.errors import ConfigError, CutError, DataError
from difftissue.fit import fit
from difftissue.incision import Incision, IncisionOptions, depth_profile, incision_boundary, plot_incision, write_incision_series
from difftissue.materials import Material, MaterialParameterization, lame_parameters, surface_tension_from_pre_stretch
from difftissue.mesh import layered_skin
from difftissue.scenarios import AnalyticIndentation, _jitted_solve

MM = 1e-3
SKIN, FAT = Material(2e5, 0.45), Material(5e3, 0.45)
T_DERMIS = 1 * MM
OPTS = IncisionOptions(scalpel_steps=2, rtol=1e-11)


@pytest.fixture(scope="module")
def cut():
    spec = layered_skin([("dermis", T_DERMIS, SKIN, 1), ("fat", 2 * MM, FAT, 2)], size=(8 * MM, 8 * MM), resolution=(8, 8))
    return cut_specimen(spec, ScalpelPath([(2 * MM, 4 * MM), (6 * MM, 4 * MM)], depth=T_DERMIS))


@pytest.fixture(scope="module")
def incision(cut):
    """The physical model (stable neo-Hookean), dermis fitted, surface profile at the pairs."""
    return Incision(cut, model="stable_neo_hookean", fitted_regions=("dermis",), options=OPTS)


@pytest.fixture(scope="module")
def reference(cut):
    """The reference FEM incision (compressible neo-Hookean)."""
    return Incision(cut, model="fem_neo_hookean", fitted_regions=("dermis",), options=OPTS)


@pytest.fixture(scope="module")
def compiled(incision):
    """The physical model's surface widths and their JVP, compiled once for the module
    (difftissue.config.SeparatelyCompiled), shared by the gradient test and the fit. Its one
    program pushes two tangents (the fit's two parameters; a primal call runs it with zero
    tangents): SeparatelyCompiled compiles a program per tangent count, so the gradient test
    takes its three columns in two-tangent passes too."""
    return SeparatelyCompiled(incision, n_tangents=2)


@pytest.fixture(scope="module")
def progressive(reference):
    """The reference's progressive opening of the lambda0 = 1.1 dermis at three scalpel
    positions (the last past the end: the whole cut released): ``(positions, us, widths,
    max opening)``. Computed once for the module; the joint fit takes its synthetic data
    from the released cut, so it does not depend on which test ran first."""
    pos = np.array([1.5 * MM, 2.5 * MM, np.inf])
    us, w, mx = (np.asarray(a) for a in reference.progress(SKIN.replace(pre_stretch=1.1), pos))
    return pos, us, w, mx


def _stable_nh_thickness_stretch(lam0, E, nu):
    """lambda_z of a stable neo-Hookean layer held at lambda0 in x, y, sigma_zz = 0 (closed form)."""
    lam, mu = (float(v) for v in lame_parameters(E, nu))
    ls = lam + mu
    return lam0**2 * (mu + ls) / (mu + ls * lam0**4)


# ------------------------------------------------------------------ forward model
def test_precut_equilibrium_and_opening(cut, incision):
    """Before the cut (pairs tied, lateral faces held) the dermis only thins, by the exact
    plane-stress stretch, and the fat stays stress-free; after the cut the wound opens
    perpendicular to the cut, widest at its centre; without pre-stretch nothing opens."""
    lam0 = 1.08
    res = incision.solve(SKIN.replace(pre_stretch=lam0))
    X = np.asarray(cut.mesh.points)
    u0 = np.asarray(res.precut_displacement)
    z_top = X[:, 2].max()
    top, interface = np.isclose(X[:, 2], z_top), np.isclose(X[:, 2], z_top - T_DERMIS)
    lz = _stable_nh_thickness_stretch(lam0, SKIN.youngs_modulus, SKIN.poisson_ratio)
    op = res.opening
    # exact up to the closure penalty: the tied pairs carry the pre-stress across the cut with a
    # gap of ~1/penalty_factor of the released opening (measured: 1.2e-5 of the thinning)
    np.testing.assert_allclose(u0[top, 2], (lz - 1.0) * T_DERMIS, rtol=1e-4)
    np.testing.assert_allclose(u0[interface, 2], 0.0, atol=1e-4 * float(op.max_width))
    np.testing.assert_allclose(u0[:, :2], 0.0, atol=1e-3 * float(op.max_width))
    w = np.asarray(op.surface_width)
    assert np.all(np.asarray(op.normal_opening) > 0.02 * MM)
    # opens across the cut (the rest of the width: the lips sink and slide, measured 6 %)
    assert np.all(np.asarray(op.normal_opening) >= 0.9 * np.asarray(op.width))
    assert float(op.max_width) == pytest.approx(w[len(w) // 2]) and w[len(w) // 2] > w[0]
    assert float(op.width_over_length) == pytest.approx(float(op.max_width) / (4 * MM), rel=1e-14)
    d, wd = depth_profile(cut, op.width)
    assert d[0] == 0.0 and float(wd[0]) == pytest.approx(float(op.max_width))
    none = incision.solve(SKIN)
    assert float(jnp.max(none.opening.width)) < 1e-12 * MM


def test_opening_gradients_match_central_differences(incision, compiled):
    """d(surface widths)/d(lambda0, E, nu) of the dermis by implicit differentiation of the
    opened equilibrium (the JVP, compiled on its own) vs central differences of the plain solve
    (float64, cut topology fixed)."""

    def material(q):
        return Material(2e5 * q[1], q[2], pre_stretch=q[0])

    def jvp_widths(q):
        return compiled.predict(material(q)) / MM

    def widths(q):
        return np.asarray(incision.solve(material(q)).opening.surface_width) / MM

    q0 = jnp.array([1.06, 1.0, 0.45])
    # the Jacobian's columns from two forward passes of two tangents each (the fixture's one
    # compiled program): d/d(lambda0, E), then d/d(E, nu); the E column of both must agree
    jac_a = np.asarray(jax.jacfwd(lambda a: jvp_widths(jnp.stack([a[0], a[1], q0[2]])))(q0[:2]))
    jac_b = np.asarray(jax.jacfwd(lambda b: jvp_widths(jnp.stack([q0[0], b[0], b[1]])))(q0[1:]))
    np.testing.assert_allclose(jac_b[:, 0], jac_a[:, 1], rtol=1e-12, atol=1e-14 * np.max(np.abs(jac_a)))
    jac = np.column_stack([jac_a[:, 0], jac_a[:, 1], jac_b[:, 1]])
    np.testing.assert_allclose(np.asarray(jvp_widths(q0)), widths(q0), rtol=1e-9)
    assert np.all(np.abs(jac[:, 0]) > 1.0)  # lambda0 drives the opening
    assert np.all(np.abs(jac[:, 1]) > 1e-3)  # E matters: the fat below is fixed
    h = 1e-5
    for i in range(3):
        dq = jnp.zeros(3).at[i].set(h)
        fd = (widths(q0 + dq) - widths(q0 - dq)) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=2e-5, atol=1e-7 * np.max(np.abs(jac)))


#: Programs traced and compiled in this process (``jax.monitoring``'s public compile events).
_COMPILE_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": 0, "/jax/core/compile/backend_compile_duration": 0}


def _count_compile_event(event, duration, **kw):
    if event in _COMPILE_EVENTS:
        _COMPILE_EVENTS[event] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compile_event)


def test_progressive_reference_opens_without_recompiling(cut, reference, progressive, tmp_path):
    """Seed 002 reference: the pairs tied by the closure are released as the scalpel advances;
    the opening grows with the scalpel position, tied pairs stay shut, all positions run in one
    compiled scan (a second sweep of the same length reuses it). The VTU series and the
    picture are written."""
    mat = SKIN.replace(pre_stretch=1.1)
    pos, us, w, mx = progressive
    n0 = dict(_COMPILE_EVENTS)
    us2, w2, _ = (np.asarray(a) for a in reference.progress(mat, pos + np.array([0.2 * MM, 0.2 * MM, 0.0])))
    assert _COMPILE_EVENTS == n0, (n0, _COMPILE_EVENTS)  # nothing traced or compiled again
    np.testing.assert_allclose(w2[-1], w[-1], rtol=1e-6)  # the released cut does not depend on the path there
    ps = np.asarray(cut.pair_s)
    for k, s in enumerate(pos):
        closed = ps > s
        if closed.any():
            assert np.max(w[k][closed]) < 1e-3 * np.max(w[k][~closed])
    assert np.all(np.diff(mx) > 0)
    pvd = write_incision_series(tmp_path, cut, us, pos)
    text = pvd.read_text()
    assert text.count("<DataSet") == 3 and (tmp_path / "incision_002.vtu").exists()
    import meshio

    m = meshio.read(tmp_path / "incision_000.vtu")
    np.testing.assert_allclose(m.point_data["displacement"], us[0])
    assert m.point_data["tied"].sum() == 2 * int(np.sum(ps > pos[0]))
    png = plot_incision(cut, us[-1], tmp_path / "opened.png")
    assert png.stat().st_size > 10_000
    with pytest.raises(Exception, match="exists"):
        plot_incision(cut, us[-1], png)


class _Data:
    """Observed values with the prediction of a shared (compiled once) scenario."""

    def __init__(self, model, observed, name):
        self.name, self.abscissa, self.x_label, self.y_label = name, model.abscissa, model.x_label, model.y_label
        self.observed = np.asarray(observed, dtype=float)
        self.sigma = np.full_like(self.observed, 0.01 * np.max(np.abs(self.observed)))
        self.predict = model.predict


# ------------------------------------------------------------------------- fits
def test_joint_indentation_incision_fit_recovers_E_and_tension(cut, compiled, progressive):
    """Synthetic data: the surface widths of the REFERENCE FEM incision (fem_neo_hookean,
    lambda0 = 1.1) and a Hertz curve of the same dermis. Fitted with the physical model
    (stable neo-Hookean), nu known, from E = 160 kPa, lambda0 = 1.07: lambda0 within 2 %
    (measured +0.105 %), E within 1 % (+0.098 %) and the surface tension T within 2 % (+1.25 %:
    T is proportional to lambda0 - 1, whose error is +1.15 %); 13 LM steps (24 from
    E = 120 kPa, lambda0 = 1.03, same result)."""
    true = SKIN.replace(pre_stretch=1.1)
    widths = progressive[2][-1][cut.surface_pairs]  # the released cut of the reference
    inc = _Data(compiled, widths, "incision")
    depths = np.linspace(0.05, 0.5, 8) * MM
    forces = np.asarray(AnalyticIndentation(depths, np.ones(8), radius=1 * MM).predict(true))
    hertz = AnalyticIndentation(depths, forces, radius=1 * MM, name="indentation")
    param = MaterialParameterization(("youngs_modulus", "pre_stretch"))
    res = fit([hertz, inc], param, SKIN.replace(youngs_modulus=1.6e5, pre_stretch=1.07), max_steps=40)
    E, lam0 = res.values["youngs_modulus"], res.values["pre_stretch"]
    T_true = float(surface_tension_from_pre_stretch(true, T_DERMIS))
    T_fit = float(surface_tension_from_pre_stretch(SKIN.replace(youngs_modulus=E, pre_stretch=lam0), T_DERMIS))
    print(f"joint fit: lambda0 {lam0:.6f} ({100 * (lam0 / 1.1 - 1):+.3f} %), E {E:.1f} ({100 * (E / 2e5 - 1):+.3f} %), T {T_fit:.4f} N/m vs {T_true:.4f} ({100 * (T_fit / T_true - 1):+.3f} %), {res.steps} steps")
    assert res.converged
    assert lam0 == pytest.approx(1.1, rel=0.02)
    assert E == pytest.approx(2e5, rel=0.01)
    assert T_fit == pytest.approx(T_true, rel=0.02)


# ---------------------------------------------------------------------- refusals
def test_bad_input_refused(cut):
    with pytest.raises(ConfigError, match="quantity"):
        Incision(cut, quantity="depth")
    with pytest.raises(DataError, match="lie on the cut"):
        Incision(cut, positions=[-1 * MM, 1 * MM])
    with pytest.raises(DataError, match="observed"):
        Incision(cut, observed=[1e-4, 2e-4])
    with pytest.raises(ConfigError, match="no region 'skin'"):
        Incision(cut, fitted_regions=("skin",))
    with pytest.raises(ConfigError, match="positions apply"):
        Incision(cut, quantity="max_width", positions=[1 * MM])
    with pytest.raises(CutError, match="Cut"):
        Incision(cut.mesh)
    with pytest.raises(ConfigError, match="rigid"):
        incision_boundary(cut.mesh, lateral="free", base="sliding")
    with pytest.raises(ConfigError, match="scalpel_steps"):
        IncisionOptions(scalpel_steps=0)
    with pytest.raises(DataError, match="non-decreasing"):
        Incision(cut).progress(SKIN, [2 * MM, 1 * MM])
    with pytest.raises(CutError, match="shape"):
        write_incision_series(".", cut, np.zeros((2, 3, 3)), [0.0, 1.0])


# ------------------------------------------------------------------------ config
def _config(**exp):
    e = {
        "name": "wound",
        "scenario": "incision",
        "length_unit": "mm",
        "data": {"quantity": "surface_width", "positions": [1.0, 2.0, 3.0], "widths": [0.2, 0.3, 0.2]},
        "specimen": {"size": [8, 8], "cells": [8, 8], "layers": [{"name": "dermis", "thickness": 1, "cells": 1, "fitted": True}, {"name": "fat", "thickness": 2, "cells": 2, "youngs_modulus": 5e3, "poisson_ratio": 0.45}]},
        "cut": {"path": [[2, 4], [6, 4]], "depth": 1},
    }
    e.update(exp)
    return {"material": {"youngs_modulus": 2e5, "poisson_ratio": 0.45, "pre_stretch": 1.05}, "fit": {"parameters": ["pre_stretch"]}, "experiment": [e]}


def test_config_builds_an_incision():
    from difftissue.config import parse_config

    cfg = parse_config(_config(boundary={"lateral": "held", "base": "sliding"}, scalpel_steps=3, sigma=1e-5))
    (exp,) = cfg.experiments
    sc = exp.scenario
    assert exp.kind == "incision" and exp.model == "stable_neo_hookean" and isinstance(sc, Incision)
    np.testing.assert_allclose(sc.observed, [0.2e-3, 0.3e-3, 0.2e-3])
    np.testing.assert_allclose(sc.positions, [1e-3, 2e-3, 3e-3])
    assert sc.fitted_regions == (0,) and sc.options.scalpel_steps == 3 and np.all(sc.sigma == 1e-5)
    assert float(sc.base_materials.youngs_modulus[1]) == 5e3 and sc.cut.length == pytest.approx(4e-3)
    cfg = parse_config(_config(data={"quantity": "width_over_length", "value": 0.07}, model="fem_neo_hookean"))
    assert cfg.experiments[0].scenario.quantity == "width_over_length" and cfg.experiments[0].scenario.observed.tolist() == [0.07]


@pytest.mark.parametrize(
    "change, match",
    [
        ({"cut": {"path": [[2, 4], [9, 4]], "depth": 1}}, r"^experiment\[0\]\.cut: .*leaves the specimen's top surface"),
        ({"cut": {"path": [[2, 4], [6, 4]], "depth": 5}}, r"^experiment\[0\]\.cut: .*exceeds the specimen thickness"),
        ({"cut": {"depth": 1}}, r"^experiment\[0\]\.cut\.path: missing"),
        ({"data": {"quantity": "depth", "value": 1}}, r"^experiment\[0\]\.data\.quantity: "),
        ({"data": {"quantity": "max_width", "value": -1}}, r"^experiment\[0\]\.data\.value: "),
        ({"data": {"quantity": "surface_width", "positions": [1, 2], "widths": [0.1]}}, r"^experiment\[0\]\.data\.widths: "),
        ({"data": {"quantity": "surface_width", "positions": [1, 9], "widths": [0.1, 0.1]}}, r"^experiment\[0\]: .*lie on the cut"),
        ({"boundary": {"lateral": "loose"}}, r"^experiment\[0\]\.boundary\.lateral: "),
        ({"scalpel_steps": 0}, r"^experiment\[0\]\.scalpel_steps: "),
        ({"blade": 1}, r"^experiment\[0\]: unknown key 'blade'"),
        ({"specimen": {"size": [8, 8], "layers": [{"name": "dermis", "thickness": 1, "fitted": True, "youngs_modulus": 1.0}]}}, r"^experiment\[0\]\.specimen\.layers\[0\]\.youngs_modulus: a fitted layer"),
        ({"specimen": {"size": [8, 8], "layers": [{"name": "dermis", "thickness": 1, "youngs_modulus": 1.0, "poisson_ratio": 0.4}]}}, r"^experiment\[0\]\.specimen\.layers: no layer has fitted"),
        ({"specimen": {"size": [8, 8], "layers": [{"name": "fat", "thickness": 1, "youngs_modulus": 1.0}, {"name": "d", "thickness": 1, "fitted": True}]}}, r"^experiment\[0\]\.specimen\.layers\[0\]\.poisson_ratio: missing"),
    ],
)
def test_config_errors_name_the_key(change, match):
    from difftissue.config import parse_config

    with pytest.raises((ConfigError, CutError, DataError), match=match):
        parse_config(_config(**change))


def test_example_config_builds():
    from pathlib import Path

    from difftissue.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[1] / "experiments" / "configs" / "incision_skin.toml")
    assert [e.kind for e in cfg.experiments] == ["incision"]
    assert cfg.parameterization.fields == ("pre_stretch",)


def test_an_incision_of_other_node_coordinates_shares_the_program(cut, incision):
    """The incision is compiled with its arrays (mesh, cut pairs, boundary data, fixed
    materials, the residual floor) and its solver setup as arguments: the same cut in a
    specimen whose fat nodes lie deeper (other node coordinates, one structure) takes the
    first one's program and gets the widths and tangents of its protocol compiled with its
    arrays closed over (the program before the arguments) to 1e-13."""
    p = np.asarray(cut.mesh.points).copy()
    below = p[:, 2].max() - T_DERMIS
    p[:, 2] = np.where(p[:, 2] < below - 1e-12, below - (below - p[:, 2]) * 1.5, p[:, 2])
    deeper = Incision(eqx.tree_at(lambda c: c.mesh.points, cut, p), model="stable_neo_hookean", fitted_regions=("dermis",), options=OPTS)
    first, second = _jitted_solve(incision), _jitted_solve(deeper)
    assert second.program is first.program
    mat = SKIN.replace(pre_stretch=1.1)
    ys = []
    for sc in (incision, deeper):
        y, t = jax.jvp(lambda E, sc=sc: sc.predict(mat.replace(youngs_modulus=E)), (2e5,), (1.0,))
        closed = lambda E, sc=sc: sc._solve_protocol(mat.replace(youngs_modulus=E))  # noqa: E731
        yc, tc = jax.jit(lambda E: jax.jvp(closed, (E,), (1.0,)))(2e5)
        np.testing.assert_allclose(np.asarray(y), np.asarray(yc), rtol=1e-13, atol=1e-13 * np.abs(np.asarray(yc)).max())
        np.testing.assert_allclose(np.asarray(t), np.asarray(tc), rtol=1e-12, atol=1e-12 * np.abs(np.asarray(tc)).max())
        ys.append(np.asarray(y))
    assert not np.allclose(ys[0], ys[1], rtol=1e-4)  # each its own widths


def test_an_incision_of_other_layer_materials_shares_the_program(incision):
    """The layer materials of the specimen that was cut are arrays of the incision (not Python
    floats compiled in by value): the same cut in a skin with another fat layer (and another
    dermis) takes the first one's program, with its own fixed materials as arguments."""
    fat, dermis = Material(3e3, 0.4), Material(1.5e5, 0.42)
    spec = layered_skin([("dermis", T_DERMIS, dermis, 1), ("fat", 2 * MM, fat, 2)], size=(8 * MM, 8 * MM), resolution=(8, 8))
    other_cut = cut_specimen(spec, ScalpelPath([(2 * MM, 4 * MM), (6 * MM, 4 * MM)], depth=T_DERMIS))
    other = Incision(other_cut, model="stable_neo_hookean", fitted_regions=("dermis",), options=OPTS)
    assert _jitted_solve(other).program is _jitted_solve(incision).program
    np.testing.assert_array_equal(np.asarray(other.base_materials.youngs_modulus), [1.5e5, 3e3])
    assert float(other.cut.materials[1].poisson_ratio) == 0.4 and other_cut.materials[1] is fat  # the caller's cut is untouched
