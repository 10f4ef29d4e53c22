"""Axisymmetric sphere and cone indentation against Hertz and Sneddon (docs/experiments.md,
"Axisymmetric indentation").

    PYTHONPATH=. python experiments/axisymmetric_indentation.py [convergence|nu|fit|all]
    PYTHONPATH=. python experiments/axisymmetric_indentation.py config sphere|cone [MODEL] [SOLVER]

- convergence: sphere R = 1 mm to d = 20 um (d/R = 0.02) and 70 deg cone to 0.1 mm, nu = 0.45,
  fem_linear, E = 10 kPa, bonded cylinder of radius and height 200 a: the automatic specimen
  (``axisymmetric_specimen_for``) refined by 1/2, 1, 2, 4 (every cell divided: first cell and
  growth), force at d/2 and d vs the half-space formula; observed order and Richardson value
  from the three finest levels.
- nu: the force vs Hertz at the default resolution for nu = 0, 0.3, 0.45, 0.49, at d/R = 0.02 and
  0.005.
- fit: E fitted (nu = 0.45 fixed) on exact Hertz / Sneddon forces at 20 depths with the default
  specimen and uniform sigma, by difftissue.fit.fit and in closed form (fem_linear: the force is
  linear in E at fixed nu, so the least-squares E follows from one evaluation).

- config: the same exact curves (200 samples to d) fitted through a TOML config as
  ``difftissue fit`` builds and runs it (``difftissue.cli.main``: no ``specimen``, so the
  automatic specimen; 20 points, the config's sigma; the start from the data (the default), nu = 0.45 fixed; the
  discretisation check on): fitted and corrected E, steps, CPU time (this process,
  user + sys) and the chosen simulation. MODEL: fem_linear (default), fem_neo_hookean or
  stable_neo_hookean. SOLVER: the experiment's ``solver`` table's content (e.g.
  "xtol = 2e-8"; default none), output file suffix ``_solver``.

Raw output: experiments/results/axisymmetric_indentation_<part>_<kind>.json
(``config``: axisymmetric_indentation_config_<kind>_<model>[_solver].json)
(``python experiments/axisymmetric_indentation.py convergence sphere`` runs one kind).
"""

import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from difftissue import analytic  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.scenarios import AxisymmetricIndentation, axisymmetric_specimen_for  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"
E, NU = 1.0e4, 0.45
SPHERE = dict(indenter="sphere", radius=1e-3)
CONE = dict(indenter="cone", half_angle=float(np.radians(70.0)))
D_SPHERE, D_CONE = 20e-6, 0.1e-3
# refinement factors of the default specimen: the cone's tip element is crushed beyond the default
# (strain ~1 under the apex at 16 cells per contact radius: the log-singular strain of a sharp tip)
FACTORS = {"sphere": (0.5, 1.0, 2.0, 4.0), "cone": (0.5, 1.0)}


def exact(kind, depths, nu, E=E):
    if kind == "sphere":
        return np.asarray(analytic.hertz_force(depths, E, nu, SPHERE["radius"]))
    return np.asarray(analytic.cone_force(depths, E, nu, CONE["half_angle"]))


def scenario(kind, depths, *, factor=1.0, nu_forces=None, forces=None, **kw):
    geo = SPHERE if kind == "sphere" else CONE
    spec = axisymmetric_specimen_for(geo["indenter"], radius=geo.get("radius"), half_angle=geo.get("half_angle"), max_depth=float(np.max(depths)))
    spec = spec.refined(factor) if factor != 1.0 else spec
    return AxisymmetricIndentation(depths, forces, mesh=spec.mesh(), **geo, **kw), spec


def convergence(kind):
    dmax = D_SPHERE if kind == "sphere" else D_CONE
    depths = dmax * np.arange(1, 11) / 10.0
    rows = []
    for f in FACTORS[kind]:
        t = time.process_time()
        sc, spec = scenario(kind, depths, factor=f)
        F = np.asarray(sc.predict(Material(E, NU)))
        ref = exact(kind, depths, NU)
        rows.append({"cells_per_contact_radius": spec.cells_per_contact_radius, "growth": spec.growth, "nodes": int(sc.model.n_nodes),
                     "force_d2": float(F[4]), "force_d": float(F[-1]), "err_d2": float(F[4] / ref[4] - 1), "err_d": float(F[-1] / ref[-1] - 1),
                     "cpu_s": time.process_time() - t})
        print(kind, rows[-1], flush=True)
    out = {"kind": kind, "depth": dmax, "rows": rows}
    for key in ("force_d2", "force_d") if len(rows) >= 3 else ():
        f1, f2, f3 = (r[key] for r in rows[-3:])
        p = np.log(abs((f1 - f2) / (f2 - f3))) / np.log(2.0)
        rich = f3 + (f3 - f2) / (2.0**p - 1.0)
        ref = exact(kind, dmax / 2 if key == "force_d2" else dmax, NU)
        out[key + "_order"] = float(p)
        out[key + "_richardson_vs_exact"] = float(rich / ref - 1)
        out[key + "_levels_vs_richardson"] = [float(r[key] / rich - 1) for r in rows]
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1), flush=True)
    return out


def nu_dependence():
    rows = []
    for d in (D_SPHERE, D_SPHERE / 4):
        for nu in (0.0, 0.3, 0.45, 0.49):
            t = time.process_time()
            sc, spec = scenario("sphere", d * np.arange(1, 6) / 5.0)
            F = float(np.asarray(sc.predict(Material(E, nu)))[-1])
            rows.append({"d_over_R": d / SPHERE["radius"], "nu": nu, "err_d": F / float(exact("sphere", d, nu)) - 1, "cpu_s": time.process_time() - t})
            print(rows[-1], flush=True)
    return {"rows": rows}


def fit(kind):
    from difftissue.fit import fit as run_fit
    from difftissue.materials import MaterialParameterization

    dmax = D_SPHERE if kind == "sphere" else D_CONE
    depths = dmax * np.arange(1, 21) / 20.0
    data = exact(kind, depths, NU)
    t = time.process_time()
    sc, spec = scenario(kind, depths, forces=data, sigma=np.full(depths.size, data.max() / 100.0))
    F1 = np.asarray(sc.predict(Material(1.0, NU)))  # force per pascal at nu fixed
    E_fit = float(F1 @ data / (F1 @ F1))
    cpu_fixed = time.process_time() - t
    res = run_fit(sc, MaterialParameterization(("youngs_modulus",)), Material(8e3, NU))
    out = {"kind": kind, "specimen": spec.record(), "nodes": int(sc.model.n_nodes), "E_fit_closed_form": E_fit, "E_err_closed_form": E_fit / E - 1,
           "cpu_s_closed_form": cpu_fixed, "E_fit": float(res.material.youngs_modulus), "E_err": float(res.material.youngs_modulus) / E - 1,
           "fit_steps": int(getattr(res, "steps", -1)), "cpu_s_total": time.process_time() - t}
    print(out, flush=True)
    return out


def config_fit(kind, model="fem_linear", solver=None):
    import tempfile

    from difftissue.cli import main as cli_main

    dmax = D_SPHERE if kind == "sphere" else D_CONE
    depths = np.linspace(dmax / 200, dmax, 200)
    data = exact(kind, depths, NU)
    ind = (f'{{ shape = "sphere", radius = {SPHERE["radius"]} }}' if kind == "sphere"
           else f'{{ shape = "cone", half_angle_deg = {np.degrees(CONE["half_angle"]):.12g} }}')
    tmp = Path(tempfile.mkdtemp(prefix=f"axi_config_{kind}_"))
    (tmp / "curve.csv").write_text("depth,force\n" + "".join(f"{a:.12g},{b:.12g}\n" for a, b in zip(depths, data)))
    (tmp / "fit.toml").write_text(f'''title = "exact {kind}, {model}"
[material]
youngs_modulus = 8000.0
poisson_ratio = {NU}
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "ind"
scenario = "indentation"
model = "{model}"
data = {{ format = "table", path = "curve.csv", columns = {{ depth = {{ name = "depth", unit = "m" }}, force = {{ name = "force", unit = "N" }} }} }}
indenter = {ind}
''' + ("" if solver is None else f"solver = {{ {solver} }}\n"))
    t, w = time.process_time(), time.perf_counter()
    rc = cli_main(["fit", str(tmp / "fit.toml"), "--out", str(tmp / "out"), "--no-progress"])
    cpu, wall = time.process_time() - t, time.perf_counter() - w
    res = json.loads((tmp / "out" / "fit.json").read_text())
    disc = res.get("discretisation") or {}
    Efit = float(res["parameters"]["youngs_modulus"]["value"]) if isinstance(res["parameters"]["youngs_modulus"], dict) else float(res["parameters"]["youngs_modulus"])
    Ecorr = (disc.get("corrected") or {}).get("youngs_modulus")
    out = {"kind": kind, "model": model, "solver": solver, "rc": rc, "E_fit": Efit, "E_err": Efit / E - 1, "E_corrected": Ecorr,
           "E_corrected_err": None if Ecorr is None else Ecorr / E - 1, "cpu_s": cpu, "wall_s": wall,
           "steps": res.get("steps", res.get("optimizer", {}).get("steps") if isinstance(res.get("optimizer"), dict) else None),
           "simulation": res.get("simulation"), "discretisation": disc}
    print({k: v for k, v in out.items() if k != "discretisation"}, flush=True)
    return out


if __name__ == "__main__":
    part = sys.argv[1] if len(sys.argv) > 1 else "all"
    if part == "config":
        kind, model = sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "fem_linear"
        solver = sys.argv[4] if len(sys.argv) > 4 else None
        OUT.mkdir(exist_ok=True)
        (OUT / f"axisymmetric_indentation_config_{kind}_{model}{'' if solver is None else '_solver'}.json").write_text(
            json.dumps(config_fit(kind, model, solver), indent=1, default=str))
        sys.exit(0)
    kinds = tuple(sys.argv[2].split(",")) if len(sys.argv) > 2 else ("sphere", "cone")
    OUT.mkdir(exist_ok=True)
    jobs = {"convergence": lambda: {k: convergence(k) for k in kinds}, "nu": nu_dependence,
            "fit": lambda: {k: fit(k) for k in kinds}}
    for name, job in jobs.items():
        if part in (name, "all"):
            (OUT / f"axisymmetric_indentation_{name}_{'_'.join(kinds) if name != 'nu' else 'sphere'}.json").write_text(json.dumps(job(), indent=1))
