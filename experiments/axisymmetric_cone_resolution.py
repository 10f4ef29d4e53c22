"""Cone (and sphere) force vs resolution on the axisymmetric specimen, and the discretisation
check's three-level estimate against fits of exact Sneddon / Hertz data
(docs/dev/axisymmetric-indentation.md, "Cone convergence and the three-level estimate" and
"The stable neo-Hookean on the meridian mesh").

    PYTHONPATH=. python experiments/axisymmetric_cone_resolution.py levels THETA_DEG|sphere [FACTORS] [--model MODEL]
    PYTHONPATH=. python experiments/axisymmetric_cone_resolution.py analyse THETA_DEG|sphere [--model MODEL]

- levels: the automatic specimen of a cone of half-angle THETA_DEG to d = 0.1 mm, or of a
  sphere of radius R = 1 mm to d = 20 um (``axisymmetric_specimen_for``), refined by each
  factor (default 1/2 .. 2 sqrt 2 in steps of sqrt 2: 4 .. 22.6 cells per contact radius),
  MODEL (default fem_linear; an ``AXISYMMETRIC_MODELS`` name), E = 10 kPa, nu = 0.45,
  penalty 100, 10 depths d/10 .. d; forces, the smallest det F at the deepest point, CPU time.
  A level whose solve fails (an inverted element, a line search with no step) is kept as NaN.
- analyse: E fitted to exact Sneddon / Hertz forces at each level (closed form: the force is
  linear in E at fixed nu for every model here, the densities and the contact penalty being
  proportional to E; uniform sigma), the observed order and Richardson value of the force at
  d/2 and d from each three consecutive levels, and at each level m with levels m / sqrt 2 and
  m / 2 below it the check's three-level estimate (``difftissue.fit.statistics._observed_order``,
  the same rule as ``discretisation_estimate``, the order capped at 2 as the config's check
  does) and the old order-2 estimate from m and m / 2.

Raw output: experiments/results/axisymmetric_cone_resolution_<theta|sphere>[_<model>].json
(no model suffix for fem_linear).
"""

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from difftissue import analytic  # noqa: E402
from difftissue.fit.statistics import _observed_order  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.scenarios import AxisymmetricIndentation, SolverOptions, axisymmetric_specimen_for  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"
E, NU, D = 1.0e4, 0.45, 0.1e-3
R_SPHERE, D_SPHERE = 1e-3, 20e-6
FACTORS = tuple(2.0 ** (k / 2) for k in range(-2, 4))
MAX_ORDER = 2.0  # the config check's cap (config.builders.AXISYMMETRIC_MAX_ORDER)


def levels(theta_deg: float | str, factors=FACTORS, model: str = "fem_linear") -> dict:
    if theta_deg == "sphere":
        d, geo = D_SPHERE, dict(indenter="sphere", radius=R_SPHERE)
        depths = d * np.arange(1, 11) / 10
        exact = {"hertz": np.asarray(analytic.hertz_force(depths, E, NU, R_SPHERE)).tolist()}
    else:
        d, geo = D, dict(indenter="cone", half_angle=float(np.radians(theta_deg)))
        depths = d * np.arange(1, 11) / 10
        exact = {"sneddon": np.asarray(analytic.cone_force(depths, E, NU, geo["half_angle"])).tolist()}
    base = axisymmetric_specimen_for(max_depth=d, **geo)
    res = {"theta_deg": theta_deg, "model": model, "nu": NU, "depths": depths.tolist(), **exact, "levels": []}
    for f in factors:
        spec = base.refined(f)
        t = time.process_time()
        sc = AxisymmetricIndentation(depths, **geo, model=model, specimen=spec, options=SolverOptions(failure="nan"))
        F, U = (np.asarray(v) for v in sc.solve(Material(E, NU)))
        X = np.asarray(sc.model.rest_points)
        J = float(np.min(np.asarray(sc.model.base.tet_jacobians(jnp.asarray(X + U[-1]))))) if np.all(np.isfinite(U[-1])) else float("nan")
        res["levels"].append({"factor": f, "m": spec.cells_per_contact_radius, "nodes": int(X.shape[0]), "forces": F.tolist(), "min_det_F_deepest": J,
                              "cpu_s": time.process_time() - t})
        print({k: v for k, v in res["levels"][-1].items() if k != "forces"}, flush=True)
    return res


def analyse(res: dict) -> list[str]:
    S = np.asarray(res["sneddon"] if "sneddon" in res else res["hertz"])
    ref = "Sneddon" if "sneddon" in res else "Hertz"
    sig = np.full(S.size, S.max() / 100)
    forces = {round(lv["m"], 3): np.asarray(lv["forces"]) for lv in res["levels"]}
    fits = {m: E * (F @ S) / (F @ F) for m, F in forces.items() if np.all(np.isfinite(F))}
    lines = [f"{m:g} cells: force at d/2, d {100 * (F[4] / S[4] - 1):+.2f}, {100 * (F[-1] / S[-1] - 1):+.2f} % vs {ref}, fitted E {100 * (fits[m] / E - 1):+.3f} %"
             if m in fits else f"{m:g} cells: solve failed" for m, F in forces.items()]
    ms = sorted(fits)
    for i in range(2, len(ms)):  # observed order and Richardson value of the force at d/2 and d, three consecutive levels
        if abs(ms[i] / ms[i - 1] - 2**0.5) > 1e-3 or abs(ms[i - 1] / ms[i - 2] - 2**0.5) > 1e-3:
            continue
        parts = []
        for j, name in ((4, "d/2"), (-1, "d")):
            f3, f2, f1 = (forces[m][j] for m in ms[i - 2:i + 1])
            p = 2 * np.log(abs((f3 - f2) / (f2 - f1))) / np.log(2.0)
            rich = f1 + (f1 - f2) / (2 ** (p / 2) - 1)
            parts.append(f"{name}: order {p:.2f}{'' if (f3 - f2) * (f2 - f1) > 0 else ' (not monotone)'}, Richardson {100 * (rich / S[j] - 1):+.2f} % vs {ref}")
        e3, e2, e1 = (fits[m] for m in ms[i - 2:i + 1])
        p = 2 * np.log(abs((e3 - e2) / (e2 - e1))) / np.log(2.0)
        rich = e1 + (e1 - e2) / (2 ** (p / 2) - 1)
        parts.append(f"fitted E: order {p:.2f}{'' if (e3 - e2) * (e2 - e1) > 0 else ' (not monotone)'}, Richardson {100 * (rich / E - 1):+.2f} %")
        lines.append(f"from {ms[i - 2]:.3g} / {ms[i - 1]:.3g} / {ms[i]:.3g} cells: force at " + "; ".join(parts))
    for i in range(2, len(ms)):
        mf, mc, mcc = ms[i], ms[i - 1], ms[i - 2]
        if abs(mf / mc - 2**0.5) > 1e-3 or abs(mc / mcc - 2**0.5) > 1e-3:
            continue
        Ef = fits[mf]
        pf, pc, pcc = (forces[m] * Ef / E for m in (mf, mc, mcc))
        q, rec, why = _observed_order(pf, pc, pcc, sig, 2**0.5, (pf / Ef / sig)[:, None])
        if why is None:
            qu = min(q, MAX_ORDER)
            e = (pc - pf) / (2 ** (qu / 2) - 1)
            dE = -(pf @ e) / (pf @ pf) * Ef
            three = f"observed order {q:.2f} (used {qu:.2f}): estimate {100 * dE / Ef:+.3f} %, corrected E {100 * ((Ef - dE) / E - 1):+.3f} %"
        else:
            three = why
        e2 = (pcc - pf) / 3.0
        dE2 = -(pf @ e2) / (pf @ pf) * Ef
        lines.append(f"check at {mf:g} cells (levels {mc:.3g}, {mcc:.3g}): fit {100 * (Ef / E - 1):+.3f} %; {three}; "
                     f"order 2 from {mf:g} / {mcc:g}: corrected E {100 * ((Ef - dE2) / E - 1):+.3f} %")
    return lines


if __name__ == "__main__":
    argv = sys.argv[1:]
    model = "fem_linear"
    if "--model" in argv:
        i = argv.index("--model")
        model = argv[i + 1]
        del argv[i:i + 2]
    part, theta = argv[0], argv[1] if argv[1] == "sphere" else float(argv[1])
    path = OUT / f"axisymmetric_cone_resolution_{theta if theta == 'sphere' else format(theta, 'g')}{'' if model == 'fem_linear' else '_' + model}.json"
    if part == "levels":
        factors = tuple(float(x) for x in argv[2].split(",")) if len(argv) > 2 else FACTORS
        OUT.mkdir(exist_ok=True)
        path.write_text(json.dumps(levels(theta, factors, model), indent=1))
    print("\n".join(analyse(json.loads(path.read_text()))))
