"""fit.json's ``simulation`` record states the model and the resolution of every simulated
experiment (a fitted number belongs to them): the indentation's cells per contact radius
(tests/test_config_axisymmetric.py), and the mesh of a compression, fem_field or incision
(nodes, tets, median edge). No solve: the record is read from the scenario's model."""

from __future__ import annotations

import numpy as np
import pytest

from difftissue.analytic import hertz_force
from difftissue.config import parse_config
from difftissue.mesh import block
from difftissue.report import simulation_record
from difftissue.scenarios import AnalyticIndentation, Compression
from lattice_incision_config import incision_config

MM = 1e-3


def test_a_compression_states_its_mesh():
    sc = Compression(block((10 * MM, 10 * MM, 5 * MM), (2, 2, 1)), [0.05, 0.1], model="fem_linear", name="c")
    rec = simulation_record(sc)
    assert rec["name"] == "c" and rec["model"] == "fem_linear" and rec["geometry"] == "3d"
    assert rec["nodes"] == 3 * 3 * 2 and rec["tets"] == 2 * 2 * 1 * 6
    # the unique edges of the Freudenthal cubes (5 mm cells): 5 mm cube edges (the median here), 7.1 mm face
    # diagonals, 8.7 mm body diagonals
    assert rec["median_edge"] == pytest.approx(5 * MM, rel=1e-12)
    assert rec["resolution"] == "3-D mesh, 18 nodes, 24 tets, median edge 5 mm"


def test_an_incision_states_its_cut_mesh():
    (e,) = parse_config(incision_config("springs_volume")).experiments
    rec = simulation_record(e.scenario)
    mesh = e.scenario.cut.mesh
    assert rec["model"] == "springs_volume" and rec["nodes"] == mesh.n_nodes and rec["tets"] == len(mesh.tets)
    assert rec["median_edge"] == pytest.approx(MM, rel=1e-12)  # the 1 mm cubes' edges
    assert rec["resolution"] == f"3-D mesh, {mesh.n_nodes} nodes, {len(mesh.tets)} tets, median edge 1 mm"


def test_a_closed_form_has_no_simulation_record():
    d = np.linspace(1e-5, 1e-4, 5)
    sc = AnalyticIndentation(d, hertz_force(d, 1e4, 0.45, 1e-3), radius=1e-3)
    assert simulation_record(sc) is None
