"""The Griffith check of the cut topology (experiments/cut_griffith.py): a centre through-cut in
a thin plate under remote tension opens, in linear plane-stress elasticity, to
``w0 = 4 sigma a / E`` at its centre. fem_linear on the graded plate converges to it at first
order in the cell size (a crack tip on linear tets): the error halves with each refinement, and
the Richardson value of two levels lies within 1 % of Griffith (the two coarsest levels here;
docs/cutting.md, "Verification: a through-cut in a plate under tension": -27.0 / -13.6 / -6.4 /
-3.2 % at 2 / 4 / 8 / 16 cells per a, extrapolated -0.2 % from 16 and 32)."""

import sys
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import cut_griffith  # noqa: E402


def test_through_cut_converges_to_griffith_at_first_order():
    coarse, fine = (cut_griffith.run(cells_per_a=n) for n in (2, 4))
    assert coarse["w_ref"] == fine["w_ref"] == pytest.approx(4 * 10.0 * 2e-3 / 1e4)
    # the documented table, to its printed digits
    assert coarse["rel_err"] == pytest.approx(-0.270, abs=0.001)
    assert fine["rel_err"] == pytest.approx(-0.136, abs=0.001)
    # first order: the error halves
    assert 1.8 < coarse["rel_err"] / fine["rel_err"] < 2.4
    richardson = 2 * fine["w_centre"] - coarse["w_centre"]
    assert abs(richardson / fine["w_ref"] - 1) < 0.01
