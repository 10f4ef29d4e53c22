"""Second-order hexahedral references (issue 19) solved by scikit-fem, an independent solver:
a bonded compression of a block (base clamped, top platen bonded and pressed down), linear
elasticity on ``ElementHex2`` (27-node, triquadratic) or ``ElementHexS2`` (20-node,
serendipity), written in VTK node order (``hexahedron27`` / ``hexahedron20``).

``python experiments/hex2_reference.py`` measures how well fem_field recovers E and nu from
such references against the model's resolution (fem_linear on a block) and the reference's
(experiments/results/hex2_reference_recovery.json; docs/dev/fem-field-interpolation.md).
"""

from __future__ import annotations

import numpy as np

from difftissue.interpolation import HEX27_FACES, HEX_EDGES, node_coordinates

L, H = 0.01, 0.005  # block L x L x H [m]
STRAIN = 0.01  # the top pressed down by STRAIN * H


def hex2_cells(basis, kind: str):
    """Nodes ``(N, 3)`` and VTK-ordered ``kind`` cells ``(M, k)`` of a scalar skfem basis on
    ``ElementHex2`` (``hexahedron27``) or ``ElementHexS2`` (``hexahedron20``) over an
    axis-aligned tensor mesh. Each element's DOFs are put in VTK order by their position
    relative to the element's centre (local coordinates -1, 0, 1), then checked: the mid-edge
    nodes are the midpoints of their corners, the face centres and body centre the means."""
    P = basis.doflocs.T  # (N, 3): the DOF of each node of a nodal (Lagrange) element
    dofs = basis.element_dofs.T  # (M, k)
    X = P[dofs]
    lo, hi = X.min(axis=1), X.max(axis=1)
    local = np.rint(2.0 * (X - (lo + hi)[:, None] / 2) / (hi - lo)[:, None]).astype(int)  # (M, k, 3)
    want = node_coordinates(kind).astype(int)
    k = len(want)
    if dofs.shape[1] != k:
        raise ValueError(f"{kind} needs {k} nodes per element, the basis has {dofs.shape[1]}")
    code = lambda a: (a[..., 0] + 1) * 9 + (a[..., 1] + 1) * 3 + (a[..., 2] + 1)  # noqa: E731
    pos = np.argsort(code(local), axis=1)
    rank = np.argsort(code(want))
    cells = np.take_along_axis(dofs, pos[:, np.argsort(rank)], axis=1)
    # the checks: each node where VTK puts it
    Y = P[cells]
    if not np.array_equal(code(np.rint(2.0 * (Y - (lo + hi)[:, None] / 2) / (hi - lo)[:, None]).astype(int)), np.broadcast_to(code(want), (len(cells), k))):
        raise RuntimeError("the nodes could not be put in VTK order")
    scale = float(np.abs(P).max())
    mids = np.stack([(Y[:, a] + Y[:, b]) / 2 for a, b in HEX_EDGES], axis=1)
    assert np.abs(Y[:, 8:20] - mids).max() <= 1e-12 * scale, "mid-edge nodes are not the edge midpoints"
    if kind == "hexahedron27":
        faces = np.stack([Y[:, list(f)].mean(axis=1) for f in HEX27_FACES], axis=1)
        assert np.abs(Y[:, 20:26] - faces).max() <= 1e-12 * scale and np.abs(Y[:, 26] - Y[:, :8].mean(axis=1)).max() <= 1e-12 * scale
    return P.copy(), cells


def platen(x, y, strain: float = STRAIN):
    """The top's prescribed z displacement [m]: a curved frictionless platen, pressed down
    ``strain * H`` at the block's corner (0, 0) and half that at (L, L)."""
    return -strain * H * (1.0 - 0.25 * ((x / L) ** 2 + (y / L) ** 2))


def curved_platen(kind: str, n, *, E: float = 12e3, nu: float = 0.42, size=(L, L, H)):
    """scikit-fem's solution of a quarter block (rollers on x = 0, y = 0, z = 0) pressed by the
    curved frictionless platen :func:`platen` on top (a smooth, non-affine field), on an
    ``n[0] x n[1] x n[2]`` hex grid: ``(points, cells, u, force)`` with ``force`` the top's z
    reaction [N]."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    element = {"hexahedron27": skfem.ElementHex2, "hexahedron20": skfem.ElementHexS2}[kind]()
    m = skfem.MeshHex.init_tensor(*[np.linspace(0.0, s, k + 1) for s, k in zip(size, n)])
    sb = skfem.Basis(m, element, intorder=4)
    vb = skfem.Basis(m, skfem.ElementVector(element), intorder=4)
    assert np.array_equal(vb.element_dofs[0::3], 3 * sb.element_dofs), "vector DOFs are not interleaved"
    points, cells = hex2_cells(sb, kind)
    K = skfem.asm(linear_elasticity(*lame_parameters(E, nu)), vb).tocsr()
    on = lambda a, v: np.flatnonzero(np.abs(points[:, a] - v) <= 1e-12 * H)  # noqa: E731
    top = on(2, size[2])
    fixed = np.unique(np.concatenate([3 * on(0, 0.0), 3 * on(1, 0.0) + 1, 3 * on(2, 0.0) + 2, 3 * top + 2]))
    x = np.zeros(vb.N)
    x[3 * top + 2] = platen(points[top, 0], points[top, 1])
    x = skfem.solve(*skfem.condense(K, np.zeros(vb.N), x=x, D=fixed))
    return points, cells, x.reshape(-1, 3), float((K @ x)[3 * top + 2].sum())


def recover(kind: str, ref_cells, model_cells, *, E: float = 12e3, nu: float = 0.42) -> dict:
    """Fit E and nu by fem_field (fem_linear on a ``model_cells`` block, the reference
    interpolated onto it) to :func:`curved_platen`'s solution on ``ref_cells`` elements."""
    import time

    from difftissue import Material
    from difftissue.config import SeparatelyCompiled
    from difftissue.data.fem import FEMResult
    from difftissue.fit import fit
    from difftissue.materials import MaterialParameterization, ScaledLogit
    from difftissue.mesh import block
    from difftissue.scenarios import FEMField

    t0 = time.process_time()
    P, C, u, F = curved_platen(kind, ref_cells, E=E, nu=nu)
    top = {"face": "z-max"}
    prescribed = [{"set": {"face": "x-min"}, "components": "x"}, {"set": {"face": "y-min"}, "components": "y"},
                  {"set": {"face": "z-min"}, "components": "z"}, {"set": top, "components": "z"}]
    sc = FEMField(FEMResult(None, u, points=P, cells={kind: C}), u, prescribed=prescribed, specimen=block((L, L, H), model_cells),
                  model="fem_linear", reaction={"set": top, "components": "z", "force": [F]})
    p = MaterialParameterization(("youngs_modulus", "poisson_ratio"), transforms={"poisson_ratio": ScaledLogit(0.0, 0.5)})
    res = fit([SeparatelyCompiled(sc, fields=p.fields)], p, Material(8e3, 0.3))
    h = L / model_cells[0]
    # Betti with the uniaxial field (in both spaces): the top force is E / H times the integral
    # of the top's displacement, the model's being the P1 interpolant of the platen on its grid
    E_expected = E * (5.0 / 6.0) / (5.0 / 6.0 - (h / L) ** 2 / 12.0)
    return dict(kind=kind, ref_cells=list(ref_cells), model_cells=list(model_cells), ref_nodes=len(P), force=F,
                E=res.values["youngs_modulus"], nu=res.values["poisson_ratio"], E_rel_error=res.values["youngs_modulus"] / E - 1,
                E_rel_vs_expected=res.values["youngs_modulus"] / E_expected - 1, nu_rel_error=res.values["poisson_ratio"] / nu - 1,
                converged=bool(res.converged), cpu_s=time.process_time() - t0)


def main():
    import json
    from pathlib import Path

    import jax

    jax.config.update("jax_enable_x64", True)
    runs = [(k, r, m) for k in ("hexahedron27", "hexahedron20") for r, m in
            [((2, 2, 1), (4, 4, 2)), ((3, 3, 2), (4, 4, 2)), ((4, 4, 2), (4, 4, 2)), ((8, 8, 4), (4, 4, 2)), ((2, 2, 1), (8, 8, 4)), ((8, 8, 4), (8, 8, 4))]]
    out = []
    for k, r, m in runs:
        out.append(recover(k, r, m))
        print(out[-1], flush=True)
    path = Path(__file__).parent / "results" / "hex2_reference_recovery.json"
    path.write_text(json.dumps({"problem": "quarter block 10 x 10 x 5 mm, rollers, curved frictionless platen (platen()), E = 12 kPa, nu = 0.42; "
                                           "reference scikit-fem ElementHex2 / ElementHexS2; model fem_linear on a block",
                                "runs": out}, indent=1) + "\n")


if __name__ == "__main__":
    main()
