"""Running exported Abaqus decks in CalculiX (``ccx``): the one place the tests find, run and
read it (tests/test_export_calculix.py).

* :func:`ccx_or_skip`: the ``ccx`` executable; skip with the reason when it is absent, FAIL when
  ``CI=true`` (``.ci/run`` installs Debian's ``calculix-ccx``, so an absent ``ccx`` there is a
  broken CI, not a reason to skip).
* :func:`run_deck`: run a deck in a fresh directory with a timeout; returns the summed reactions
  [N] that the deck prints (``*NODE PRINT, ..., TOTALS=ONLY``) and every node's displacement [m].
  :func:`run_ccx`: the bare run (exit status and output), for decks expected to fail.

The displacements come from one probe added to a copy of the deck: ``*NSET, NSET=DT_PROBE_ALL,
GENERATE`` (all nodes, before the first ``*STEP``) and ``*NODE PRINT, NSET=DT_PROBE_ALL`` with
``U`` (before ``*END STEP``). Output requests only: the model, loads and the deck's own
reaction print are run as written. CalculiX prints 7 significant digits (``-2.094658E-01``), so
every value read back carries up to 5e-7 relative rounding.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

PROBE = "DT_PROBE_ALL"
_HEAD = re.compile(r"^\s*(total force \(fx,fy,fz\)|displacements \(vx,vy,vz\)) for set (\S+) and time\s+(\S+)", re.I)


def ccx_or_skip() -> str:
    """Path of ``ccx`` on PATH. Absent: ``pytest.fail`` when the environment has ``CI=true``,
    else ``pytest.skip`` with how to install it."""
    exe = shutil.which("ccx")
    if exe:
        return exe
    if os.environ.get("CI") == "true":
        pytest.fail("CI=true but CalculiX (ccx) is not on PATH: .ci/run installs Debian's calculix-ccx", pytrace=False)
    pytest.skip("CalculiX (ccx) not on PATH (Debian/Ubuntu: apt-get install calculix-ccx); CalculiX tests not run")


@dataclass
class CalculixRun:
    """What one ccx run printed at the end of its step (the last time in the .dat).

    totals: ``{NSET: (3,) summed reaction force [N]}`` from the deck's ``TOTALS=ONLY`` prints.
    displacement: ``(N, 3)`` node displacements [m], node i + 1 in row i.
    time: the step time of those values (1.0 when the step completed).
    stdout: ccx's output (for messages on failure).
    """

    totals: dict
    displacement: np.ndarray
    time: float
    stdout: str


def _node_count(lines: list[str]) -> int:
    """Largest node id in the deck's ``*NODE`` blocks."""
    n, inside = 0, False
    for ln in lines:
        if ln.startswith("*"):
            inside = ln.split(",")[0].strip().upper() == "*NODE" and not ln.startswith("**")
            continue
        if inside and ln.strip():
            n = max(n, int(ln.split(",")[0]))
    return n


def with_displacement_probe(text: str) -> str:
    """``text`` plus the output requests that print every node's ``U`` to the .dat (module doc)."""
    lines = text.splitlines()
    n = _node_count(lines)
    step = next(i for i, ln in enumerate(lines) if ln.upper().startswith("*STEP"))
    end = max(i for i, ln in enumerate(lines) if ln.upper().startswith("*END STEP"))
    out = lines[:step] + [f"*NSET, NSET={PROBE}, GENERATE", f"1, {n}, 1"] + lines[step:end]
    out += [f"*NODE PRINT, NSET={PROBE}", "U"] + lines[end:]
    return "\n".join(out) + "\n"


def parse_dat(text: str, n_nodes: int, time: float | None = None) -> tuple[dict, np.ndarray, float]:
    """Summed reactions per set, the probe's displacements and their time, from the last time
    that a ``.dat`` prints (a nonlinear step prints every increment), or from the printed time
    nearest ``time``."""
    blocks: dict = {}
    cur = None
    for ln in text.splitlines():
        m = _HEAD.match(ln)
        if m:
            cur = ("F" if m.group(1).lower().startswith("total") else "U", m.group(2).upper(), float(m.group(3)))
            blocks[cur] = []
            continue
        vals = ln.split()
        if cur is not None and vals:
            blocks[cur].append([float(v) for v in vals])
    t_end = max(k[2] for k in blocks) if time is None else min({k[2] for k in blocks}, key=lambda t: abs(t - time))
    totals = {k[1]: np.array(v[0]) for k, v in blocks.items() if k[0] == "F" and k[2] == t_end}
    rows = np.array(blocks[("U", PROBE, t_end)])
    u = np.full((n_nodes, 3), np.nan)
    u[rows[:, 0].astype(int) - 1] = rows[:, 1:4]
    return totals, u, t_end


def run_ccx(text: str, workdir: Path, *, timeout: float = 120.0) -> tuple[int, str]:
    """Run the deck ``text`` as ``workdir/job.inp`` (``workdir`` created; one thread); returns
    ccx's exit status and output. Fails the test on a timeout."""
    exe = ccx_or_skip()
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / "job.inp").write_text(text)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CCX_NPROC_EQUATION_SOLVER": "1"}
    try:
        r = subprocess.run([exe, "-i", "job"], cwd=workdir, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail(f"ccx did not finish {workdir / 'job.inp'} within {timeout:g} s")
    return r.returncode, r.stdout + r.stderr


def run_deck(deck: Path, workdir: Path, *, timeout: float = 120.0) -> CalculixRun:
    """Run ``deck`` (an ``.inp`` file) with ccx in ``workdir`` after
    :func:`with_displacement_probe`. Fails the test on a timeout, a nonzero exit, an
    ``*ERROR`` in ccx's output or a step that did not reach time 1."""
    text = with_displacement_probe(Path(deck).read_text())
    rc, out = run_ccx(text, workdir, timeout=timeout)
    if rc != 0 or "*ERROR" in out or "Job finished" not in out:
        pytest.fail(f"ccx failed on {deck.name} (exit {rc}):\n{out[-3000:]}")
    totals, u, t = parse_dat((workdir / "job.dat").read_text(), _node_count(text.splitlines()))
    assert t == pytest.approx(1.0, abs=1e-9), f"the step stopped at time {t}"
    assert np.isfinite(u).all(), "the .dat lacks some nodes' displacements"
    return CalculixRun(totals, u, t, out)
