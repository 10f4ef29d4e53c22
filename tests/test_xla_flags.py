"""The XLA CPU option of batched fits: set per program (``jax.jit(compiler_options=...)``),
never by editing ``XLA_FLAGS`` at import."""

import os
import subprocess
import sys

import numpy as np
import pytest

from difftissue import Material
from difftissue.analytic import hertz_force
from difftissue.fit import batch as batch_module
from difftissue.fit import fit_batch
from difftissue.materials import MaterialParameterization
from difftissue.scenarios import AnalyticIndentation


def test_importing_difftissue_leaves_the_environment_alone():
    code = "import os, difftissue, difftissue.fit, difftissue.cli; print('FLAGS=' + repr(os.environ.get('XLA_FLAGS')))"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300, check=True).stdout
    assert "FLAGS=None" in out, out


def _specimens(n_depths, moduli):
    depths = np.linspace(20e-6, 200e-6, n_depths)
    return [AnalyticIndentation(depths, np.asarray(hertz_force(depths, E, 0.45, 1e-3)), radius=1e-3, name="hertz") for E in moduli]


def test_batched_programs_are_compiled_with_the_cpu_options(monkeypatch):
    """The batched step is compiled with CPU_COMPILER_OPTIONS: an option XLA does not know
    makes the compilation fail, so the options do reach the compiler."""
    param = MaterialParameterization(("youngs_modulus",))
    good = fit_batch(_specimens(5, (3e3, 5e3)), param, [Material(2e3, 0.45)] * 2, max_steps=20)
    np.testing.assert_allclose(np.asarray(good.values)[:, 0], [3e3, 5e3], rtol=1e-6)
    monkeypatch.setattr(batch_module, "CPU_COMPILER_OPTIONS", {"xla_cpu_no_such_option_for_this_test": True})
    # another structure (7 depths): a new engine, compiled anew with the patched options
    with pytest.raises(Exception, match="xla_cpu_no_such_option_for_this_test"):
        fit_batch(_specimens(7, (3e3, 5e3, 7e3)), param, [Material(2e3, 0.45)] * 3, max_steps=20)
