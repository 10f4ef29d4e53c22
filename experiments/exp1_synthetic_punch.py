"""Experiment 1: synthetic recovery of E and nu from a scikit-fem flat-punch field.

scikit-fem (an independent linear-elasticity assembler) solves a bonded block indented by a
flat frictionless punch (prescribed u_z on the top nodes under the punch, base fully fixed)
with known E and nu, on the same Freudenthal tet mesh as :func:`difftissue.mesh.block`
(uniform cubes, so the springs_volume model's cube lattice is recovered from the file).
The field is written to a VTU with the node sets ``bottom`` and ``punch`` (int masks) and the
nodal reaction ``reaction = K u`` (N, 3) (nonzero only on prescribed DOFs). The file is read
back with :func:`difftissue.data.load_fem_result` and fitted with
:class:`difftissue.scenarios.FEMField` (prescribed: bottom xyz + punch z; reaction: sum of
the punch z reactions) by ``fem_linear`` and by ``springs_volume`` (E and nu free).

With ``--symmetry quarter`` only the quarter x, y >= 0 of the same block is modelled (by both
scikit-fem and the fitted models): the symmetry planes are the extra node sets ``symx``
(x = 0, u_x = 0) and ``symy`` (y = 0, u_y = 0), prescribed like the others; the reaction is the
quarter's punch force. The Freudenthal split is not mirror-symmetric, so the quarter is a
different (equally valid) P1 discretisation of the same problem, not a quarter of the full one.
``--cell-size`` sets the cube edge [mm] (1 mm: 3 cubes per punch radius). ``--probe`` only
compares the punch forces at the true material (no fit): a cheap convergence table.

Run:  python experiments/exp1_synthetic_punch.py [OUT_DIR] [--refine 2] [--symmetry quarter]
      [--cell-size 0.25] [--probe]                             (default OUT_DIR experiments/results/)
Writes OUT_DIR/exp1_punch{tag}.vtu, exp1_synthetic_punch{tag}.json and .png; prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue.data import load_fem_result  # noqa: E402
from difftissue.fit import fit  # noqa: E402
from difftissue.materials import Material, MaterialParameterization, ScaledLogit, lame_parameters  # noqa: E402
from difftissue.mesh import block, write_mesh  # noqa: E402
from difftissue.scenarios import FEMField, SolverOptions  # noqa: E402

E_TRUE, NU_TRUE = 12.0e3, 0.42  # Pa, -
SIZE = (12e-3, 12e-3, 6e-3)  # m: full block, punch on the axis of the top face
CELLS = (12, 12, 6)  # 1 mm cubes
PUNCH_RADIUS = 3.05e-3  # m: the top nodes within 3 mm of the axis (29 nodes)
DEPTH = 0.06e-3  # m (1 % of the thickness: small strain, the springs' geometric
#                  nonlinearity is negligible)
INITIAL = Material(youngs_modulus=8e3, poisson_ratio=0.33)


def make_mesh(cells=CELLS, symmetry: str = "none", size=SIZE):
    if symmetry == "quarter":
        return block((size[0] / 2, size[1] / 2, size[2]), cells, origin=(0.0, 0.0, 0.0))
    return block(size, cells, origin=(-size[0] / 2, -size[1] / 2, 0.0))


def make_reference(out: Path, cells=CELLS, tag: str = "", symmetry: str = "none", size=SIZE) -> Path:
    import skfem
    from skfem.models.elasticity import linear_elasticity

    mesh = make_mesh(cells, symmetry, size)
    p = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets)
    n = len(p)
    m = skfem.MeshTet(p.T.copy(), tets.T.copy())
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
    lam, mu = (float(v) for v in lame_parameters(E_TRUE, NU_TRUE))
    K = skfem.asm(linear_elasticity(lam, mu), basis).tocsr()
    perm = np.asarray(basis.nodal_dofs).T.reshape(-1)  # our DOF 3 a + c -> skfem DOF
    K = K[perm][:, perm]
    z = p[:, 2]
    bottom = np.isclose(z, 0.0)
    top = np.isclose(z, size[2])
    punch = top & (np.hypot(p[:, 0], p[:, 1]) <= PUNCH_RADIUS)
    fixed = np.zeros((n, 3), dtype=bool)
    fixed[bottom] = True
    fixed[punch, 2] = True
    sets = {"bottom": bottom, "punch": punch}
    if symmetry == "quarter":
        sets["symx"], sets["symy"] = np.isclose(p[:, 0], 0.0), np.isclose(p[:, 1], 0.0)
        fixed[sets["symx"], 0] = True
        fixed[sets["symy"], 1] = True
    u = np.zeros((n, 3))
    u[punch, 2] = -DEPTH
    fx, uf = fixed.reshape(-1), u.reshape(-1)
    free = ~fx
    import scipy.sparse.linalg as spla

    uf[free] = spla.spsolve(K[free][:, free].tocsc(), -K[free][:, fx] @ uf[fx])
    u = uf.reshape(n, 3)
    reaction = (K @ uf).reshape(n, 3)
    reaction[~fixed] = 0.0  # equilibrium residual of free DOFs (~1e-18 N) dropped
    path = out / f"exp1_punch{tag}.vtu"
    write_mesh(path, mesh, point_data={"displacement": u, "reaction": reaction, **{k: v.astype(np.int32) for k, v in sets.items()}}, overwrite=True)
    return path, int(punch.sum()), float(-reaction[punch, 2].sum())


def make_scenario(path: Path, model: str, linear_solver: str = "dense"):
    ref = load_fem_result(path)
    prescribed = [{"set": "bottom", "components": "xyz"}, {"set": "punch", "components": "z"}]
    if "symx" in ref.mesh.point_data:
        prescribed += [{"set": "symx", "components": "x"}, {"set": "symy", "components": "y"}]
    return FEMField(
        ref.mesh,
        ref.displacement,
        prescribed=prescribed,
        reaction={"set": "punch", "field": "reaction", "components": "z"},
        model=model,
        options=SolverOptions(linear_solver=linear_solver),
        name=f"punch_field_{model}",
    )


def probe_model(path: Path, model: str, linear_solver: str = "dense"):
    """Punch force of the model at the TRUE material vs the reference (no fit)."""
    sc = make_scenario(path, model, linear_solver)
    t0 = time.perf_counter()
    f_true = float(np.asarray(sc.predict(Material(E_TRUE, NU_TRUE)))[-1])
    return {"model": model, "force_error_at_true_material": f_true / sc.observed[-1] - 1.0, "solve_seconds": time.perf_counter() - t0, "n_unknowns": int(sc.observe_dofs.size)}


def fit_model(path: Path, model: str, linear_solver: str = "dense"):
    sc = make_scenario(path, model, linear_solver)
    t0 = time.perf_counter()
    # nu bounded to the range the model accepts (springs_volume: 1/4 <= nu < 1/2); the default
    # ScaledLogit(-1, 0.5) let a first Levenberg-Marquardt step saturate nu at -1 (NaN).
    lower = 0.25 if model == "springs_volume" else 0.0
    param = MaterialParameterization(("youngs_modulus", "poisson_ratio"), {"poisson_ratio": ScaledLogit(lower, 0.499)})
    # Gauss-Newton: Levenberg-Marquardt failed on its first step here (see docs/experiments.md).
    res = fit(sc, param, INITIAL, method="gauss_newton", max_steps=40)
    dt = time.perf_counter() - t0
    pred = res.predictions[sc.name]
    obs = sc.observed
    nu_obs = obs.size - 1
    rel_u = float(np.sqrt(np.mean((pred[:nu_obs] - obs[:nu_obs]) ** 2)) / np.abs(obs[:nu_obs]).max())
    rel_f = float(pred[-1] / obs[-1] - 1.0)
    # force of the punch predicted at the TRUE material by this model (a model-error measure)
    f_true = float(np.asarray(sc.predict(Material(E_TRUE, NU_TRUE)))[-1])
    return {
        "model": model,
        "E": res.values["youngs_modulus"],
        "E_se": res.standard_errors["youngs_modulus"],
        "nu": res.values["poisson_ratio"],
        "nu_se": res.standard_errors["poisson_ratio"],
        "E_error": res.values["youngs_modulus"] / E_TRUE - 1.0,
        "nu_error": res.values["poisson_ratio"] - NU_TRUE,
        "rms_displacement_error_rel_to_max": rel_u,
        "force_error_at_fit": rel_f,
        "force_error_at_true_material": f_true / obs[-1] - 1.0,
        "converged": res.converged,
        "steps": res.steps,
        "loss": res.loss,
        "fit_seconds": dt,
        "n_observations": int(obs.size),
    }, (obs[:nu_obs], pred[:nu_obs])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=str(Path(__file__).parent / "results"))
    ap.add_argument("--refine", type=int, default=1, help="cubes per mm (1: 12 x 12 x 6 cubes; 2: 24 x 24 x 12)")
    ap.add_argument("--cell-size", type=float, default=None, help="cube edge [mm] (overrides --refine; must divide 6 mm)")
    ap.add_argument("--size", type=float, nargs=3, default=None, metavar=("LX", "LY", "H"), help="whole block [mm] (default 12 12 6)")
    ap.add_argument("--symmetry", choices=("none", "quarter"), default="none", help="quarter: model x, y >= 0 with symmetry planes")
    ap.add_argument("--models", default="fem_linear,springs_volume", help="comma-separated models to fit")
    ap.add_argument("--probe", action="store_true", help="only compare the punch forces at the true material (no fit)")
    ap.add_argument("--linear-solver", default=None, help="default: dense up to 3000 unknowns, sparse otherwise")
    args = ap.parse_args()
    h = 1.0 / args.refine if args.cell_size is None else float(args.cell_size)
    size = SIZE if args.size is None else tuple(v * 1e-3 for v in args.size)
    cells = tuple(int(round(L * 1e3 / h)) for L in size)
    if not np.allclose(np.array(cells) * h, np.array(size) * 1e3) or (args.symmetry == "quarter" and (cells[0] % 2 or cells[1] % 2)):
        ap.error(f"--cell-size {h} mm does not divide the block {size} m")
    if args.symmetry == "quarter":
        cells = (cells[0] // 2, cells[1] // 2, cells[2])
    tag = "" if (h == 1.0 and args.symmetry == "none") else f"_refine{args.refine}" if (args.cell_size is None and args.symmetry == "none") else f"_{args.symmetry}_h{h:g}mm"
    if args.size is not None:
        tag += "_size" + "x".join(f"{v:g}" for v in args.size)
    n_nodes = (cells[0] + 1) * (cells[1] + 1) * (cells[2] + 1)
    solver = args.linear_solver or ("dense" if 3 * n_nodes <= 4500 else "sparse")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    path, n_punch, force = make_reference(out, cells, tag, args.symmetry, size)
    t_ref = time.perf_counter() - t0
    models = [m for m in args.models.split(",") if m]
    specimen = {"size_m": size, "symmetry": args.symmetry, "cell_size_m": h * 1e-3, "cells_per_punch_radius": 3.0 / h, "cells": cells, "nodes": n_nodes, "linear_solver": solver, "punch_radius_m": PUNCH_RADIUS, "punch_nodes": n_punch, "depth_m": DEPTH, "reference_force_N": force}
    if args.probe:
        rows = [probe_model(path, m, solver) for m in models]
        result = {"experiment": "exp1_synthetic_punch_probe", "specimen": specimen, "reference_seconds": t_ref, "probes": rows, "total_seconds": time.perf_counter() - t0}
        (out / f"exp1_probe{tag}.json").write_text(json.dumps(result, indent=2))
        for r in rows:
            print(f"| {args.symmetry} {size[0] * 1e3:g}x{size[1] * 1e3:g}x{size[2] * 1e3:g} | {h:g} mm | {3.0 / h:g} | {r['n_unknowns']} | {r['model']} | {100 * r['force_error_at_true_material']:+.3f} % | {r['solve_seconds']:.1f} s |")
        return
    rows, scatter = [], {}
    for model in models:
        row, sc = fit_model(path, model, solver)
        rows.append(row)
        scatter[model] = sc
    result = {
        "experiment": "exp1_synthetic_punch",
        "truth": {"youngs_modulus": E_TRUE, "poisson_ratio": NU_TRUE},
        "specimen": specimen,
        "targets": {"E_rel": 0.02, "nu_abs": 0.02},
        "reference_seconds": t_ref,
        "fits": rows,
        "total_seconds": time.perf_counter() - t0,
    }
    (out / f"exp1_synthetic_punch{tag}.json").write_text(json.dumps(result, indent=2))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, len(scatter), figsize=(4.5 * len(scatter), 4), squeeze=False)
    axs = axs[0]
    for ax, (model, (o, pr)) in zip(axs, scatter.items()):
        ax.plot(o * 1e6, pr * 1e6, ".", ms=2)
        lim = [o.min() * 1e6, o.max() * 1e6]
        ax.plot(lim, lim, "k-", lw=0.8)
        r = next(r for r in rows if r["model"] == model)
        ax.set_title(f"{model}: E = {r['E'] / 1e3:.3f} kPa, nu = {r['nu']:.4f}")
        ax.set_xlabel("scikit-fem displacement [um]")
        ax.set_ylabel("fitted model displacement [um]")
    fig.suptitle(f"Exp 1: flat punch field ({args.symmetry} symmetry, {h:g} mm cubes), truth E = {E_TRUE / 1e3:g} kPa, nu = {NU_TRUE}")
    fig.tight_layout()
    fig.savefig(out / f"exp1_synthetic_punch{tag}.png", dpi=110)

    print(f"| model | E [kPa] (truth {E_TRUE / 1e3:g}) | E error | nu (truth {NU_TRUE}) | nu error | force error at truth | fit time [s] | unknowns | target met |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ok = abs(r["E_error"]) <= 0.02 and abs(r["nu_error"]) <= 0.02
        print(f"| {r['model']} | {r['E'] / 1e3:.4f} ± {r['E_se'] / 1e3:.2g} | {100 * r['E_error']:+.2f} % | {r['nu']:.4f} ± {r['nu_se']:.2g} | {r['nu_error']:+.4f} | {100 * r['force_error_at_true_material']:+.2f} % | {r['fit_seconds']:.1f} | {r['n_observations'] - 1} | {'yes' if ok else 'NO'} |")
    print(f"\nreference: {n_punch} punch nodes, force {force * 1e3:.4f} mN, skfem solve {t_ref:.1f} s; total {result['total_seconds']:.0f} s")


if __name__ == "__main__":
    main()
