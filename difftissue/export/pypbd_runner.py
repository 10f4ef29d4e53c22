"""pypbd scenes: read, load into pypbd, run to a static state or at their written budget, and
the scene's energy (docs/export.md).

pypbd (PyPI ``pypbd``, Python bindings of InteractiveComputerGraphics/PositionBasedDynamics,
checked with 2.2.2) is driven through its public Python API only. A scene is a JSON file
(``"format": "difftissue-pbd/1"``, written by :func:`difftissue.export.pypbd.pbd_scene` /
:func:`difftissue.export.pypbd.write_pbd`, read by :func:`read_pbd_scene`) holding the
particles (rest positions, masses; mass 0 = static, pypbd's convention), the tetrahedra and the
constraints with the stiffness values pypbd's ``add*Constraint*`` calls take, plus the
boundary motion of the specimen. :func:`pbd_simulation_from_scene` builds the pypbd
simulation from such a file and :func:`run_pbd_scene` drives it to a static state.

Conventions of pypbd 2.2.2 that the conversion relies on (source:
``PositionBasedDynamics/XPBD.cpp``, ``Simulation/Constraints.cpp``,
``PositionBasedDynamics/PositionBasedDynamics.cpp``; each one also measured, see
``tests/test_export_pbd.py``):

* ``addDistanceConstraint_XPBD(i, j, k)``: ``C = |x_i - x_j| - L0`` with compliance
  ``alpha = 1 / (k dt^2)`` and gradient ``dC/dx``: energy ``k/2 C^2``, ``k`` in N/m (the same
  ``k`` as a difftissue spring). ``k = 0`` means *infinitely stiff* (``alpha = 0``).
* ``addVolumeConstraint_XPBD(a, b, c, d, k)``: ``C = V - |V0|`` with
  ``V = (x_b - x_a) x (x_c - x_a) . (x_d - x_a) / 6``, ``alpha = 1 / (k dt^2)``, but the
  position update uses the gradients **without** the 1/6 (``grad_d = (x_b - x_a) x (x_c - x_a)``),
  so the converged state minimises ``6 k/2 C^2 = 3 k (V - V0)^2``. A term
  ``K (V - V0)^2 / (2 V0)`` therefore needs ``k = K / (6 V0)``.
* ``addFEMTetConstraint(a, b, c, d, E, nu)`` calls the *PBD* (not the XPBD) FEM projection
  ``PositionBasedDynamics::solve_FEMTetraConstraint``: ``C`` = the St. Venant-Kirchhoff energy
  of the tet, projected towards 0 with no compliance. ``E`` cancels out of the correction
  ``-C grad C / |grad C|^2_w``; it only enters through the cut-off ``sum_i w_i |grad_i C|^2 <
  1e-6`` below which no correction is applied. The converged (many-iteration) response is
  therefore rigid up to that cut-off and does **not** represent ``E``; the softness of a
  PBD-FEM scene comes from its iteration count. Such scenes are written only with
  ``approximate=True``.
* Gravity is applied to every particle of non-zero mass (``Simulation`` default
  ``(0, -9.81, 0)`` m/s^2; the Python bindings offer no setter). :func:`run_pbd_scene`
  cancels it exactly in quasi-static runs by setting each dynamic particle's velocity to
  ``-g h`` before a step (the semi-implicit Euler predictor then leaves it in place), or
  keeps it as the specimen's own weight.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from ..energies.volume import volume_energy
from ..errors import ExportError
from ..materials import lame_parameters
from ..mesh import signed_volumes
from ..models import ElementTerm, SpringVolumeModel

__all__ = [
    "SCENE_FORMAT",
    "PYPBD_GRAVITY",
    "signed_tet_volumes",
    "read_pbd_scene",
    "pbd_simulation_from_scene",
    "run_pbd_scene",
    "PBDRun",
    "scene_forces",
    "scene_energy",
    "pbd_reference_model",
    "scaled_scene",
    "run_pbd_budget",
    "PBDBudgetRun",
]


#: Value of the ``"format"`` key of a scene file.
SCENE_FORMAT = "difftissue-pbd/1"


#: pypbd's default gravitational acceleration [m/s^2] (``Simulation::GRAVITATION``).
PYPBD_GRAVITY = (0.0, -9.81, 0.0)


def signed_tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes ``(x1 - x0) . ((x2 - x0) x (x3 - x0)) / 6`` [m^3]."""
    return signed_volumes(points, tets)


def read_pbd_scene(path) -> dict:
    """Read a scene written by :func:`write_pbd` and check its format and arrays."""
    path = Path(path)
    try:
        scene = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise ExportError(f"{path}: cannot read a pypbd scene: {e}") from None
    if not isinstance(scene, dict) or scene.get("format") != SCENE_FORMAT:
        raise ExportError(f"{path}: not a {SCENE_FORMAT} scene (format = {scene.get('format') if isinstance(scene, dict) else None!r})")
    return scene


def _need_pypbd():
    try:
        import pypbd
    except ImportError:
        raise ExportError("running a pypbd scene needs pypbd (pip install pypbd)") from None
    return pypbd


def _scene_arrays(scene: dict):
    if "particles" not in scene:
        raise ExportError("the scene holds the material alone (no particles); write it with a mesh (--specimen) to run it")
    pts = np.asarray(scene["particles"]["positions"], dtype=float)
    masses = np.asarray(scene["particles"]["masses"], dtype=float)
    tets = np.asarray(scene["tets"], dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or masses.shape != (len(pts),) or tets.ndim != 2 or tets.shape[1] != 4:
        raise ExportError("scene arrays have wrong shapes (positions (N, 3), masses (N,), tets (M, 4))")
    return pts, masses, tets


def pbd_simulation_from_scene(scene: dict, *, dt: float | None = None, iterations: int | None = None,
                              substeps: int | None = None):
    """Build pypbd's current ``Simulation`` from ``scene`` (a dict from :func:`read_pbd_scene`).

    pypbd keeps one global simulation: this call replaces its model (``Simulation.initDefault``).
    ``dt``, ``iterations``, ``substeps`` override the scene's setting. Returns
    ``(simulation, model)``; particle ``i`` of the scene is pypbd particle ``i``.
    """
    pbd = _need_pypbd()
    pts, masses, tets = _scene_arrays(scene)
    setting = scene.get("setting", {})
    dt = float(setting.get("dt", 1.0 / 60.0) if dt is None else dt)
    iterations = int(setting.get("iterations", 10) if iterations is None else iterations)
    substeps = int(setting.get("substeps", 1) if substeps is None else substeps)
    sim = pbd.Simulation.getCurrent()
    sim.initDefault()
    model = sim.getModel()
    ts = sim.getTimeStep()
    ts.setValueUInt(pbd.TimeStepController.NUM_SUB_STEPS, substeps)
    ts.setValueUInt(pbd.TimeStepController.MAX_ITERATIONS, iterations)
    pbd.TimeManager.getCurrent().setTimeStepSize(dt)
    pbd.TimeManager.getCurrent().setTime(0.0)
    model.addTetModel([p for p in pts], tets.reshape(-1).tolist())
    pd = model.getParticles()
    if pd.size() != len(pts):
        raise ExportError(f"pypbd created {pd.size()} particles for {len(pts)} scene particles")
    for i, m in enumerate(masses):
        pd.setMass(i, float(m))
    ok = True
    if "distance_constraints" in scene:
        dc = scene["distance_constraints"]
        for (i, j), k in zip(dc["pairs"], dc["stiffness"]):
            ok &= model.addDistanceConstraint_XPBD(int(i), int(j), float(k))
    if "volume_constraints" in scene:
        vc = scene["volume_constraints"]
        for t, k in zip(vc["tets"], vc["stiffness"]):
            ok &= model.addVolumeConstraint_XPBD(*(int(n) for n in t), float(k))
    if "fem_constraints" in scene:
        fc = scene["fem_constraints"]
        for t in fc["tets"]:
            ok &= model.addFEMTetConstraint(*(int(n) for n in t), float(fc["youngs_modulus"]), float(fc["poisson_ratio"]))
    if not ok:
        raise ExportError("pypbd refused a constraint of the scene (degenerate element?)")
    return sim, model


def scene_forces(scene: dict, x: np.ndarray) -> np.ndarray:
    """Gradient [N] of the energy the scene's XPBD constraints minimise at positions ``x`` (N, 3).

    Distance: ``k/2 C^2``; volume: ``3 k C^2`` (pypbd's factor 6, module notes). The reaction
    on a static particle is this gradient there; on a dynamic particle at equilibrium it is
    zero (without gravity) or its weight ``m g`` (with gravity).
    """
    if "fem_constraints" in scene:
        raise ExportError("scene_forces: a PBD FEM scene has no compliance energy (module notes)")
    x = np.asarray(x, dtype=float)
    g = np.zeros_like(x)
    if "distance_constraints" in scene:
        dc = scene["distance_constraints"]
        ij = np.asarray(dc["pairs"], dtype=np.int64)
        k = np.asarray(dc["stiffness"], dtype=float)
        p0 = np.asarray(scene["particles"]["positions"], dtype=float)
        L0 = np.linalg.norm(p0[ij[:, 1]] - p0[ij[:, 0]], axis=1)
        d = x[ij[:, 1]] - x[ij[:, 0]]
        L = np.linalg.norm(d, axis=1)
        f = (k * (L - L0) / L)[:, None] * d  # dU/dx_j
        np.add.at(g, ij[:, 1], f)
        np.add.at(g, ij[:, 0], -f)
    if "volume_constraints" in scene:
        vc = scene["volume_constraints"]
        t = np.asarray(vc["tets"], dtype=np.int64)
        k = np.asarray(vc["stiffness"], dtype=float)
        p0 = np.asarray(scene["particles"]["positions"], dtype=float)
        C = signed_tet_volumes(x, t) - np.abs(signed_tet_volumes(p0, t))
        a, b, c, e = (x[t[:, i]] for i in range(4))
        grads = [np.cross(e - b, c - b), np.cross(c - a, e - a), np.cross(e - a, b - a), np.cross(b - a, c - a)]
        for i, gr in enumerate(grads):  # dV/dx_i = gr / 6; energy 3 k C^2 -> 6 k C dV/dx_i
            np.add.at(g, t[:, i], (6.0 * k * C)[:, None] * gr / 6.0)
    return g


def scene_energy(scene: dict, x: np.ndarray) -> float:
    """Energy [J] the scene's XPBD constraints minimise at positions ``x``: ``sum k/2 C^2`` over
    distance constraints plus ``sum 3 k C^2`` over volume constraints (gradient: :func:`scene_forces`)."""
    if "fem_constraints" in scene:
        raise ExportError("scene_energy: a PBD FEM scene has no compliance energy (module notes)")
    x = np.asarray(x, dtype=float)
    p0 = np.asarray(scene["particles"]["positions"], dtype=float)
    U = 0.0
    if "distance_constraints" in scene:
        dc = scene["distance_constraints"]
        ij = np.asarray(dc["pairs"], dtype=np.int64)
        C = np.linalg.norm(x[ij[:, 1]] - x[ij[:, 0]], axis=1) - np.linalg.norm(p0[ij[:, 1]] - p0[ij[:, 0]], axis=1)
        U += float(np.sum(0.5 * np.asarray(dc["stiffness"], dtype=float) * C * C))
    if "volume_constraints" in scene:
        vc = scene["volume_constraints"]
        t = np.asarray(vc["tets"], dtype=np.int64)
        C = signed_tet_volumes(x, t) - np.abs(signed_tet_volumes(p0, t))
        U += float(np.sum(3.0 * np.asarray(vc["stiffness"], dtype=float) * C * C))
    return U


@dataclasses.dataclass
class PBDRun:
    """Result of :func:`run_pbd_scene`.

    Attributes:
        positions: ``(N, 3)`` final particle positions [m].
        displacement: ``positions - rest`` [m].
        reaction: ``(N, 3)`` gradient of the scene energy [N] on static particles (zero elsewhere).
        residual: max over dynamic particles of ``|dU/dx - m g|`` (gravity on) or ``|dU/dx|`` [N].
        steps: pypbd time steps taken.
        converged: ``residual <= rtol * max |reaction|`` (or ``atol``).
        dt, iterations: the setting the run used.
    """

    positions: np.ndarray
    displacement: np.ndarray
    reaction: np.ndarray
    residual: float
    steps: int
    converged: bool
    dt: float
    iterations: int


def run_pbd_scene(scene: dict, *, dt: float | None = None, iterations: int = 20, gravity: bool = False,
                  damping: float = 0.9, ramp_steps: int = 20, max_steps: int = 200_000,
                  check_every: int = 200, rtol: float = 1e-4, atol: float = 0.0) -> PBDRun:
    """Run ``scene`` in pypbd to a static state and check it against the scene energy.

    Quasi-static drive, using only pypbd's own time stepping (``TimeStepController.step``,
    one substep, ``iterations`` XPBD iterations per step): the moved particles are displaced
    linearly over ``ramp_steps`` steps, then held; before every step each dynamic particle gets
    the velocity ``-g h`` (``gravity=False``: the semi-implicit Euler predictor then returns it
    to where it is, which removes both gravity and inertia from the step) or ``0``
    (``gravity=True``: the specimen carries its own weight). Every ``check_every`` steps the
    residual of the scene energy (:func:`scene_forces`) on the dynamic particles is evaluated;
    the run stops when it is below ``max(atol, rtol * max |reaction|)``.

    Default ``rtol = 1e-4``: the residual of pypbd's XPBD iterate does not go to zero, it
    floors at a few 1e-7 of the reaction (3e-7 N on the 10 mm test block: the iterate is
    XPBD's fixed point, not the energy's minimum, plus pypbd's rounding), so the former
    default 1e-6 was never reached and every run went to ``max_steps``; 1e-4 is reached by the
    test scenes in a few thousand steps and is far below the 1e-3 agreement they check.

    Each step then solves ``M (x - x_prev) = -h^2 grad U`` by XPBD, i.e. it is a damped
    (implicit) descent step on ``U``; its fixed points are equilibria of ``U`` up to XPBD's
    approximation of using the constraint gradients of each iterate (small when
    ``h^2 k / m`` is small, which ``dt`` must ensure). ``dt`` defaults to
    ``0.5 sqrt(min mass / max stiffness)`` estimated from the scene.
    """
    _need_pypbd()
    pts, masses, tets = _scene_arrays(scene)
    if not 0.0 <= damping < 1.0:
        raise ExportError(f"damping = {damping!r}: expected the retained velocity fraction in [0, 1)")
    if "fem_constraints" in scene:
        raise ExportError("run_pbd_scene: a PBD FEM scene has no energy to check convergence against (module notes); "
                          "build it with pbd_simulation_from_scene and step it yourself")
    dyn = np.flatnonzero(masses > 0)
    if dt is None:
        dt = 0.5 * math.sqrt(float(np.min(masses[dyn] / _particle_stiffness(scene)[dyn])))
    sim, model, ts, pd, g, moved, dvec = _scene_run(scene, dt, iterations)
    v_pre = np.zeros(3) if gravity else -g * dt
    steps = 0
    residual = math.inf
    reaction = np.zeros_like(pts)
    converged = False
    while steps < max_steps:
        s = min(1.0, (steps + 1) / max(ramp_steps, 1))
        for i in moved:
            pd.setPosition(int(i), pts[i] + s * dvec)
        for i in dyn:
            pd.setVelocity(int(i), damping * np.asarray(pd.getVelocity(int(i))) + v_pre if damping else v_pre)
        ts.step(model)
        steps += 1
        if steps >= ramp_steps and (steps % check_every == 0 or steps == max_steps):
            x = np.array([pd.getPosition(i) for i in range(len(pts))])
            grad = scene_forces(scene, x)
            res = grad[dyn] - (masses[dyn, None] * g[None, :] if gravity else 0.0)
            residual = float(np.max(np.linalg.norm(res, axis=1))) if dyn.size else 0.0
            reaction = np.zeros_like(grad)
            static = np.flatnonzero(masses == 0)
            reaction[static] = grad[static]
            scale = float(np.max(np.linalg.norm(reaction, axis=1))) if static.size else 0.0
            if gravity:
                scale = max(scale, float(np.max(masses)) * float(np.linalg.norm(g)))
            if residual <= max(atol, rtol * scale):
                converged = True
                break
    x = np.array([pd.getPosition(i) for i in range(len(pts))])
    return PBDRun(positions=x, displacement=x - pts, reaction=reaction, residual=residual, steps=steps,
                  converged=converged, dt=float(dt), iterations=int(iterations))


def scaled_scene(scene: dict, factor: float) -> dict:
    """A copy of ``scene`` with every distance and volume constraint stiffness multiplied by
    ``factor`` (> 0): the energy scales by ``factor``, the ratio of the two constraint kinds
    (the lattice's nu) is kept."""
    factor = float(factor)
    if not (math.isfinite(factor) and factor > 0):
        raise ExportError(f"stiffness factor {factor!r} must be finite and > 0")
    out = dict(scene)
    for key in ("distance_constraints", "volume_constraints"):
        if key in out:
            out[key] = {**out[key], "stiffness": (np.asarray(out[key]["stiffness"], dtype=float) * factor).tolist()}
    return out


@dataclasses.dataclass
class PBDBudgetRun:
    """Result of :func:`run_pbd_budget`.

    Attributes:
        fractions: load fractions run (the moved particles at ``fraction * displacement``).
        reactions: ``(len(fractions),)`` [N]: the summed reaction on the moved particles along the
            boundary displacement ``d``, ``sum_i dU/dx_i . d / |d|`` (positive when the specimen
            resists the motion; ``U`` the scene energy, :func:`scene_forces`: pypbd itself reports
            no forces, so the force is the scene energy's at the positions pypbd reached).
        positions: ``(len(fractions), N, 3)`` [m] rest states reached.
        steps: pypbd steps taken per fraction; converged: whether each came to rest.
        dt, substeps, iterations: the budget run (``substeps`` substeps of ``dt / substeps``).
    """

    fractions: np.ndarray
    reactions: np.ndarray
    positions: np.ndarray
    steps: np.ndarray
    converged: np.ndarray
    dt: float
    substeps: int
    iterations: int


def run_pbd_budget(scene: dict, fractions=(1.0,), *, tol: float = 1e-7, max_steps: int = 20_000) -> PBDBudgetRun:
    """Run ``scene`` in pypbd **at its written budget** (``setting``: ``dt``, ``substeps``,
    ``iterations``) to the state it comes to rest in, at each load fraction in turn.

    This is the state a real-time pypbd loop with that budget settles to once the motion has
    died out (pypbd resets the XPBD multipliers every step and runs a fixed number of
    iterations, so this is the fixed point of one step, not the energy minimum that
    :func:`run_pbd_scene` drives to): before every step each free particle gets the velocity
    ``-g h`` (the semi-implicit Euler predictor then returns it to where it is: no inertia,
    no gravity), and the run stops when no particle moves by more than ``tol`` times the
    largest prescribed displacement in a step. A step of ``substeps`` substeps is run as
    ``substeps`` pypbd steps of ``h = dt / substeps`` with one substep each (pypbd's substep
    is a full semi-implicit Euler + projection of size ``h``; with the velocities zeroed the
    two have the same rest states, and only this way is gravity cancelled in every substep).
    The moved particles jump to each fraction's position (the fractions in the given order).
    """
    _need_pypbd()
    pts, masses, tets = _scene_arrays(scene)
    if "fem_constraints" in scene:
        raise ExportError("run_pbd_budget: a PBD FEM scene has no energy to read a reaction from (module notes)")
    st = scene.get("setting", {})
    dt, substeps, iterations = float(st["dt"]), int(st["substeps"]), int(st["iterations"])
    h = dt / substeps
    sim, model, ts, pd, g, moved, dvec = _scene_run(scene, h, iterations)
    if moved.size == 0 or not np.any(dvec):
        raise ExportError("run_pbd_budget: the scene moves no particles (boundary.moved / displacement): no reaction to measure")
    direction = dvec / np.linalg.norm(dvec)
    dyn = np.flatnonzero(masses > 0)
    v_pre = -g * h
    x = pts.copy()
    R, X, S, C = [], [], [], []
    for f in np.asarray(fractions, dtype=float):
        for i in moved:
            pd.setPosition(int(i), pts[i] + f * dvec)
        x[moved] = pts[moved] + f * dvec
        limit = tol * max(abs(f) * float(np.max(np.abs(dvec))), 1e-300)
        n, ok = 0, False
        while n < max_steps:
            for i in dyn:
                pd.setVelocity(int(i), v_pre)
            ts.step(model)
            n += 1
            xn = np.array([pd.getPosition(i) for i in range(len(pts))])
            change = float(np.max(np.abs(xn - x)))
            x = xn
            if not np.all(np.isfinite(x)):
                break
            if change <= limit:
                ok = True
                break
        grad = scene_forces(scene, x) if np.all(np.isfinite(x)) else np.full_like(x, np.nan)
        R.append(float(np.sum(grad[moved] @ direction)))
        X.append(x.copy())
        S.append(n)
        C.append(ok)
    return PBDBudgetRun(fractions=np.asarray(fractions, dtype=float), reactions=np.asarray(R), positions=np.asarray(X),
                        steps=np.asarray(S), converged=np.asarray(C), dt=dt, substeps=substeps, iterations=iterations)


def _scene_run(scene: dict, dt: float, iterations: int):
    """A pypbd simulation of ``scene`` stepping ``dt`` [s] with ``iterations`` per step (one
    substep) and what a run reads off it: ``(simulation, model, time_step, particles, gravity
    (3,) [m/s^2], moved particle ids, their displacement (3,) [m])``."""
    sim, model = pbd_simulation_from_scene(scene, dt=dt, iterations=iterations, substeps=1)
    bnd = scene.get("boundary", {})
    return (sim, model, sim.getTimeStep(), model.getParticles(), np.asarray(scene.get("gravity", PYPBD_GRAVITY), dtype=float),
            np.asarray(bnd.get("moved", []), dtype=np.int64), np.asarray(bnd.get("displacement", [0.0, 0.0, 0.0]), dtype=float))


def _particle_stiffness(scene: dict) -> np.ndarray:
    """Diagonal of the scene energy's Hessian at rest, per particle [N/m] (for the default dt)."""
    pts = np.asarray(scene["particles"]["positions"], dtype=float)
    K = np.zeros(len(pts))
    if "distance_constraints" in scene:
        dc = scene["distance_constraints"]
        ij = np.asarray(dc["pairs"], dtype=np.int64)
        k = np.asarray(dc["stiffness"], dtype=float)
        np.add.at(K, ij[:, 0], k)
        np.add.at(K, ij[:, 1], k)
    if "volume_constraints" in scene:
        vc = scene["volume_constraints"]
        t = np.asarray(vc["tets"], dtype=np.int64)
        k = np.asarray(vc["stiffness"], dtype=float)
        a, b, c, e = (pts[t[:, i]] for i in range(4))
        grads = [np.cross(e - b, c - b), np.cross(c - a, e - a), np.cross(e - a, b - a), np.cross(b - a, c - a)]
        for i, gr in enumerate(grads):  # energy 3 k C^2: Hessian diagonal 6 k |dV/dx_i|^2
            np.add.at(K, t[:, i], 6.0 * k * np.sum(gr * gr, axis=1) / 36.0)
    return np.maximum(K, 1e-300)


def _tet_volume_energy(x, rest_volume, bulk):
    return volume_energy(x, rest_volume, bulk)


class PBDSpringsTetVolumeModel(SpringVolumeModel):
    """Springs of :class:`~difftissue.models.SpringVolumeModel` plus a per-tet volume term (the
    energy of an XPBD pypbd scene, :func:`pbd_reference_model`)."""

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        springs = SpringVolumeModel.terms(self, material)[0]
        bulk = (lam - mu)[self.tet_regions]
        return (springs, ElementTerm("tet_volume", self.tets, _tet_volume_energy, (self.tet_volumes, bulk)))


def pbd_reference_model(mesh) -> PBDSpringsTetVolumeModel:
    """difftissue's model of the energy an XPBD pypbd scene minimises (for comparisons).

    :class:`~difftissue.models.SpringVolumeModel`'s springs (same ``k`` and cubic ``a``) with
    the volume term on each tetrahedron, ``(lambda - mu) (V - V0)^2 / (2 V0)``, instead of on
    each cube. Solve it with :func:`difftissue.solvers.static.solve_static`.
    """
    return PBDSpringsTetVolumeModel(mesh)
