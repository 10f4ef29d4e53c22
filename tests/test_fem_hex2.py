"""fem_field on second-order hexahedral references (issue 19): the 20-node serendipity
(``hexahedron20``: Abaqus C3D20, FEBio hex20) and 27-node triquadratic (``hexahedron27``:
FEBio hex27) hexahedra in VTK node order — shape functions, the interpolation operator, the
reference files (VTU, XDMF, Abaqus .inp) and a fit to a reference solved by scikit-fem
(experiments/hex2_reference.py; docs/dev/fem-field-interpolation.md)."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from difftissue import errors
from difftissue.data import load_fem_result
from difftissue.interpolation import interpolation_operator, node_coordinates, shape_functions, shape_gradients

L, H = 0.01, 0.005
QUADRATIC_HEXES = ("hexahedron20", "hexahedron27")

# The nodes' local coordinates written out from VTK's own tables (vtkQuadraticHexahedron,
# vtkTriQuadraticHexahedron parametric coordinates in [0, 1], here 2 r - 1), independent of
# the implementation: corners, mid-edge nodes of (0,1) (1,2) (2,3) (3,0) (4,5) (5,6) (6,7)
# (7,4) (0,4) (1,5) (2,6) (3,7), face centres x-min x-max y-min y-max z-min z-max, centre.
VTK_HEX27 = np.array([
    [-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1],
    [0, -1, -1], [1, 0, -1], [0, 1, -1], [-1, 0, -1], [0, -1, 1], [1, 0, 1], [0, 1, 1], [-1, 0, 1],
    [-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],
    [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1], [0, 0, 0]], dtype=float)


def _serendipity(e):
    """Is xi^a eta^b zeta^c in the 20-node serendipity space? The trilinear monomials (8) and
    those with one exponent 2, the others at most 1 (12)."""
    return sum(1 for a in e if a == 2) <= 1


def _eval_monomials(exps, x):
    return np.stack([np.prod(x ** np.array(e), axis=1) for e in exps], axis=1)


def test_quadratic_hex_shape_functions():
    """Partition of unity, gradients (central differences), Kronecker delta at the nodes in
    VTK's order, and reproduction of the whole element space (27 triquadratic monomials; the
    20 serendipity monomials, but not x^2 y^2)."""
    rng = np.random.default_rng(0)
    xi = rng.uniform(-1.0, 1.0, (9, 3))
    for kind in QUADRATIC_HEXES:
        k = int(kind[len("hexahedron"):])
        nodes = VTK_HEX27[:k]
        np.testing.assert_array_equal(node_coordinates(kind), nodes)
        np.testing.assert_allclose(shape_functions(kind, nodes), np.eye(k), rtol=0, atol=1e-15)
        N = shape_functions(kind, xi)
        np.testing.assert_allclose(N.sum(axis=1), 1.0, rtol=0, atol=1e-14)
        np.testing.assert_allclose(shape_gradients(kind, xi).sum(axis=1), 0.0, rtol=0, atol=1e-13)
        e = 1e-6
        fd = np.stack([(shape_functions(kind, xi + e * d) - shape_functions(kind, xi - e * d)) / (2 * e) for d in np.eye(3)], axis=2)
        np.testing.assert_allclose(shape_gradients(kind, xi), fd, rtol=0, atol=1e-8)
        exps = [e_ for e_ in itertools.product(range(3), repeat=3) if kind == "hexahedron27" or _serendipity(e_)]
        assert len(exps) == k
        np.testing.assert_allclose(N @ _eval_monomials(exps, nodes), _eval_monomials(exps, xi), rtol=0, atol=1e-13)
    # the serendipity element does not hold x^2 y^2 (the check can fail)
    bad = _eval_monomials([(2, 2, 0)], VTK_HEX27[:20])
    assert np.abs(shape_functions("hexahedron20", xi) @ bad - _eval_monomials([(2, 2, 0)], xi)).max() > 1e-2


def _quadratic_hex_grid(kind, n, size=(L, L, H)):
    """``(points, cells)`` of an ``n[0] x n[1] x n[2]`` grid of ``kind`` cells (VTK order) on
    the box [0, size]: the nodes of a grid of half the spacing (20 nodes: those at the face and
    body centres dropped)."""
    m = [2 * k + 1 for k in n]
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in m], indexing="ij"), axis=-1).reshape(-1, 3)
    keep = np.ones(len(ijk), dtype=bool) if kind == "hexahedron27" else (ijk % 2 == 1).sum(axis=1) <= 1
    index = np.full(len(ijk), -1)
    index[keep] = np.arange(keep.sum())
    pts = ijk[keep] * (np.array(size) / (np.array(m) - 1))
    local = node_coordinates(kind).astype(int)
    origins = np.stack(np.meshgrid(*[2 * np.arange(k) + 1 for k in n], indexing="ij"), axis=-1).reshape(-1, 3)
    nodes = origins[:, None, :] + local[None]
    cells = index[(nodes[..., 0] * m[1] + nodes[..., 1]) * m[2] + nodes[..., 2]]
    assert (cells >= 0).all()
    return pts, cells


def _check_mid_nodes(kind, P, cells):
    """The mid-edge (and face, body centre) nodes at the midpoints (means) of their corners."""
    from difftissue.interpolation import HEX27_FACES, HEX_EDGES

    Y = P[cells]
    np.testing.assert_allclose(Y[:, 8:20], np.stack([(Y[:, a] + Y[:, b]) / 2 for a, b in HEX_EDGES], axis=1), rtol=0, atol=1e-15)
    if kind == "hexahedron27":
        np.testing.assert_allclose(Y[:, 20:26], np.stack([Y[:, list(f)].mean(axis=1) for f in HEX27_FACES], axis=1), rtol=0, atol=1e-15)
        np.testing.assert_allclose(Y[:, 26], Y[:, :8].mean(axis=1), rtol=0, atol=1e-15)


@pytest.mark.parametrize("kind", QUADRATIC_HEXES)
def test_operator_exact_for_quadratic_fields_on_quadratic_hexes(tmp_path, kind):
    """The operator on a 3 x 2 x 2 grid read back from VTU and XDMF: exact for quadratic fields
    on a sheared (affine-mapped) grid, for the element's whole space (triquadratic / x^2 y z) on
    an axis-aligned one; on curved elements (mid-side nodes moved) exact for affine fields and
    for fields in the element's space of the local coordinates, not for a quadratic field."""
    rng = np.random.default_rng(1)
    P0, cells = _quadratic_hex_grid(kind, (3, 2, 2))
    _check_mid_nodes(kind, P0, cells)
    A = np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3))
    sheared = P0 @ A.T + 1e-3
    Q = rng.normal(size=(3, 3, 3))
    b = rng.normal(size=(3, 3))
    quad = lambda x: np.einsum("ijk,nj,nk->ni", Q, x / L, x / L) + (x / L) @ b.T  # noqa: E731
    full = {"hexahedron27": lambda x: np.stack([x[:, 0] ** 2 * x[:, 1] ** 2 * x[:, 2] ** 2 / L**6, x[:, 0] * x[:, 1] ** 2 * x[:, 2] / L**4,
                                                x[:, 2] ** 2 * x[:, 0] ** 2 / L**4], axis=1),
            "hexahedron20": lambda x: np.stack([x[:, 0] ** 2 * x[:, 1] * x[:, 2] / L**4, x[:, 0] * x[:, 1] * x[:, 2] / L**3,
                                                x[:, 1] ** 2 * x[:, 2] / L**3], axis=1)}[kind]
    u01 = rng.uniform(0.0, 1.0, (300, 3))
    for fmt in ("vtu", "xdmf"):
        for pts, field in ((sheared, quad), (P0, full), (P0, quad)):
            meshio.write(tmp_path / f"ref.{fmt}", meshio.Mesh(pts, [(kind, cells)], point_data={"displacement": 1e-4 * field(pts)}))
            ref = load_fem_result(tmp_path / f"ref.{fmt}")
            assert ref.mesh is None and list(ref.cells) == [kind] and ref.metadata["cell_types"] == [kind]
            q = (u01 * [L, L, H]) @ (A.T if pts is sheared else np.eye(3)) + (1e-3 if pts is sheared else 0.0)
            op = interpolation_operator(ref.points, ref.cells, q)
            assert op.distances.max() == 0.0
            np.testing.assert_allclose(np.asarray(op(ref.displacement)), 1e-4 * field(q), rtol=0, atol=1e-16 * np.abs(field(q)).max(), err_msg=fmt)
    # curved: every non-corner node moved by up to 10 % of a cell
    moved = P0.copy()
    corner = np.zeros(len(P0), dtype=bool)
    corner[cells[:, :8]] = True
    h = np.array([L / 3, L / 2, H / 2])
    moved[~corner] += 0.1 * h * rng.uniform(-1, 1, ((~corner).sum(), 3))
    el = rng.integers(0, len(cells), 200)
    q = np.einsum("nk,nkd->nd", shape_functions(kind, rng.uniform(-0.95, 0.95, (200, 3))), moved[cells[el]])  # inside the curved elements
    B = rng.normal(size=(3, 3))
    f = lambda x: x @ B.T / L + 1.0  # noqa: E731
    meshio.write(tmp_path / "curved.vtu", meshio.Mesh(moved, [(kind, cells)], point_data={"displacement": np.zeros_like(moved)}))
    assert list(load_fem_result(tmp_path / "curved.vtu").cells) == [kind]  # curved, not refused
    op = interpolation_operator(moved, {kind: cells}, q)
    assert op.distances.max() == 0.0
    np.testing.assert_allclose(np.asarray(op(f(moved))), f(q), rtol=0, atol=1e-12)
    assert np.abs(np.asarray(op(quad(moved))) - quad(q)).max() > 1e-4 * np.abs(quad(moved)).max()
    # one curved element: a field of its space in the local coordinates is reproduced at x(xi)
    X = moved[cells[0]]
    xi = rng.uniform(-0.9, 0.9, (50, 3))
    g = lambda s: np.stack([s[:, 0] ** 2 * s[:, 1] + s[:, 2], s[:, 1] ** 2 - s[:, 0] * s[:, 2], s[:, 0] * s[:, 1] * s[:, 2]], axis=1)  # noqa: E731
    op = interpolation_operator(X, {kind: np.arange(len(X))[None]}, shape_functions(kind, xi) @ X)
    np.testing.assert_allclose(np.asarray(op(g(node_coordinates(kind)))), g(xi), rtol=0, atol=1e-11)


def test_abaqus_c3d20_and_c3d27(tmp_path):
    """An Abaqus C3D20R mesh (labels not 1..N) with a displacement table reads as hexahedron20
    (meshio keeps Abaqus's node order, which is VTK's) and interpolates a quadratic field
    exactly; C3D27, which meshio cannot read, is refused with the fix."""
    P, cells = _quadratic_hex_grid("hexahedron20", (2, 1, 1))
    labels = 1000 + 7 * np.arange(len(P))[::-1]
    lines = ["*HEADING", "hand-written C3D20R", "*NODE"] + [f"{k}, {float(x)!r}, {float(y)!r}, {float(z)!r}" for k, (x, y, z) in zip(labels, P * 1e3)]
    lines += ["*ELEMENT, TYPE=C3D20R, ELSET=tissue"]
    for e, c in enumerate(cells):
        ids = [str(labels[i]) for i in c]
        lines += [f"{e + 1}, " + ", ".join(ids[:15]) + ",", ", ".join(ids[15:])]  # Abaqus: at most 16 entries a line
    (tmp_path / "ref.inp").write_text("\n".join(lines) + "\n")
    f = lambda x: np.stack([(x[:, 0] / L) ** 2, x[:, 1] * x[:, 2] / L**2, x[:, 0] * x[:, 2] / L**2], axis=1) * 1e-4  # noqa: E731
    u = f(P)
    (tmp_path / "u.csv").write_text("node,ux,uy,uz\n" + "".join(f"{k},{float(a) * 1e3!r},{float(b) * 1e3!r},{float(c) * 1e3!r}\n"
                                                                 for k, (a, b, c) in zip(labels, u)))
    ref = load_fem_result(tmp_path / "ref.inp", length_unit="mm", displacement_table=tmp_path / "u.csv")
    assert list(ref.cells) == ["hexahedron20"] and ref.mesh is None
    np.testing.assert_array_equal(ref.cells["hexahedron20"], cells)
    q = np.random.default_rng(2).uniform(0, 1, (100, 3)) * [L, L / 2, H / 2]
    op = interpolation_operator(ref.points, ref.cells, q)
    np.testing.assert_allclose(np.asarray(op(ref.displacement)), f(q), rtol=0, atol=1e-12 * np.abs(f(q)).max())
    P27, c27 = _quadratic_hex_grid("hexahedron27", (1, 1, 1))
    lines = ["*NODE"] + [f"{k + 1}, {x}, {y}, {z}" for k, (x, y, z) in enumerate(P27)] + ["*ELEMENT, TYPE=C3D27"]
    ids = [str(i + 1) for i in c27[0]]
    lines += ["1, " + ", ".join(ids[:15]) + ",", ", ".join(ids[15:])]
    (tmp_path / "c3d27.inp").write_text("\n".join(lines) + "\n")
    with pytest.raises(errors.UnsupportedMeshError, match="cannot read Abaqus C3D27.*VTU or XDMF"):
        load_fem_result(tmp_path / "c3d27.inp")


@pytest.mark.parametrize("kind", QUADRATIC_HEXES)
def test_misordered_or_flat_quadratic_hexes_are_refused(tmp_path, kind):
    """A quadratic hexahedron written in Gmsh's node order (not VTK's), or with two mid-edge
    nodes of parallel edges swapped, or flat, is refused: its Jacobian (at the centre and the
    nodes) changes sign or vanishes."""
    from meshio.gmsh.common import _meshio_to_gmsh_order

    P, cells = _quadratic_hex_grid(kind, (2, 1, 1))
    swapped = cells.copy()
    swapped[:, [8, 10]] = swapped[:, [10, 8]]
    flat = P.copy()
    flat[:, 2] = 0.0
    for pts, c in ((P, _meshio_to_gmsh_order(kind, cells)), (P, swapped), (flat, cells)):
        meshio.write(tmp_path / "bad.vtu", meshio.Mesh(pts, [(kind, c)], point_data={"displacement": np.zeros_like(P)}))
        with pytest.raises(errors.DegenerateElementError, match=rf"{kind} cells \[0, 1\] are degenerate or inverted.*VTK order"):
            load_fem_result(tmp_path / "bad.vtu")


# ============================================================ fit to a scikit-fem reference
@pytest.mark.parametrize("kind", QUADRATIC_HEXES)
def test_skfem_hex2_reference_recovers_E_and_nu(tmp_path, kind):
    """A reference solved by scikit-fem on 3 x 3 x 2 ElementHex2 / ElementHexS2 elements (a
    quarter block on rollers pressed by a curved frictionless platen: a smooth, non-affine
    field), written as VTU in VTK order, read back and fitted by fem_linear on a 4 x 4 x 2 grid.

    E: the top's force is E / H times the integral of the top's displacement in both
    discretisations (Betti with the uniaxial field, which both spaces hold), so the reference's
    force is exact and the fitted E is the model's own, E (5/6) / (5/6 - (h/L)^2 / 12) with the
    P1 interpolant of the platen on its grid (h = L/4: +0.63 %): asserted to 1e-6, which needs
    the platen's values transferred exactly (quadratic) by the element's shape functions. nu:
    the model's and the reference's discretisation (experiments/results/
    hex2_reference_recovery.json: -8e-6 for hex27, -2.6e-3 for hex20 here; the model alone,
    against an 8 x 8 x 4 reference, +2.7e-3 / +1.3e-3): asserted to 5e-3."""
    pytest.importorskip("skfem")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    import hex2_reference as R

    from difftissue import Material
    from difftissue.config import SeparatelyCompiled
    from difftissue.fit import fit
    from difftissue.materials import MaterialParameterization, ScaledLogit
    from difftissue.mesh import block
    from difftissue.scenarios import FEMField

    E, nu = 12e3, 0.42
    P, cells, u, force = R.curved_platen(kind, (3, 3, 2), E=E, nu=nu)
    _check_mid_nodes(kind, P, cells)  # skfem's DOFs put in VTK order
    top = np.abs(P[:, 2] - H) < 1e-12
    np.testing.assert_allclose(u[top, 2], R.platen(P[top, 0], P[top, 1]), rtol=0, atol=1e-18)  # its displacement too
    meshio.write(tmp_path / "ref.vtu", meshio.Mesh(P * 1e3, [(kind, cells)], point_data={"displacement": u * 1e3}))
    ref = load_fem_result(tmp_path / "ref.vtu", length_unit="mm")
    faces = {f: {"face": f} for f in ("x-min", "y-min", "z-min", "z-max")}
    prescribed = [{"set": faces["x-min"], "components": "x"}, {"set": faces["y-min"], "components": "y"},
                  {"set": faces["z-min"], "components": "z"}, {"set": faces["z-max"], "components": "z"}]
    sc = FEMField(ref, ref.displacement, prescribed=prescribed, specimen=block((L, L, H), (4, 4, 2)), model="fem_linear",
                  reaction={"set": faces["z-max"], "components": "z", "force": [force]})
    p = MaterialParameterization(("youngs_modulus", "poisson_ratio"), transforms={"poisson_ratio": ScaledLogit(0.0, 0.5)})
    res = fit([SeparatelyCompiled(sc, fields=p.fields)], p, Material(8e3, 0.3))
    assert res.converged
    assert res.values["youngs_modulus"] == pytest.approx(E * (5 / 6) / (5 / 6 - (1 / 4) ** 2 / 12), rel=1e-6)
    assert res.values["poisson_ratio"] == pytest.approx(nu, rel=5e-3)
