"""Experiment 2: Ecoflex 00-10 (EF10_50T) unconfined compression: small-strain E and strain stiffening.

Data: ``data/compression/EF10_50T_A1.csv`` (Tissue Phantom Material Database, CC BY 4.0), read
with :func:`difftissue.data.load_instron_compression`, loading segment, engineering strain and
stress (compression positive). The authors report E = 16.29 +- 0.40 kPa for EF10_50T.

1. Small-strain E: least-squares line ``stress = E strain + c`` (intercept absorbs the
   preload/toe offset) over engineering strain 0-10 % (main value) and 0-5 % (for comparison).
2. The springs_volume model (cubic springs + cell volume) in a
   :class:`difftissue.scenarios.Compression` scenario (frictionless platens, so the
   deformation is homogeneous and a 2 x 2 x 2-cube block is exact for any specimen shape),
   E and the cubic coefficient b fitted to the engineering stress up to 40 % strain with nu
   fixed at 0.45 (a uniaxial curve does not determine nu; in this model nu also sets the
   geometric stiffening: with nu = 0.49 the b = 0 curve is already stiffer than the data at
   40 % and the fit needs b < 0, which makes the Newton solves fail).
   Reported: RMS residual [kPa] and relative to the RMS stress, up to 40 % strain, and the
   model's extrapolation to 55 %.

Run:  python experiments/exp2_ecoflex.py [OUT_DIR]   (default experiments/results/)
Writes OUT_DIR/exp2_ecoflex.json and .png; prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue.data import load_instron_compression  # noqa: E402
from difftissue.fit import fit  # noqa: E402
from difftissue.materials import Material, MaterialParameterization  # noqa: E402
from difftissue.mesh import block  # noqa: E402
from difftissue.scenarios import Compression, SolverOptions  # noqa: E402

DATA = Path(__file__).resolve().parent.parent / "data" / "compression" / "EF10_50T_A1.csv"
E_AUTHORS = 16.29e3  # Pa
NU = 0.45
MAX_STRAIN = 0.40
N_POINTS = 40
LINEAR_RANGES = ((0.0, 0.10), (0.0, 0.05))


def linear_E(strain, stress, lo, hi):
    m = (strain >= lo) & (strain <= hi)
    E, c = np.polyfit(strain[m], stress[m], 1)
    return float(E), float(c), int(m.sum())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=str(Path(__file__).parent / "results"))
    ap.add_argument("--method", default="gauss_newton")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    curve = load_instron_compression(DATA).loading()
    e, s = curve.strain, curve.stress

    lin = []
    for lo, hi in LINEAR_RANGES:
        E, c, n = linear_E(e, s, lo, hi)
        lin.append({"strain_range": [lo, hi], "E": E, "intercept_Pa": c, "n_points": n, "error_vs_authors": E / E_AUTHORS - 1.0})

    # springs_volume fit up to 40 % strain: N_POINTS samples, evenly spaced in strain
    targets = np.linspace(MAX_STRAIN / N_POINTS, MAX_STRAIN, N_POINTS)
    idx = np.array([np.argmin(np.abs(e - t)) for t in targets])
    eps, sig = e[idx], s[idx]
    mesh = block((2e-3, 2e-3, 2e-3), (2, 2, 2))
    sc = Compression(mesh, eps, sig, model="springs_volume", options=SolverOptions(linear_solver="dense"), name="ecoflex_40")
    initial = Material(youngs_modulus=lin[0]["E"], poisson_ratio=NU, cubic_coefficient=1.0)
    t1 = time.perf_counter()
    res = fit(sc, MaterialParameterization(("youngs_modulus", "cubic_coefficient")), initial, method=args.method, max_steps=60)
    t_fit = time.perf_counter() - t1
    pred = res.predictions[sc.name]
    rms = float(np.sqrt(np.mean((pred - sig) ** 2)))
    rms_rel = rms / float(np.sqrt(np.mean(sig**2)))
    max_abs = float(np.abs(pred - sig).max())
    # extrapolation to 55 % strain with the fitted material
    # (0.5 % increments: with 1 % increments the Newton solves fail beyond ~55 %)
    ext_e = np.arange(1, 111) * 0.005  # 0.5 % .. 55 %
    ext_s = np.interp(ext_e, e, s)
    ext = Compression(mesh, ext_e, ext_s, model="springs_volume", options=SolverOptions(linear_solver="dense", max_steps=200), name="ecoflex_55")
    beyond = ext_e > MAX_STRAIN + 1e-9
    try:
        ext_pred = np.asarray(ext.predict(res.material))
        ext_rel = float(np.sqrt(np.mean((ext_pred[beyond] - ext_s[beyond]) ** 2)) / np.sqrt(np.mean(ext_s[beyond] ** 2)))
    except Exception as exc:  # noqa: BLE001 -- reported, not hidden
        print(f"extrapolation to 55 % failed: {str(exc).splitlines()[0]}")
        ext_pred, ext_rel = np.full(ext_e.shape, np.nan), float("nan")

    result = {
        "experiment": "exp2_ecoflex",
        "data": str(DATA.relative_to(DATA.parent.parent.parent)),
        "authors_E": E_AUTHORS,
        "linear_fits": lin,
        "springs_volume_fit": {
            "nu_fixed": NU,
            "strain_range": [float(eps.min()), float(eps.max())],
            "n_points": int(eps.size),
            "E": res.values["youngs_modulus"],
            "E_se": res.standard_errors["youngs_modulus"],
            "cubic_coefficient": res.values["cubic_coefficient"],
            "cubic_coefficient_se": res.standard_errors["cubic_coefficient"],
            "rms_residual_Pa": rms,
            "rms_residual_rel": rms_rel,
            "max_abs_residual_Pa": max_abs,
            "converged": res.converged,
            "steps": res.steps,
            "method": args.method,
            "fit_seconds": t_fit,
            "extrapolation_40_55_rms_rel": ext_rel,
            "stress_at_55_model_vs_data_Pa": [float(ext_pred[-1]), float(ext_s[-1])],
        },
        "total_seconds": time.perf_counter() - t0,
    }
    (out / "exp2_ecoflex.json").write_text(json.dumps(result, indent=2))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax.plot(e * 100, s / 1e3, "-", color="0.6", lw=1, label="EF10_50T_A1 (loading)")
    ax.plot(eps * 100, pred / 1e3, "o", ms=3, label=f"springs_volume fit (E = {res.values['youngs_modulus'] / 1e3:.2f} kPa, b = {res.values['cubic_coefficient']:.2f})")
    ax.plot(ext_e[beyond] * 100, ext_pred[beyond] / 1e3, "x", ms=3, label="extrapolation 40-55 %")
    E0, c0 = lin[0]["E"], lin[0]["intercept_Pa"]
    xx = np.linspace(0, 0.2, 10)
    ax.plot(xx * 100, (E0 * xx + c0) / 1e3, "k--", lw=0.8, label=f"linear 0-10 %: E = {E0 / 1e3:.2f} kPa")
    ax.set_xlim(0, 57)
    ax.set_ylim(0, 1.1 * ext_s.max() / 1e3)
    ax.set_xlabel("engineering strain [%]")
    ax.set_ylabel("engineering stress [kPa]")
    ax.legend(fontsize=7)
    ax2.plot(eps * 100, (pred - sig) / 1e3, "o-", ms=3)
    ax2.axhline(0, color="k", lw=0.8)
    ax2.set_xlabel("engineering strain [%]")
    ax2.set_ylabel("model - data [kPa]")
    ax2.set_title(f"RMS {rms / 1e3:.3f} kPa ({100 * rms_rel:.1f} % of RMS stress)")
    fig.tight_layout()
    fig.savefig(out / "exp2_ecoflex.png", dpi=110)

    print("| quantity | value | target | met |")
    print("|---|---|---|---|")
    for r in lin:
        lo, hi = r["strain_range"]
        print(f"| small-strain E, line fit {100 * lo:.0f}-{100 * hi:.0f} % strain | {r['E'] / 1e3:.2f} kPa ({100 * r['error_vs_authors']:+.1f} % vs 16.29) | within 10 % | {'yes' if abs(r['error_vs_authors']) <= 0.10 else 'NO'} |")
    f = result["springs_volume_fit"]
    print(f"| springs_volume E (nu = {NU} fixed), 0-40 % | {f['E'] / 1e3:.2f} ± {f['E_se'] / 1e3:.2f} kPa | - | - |")
    print(f"| springs_volume cubic coefficient b | {f['cubic_coefficient']:.3f} ± {f['cubic_coefficient_se']:.3f} | - | - |")
    print(f"| RMS residual 0-40 % | {f['rms_residual_Pa'] / 1e3:.3f} kPa ({100 * f['rms_residual_rel']:.1f} % of RMS stress; max {f['max_abs_residual_Pa'] / 1e3:.3f} kPa) | follows the curve to 40 % | see text |")
    print(f"| extrapolation 40-55 % (RMS rel.) | {100 * ext_rel:.0f} % | - | - |")
    print(f"\nfit {t_fit:.1f} s ({f['steps']} steps, converged {f['converged']}); total {result['total_seconds']:.0f} s")


if __name__ == "__main__":
    main()
