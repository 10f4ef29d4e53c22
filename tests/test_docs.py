"""The ``>>>`` examples in the user docs run and print what the docs show."""

import pytest
from docblocks import assert_doctests_pass
# installation.md demonstrates float32 round-off and must run without float64; it is not here.
PAGES = ["quickstart.md", "meshes.md", "materials.md"]


@pytest.mark.parametrize("page", PAGES)
def test_doc_examples(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert_doctests_pass(page)


def test_mkdocs_strict_build(tmp_path):
    """The manual builds with ``mkdocs build --strict``: no broken links or anchors, every
    page in the nav, the API reference generated from the docstrings (mkdocstrings). Needs the
    ``docs`` extra (``pip install ".[docs]"``); skipped without it."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    missing = [m for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python") if _find_spec(m) is None]
    if missing:
        pytest.skip(f"mkdocs build not checked: {', '.join(missing)} not installed (pip install '.[docs]')")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH", "")]))}
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-8000:]
    assert (tmp_path / "site" / "api" / "fit" / "index.html").is_file()
    assert "difftissue.fit.fit_batch" in (tmp_path / "site" / "api" / "fit" / "index.html").read_text()
    assert "difftissue.report.write_fit_outputs" in (tmp_path / "site" / "api" / "report" / "index.html").read_text()
    export_page = (tmp_path / "site" / "api" / "export" / "index.html").read_text()
    assert "difftissue.export.card.MaterialCard" in export_page and "difftissue.export.dispatch.export" in export_page


def _find_spec(name):
    import importlib.util

    try:
        return importlib.util.find_spec(name)
    except ModuleNotFoundError:  # a missing parent package
        return None


def test_the_code_blocks_of_cutting_md_run(tmp_path, monkeypatch):
    """Every python block of docs/cutting.md runs, in order in one namespace (the cut and its
    closure, the jitted scalpel sweep, a cut on a dome, pre-tension, the seed 003 surrogate, the incision), and
    the values its comments state hold."""
    import numpy as np
    from docblocks import exec_blocks, python_blocks

    blocks = python_blocks("cutting.md")
    assert len(blocks) == 6
    monkeypatch.chdir(tmp_path)
    ns = {}
    out = exec_blocks("cutting.md", blocks, ns)
    assert "cut quality:" in out and "max opening" in out and "max surface width" in out
    # The cut and its closure: pairs behind the scalpel open, those ahead stay tied.
    cut, o, s = ns["cut"], ns["o"], ns["s"]
    first = ns["cut_specimen"](ns["specimen"], ns["path"])
    released = np.asarray(first.pair_s) <= s
    width = np.asarray(o.width)
    assert released.any() and (~released).any()
    assert width[released].min() > 1e-7 and width[~released].max() < 1e-3 * width[released].min()
    # The sweep: the widest opening grows as the scalpel advances.
    sweep = [float(np.max(w)) for w in ns["sweep"]]
    assert sweep[0] > 1e-7 and np.all(np.diff(sweep) > 0)
    # The cut on a dome (R = 50 mm): its length is the arc over the 4 mm chord, 2 R asin(c / 2R).
    np.testing.assert_allclose(ns["dome_cut"].length, 2 * 50e-3 * np.arcsin(4e-3 / (2 * 50e-3)), rtol=1e-3)
    assert ns["dome_cut"].length > 4e-3 * (1 + 1e-5)
    # Pre-tension: the numbers in the comments.
    np.testing.assert_allclose(ns["T"], 23.70, rtol=2e-3)  # the model's own tension
    np.testing.assert_allclose(ns["T_lin"], 27.27, rtol=2e-3)  # the linear formula
    np.testing.assert_allclose(ns["lam0"], 1.0194, rtol=1e-4)
    np.testing.assert_allclose(ns["lam0_lin"], 1.0183, rtol=1e-4)
    # The surrogate: exact and smooth widths, copies w apart.
    w, w_smooth = np.asarray(ns["w"]), np.asarray(ns["w_smooth"])
    np.testing.assert_allclose(w, 0.5 * 1.1 * (1e-3 - ns["depths"]), rtol=1e-12, atol=1e-18)
    assert np.all(w_smooth <= w) and np.all(w - w_smooth <= 1e-5 * np.log(2))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(ns["side_a"]) - np.asarray(ns["side_b"]), axis=1), w, atol=1e-15)
    # The incision: the opening grows with the scalpel and the files are written.
    max_w = np.asarray(ns["max_w"])
    assert np.all(np.diff(max_w) >= -1e-12) and max_w[0] > 0
    np.testing.assert_allclose(max_w[-1], float(ns["res"].opening.max_width), rtol=1e-6)
    assert (tmp_path / "opened.png").is_file() and (tmp_path / "vtu" / "incision.pvd").is_file()
