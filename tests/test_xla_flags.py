"""difftissue/_xla.py: the XLA CPU flag set at import (against a deadlock of batched fits)."""

import os
import subprocess
import sys

FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
CODE = "import os, difftissue; print('FLAGS=' + os.environ.get('XLA_FLAGS', ''))"


def _flags(env_update):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "DIFFTISSUE_KEEP_XLA_FLAGS")}
    env.update(env_update)
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, env=env, timeout=300, check=True).stdout
    return [ln for ln in out.splitlines() if ln.startswith("FLAGS=")][-1][len("FLAGS="):]


def test_import_appends_the_flag_and_keeps_the_users_flags():
    assert _flags({}) == f"{FLAG}=false"
    assert _flags({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}) == f"--xla_force_host_platform_device_count=4 {FLAG}=false"


def test_a_flag_the_user_set_or_an_opt_out_is_respected():
    assert _flags({"XLA_FLAGS": f"{FLAG}=true"}) == f"{FLAG}=true"
    assert _flags({"DIFFTISSUE_KEEP_XLA_FLAGS": "1"}) == ""


def test_no_flag_once_jax_has_started_and_fit_batch_warns():
    code = ("import jax, jax.numpy as jnp, os, warnings; jnp.ones(1).block_until_ready(); import difftissue; "
            "print('FLAGS=' + os.environ.get('XLA_FLAGS', '')); "
            "from difftissue.fit import fit_batch\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    try:\n        fit_batch([], None, None)\n    except Exception:\n        pass\n"
            "print('WARNED=' + str(any('deadlock' in str(x.message) for x in w)))")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "DIFFTISSUE_KEEP_XLA_FLAGS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300, check=True).stdout
    assert "FLAGS=\n" in out + "\n" and "WARNED=True" in out, out
