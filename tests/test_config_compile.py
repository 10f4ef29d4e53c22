"""The compile cache of :class:`difftissue.config.SeparatelyCompiled` (issue 18): equal
scenarios built twice in one process share one compiled program; scenarios that differ in
anything compiled into the program (static configuration, model) get their own, with the
numbers of a fresh build; measured data are arguments of the programs, not constants, and so
are the mesh, the protocol and the solver setup of the scenarios whose protocol takes its
arrays as arguments (other node coordinates or depths of the same shapes share a program,
each with its own numbers).

Compilations are counted two ways: XLA backend compilations reported by
``jax.monitoring`` ('/jax/core/compile/backend_compile_duration') and the cache's own
counters (:func:`difftissue.config.compile_cache_info`)."""

import hashlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import Material
from difftissue.config import SeparatelyCompiled, clear_compile_cache, compile_cache_info, parse_config
from difftissue.config.compile import scenario_structure
from difftissue.fit import FitProblem
from difftissue.fit.problem import hash_scenario_leaves
from difftissue.materials import MaterialParameterization
from program_events import ObtainedPrograms

jax.config.update("jax_enable_x64", True)

_BACKEND_COMPILES = {"n": 0}


def _count(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        _BACKEND_COMPILES["n"] += 1


jax.monitoring.register_event_duration_secs_listener(_count)


class _Compiles:
    """XLA backend compilations and cache counters between ``__enter__`` and ``__exit__``."""

    def __enter__(self):
        self.n0, self.info0 = _BACKEND_COMPILES["n"], compile_cache_info()
        return self

    def __exit__(self, *exc):
        self.backend = _BACKEND_COMPILES["n"] - self.n0
        info = compile_cache_info()
        self.compiled = info["compilations"] - self.info0["compilations"]
        self.hits = info["hits"] - self.info0["hits"]


@pytest.fixture(scope="module", autouse=True)
def _compiled_protocols():
    """These tests are about the compiled protocols: the one-cube specimens here would
    otherwise solve on the host (HOST_SOLVES; tested at the end of this file)."""
    from difftissue.config import compile as cc

    before, cc.HOST_SOLVES = cc.HOST_SOLVES, False
    yield
    cc.HOST_SOLVES = before


STRAINS = [0.05, 0.1, 0.15, 0.2]
MATERIAL = Material(2.0e4, 0.45, cubic_coefficient=0.5)


def _config(tmp_path, *, scale=1.0, size=0.01, strains=STRAINS, model="springs_volume", name="cube", platens="frictionless", cells=1):
    """A one-cube compression config; ``scale`` multiplies the measured stresses (other data,
    same specimen and protocol)."""
    stress = [scale * 2.0e4 * e for e in strains]
    csv = tmp_path / f"curve_{scale}_{len(strains)}_{strains[-1]}.csv"
    csv.write_text("strain,stress\n" + "".join(f"{e!r},{s!r}\n" for e, s in zip(strains, stress)))
    raw = {
        "material": {"youngs_modulus": 2.0e4, "poisson_ratio": 0.45, "cubic_coefficient": 0.0},
        "fit": {"parameters": ["youngs_modulus", "cubic_coefficient"], "bounds": {"cubic_coefficient": [-3.0, 5.0]}, "start": "material"},
        "experiment": [{
            "name": name, "scenario": "compression", "model": model, "platens": platens, "points": "all", "sigma": {"relative": 0.01},
            "data": {"format": "table", "path": csv.name,
                     "columns": {"strain": {"name": "strain", "unit": "-"}, "stress": {"name": "stress", "unit": "Pa"}}},
            "specimen": {"size": [size] * 3, "cells": [cells] * 3},
        }],
    }
    return parse_config(raw, base_dir=tmp_path)


def _wrapped(cfg):
    (sc,) = cfg.fit_scenarios()
    assert isinstance(sc, SeparatelyCompiled) and sc.mode == "forward"
    return sc


def _value_and_tangents(sc):
    """The prediction (host call, counted by :class:`_Compiles` around it) and the Jacobian in
    E and b (``jax.jacfwd`` through the same compiled program, one model solve)."""
    with _Compiles() as c:
        y = np.asarray(sc.evaluate(MATERIAL))
    jac = jax.jacfwd(lambda E, b: sc.predict(Material(E, 0.45, cubic_coefficient=b)), argnums=(0, 1))(2.0e4, 0.5)
    return y, np.stack([np.asarray(j) for j in jac]), c


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    """The reference program: compiled once for this module (a clean cache first)."""
    clear_compile_cache()
    sc = _wrapped(_config(tmp_path_factory.mktemp("first")))
    y, jac, c = _value_and_tangents(sc)
    assert c.compiled == 1 and c.hits == 0 and c.backend >= 1
    return sc, (y, jac)


def test_an_equal_config_built_again_reuses_the_compiled_program(first, tmp_path):
    sc1, (y1, jt1) = first
    sc2 = _wrapped(_config(tmp_path))
    assert sc2 is not sc1 and sc2.inner is not sc1.inner
    y2, jt2, c = _value_and_tangents(sc2)
    assert c.backend == 0 and c.compiled == 0 and c.hits == 1, vars(c)
    np.testing.assert_array_equal(y2, y1)
    np.testing.assert_array_equal(jt2, jt1)
    assert sc2.calls == sc1.calls == {"value": 1, "value_and_tangents": 1}  # each wrapper counts its own solves


def test_a_program_compiled_outside_a_fit_is_the_one_the_fit_runs(first, tmp_path):
    """A fit evaluates its scenarios inside a host callback, where JAX sets the default device to
    the CPU device; outside it is None. Both resolve to one device here, so the program compiled
    before the fit is the fit's own (the key held the unresolved setting and compiled again)."""
    sc1, (y1, jt1) = first
    sc2 = _wrapped(_config(tmp_path))
    with jax.default_device(jax.devices("cpu")[0]):
        y2, jt2, c = _value_and_tangents(sc2)
    # (JAX's own small eager programs around the call are compiled again under the other
    # setting: ``c.backend`` counts them; the scenario's program is not among them)
    assert c.compiled == 0 and c.hits == 1, vars(c)
    np.testing.assert_array_equal(y2, y1)
    np.testing.assert_array_equal(jt2, jt1)


def test_other_measurements_of_the_same_specimen_and_protocol_share_the_program(first, tmp_path):
    """The measured stresses (and sigma) are arguments: 3x other data, same program, same
    predictions; each wrapper keeps its own observed data."""
    sc1, (y1, jt1) = first
    sc3 = _wrapped(_config(tmp_path, scale=3.0))
    np.testing.assert_allclose(sc3.observed, 3.0 * np.asarray(sc1.observed), rtol=1e-12)
    y3, jt3, c = _value_and_tangents(sc3)
    assert c.backend == 0 and c.compiled == 0 and c.hits == 1, vars(c)
    np.testing.assert_array_equal(y3, y1)
    np.testing.assert_array_equal(jt3, jt1)


@pytest.mark.parametrize("change", [
    {"size": 0.02},                          # another cube size: its height and area are static floats, compiled in
    {"platens": "bonded"},                   # another static configuration (and boundary data)
])
def test_a_scenario_that_differs_in_what_is_compiled_in_gets_its_own_program(first, tmp_path, change):
    """Two compilations, and the second program gives the numbers of a fresh build (cache
    cleared) and of the scenario's own protocol solved on the host (``solve_on_host``: the
    same Newton iteration outside any compiled protocol, equal to ``predict`` to round-off;
    no third protocol compiled per case)."""
    sc1, (y1, jt1) = first
    sc = _wrapped(_config(tmp_path, **change))
    assert scenario_structure(sc.inner)[0] != scenario_structure(sc1.inner)[0]
    y, jt, c = _value_and_tangents(sc)
    assert c.compiled == 1 and c.hits == 0 and c.backend >= 1, vars(c)
    if "size" not in change:  # frictionless platens: a cube's stress does not depend on its size
        assert not np.allclose(y, y1, rtol=1e-6)
    assert sc.inner.solves_on_host
    direct, _ = sc.inner.solve_on_host(MATERIAL)
    np.testing.assert_allclose(y, direct, rtol=1e-10, atol=1e-12 * np.max(np.abs(direct)))
    clear_compile_cache()  # (the tests above hold their programs; none below needs the cache)
    fresh = _wrapped(_config(tmp_path, **change))
    yf, jtf, c2 = _value_and_tangents(fresh)
    assert c2.compiled == 1 and c2.hits == 0
    np.testing.assert_array_equal(y, yf)
    np.testing.assert_array_equal(jt, jtf)


def test_another_protocol_of_the_same_shapes_shares_the_program_and_gets_its_own_numbers(first, tmp_path):
    """The compression's arrays (mesh, boundary data, the strains) are arguments of its
    programs: other strains of the same number share the program, with the numbers of the
    scenario's own predict."""
    sc1, (y1, _) = first
    assert sc1.arrays_as_arguments
    base = _wrapped(_config(tmp_path))
    base.evaluate(MATERIAL)  # the reference program in the cache (compiled or shared)
    other = _wrapped(_config(tmp_path, strains=[0.05, 0.1, 0.15, 0.25]))
    assert scenario_structure(other.inner, arrays=True)[0] == scenario_structure(base.inner, arrays=True)[0]
    y, _, c = _value_and_tangents(other)
    assert c.compiled == 0 and c.hits == 1 and c.backend == 0, vars(c)
    assert not np.allclose(y, y1, rtol=1e-6)
    direct = np.asarray(other.inner.predict(MATERIAL))
    np.testing.assert_allclose(y, direct, rtol=1e-12, atol=1e-12 * np.max(np.abs(direct)))


def _indentation(width):
    """A small sphere indentation (stable neo-Hookean, full solve) on a quarter block of the
    given width [m] (1 mm thick): the same pytree structure and shapes for any width (the
    indenter, placed on the top surface, is a static field)."""
    from difftissue.scenarios import Indentation, indentation_block

    mesh = indentation_block((width, width, 1e-3), (3, 3, 2), symmetry="quarter")
    d = np.array([20e-6, 40e-6])
    return Indentation(mesh, d, np.ones(2), indenter="sphere", radius=1e-3, model="stable_neo_hookean", symmetry="quarter", name="s")


def test_other_mesh_coordinates_share_the_program_and_get_their_own_predictions():
    """Two indentation blocks of other width (other node coordinates, the same structure):
    the mesh and the solver setup are arguments, not constants, so the second scenario takes
    the first one's program (no compilation) and still gets its own forces and tangents,
    those of its own ``predict`` (its own compiled protocol) to 1e-12."""
    thin, thick = _indentation(1.0e-3), _indentation(3.0e-3)
    assert not np.array_equal(np.asarray(thin.model.rest_points), np.asarray(thick.model.rest_points))
    assert scenario_structure(thin)[0] != scenario_structure(thick)[0]  # the closed-over key tells them apart
    _assert_one_program_and_own_numbers(thin, thick, differ_rtol=1e-4)


def _assert_one_program_and_own_numbers(first, second, *, differ_rtol):
    """``first`` and ``second`` (scenarios of one structure, other arrays) through
    :class:`SeparatelyCompiled`: the second takes the first one's program (no compilation) and
    each gets its own forces (differing by more than ``differ_rtol``) and Poisson's ratio
    tangents, those of its own ``predict`` (its own compiled protocol) to 1e-12 / 1e-10."""
    w1, w2 = (SeparatelyCompiled(sc, fields=("youngs_modulus", "poisson_ratio")) for sc in (first, second))
    assert w1.arrays_as_arguments and w2.arrays_as_arguments
    assert scenario_structure(first, arrays=True)[0] == scenario_structure(second, arrays=True)[0]
    m = Material(1.0e4, 0.45)
    with _Compiles() as c1:
        y1 = w1.evaluate(m)
    with _Compiles() as c2:
        y2 = w2.evaluate(m)
    assert c1.compiled == 1 and c2.compiled == 0 and c2.hits == 1 and c2.backend == 0, (vars(c1), vars(c2))
    assert not np.allclose(y2, y1, rtol=differ_rtol)  # other forces: each its own numbers
    for w, sc, y in ((w1, first, y1), (w2, second, y2)):
        np.testing.assert_allclose(y, np.asarray(sc.predict(m)), rtol=1e-12, atol=0)
        # the Poisson's ratio tangent (an implicit solve per depth) through the shared program
        _, t = jax.jvp(lambda nu: w.predict(Material(1.0e4, nu)), (0.45,), (1.0,))
        _, td = jax.jvp(lambda nu: sc.predict(Material(1.0e4, nu)), (0.45,), (1.0,))
        np.testing.assert_allclose(np.asarray(t), np.asarray(td), rtol=1e-10, atol=1e-12 * np.max(np.abs(td)))


@pytest.mark.parametrize("linear_solver", ["auto", "spectral"])
def test_condensed_indentations_of_other_mesh_coordinates_share_the_program(linear_solver):
    """The condensed indentation (a config's 3-D fem_linear sphere or cone) takes its mesh,
    its index sets, its condensation data and its solver setup (the spectral decomposition
    with ``linear_solver="spectral"``) as arguments: a specimen of one structure with other
    node coordinates (deeper nodes moved, the same candidate contact nodes) takes the first
    one's program and gets its own forces and Poisson's ratio tangents, those of its own
    ``predict`` to 1e-12."""
    from difftissue.scenarios import Indentation, SolverOptions, indentation_block

    mesh = indentation_block((2e-3, 2e-3, 1e-3), (3, 3, 2), symmetry="quarter")
    p = np.asarray(mesh.points).copy()
    p[:, 2] = 1e-3 - (1e-3 - p[:, 2]) * 1.5  # a thicker block, the same top surface
    opts = SolverOptions(linear_solver=linear_solver)
    a, b = (Indentation(m, np.array([20e-6, 40e-6]), np.ones(2), indenter="sphere", radius=1e-3, model="fem_linear", symmetry="quarter",
                        options=opts) for m in (mesh, eqx.tree_at(lambda m: m.points, mesh, p)))
    assert a.condensation is not None and (a.condensation.spectral is not None) == (linear_solver == "spectral")
    _assert_one_program_and_own_numbers(a, b, differ_rtol=1e-3)


def test_the_key_holds_what_is_compiled_in_and_not_the_measured_data(tmp_path):
    """No compilation here: keys of built scenarios."""
    key = lambda cfg: scenario_structure(cfg.experiments[0].scenario)[0]  # noqa: E731
    base = key(_config(tmp_path))
    assert base is not None and base == key(_config(tmp_path))
    assert base == key(_config(tmp_path, scale=2.0))      # measured data: arguments
    assert base != key(_config(tmp_path, name="other"))   # the name is a static field: kept (conservative)
    assert base != key(_config(tmp_path, size=0.011))
    assert base != key(_config(tmp_path, strains=[0.05, 0.1, 0.15, 0.2001]))
    assert base != key(_config(tmp_path, strains=[0.05, 0.1, 0.15]))
    assert base != key(_config(tmp_path, model="fem_linear"))
    assert base != key(_config(tmp_path, platens="bonded"))


class _ScaledData(eqx.Module):
    """A scenario whose prediction READS its observed data (``E * observed + b``): a shared
    program must still give each scenario its own numbers."""

    name: str = eqx.field(static=True)
    observed: np.ndarray
    sigma: np.ndarray
    abscissa: np.ndarray
    x_label: str = eqx.field(static=True, default="x [-]")
    y_label: str = eqx.field(static=True, default="y [-]")

    def predict(self, material):
        return material.youngs_modulus * jnp.asarray(self.observed) + material.cubic_coefficient


class _Opaque:
    """A scenario that is not a pytree: keyed by identity (never shared)."""

    name, x_label, y_label = "opaque", "x [-]", "y [-]"

    def __init__(self, observed):
        self.observed = np.asarray(observed, dtype=float)
        self.sigma = np.ones_like(self.observed)
        self.abscissa = np.arange(self.observed.size, dtype=float)

    def predict(self, material):
        return material.youngs_modulus * jnp.asarray(self.observed)


@pytest.mark.parametrize("mode", ["forward", "reverse"])
def test_measured_data_are_arguments_of_the_shared_program(mode):
    a = _ScaledData("s", np.array([1.0, 2.0, 3.0]), np.ones(3), np.arange(3.0))
    b = _ScaledData("s", np.array([5.0, -1.0, 0.5]), np.ones(3), np.arange(3.0))
    m = Material(2.0, 0.3, cubic_coefficient=0.25)
    wa, wb = SeparatelyCompiled(a, mode=mode, n_tangents=1), SeparatelyCompiled(b, mode=mode, n_tangents=1)
    with _Compiles() as ca:
        ya = wa.evaluate(m)
    with _Compiles() as cb:
        yb = wb.evaluate(m)
    assert ca.compiled == 1 and cb.compiled == 0 and cb.hits == 1 and cb.backend == 0
    np.testing.assert_allclose(ya, 2.0 * a.observed + 0.25, rtol=1e-15)
    np.testing.assert_allclose(yb, 2.0 * b.observed + 0.25, rtol=1e-15)
    # the derivative through the shared program: d/dE = observed
    if mode == "forward":
        _, jb = jax.jvp(lambda E: wb.predict(Material(E, 0.3, cubic_coefficient=0.25)), (2.0,), (1.0,))
    else:
        _, pullback = jax.vjp(lambda E: wb.predict(Material(E, 0.3, cubic_coefficient=0.25)), 2.0)
        jb = np.array([float(pullback(jnp.eye(3)[i])[0]) for i in range(3)])
    np.testing.assert_allclose(np.asarray(jb), b.observed, rtol=1e-15)


def test_a_scenario_that_is_not_a_pytree_is_not_shared():
    m = Material(2.0, 0.3)
    a, b = _Opaque([1.0, 2.0]), _Opaque([1.0, 2.0])
    assert scenario_structure(a)[0] != scenario_structure(b)[0]  # by identity
    with _Compiles() as c:
        ya, yb = SeparatelyCompiled(a).evaluate(m), SeparatelyCompiled(b).evaluate(m)
    assert c.compiled == 2 and c.hits == 0
    np.testing.assert_array_equal(ya, yb)


# ------------------------------------------------------------ one formula for both caches
def _fit_key(*scenarios):
    return FitProblem(scenarios, MaterialParameterization(("youngs_modulus", "poisson_ratio")), MATERIAL).structure_key()


def _with_leaf(scenario, index, value):
    """``scenario`` with its pytree leaf ``index`` replaced by ``value`` (the other leaves, the
    measured data included, are the same objects)."""
    leaves, treedef = jax.tree_util.tree_flatten(scenario)
    leaves[index] = value
    return jax.tree_util.tree_unflatten(treedef, leaves)


def test_the_compile_cache_and_the_fit_engine_key_scenarios_by_one_formula(tmp_path):
    """``config.compile.scenario_structure`` and ``FitProblem.structure_key`` hash a scenario's
    leaves with ``fit.problem.hash_scenario_leaves``: equal scenarios built twice give equal keys
    in both, an array leaf changed in its last bit (or other measured data of the same shape) is
    told apart (kept), an equal copy of an array is not (content, not identity), and the digests are
    those of the formula each used before it was shared."""
    sc = _config(tmp_path).experiments[0].scenario
    again = _config(tmp_path).experiments[0].scenario
    other_data = _config(tmp_path, scale=2.0).experiments[0].scenario
    key, leaves, _, data = scenario_structure(sc)
    assert data and key is not None
    assert key == scenario_structure(again)[0] == scenario_structure(other_data)[0]
    assert _fit_key(sc) == _fit_key(again) == _fit_key(other_data)
    # the compile key's digest IS the shared function's (tag "data")
    h = hashlib.sha256()
    assert hash_scenario_leaves(h, leaves, data, data_tag="data") == [] and key[2] == h.hexdigest()

    i = next(i for i, leaf in enumerate(leaves) if i not in data and eqx.is_array(leaf) and leaf.dtype == np.float64 and leaf.size)
    a = np.array(leaves[i])
    changed = a.copy()
    changed.flat[0] = np.nextafter(changed.flat[0], np.inf)
    bit = _with_leaf(sc, i, changed)
    same = _with_leaf(sc, i, a.copy())
    assert scenario_structure(bit)[0] != key and _fit_key(bit) != _fit_key(sc)
    assert scenario_structure(same)[0] == key and _fit_key(same) == _fit_key(sc)

    # the formula of main 79e6b1a (before it was shared), on fixed leaves: sha256 of each leaf's
    # shape, dtype and bytes / type name and value, data leaves by shape and dtype after the tag
    fixed = [np.arange(6.0).reshape(2, 3), jnp.asarray([1, 2, 3], dtype=jnp.int32), None, 1.5, True, 7, "frictionless",
             np.float64(0.25), np.array([4.0, 5.0])]
    for tag, digest in (("data", "44eea529e21a1b59379ddade62a56773c1a17e33f318d889e8a7020cff3346b2"),
                        ("dyn", "e3e0cf76d80dd7446dfe3d639cbbfa9ada78757e56a238f9d35c39207e5624ff")):
        h = hashlib.sha256()
        assert hash_scenario_leaves(h, fixed, (8,), data_tag=tag) == []
        assert h.hexdigest() == digest, tag
    obj = object()
    assert hash_scenario_leaves(hashlib.sha256(), [obj, 1.0], ()) == [id(obj)]  # not an array: by identity


# ------------------------------------------------------------ compiler options of small models
def test_small_models_are_compiled_at_low_optimisation_with_the_same_numbers(first, tmp_path, monkeypatch):
    """A model of at most SMALL_MODEL_NODES nodes (the one cube: 8) gets
    SMALL_MODEL_COMPILER_OPTIONS (compiles faster) with the static programs' options; its
    prediction and Jacobian agree with the program compiled at XLA's defaults to 1e-12
    (measured ~1e-15); a larger specimen (125 nodes) gets the static programs' options only.
    The options are part of the program's key."""
    from difftissue import xla_options
    from difftissue.config import compile as cc

    sc, (y, jac) = first
    assert sc.inner.model.n_nodes == 8
    assert cc._compiler_options(sc.inner) == {**xla_options.compiler_options("static"), **cc.SMALL_MODEL_COMPILER_OPTIONS}
    monkeypatch.setattr(cc, "SMALL_MODEL_NODES", 0)
    assert cc._compiler_options(sc.inner) == xla_options.compiler_options("static")
    # XLA's default level (3) stated for this program, so that a lower level in the
    # environment's XLA_FLAGS cannot make both programs the same
    monkeypatch.setattr(cc, "_compiler_options", lambda scenario: {"xla_backend_optimization_level": 3})
    default = _wrapped(_config(tmp_path))
    y0, jac0, c = _value_and_tangents(default)
    assert c.compiled == 1 and c.hits == 0  # its own program: the options are in the key
    np.testing.assert_allclose(y, y0, rtol=1e-12, atol=0)
    np.testing.assert_allclose(jac, jac0, rtol=1e-12, atol=1e-12 * np.max(np.abs(jac0)))
    # ... and they are two different executables: the level reached XLA. Were the options dropped
    # on the way (or overridden by XLA_FLAGS), both programs would be the same and the comparison
    # above would hold trivially. The witness is round-off: level 0 and level 3 differ in the last
    # digits of this program's numbers (measured: sum of the stresses 10495.803499486858 vs
    # ...861, the same with XLA_FLAGS=--xla_backend_optimization_level=0 in the environment,
    # which the per-program option overrides).
    assert not (np.array_equal(y, y0) and np.array_equal(jac, jac0)), "level 0 and level 3 gave bit-identical numbers: the compiler options did not reach XLA"
    monkeypatch.undo()
    big = _wrapped(_config(tmp_path, cells=4)).inner
    assert big.model.n_nodes == 125 and cc._compiler_options(big) == xla_options.compiler_options("static")


def _hertz_config(tmp_path, modulus, depths):
    """An analytic-indentation (Hertz, 1 mm sphere, nu = 0) config of a synthetic curve of
    ``modulus`` [Pa] at ``depths`` [m] with 1 % noise; the fit starts from the data (the
    default ``fit.start = "data"``: the transforms are scaled at the data's Hertz modulus)."""
    d = np.asarray(depths, dtype=float)
    f = 4.0 / 3.0 * modulus * np.sqrt(1e-3) * d**1.5
    f = f + 0.01 * f.max() * np.random.default_rng(1).normal(size=d.size)
    csv = tmp_path / f"hertz_{modulus:g}_{d[0]:g}.csv"
    csv.write_text("depth,force\n" + "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(d, f)))
    raw = {
        "material": {"youngs_modulus": 100.0, "poisson_ratio": 0.0},
        "fit": {"parameters": ["youngs_modulus"], "method": "levenberg_marquardt"},
        "experiment": [{
            "name": "afm", "scenario": "analytic_indentation", "points": "all", "sigma": {"relative": 0.01},
            "data": {"format": "table", "path": csv.name,
                     "columns": {"depth": {"name": "depth", "unit": "m"}, "force": {"name": "force", "unit": "N"}}},
            "indenter": {"shape": "sphere", "radius": 1e-3},
        }],
    }
    return parse_config(raw, base_dir=tmp_path)


def test_a_second_fit_of_the_same_config_with_another_modulus_compiles_no_program(tmp_path):
    """The fit engine's programs (the batched start, the step, the final evaluation) take the
    measured data and the transforms' numbers (a ``Log`` scaled at the data-driven start) as
    arguments: a second fit of the same config with a curve 100 x stiffer (so a start 100 x
    higher) obtains no program and fits its own modulus."""
    depths = np.linspace(5e-6, 100e-6, 37)
    soft, stiff = _hertz_config(tmp_path, 1e3, depths), _hertz_config(tmp_path, 1e5, depths)
    assert stiff.start["youngs_modulus"]["value"] == pytest.approx(1e5, rel=0.02)
    first = soft.run()
    with ObtainedPrograms() as got:
        second = stiff.run()
    assert got.count == {"compiled": 0, "loaded": 0}, got.count
    assert first.values["youngs_modulus"] == pytest.approx(1e3, rel=0.02)
    assert second.values["youngs_modulus"] == pytest.approx(1e5, rel=0.02)


def test_a_fit_of_another_curve_at_other_depths_compiles_no_program(tmp_path):
    """The depths of a closed-form indentation are arguments of the fit's programs too
    (``AnalyticIndentation.fit_arguments``): a curve of another modulus at other depths, as
    many points, obtains no program and fits its own modulus; one with another number of
    points compiles its own."""
    first = _hertz_config(tmp_path, 2e3, np.linspace(5e-6, 100e-6, 31)).run()
    other = _hertz_config(tmp_path, 3e4, np.linspace(8e-6, 70e-6, 31))
    with ObtainedPrograms() as got:
        second = other.run()
    assert got.count == {"compiled": 0, "loaded": 0}, got.count
    assert first.values["youngs_modulus"] == pytest.approx(2e3, rel=0.02)
    assert second.values["youngs_modulus"] == pytest.approx(3e4, rel=0.02)
    with ObtainedPrograms() as got:
        longer = _hertz_config(tmp_path, 3e4, np.linspace(8e-6, 70e-6, 32)).run()
    assert got.count["compiled"] + got.count["loaded"] > 0
    assert longer.values["youngs_modulus"] == pytest.approx(3e4, rel=0.02)
