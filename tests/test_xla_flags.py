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


# --- The command line's XLA options (XLA_FLAGS set by `difftissue.cli.main`, and by conftest.py) ---

from difftissue import cli  # noqa: E402

_KNOWN = cli.xla_flags(None) is not None  # the installed jaxlib is one of cli.XLA_CPU_FLAGS_JAXLIB
_REDUCTION = ("import jax, jax.numpy as jnp\n"
              "text = jax.jit(lambda x: jnp.sum(jnp.sin(x) * jnp.exp(x))).lower(jnp.ones(100)).compile().as_text()\n"
              "print('NEW_FUSION=' + str('wrapped_reduce' in text))\n")


def test_xla_flags_add_the_cpu_option_and_keep_the_users_flags():
    assert cli.xla_flags(None, "0.10.2") == "--xla_cpu_use_fusion_emitters=false"
    assert cli.xla_flags("", "0.10.0") == "--xla_cpu_use_fusion_emitters=false"
    assert cli.xla_flags("--xla_force_host_platform_device_count=4", "0.10.2") == (
        "--xla_force_host_platform_device_count=4 --xla_cpu_use_fusion_emitters=false")
    for own in ("--xla_cpu_use_fusion_emitters=true", "--xla_dump_to=/tmp/x --xla_cpu_use_fusion_emitters true"):
        assert cli.xla_flags(own, "0.10.2") == own  # the user's own setting wins
    # a flag whose name only begins like the option's is another flag
    assert cli.xla_flags("--xla_cpu_use_fusion_emitters_x=1", "0.10.2").endswith(" --xla_cpu_use_fusion_emitters=false")


def test_a_jaxlib_not_known_to_have_the_options_gets_none():
    """XLA stops the process on an XLA_FLAGS flag it does not know: other releases get nothing."""
    for version in ("0.4.30", "0.9.1", "0.11.0", "1.10.0"):
        assert cli.xla_flags(None, version) is None
        assert cli.xla_flags("--xla_force_host_platform_device_count=4", version) == "--xla_force_host_platform_device_count=4"


@pytest.mark.skipif(not _KNOWN, reason="this jaxlib is not one cli.XLA_CPU_FLAGS_JAXLIB lists")
@pytest.mark.parametrize("user_flags", [None, "--xla_cpu_use_fusion_emitters=true"])
def test_the_command_line_sets_the_option_before_jax_compiles(user_flags):
    """`main` puts the option in XLA_FLAGS and XLA compiles with it: a reduction is then not
    a fusion of the newer emitters (``wrapped_reduce``); a user's own setting is kept and used."""
    code = "import os, difftissue.cli as c\nc.main([])\nprint('FLAGS=' + os.environ.get('XLA_FLAGS', ''))\n" + _REDUCTION
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if user_flags:
        env["XLA_FLAGS"] = user_flags
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300, check=True).stdout
    if user_flags is None:
        assert "FLAGS=--xla_cpu_use_fusion_emitters=false" in out and "NEW_FUSION=False" in out, out
    else:
        assert f"FLAGS={user_flags}\n" in out and "NEW_FUSION=True" in out, out


@pytest.mark.skipif(not _KNOWN, reason="this jaxlib is not one cli.XLA_CPU_FLAGS_JAXLIB lists")
def test_the_suite_compiles_with_the_command_lines_option():
    assert "--xla_cpu_use_fusion_emitters=" in os.environ.get("XLA_FLAGS", "")
    import jax
    import jax.numpy as jnp

    text = jax.jit(lambda x: jnp.sum(jnp.sin(x) * jnp.exp(x))).lower(jnp.ones(100)).compile().as_text()
    assert "wrapped_reduce" not in text
