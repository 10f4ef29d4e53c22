"""Batched and sharded fits (difftissue.fit.fit_batch) against the serial loop of fit calls.

The sharded runs need several devices, i.e. XLA_FLAGS=--xla_force_host_platform_device_count=4
set before jax is imported: they run in a child process (a script written to tmp_path).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
import warnings

import equinox as eqx
import jax
import numpy as np
import pytest

from difftissue import Material
from difftissue.analytic import hertz_force
from difftissue.fit import fit_batch, specimen_mesh
from difftissue.errors import FitError, IdentifiabilityWarning
from difftissue.fit import fit
from difftissue.materials import MaterialParameterization
from difftissue.mesh import block
from difftissue.scenarios import AnalyticIndentation, Compression, SolverOptions

NAN = SolverOptions(failure="nan")  # a failed solve gives NaN predictions (what fits use)

P_E = MaterialParameterization(("youngs_modulus",))
DEPTHS = np.linspace(20e-6, 200e-6, 15)


def hertz_specimens(n, seed=0, radius=1e-3):
    """``n`` Hertz curves, each with its own E (2-9 kPa), noise and start (0.5 E)."""
    rng = np.random.default_rng(seed)
    specs, starts = [], []
    for b in range(n):
        E = 2e3 + 7e3 * rng.random()
        f = np.asarray(hertz_force(DEPTHS, E, 0.45, radius))
        noise = 0.01 * f.max()
        specs.append(AnalyticIndentation(DEPTHS, f + noise * rng.normal(size=f.size), radius=radius, sigma=noise, name="hertz"))
        starts.append(Material(0.5 * E, 0.45))
    return specs, starts


def small_block():
    return block((0.01, 0.01, 0.0075), (4, 4, 3))  # 288 tets, 2.5 mm cubes (topology test)


@pytest.fixture(scope="module")
def cube():
    return small_block()


def indentation_scenario(observed=None, sigma=None):
    """The simulated sphere indentation of :func:`indentation_specimens` (quarter block of 384
    tets, fem_linear, condensed penalty contact) with the data ``observed`` [N], ``sigma`` [N]."""
    from difftissue.scenarios import Indentation, indentation_block

    mesh = indentation_block((4e-3, 4e-3, 1.6e-3), (4, 4, 4), symmetry="quarter")
    depths = np.linspace(0.04, 0.2, 4) * 1e-3
    kw = dict(model="fem_linear", indenter="sphere", radius=1e-3, symmetry="quarter", options=NAN, name="sphere")
    return Indentation(mesh, depths, observed, sigma=sigma, **kw)


def indentation_specimens(n, seed=0):
    """``n`` simulated sphere indentations (:func:`indentation_scenario`, nu = 0.45 known), each
    with its own E (5-15 kPa), noise and start (0.6 E)."""
    probe = indentation_scenario()
    rng = np.random.default_rng(seed)
    specs, starts = [], []
    for b in range(n):
        E = 5e3 + 1e4 * rng.random()
        f = np.asarray(probe.predict(Material(E, 0.45)))
        noise = 0.01 * f.max()
        specs.append(indentation_scenario(f + noise * rng.normal(size=f.size), noise))
        starts.append(Material(0.6 * E, 0.45))
    return specs, starts


@pytest.fixture(scope="module")
def indentation_serial():
    """Five simulated indentations (``indentation_specimens(5, seed=2)``) and their serial loop of
    fits, computed once for the module: the batched test uses the first three (the same
    specimens as ``indentation_specimens(3, seed=2)``: one random stream, drawn in order), the
    sharded child process all five, so the child compiles neither the scenario nor the
    single-specimen fit."""
    specs, starts = indentation_specimens(5, seed=2)
    return specs, starts, [fit(s, P_E, m) for s, m in zip(specs, starts)]


def fit_summary(r) -> dict:
    """What :func:`assert_same_fits` compares of a serial fit, as JSON (exact floats)."""
    return {"fields": list(r.fields), "values": {f: float(v) for f, v in r.values.items()},
            "standard_errors": {f: float(v) for f, v in r.standard_errors.items()}, "loss": float(r.loss),
            "converged": bool(r.converged), "steps": int(r.steps), "best_start": int(r.best_start),
            "start_losses": np.asarray(r.start_losses).tolist(), "covariance": np.asarray(r.covariance).tolist(),
            "loss_history": np.asarray(r.loss_history).tolist()}


def fit_from_summary(d):
    """A :func:`fit_summary` read back: the attributes :func:`assert_same_fits` reads."""
    import types

    arrays = {k: np.asarray(d[k], dtype=float) for k in ("start_losses", "covariance", "loss_history")}
    return types.SimpleNamespace(**{**d, "fields": tuple(d["fields"]), **arrays})


def assert_same_fits(batch, serial, rtol=1e-7, steps_tol=0):
    """Same values, standard errors, losses and convergence; steps equal within ``steps_tol``
    (the last steps of a simulated fit change the loss at round-off level, where batched and
    single linear algebra may round differently)."""
    assert len(batch) == len(serial)
    for b, (a, s) in enumerate(zip(batch.fits, serial)):
        for f in s.fields:
            assert a.values[f] == pytest.approx(s.values[f], rel=rtol), (b, f, a.values[f], s.values[f])
            assert a.standard_errors[f] == pytest.approx(s.standard_errors[f], rel=1e-5), (b, f)
        assert a.loss == pytest.approx(s.loss, rel=1e-6, abs=1e-12)
        assert a.converged == s.converged and abs(a.steps - s.steps) <= steps_tol and a.best_start == s.best_start, b
        np.testing.assert_allclose(a.start_losses, s.start_losses, rtol=1e-6)
        np.testing.assert_allclose(a.covariance, s.covariance, rtol=1e-5)
        assert a.loss_history.shape == (a.steps + 1, s.loss_history.shape[1])


# ------------------------------------------------------------------ batched == serial
@pytest.mark.parametrize("method", ["levenberg_marquardt", "gauss_newton"])
def test_batched_hertz_fits_equal_the_serial_loop(method):
    specs, starts = hertz_specimens(5, seed=1)
    batch = fit_batch(specs, P_E, starts, method=method, starts=2, seed=3)
    serial = [fit(s, P_E, m, method=method, starts=2, seed=3) for s, m in zip(specs, starts)]
    assert_same_fits(batch, serial)
    assert all(batch.converged) and batch.batch_steps == batch.steps.max()
    assert batch.values.shape == (5, 1) and batch.fields == ("youngs_modulus",)
    # the fits recover each specimen's own modulus (within 3 standard errors of the noise)
    true_E = np.array([2.0 * m.youngs_modulus for m in starts])
    assert np.all(np.abs(batch.value("youngs_modulus") - true_E) < 4 * batch.standard_errors[:, 0])
    assert "| specimen | youngs_modulus |" in batch.table()


def test_batched_indentation_fits_equal_the_serial_loop_and_compile_once(caplog, monkeypatch, indentation_serial):
    from difftissue.scenarios import Indentation

    specs, starts, serial = (v[:3] for v in indentation_serial)
    # the batch switches the condensed fem_linear indentations to the spectral solver itself
    # (SPECTRAL_MIN_SPECIMENS); the serial loop used the default dense Cholesky
    variant, chosen = Indentation.spectral_variant, []
    monkeypatch.setattr(Indentation, "spectral_variant", lambda self, **kw: chosen.append(variant(self, **kw).options.linear_solver) or variant(self, **kw))
    batch = fit_batch(specs, P_E, starts)
    assert chosen == ["spectral"] * 3 and specs[0].options.linear_solver == "auto"
    assert batch.compilations == 1  # one trace of the batched step for all specimens and steps
    assert_same_fits(batch, serial, rtol=1e-6, steps_tol=2)
    assert all(batch.converged)
    # the serial loop compiled once for the first specimen only: the data are arguments
    assert [r.compilations for r in serial][1:] == [0, 0]
    # new specimens of the same structure (other data, other starts): nothing is compiled again
    specs2, starts2 = indentation_specimens(3, seed=7)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        caplog.clear()
        again = fit_batch(specs2, P_E, starts2)
    big = [r.getMessage() for r in caplog.records if "ompiling" in r.getMessage() and ("step" in r.getMessage() or "evaluate" in r.getMessage())]
    assert again.compilations == 0 and big == [], big
    assert not np.allclose(again.values, batch.values)


def test_batched_indentation_fits_without_the_spectral_solver_equal_the_serial_loop(indentation_serial):
    """``spectral=False``: every specimen factorises its own stiffness (vmapped dense Cholesky)."""
    specs, starts, serial = (v[:3] for v in indentation_serial)
    batch = fit_batch(specs, P_E, starts, spectral=False)
    assert_same_fits(batch, serial, rtol=1e-6, steps_tol=2)


def test_the_spectral_option_of_fit_batch_refuses_what_it_cannot_do():
    specs, starts = hertz_specimens(2)
    with pytest.raises(FitError, match="none of its scenarios offers the spectral solver"):
        fit_batch(specs, P_E, starts, spectral=True)
    with pytest.raises(FitError, match="spectral must be None"):
        fit_batch(specs, P_E, starts, spectral="yes")
    from difftissue.scenarios import Indentation, indentation_block

    punch = Indentation(indentation_block((4e-3, 4e-3, 1.6e-3), (4, 4, 4)), np.array([1e-4, 2e-4]), np.ones(2), model="fem_linear",
                        indenter="flat_punch", radius=5e-4, symmetry="quarter")
    with pytest.raises(FitError, match="specimen 0: spectral=True: .*not a condensed indentation"):
        fit_batch([punch, punch], P_E, starts, spectral=True)


def test_batched_compression_fits_equal_the_serial_loop():
    """Bonded fem_linear compressions of a 288-tet block (this batch hung in earlier versions,
    while the optimiser state held the model's whole linearisation)."""
    cube = small_block()
    strains = np.array([0.02, 0.05, 0.1])
    probe = Compression(cube, strains, None, model="fem_linear", bonded=True, options=NAN, name="compression")
    specs, starts = [], []
    for E in (5e3, 9e3, 14e3):
        f = np.asarray(probe.predict(Material(E, 0.45)))
        specs.append(Compression(cube, strains, f * (1 + 0.01 * np.sin(np.arange(3) + E)), model="fem_linear", bonded=True, options=NAN, name="compression"))
        starts.append(Material(0.6 * E, 0.45))
    batch = fit_batch(specs, P_E, starts)
    serial = [fit(s, P_E, m) for s, m in zip(specs, starts)]
    assert_same_fits(batch, serial, rtol=1e-7, steps_tol=2)
    assert all(batch.converged)


def test_a_differing_float_leaf_is_batched_and_an_identifiability_warning_names_the_specimen():
    """Specimens with other depth protocols (a float leaf that is not data) are batched too;
    E and nu from one Hertz curve each: nu is not determined, said per specimen."""
    specs, starts = hertz_specimens(2, seed=4)
    other = np.linspace(10e-6, 150e-6, 15)
    f = np.asarray(hertz_force(other, 4e3, 0.45, 1e-3))
    specs[1] = AnalyticIndentation(other, f * (1 + 0.01 * np.random.default_rng(0).normal(size=15)), radius=1e-3, sigma=0.01 * f.max(), name="hertz")
    P_E_NU = MaterialParameterization(("youngs_modulus", "poisson_ratio"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batch = fit_batch(specs, P_E_NU, starts, labels=["left", "right"], max_steps=30)
    msgs = [str(w.message) for w in caught if issubclass(w.category, IdentifiabilityWarning)]
    assert any(m.startswith("specimen left: poisson_ratio") for m in msgs) and any(m.startswith("specimen right:") for m in msgs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        serial = [fit(s, P_E_NU, m, max_steps=30) for s, m in zip(specs, starts)]
    for a, s in zip(batch.fits, serial):
        assert a.values["youngs_modulus"] == pytest.approx(s.values["youngs_modulus"], rel=1e-6)
        assert a.steps == s.steps and "poisson_ratio" in a.unidentified


# ------------------------------------------------------------------ bad input
def test_bad_batches_are_refused_with_clear_errors():
    specs, starts = hertz_specimens(3)
    with pytest.raises(FitError, match="3 materials for 2 specimens"):
        fit_batch(specs[:2], P_E, starts)
    short = AnalyticIndentation(DEPTHS[:10], specs[0].observed[:10], radius=1e-3, name="hertz")
    with pytest.raises(FitError, match="specimen 1: scenario 'hertz' has 10 points, specimen 0 has 15"):
        fit_batch([specs[0], short], P_E, starts[0])
    other_radius = AnalyticIndentation(DEPTHS, specs[1].observed, radius=2e-3, name="hertz")
    with pytest.raises(FitError, match="specimen 1: scenario 'hertz' differs .* in size"):
        fit_batch([specs[0], other_radius], P_E, starts[0])
    renamed = AnalyticIndentation(DEPTHS, specs[1].observed, radius=1e-3, name="hertz-2")
    with pytest.raises(FitError, match="scenario names"):
        fit_batch([specs[0], renamed], P_E, starts[0])
    nan = eqx.tree_at(lambda s: s.observed, specs[2], np.where(np.arange(15) == 4, np.nan, specs[2].observed))
    with pytest.raises(FitError, match="specimen 2: scenario 'hertz': observed holds 1 non-finite"):
        fit_batch([specs[0], specs[1], nan], P_E, starts[0])
    with pytest.raises(FitError, match="non-fitted fields"):
        fit_batch(specs[:2], P_E, [starts[0], Material(3e3, 0.3)])
    with pytest.raises(FitError, match="non-empty sequence"):
        fit_batch([], P_E, starts[0])
    with pytest.raises(FitError, match="distinct"):
        fit_batch(specs[:2], P_E, starts[0], labels=["a", "a"])
    with pytest.raises(FitError, match="device_count"):
        specimen_mesh(len(jax.devices()) + 1)


def test_differing_topology_is_refused(cube):
    strains = np.array([0.01, 0.03])
    base = Compression(cube, strains, np.array([100.0, 300.0]), model="fem_linear", bonded=True, options=NAN, name="compression")
    other = small_block()
    # same shapes, other connectivity: the tets' nodes in another (even) order
    tets = np.asarray(other.tets)[:, [1, 2, 0, 3]]
    from difftissue.mesh import TetMesh

    renumbered = TetMesh(other.points, tets, other.region_ids, other.region_names)
    sc = Compression(renumbered, strains, np.array([100.0, 300.0]), model="fem_linear", bonded=True, options=NAN, name="compression")
    with pytest.raises(FitError, match="topology"):
        fit_batch([base, sc], P_E, Material(1e4, 0.45))


# ------------------------------------------------------------------ sharded (child process)
CHILD = textwrap.dedent(
    """
    import os, sys, json, warnings
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    sys.path.insert(0, {here!r})
    import test_batch as tb
    from difftissue.fit import fit_batch
    out = {{"devices": len(jax.devices())}}
    specs, starts = tb.hertz_specimens(6, seed=5)           # 6 specimens on 4 devices: 2 padded
    per_device = lambda w: [str(x.message) for x in w if "specimens per CPU device" in str(x.message)]
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        sharded = fit_batch(specs, tb.P_E, starts, starts=2, devices=4)
    given = json.loads(open({given!r}).read())
    serial = [tb.fit_from_summary(d) for d in given["hertz_serial"]]  # the parent's serial fits of these specimens
    tb.assert_same_fits(sharded, serial)
    out["hertz"] = {{"padding": sharded.padding, "devices": list(sharded.devices), "compilations": sharded.compilations, "warned": per_device(w)}}
    # simulated specimens (384-tet fem_linear sphere indentations): 5 on 4 devices, 3 padded,
    # two per device (a GSPMD-partitioned batch of this hung in XLA's CPU collectives). The
    # specimens' data and their serial fits come from the parent (tb.indentation_serial).
    specs = [tb.indentation_scenario(np.asarray(o), s) for o, s in zip(given["observed"], given["sigma"])]
    starts = [tb.Material(E, 0.45) for E in given["starts"]]
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        sharded = fit_batch(specs, tb.P_E, starts, devices=4)
    out["indentation_warned"] = per_device(w)
    serial = [tb.fit_from_summary(d) for d in given["serial"]]
    tb.assert_same_fits(sharded, serial, rtol=1e-6, steps_tol=2)
    out["indentation"] = {{"padding": sharded.padding, "converged": bool(all(sharded.converged)), "devices": list(sharded.devices)}}
    print("RESULT " + json.dumps(out))
    """
)


def test_sharded_fits_on_four_simulated_devices_equal_the_serial_loop(tmp_path, indentation_serial):
    specs, starts, serial = indentation_serial
    # The serial Hertz fits the child compares with run here, in this process (whose fit
    # engine cache already holds the compiled Levenberg-Marquardt step of these Hertz curves
    # when test_batched_hertz_fits_equal_the_serial_loop ran before): the child compiles only
    # its sharded programs. Exact floats through JSON (fit_summary).
    hertz_specs, hertz_starts = hertz_specimens(6, seed=5)
    hertz_serial = [fit_summary(fit(s, P_E, m, starts=2)) for s, m in zip(hertz_specs, hertz_starts)]
    given = tmp_path / "given.json"
    given.write_text(json.dumps({"hertz_serial": hertz_serial, "observed": [np.asarray(s.observed).tolist() for s in specs],
                                 "sigma": [float(np.asarray(s.sigma).flat[0]) for s in specs],
                                 "starts": [float(m.youngs_modulus) for m in starts], "serial": [fit_summary(r) for r in serial]}))
    script = tmp_path / "sharded.py"
    script.write_text(CHILD.format(here=os.path.dirname(os.path.abspath(__file__)), given=str(given)))
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env["JAX_PLATFORMS"] = "cpu"  # simulated CPU devices, also on a machine with a GPU
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    out = json.loads(line[len("RESULT "):])
    assert out["devices"] == 4
    assert out["hertz"]["padding"] == 2 and out["hertz"]["devices"] == ["cpu:0", "cpu:1", "cpu:2", "cpu:3"]
    assert out["hertz"]["compilations"] == 1
    # several specimens per device run (one program per device, no collectives): no warning
    assert out["hertz"]["warned"] == [] and out["indentation_warned"] == []
    assert out["indentation"] == {"padding": 3, "converged": True, "devices": ["cpu:0", "cpu:1", "cpu:2", "cpu:3"]}


def test_a_scenario_that_is_not_a_pytree_is_refused_by_name():
    import dataclasses

    @dataclasses.dataclass(frozen=True, eq=False)
    class Plain:
        name: str
        abscissa: np.ndarray
        observed: np.ndarray
        sigma: np.ndarray
        x_label: str = "depth [m]"
        y_label: str = "force [N]"

        def predict(self, m):
            return hertz_force(self.abscissa, m.youngs_modulus, m.poisson_ratio, 1e-3)

    specs, starts = hertz_specimens(2)
    plain = [Plain("hertz", DEPTHS, s.observed, s.sigma) for s in specs]
    with pytest.raises(FitError, match="not a pytree"):
        fit_batch(plain, P_E, starts)


def test_the_scale_page_example_runs_and_prints_its_table():
    """docs/scale.md's first example (5 Hertz specimens) runs and prints what the page shows."""
    import re

    from docblocks import exec_blocks, page_text, python_blocks

    shown = re.findall(r"prints one row per specimen.*?```\n(.*?)```", page_text("scale.md"), flags=re.S)[0]
    printed = exec_blocks("scale.md", python_blocks("scale.md")[:1]).splitlines()
    for line in shown.splitlines():
        if line.strip() != "...":
            assert line in printed, (line, printed)
