"""Cut openings at resolution: springs_volume (staircase cut, 0 and 25 deg) against a converged
quadratic-tet (P2) reference of the incision geometry of docs/cutting.md.

Geometry (experiments/cut_staircase.py): 12 x 12 mm, "dermis" 2 mm (E = 200 kPa, nu = 0.45,
pre-stretch lambda0) on "fat" 4 mm (E = 5 kPa, nu = 0.45), lateral faces held in x and y, base
clamped; a 6 mm x 2 mm cut through the centre of the top, at 0 deg (along x) or 25 deg.
Measure: the max surface width of the opened cut [m] (and the mean surface width).

Parts (each writes its JSON into experiments/results/ and can be run alone):

--springs CELL...  springs_volume on the staircase cut (0 and 25 deg) at lambda0 = 1.001 (the
                   linear limit, reported per unit pre-strain), 1.05, 1.10, 1.15;
                   `Incision.solve`, scalpel in one step, sparse solver. Cell sizes must divide
                   3 mm and 2 mm (cut ends and bottom on lattice faces): 1, 0.5, 1/3 mm.
                   -> cut_convergence_springs_cell{h}mm.json
--p2 N...          the P2 reference (scikit-fem, see `p2_reference`): quarter model of the
                   aligned cut (two mirror planes; the cut is a traction-free part of the
                   y-symmetry plane), graded tensor-product tet mesh with N cells per unit of
                   the coarse grid, linear limit and neo-Hookean (fem_neo_hookean's energy) at
                   lambda0 = 1.05, 1.10, 1.15 by Newton continuation.
                   -> cut_convergence_p2.json. Other meshes, each into its own file
                   (`p2_file`): ``--grading front+corner`` (also graded towards the max-width
                   corner x = 0, z = 6; _corner), ``--q Q`` (grading exponent; _q{Q}),
                   ``--p2-out NAME`` (e.g. cut_convergence_p2_fine.json: levels 7, 8).
--rotation CELL... the finite-square effect on the 25 deg cut: P2 (scikit-fem) in the linear
                   limit on the whole square, the library's snapped cut mesh (0 and 25 deg)
                   promoted to P2; the ratio 25/0 deg.  -> cut_convergence_rotation.json
--table            the convergence table (markdown) from the JSON files present; ``--p2-fine``
                   adds cut_convergence_p2_fine.json's levels to the reference,
                   ``--rotation-source conforming|snapped`` where the 25 deg references'
                   25/0 ratio comes from (default: conforming meshes, experiments/cut_conforming.py),
                   ``--rotation-cell MM`` the snapped ratio's cell size (default 1 mm).
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SIZE, DERMIS, FAT, DEPTH, LENGTH = 12e-3, 2e-3, 4e-3, 2e-3, 6e-3
E_DERMIS, E_FAT, NU = 2e5, 5e3, 0.45
LAMS = (1.001, 1.05, 1.10, 1.15)
LINEAR = 1.001


def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _write(name, data):
    from difftissue._io import atomic_output

    with atomic_output(RESULTS / name, overwrite=True) as tmp:
        Path(tmp).write_text(json.dumps(data, indent=1))


# --------------------------------------------------------------------------------------------
# springs_volume on the staircase cut


def springs_cell(cell, lams=LAMS, angles=(0.0, 25.0), size=SIZE, model="springs_volume"):
    """Max / mean surface width of springs_volume (or ``model``, e.g. its variant
    ``springs_volume_mesh_lattice``) on the staircase cut at one cell size [m]."""
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE))
    from cut_staircase import path, specimen, surface_measures

    from difftissue.cutting import cut_specimen
    from difftissue.incision import Incision, IncisionOptions
    from difftissue.materials import Material

    skin = Material(E_DERMIS, NU)
    spec = specimen(cell)
    opts = IncisionOptions(scalpel_steps=1, linear_solver="sparse")
    out = {"cell": cell, "model": model, "nodes": spec.mesh.n_nodes, "rows": []}
    for angle in angles:
        cut = cut_specimen(spec, path(angle), method="staircase")
        inc = Incision(cut, model=model, fitted_regions=("dermis",), options=opts)
        for lam in lams:
            t0 = time.process_time()
            res = inc.solve(skin.replace(pre_stretch=lam))
            wmax, wmean = surface_measures(cut, res.opening.width)
            row = dict(angle=angle, pre_stretch=lam, max_width=wmax, mean_width=wmean, cpu_seconds=time.process_time() - t0,
                       pairs=int(cut.n_pairs), cut_area_ratio=float(cut.quality.cut_area / cut.quality.ideal_area), rss_mb=rss_mb())
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
    return out



def _suitesparse_cholmod():
    """``sksparse.cholmod`` where scikit-sparse is installed, else None (cholespy is used)."""
    try:
        from sksparse import cholmod
    except ImportError:
        return None
    return cholmod


# --------------------------------------------------------------------------------------------
# P2 (quadratic tets) reference: fem_neo_hookean's energy on quadratic elements (scikit-fem
# basis, energy and element Hessians in JAX, Newton with a sparse Cholesky). Units inside: mm, kPa.


class P2Problem:
    """Compressible neo-Hookean (`difftissue.energies.neo_hookean_energy_density`) on P2 tets
    with a per-tet pre-stretch ``diag(l0, l0, 1)`` (the stress-free state of a pre-stretched
    region is the mesh shrunk by ``1/l0`` in x and y, as in `difftissue.models`).

    points: ``(N, 3)`` [mm]; tets: ``(M, 4)``; youngs: ``(M,)`` [kPa]; prestretched: ``(M,)``
    bool; fixed: function ``(doflocs (n, 3)) -> (n, 3) bool`` of the prescribed (zero)
    displacement components at the P2 nodes."""

    def __init__(self, points, tets, youngs, prestretched, fixed, nu=NU, intorder=4, chunk=4096, open_edges=(), minus=None):
        import jax
        import jax.numpy as jnp
        import skfem

        from difftissue.energies import neo_hookean_energy_density

        jax.config.update("jax_enable_x64", True)
        mesh = skfem.MeshTet(np.ascontiguousarray(np.asarray(points, float).T), np.ascontiguousarray(np.asarray(tets).T))
        basis = skfem.CellBasis(mesh, skfem.ElementTetP2(), intorder=intorder)
        self.n = basis.N
        self.n_p2 = basis.N
        self.doflocs = basis.doflocs.T
        self.n_vertices = mesh.p.shape[1]
        edofs = basis.element_dofs.T.copy()  # (M, 10)
        # open_edges: vertex pairs (a, b) on the cut used by tets of both sides (two crack-front
        # nodes joined across the opened face); their P2 midside node gets a copy for the tets
        # with minus[k] so that the sides do not stay glued there
        for a, b in open_edges:
            mid = 0.5 * (self.doflocs[a] + self.doflocs[b])
            d = int(np.argmin(np.linalg.norm(self.doflocs - mid, axis=1)))
            assert np.linalg.norm(self.doflocs[d] - mid) < 1e-9
            rows = np.nonzero(np.asarray(minus, bool)[:, None] & (edofs == d))
            edofs[rows] = self.n
            self.doflocs = np.vstack([self.doflocs, mid])
            self.n += 1
        dphi = np.stack([basis.basis[a][0].grad for a in range(10)])  # (10, 3, M, nq)
        self.dphi = np.ascontiguousarray(np.transpose(dphi, (2, 3, 0, 1)))  # (M, nq, 10, 3)
        self.dxw = np.asarray(basis.dx)  # (M, nq)
        youngs = np.asarray(youngs, float)
        self.lame = youngs * nu / ((1 + nu) * (1 - 2 * nu))
        self.mu = youngs / (2 * (1 + nu))
        self.pre = np.asarray(prestretched, bool)
        self.gdofs = (3 * edofs[:, :, None] + np.arange(3)).reshape(-1, 30)
        fx = np.asarray(fixed(self.doflocs), bool)
        self.free = ~fx.reshape(-1)
        self.chunk = chunk
        M = len(edofs)
        self.M = M
        rows = np.repeat(self.gdofs, 30, axis=1).reshape(-1)
        cols = np.tile(self.gdofs, (1, 30)).reshape(-1)
        import scipy.sparse as sps

        ff = self.free[rows] & self.free[cols]
        fidx = -np.ones(3 * self.n, int)
        fidx[self.free] = np.arange(self.free.sum())
        self._fr, self._fc, self._ff = fidx[rows[ff]], fidx[cols[ff]], ff
        nf = int(self.free.sum())
        pat = sps.csr_matrix((np.arange(1, self._fr.size + 1, dtype=float), (self._fr, self._fc)), shape=(nf, nf))
        self._nf = nf
        del pat
        I3 = jnp.eye(3)

        def elem_energy(ue, dphi_e, dx_e, lam_e, mu_e, l0_e):
            G = jnp.einsum("ai,qaj->qij", ue.reshape(10, 3), dphi_e)
            D = jnp.stack([l0_e, l0_e, 1.0])
            F = (I3 + G) * D
            return jnp.sum(dx_e * neo_hookean_energy_density(F, lam_e, mu_e)) / (l0_e * l0_e)

        self._e = jax.jit(jax.vmap(elem_energy))
        self._g = jax.jit(jax.vmap(jax.grad(elem_energy)))
        self._h = jax.jit(jax.vmap(jax.hessian(elem_energy)))

    def _chunks(self, fn, u, l0):
        ue = u.reshape(-1)[self.gdofs]
        l0e = np.where(self.pre, l0, 1.0)
        out = []
        for s in range(0, self.M, self.chunk):
            sl = slice(s, min(s + self.chunk, self.M))
            k = sl.stop - sl.start
            pad = self.chunk - k

            def p(a):
                return np.concatenate([a[sl], np.repeat(a[sl.stop - 1 : sl.stop], pad, axis=0)]) if pad else a[sl]

            out.append(np.asarray(fn(p(ue), p(self.dphi), p(self.dxw), p(self.lame), p(self.mu), p(l0e)))[:k])
        return np.concatenate(out)

    def energy(self, u, l0):
        return float(np.sum(self._chunks(self._e, u, l0)))

    def gradient(self, u, l0):
        g = np.zeros(3 * self.n)
        np.add.at(g, self.gdofs.reshape(-1), self._chunks(self._g, u, l0).reshape(-1))
        return g

    def hessian(self, u, l0):
        import scipy.sparse as sps

        h = self._chunks(self._h, u, l0).reshape(-1)[self._ff]
        return sps.csr_matrix((h, (self._fr, self._fc)), shape=(self._nf, self._nf))

    @staticmethod
    def _factorise(K):
        """Cholesky of K, or of K + tau diag(K) with the smallest tau in 1e-8 * 10^k that is
        positive definite (a descent direction away from the solution, where the tangent of the
        cut flaps can be indefinite). Returns the solve ``b -> x`` and tau. CHOLMOD's supernodal
        factorisation through scikit-sparse where it is installed, else cholespy's simplicial one
        (same factor up to rounding; a level-6 linear limit took 16 s of CPU with the supernodal one,
        36 s with cholespy, on different days' load)."""
        import scipy.sparse as sps

        cholmod = _suitesparse_cholmod()
        diag = K.diagonal()
        tau = 0.0
        while True:
            A = K if tau == 0.0 else (K + sps.diags(tau * diag)).tocsr()
            if cholmod is not None:  # supernodal, CHOLMOD's own fill-reducing ordering
                try:
                    factor = cholmod.cholesky(A.tocsc(), mode="supernodal")
                except cholmod.CholmodNotPositiveDefiniteError:
                    tau = 1e-8 if tau == 0.0 else 10.0 * tau
                    if tau > 1e3:
                        raise RuntimeError("no positive definite shift of the tangent") from None
                    continue
                return factor, tau
            import cholespy

            try:
                fac = cholespy.CholeskySolverD(A.shape[0], A.indptr.astype(np.int32), A.indices.astype(np.int32), np.array(A.data), cholespy.MatrixType.CSR)
            except ValueError:
                tau = 1e-8 if tau == 0.0 else 10.0 * tau
                if tau > 1e3:
                    raise RuntimeError("no positive definite shift of the tangent") from None
                continue

            def solve(b, fac=fac):
                x = np.zeros_like(b)
                fac.solve(np.ascontiguousarray(b), x)
                return x

            return solve, tau

    @classmethod
    def _shifted_solve(cls, K, b):
        """``K^-1 b`` through `_factorise` (one analysis and factorisation)."""
        return cls._factorise(K)[0](b)

    def continuation(self, start, stop, u=None, step=0.025):
        """Solve at ``stop`` from the solution ``u`` at ``start`` in pre-stretch steps <= ``step``."""
        its = 0
        for sub in np.linspace(start, stop, int(np.ceil((stop - start) / step - 1e-9)) + 1)[1:]:
            u, k = self.solve(sub, u)
            its += k
        return u, its

    #: print one line per Newton iteration (``--newton-log``): time, |g|, line-search step, CPU split
    log_iterations = False
    #: frozen-tangent Newton (``--full-newton`` turns it off): the tangent is factorised at the
    #: first iteration of a solve and kept while |g|_inf falls by at least ``1 / frozen_rate``
    #: per iteration; a slower fall, or a line search that has to shorten a step taken with a
    #: kept factor, refactorises at the current iterate. Same stopping rule as full Newton; at
    #: the stop the error left is about ``frozen_rate / (1 - frozen_rate)`` times the last step.
    frozen_tangent = True
    frozen_rate = 0.25
    #: tangent factorisations so far (all solves of this problem)
    factorisations = 0

    def solve(self, l0, u=None, tol=1e-9, max_iter=100):
        """Newton (sparse Cholesky, backtracking on the energy; frozen tangent while the residual
        falls fast, see `frozen_tangent`) to |du|_inf < tol * max(|u|_inf, 1 um).
        Returns the displacement ``(n, 3)`` [mm] and the iteration count."""
        u = np.zeros((self.n, 3)) if u is None else u.copy()
        fac, gprev = None, None
        for it in range(max_iter):
            c0 = time.process_time()
            g = self.gradient(u, l0)[self.free]
            gn = float(np.max(np.abs(g)))
            fresh = fac is None or not self.frozen_tangent or gn > self.frozen_rate * gprev
            if fresh:
                K = self.hessian(u, l0)
                c1 = time.process_time()
                fac, tau = self._factorise(K)
                self.factorisations += 1
            else:
                c1 = time.process_time()
            d = fac(-g)
            c2 = time.process_time()
            e0, t, halvings = self.energy(u, l0), 1.0, 0
            while True:
                v = u.reshape(-1).copy()
                v[self.free] += t * d
                v = v.reshape(-1, 3)
                if self.energy(v, l0) <= e0 + 1e-12 * abs(e0) or t < 1e-4:
                    break
                t *= 0.5
                halvings += 1
            u = v
            if halvings and not fresh:
                fac = None  # a kept factor that needs a shortened step: refactorise
            gprev = gn
            if self.log_iterations:
                print(f"[{time.strftime('%H:%M:%S')}] l0={l0:.4f} it={it} |g|inf={gn:.3e} t={t:.4g} (halvings {halvings}) "
                      f"step={np.max(np.abs(t * d)):.3e} E0={e0:.10e} {'factorised' + (f' (shift {tau:g})' if tau else '') if fresh else 'kept factor'} "
                      f"cpu grad(+hess)={c1-c0:.1f}s chol+solve={c2-c1:.1f}s ls={time.process_time()-c2:.1f}s", flush=True)
            if np.max(np.abs(t * d)) < tol * max(np.max(np.abs(u)), 1e-3):
                return u, it + 1
        raise RuntimeError(f"Newton did not converge at lambda0 = {l0} (last step {np.max(np.abs(t * d)):.3e} mm)")


def graded(a, b, n, toward, q):
    """n cells on [a, b] graded with exponent q towards the end ``toward`` (a or b)."""
    t = np.linspace(0.0, 1.0, n + 1) ** q
    x = a + (b - a) * t if toward == a else b - (b - a) * t
    return np.sort(x)


def graded_both(a, b, n, q):
    """n cells on [a, b] graded with exponent q towards both ends: ``t = s^q / (s^q + (1-s)^q)``.
    The end cells tend to `graded`'s fine end, ``(b - a) / n^q``, for large n, but are coarser
    at the levels used (``1 / (1 + (n - 1)^q)`` against ``n^-q``: 1.29x at n = 4, 1.16x at
    n = 8); the middle ones are coarser still."""
    s = np.linspace(0.0, 1.0, n + 1)
    return a + (b - a) * s**q / (s**q + (1.0 - s) ** q)


#: the quarter mesh's gradings: "front" grades x towards the cut end x = 3, y towards the cut
#: plane, z towards the cut bottom z = 4; "front+corner" in addition grades x in [0, 3] towards
#: the mirror plane x = 0 and z in [4, 6] towards the top z = 6, i.e. also towards the corner
#: x = 0, y = 0, z = 6 where the max surface width sits (same node counts per level)
GRADINGS = ("front", "front+corner")


def quarter_mesh(n, q=1.5, flip_x=False, grading="front"):
    """Graded tensor-product tet mesh of the quarter model [mm]: x in [0, 6] (x = 0 the mirror
    plane through the middle of the cut, the cut end at x = 3), y in [0, 6] (y = 0 the cut plane),
    z in [0, 6] (base z = 0, dermis 4..6). n cells on each graded segment (x: 0-3, 3-6;
    y: 0-6 with 2n; z: 0-4, 4-6); ``grading`` one of `GRADINGS`."""
    import skfem

    if grading not in GRADINGS:
        raise ValueError(f"grading {grading!r} not in {GRADINGS}")
    corner = grading == "front+corner"
    x = np.unique(np.concatenate([graded_both(0, 3, n, q) if corner else graded(0, 3, n, 3, q), graded(3, 6, n, 3, q)]))
    y = graded(0, 6, 2 * n, 0, q)
    z = np.unique(np.concatenate([graded(0, 4, n, 4, q), graded_both(4, 6, n, q) if corner else graded(4, 6, n, 4, q)]))
    if not flip_x:
        m = skfem.MeshTet.init_tensor(x, y, z)
        return m.p.T, m.t.T
    m = skfem.MeshTet.init_tensor(np.sort(6.0 - x), y, z)  # the same grid, hexes split the other way in x
    p = m.p.T.copy()
    p[:, 0] = 6.0 - p[:, 0]
    return p, m.t.T


def quarter_problem(n, q=1.5, flip_x=False, grading="front"):
    p, t = quarter_mesh(n, q, flip_x, grading)
    zc = p[t].mean(axis=1)[:, 2]
    derm = zc > 4.0
    eps = 1e-9

    def fixed(X):
        f = np.zeros(X.shape, bool)
        f[:, 0] |= X[:, 0] < eps  # mirror x = 0
        cutface = (X[:, 0] < 3 - eps) & (X[:, 2] > 4 + eps)
        f[:, 1] |= (X[:, 1] < eps) & ~cutface  # mirror y = 0 outside the cut
        held = (X[:, 0] > 6 - eps) | (X[:, 1] > 6 - eps)
        f[:, 0] |= held
        f[:, 1] |= held
        f[X[:, 2] < eps] = True  # clamped base
        return f

    return P2Problem(p, t, np.where(derm, E_DERMIS * 1e-3, E_FAT * 1e-3), derm, fixed)


def quarter_widths(prob, u):
    """Max and mean surface width [mm] of the quarter model (mirror: width = 2 u_y on y = 0)."""
    X = prob.doflocs
    top = (np.abs(X[:, 1]) < 1e-9) & (np.abs(X[:, 2] - 6.0) < 1e-9) & (X[:, 0] <= 3 + 1e-9)
    xs, w = X[top, 0], 2.0 * u[top, 1]
    o = np.argsort(xs)
    xs, w = xs[o], w[o]
    # P2 along the top edge: vertices at even positions, midside nodes at odd ones: Simpson
    mean = np.sum((xs[2::2] - xs[:-2:2]) / 6.0 * (w[:-2:2] + 4 * w[1::2] + w[2::2])) / 3.0
    return float(w.max()), float(mean)


def p2_reference(levels, lams=LAMS, q=1.5, on_row=None, grading="front"):
    """P2 quarter-model rows (max / mean surface width [mm], Newton iterations, tangent
    factorisations, CPU seconds) per level n and lambda0 (continuation through ``lams`` in
    order), on the mesh graded as ``grading`` (`GRADINGS`). ``on_row(out)`` is called after each
    row (the script writes the JSON there, so that an interrupted level keeps the lambda0 it
    finished)."""
    out = {"q": q, "grading": grading, "rows": []}
    for n in levels:
        t0 = time.process_time()
        prob = quarter_problem(n, q, grading=grading)
        u, prev = None, 1.0
        for lam in lams:
            t1, f1 = time.process_time(), prob.factorisations
            u, its = prob.continuation(prev, lam, u)
            prev = lam
            wmax, wmean = quarter_widths(prob, u)
            row = dict(n=n, dofs=3 * int(prob.n), free=int(prob.free.sum()), tets=int(prob.M), pre_stretch=lam, max_width_mm=wmax, mean_width_mm=wmean,
                       newton=its, factorisations=prob.factorisations - f1, frozen_tangent=bool(prob.frozen_tangent),
                       cpu_seconds=time.process_time() - t1, rss_mb=rss_mb())
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
            if on_row is not None:
                on_row(out)
        print(f"level {n}: {time.process_time() - t0:.1f} s cpu", flush=True)
    return out


def p2_file(grading="front", q=1.5):
    """The P2 JSON of a grading and exponent: cut_convergence_p2.json (the "front" grading with
    q = 1.5, no ``grading`` key), else with ``_corner`` ("front+corner") and ``_q{q}`` (q other
    than 1.5) appended."""
    return "cut_convergence_p2" + ("_corner" if grading == "front+corner" else "") + ("" if q == 1.5 else f"_q{q:g}") + ".json"


def _merge_p2(new, name=None):
    """Write ``new``'s rows into ``name`` (default: its grading's P2 JSON, `p2_file`): a
    (level, lambda0) given again is replaced, the other rows kept."""
    grading = new.get("grading", "front")
    name = name or p2_file(grading, new["q"])
    old = _load(name)
    rows = list(new["rows"])
    if old is not None and old.get("q") == new["q"] and old.get("grading", "front") == grading:
        keys = {(r["n"], round(r["pre_stretch"], 9)) for r in rows}
        rows = [r for r in old["rows"] if (r["n"], round(r["pre_stretch"], 9)) not in keys] + rows
    rows.sort(key=lambda r: (r["n"], r["pre_stretch"]))
    _write(name, {"q": new["q"], "rows": rows} | ({} if grading == "front" else {"grading": grading}))


def _open_edges(cut, X, angle):
    """Tet edges of a snapped cut mesh between two undivided (crack-front) nodes, used by tets
    of both sides, whose midpoint lies inside the opened face (between the ends, above the
    bottom): P2 would glue the sides at their midside node (P1 has none)."""
    import itertools

    t, side = np.asarray(cut.mesh.tets), np.asarray(cut.tet_side)
    dup = set(np.asarray(cut.pairs).ravel().tolist())
    sides = {}
    for k in np.nonzero(side)[0]:
        for a, b in itertools.combinations(sorted(t[k].tolist()), 2):
            if a not in dup and b not in dup:
                sides.setdefault((a, b), set()).add(int(side[k]))
    c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
    top = X[:, 2].max()
    out = []
    for (a, b), sd in sides.items():
        m = 0.5 * (X[a] + X[b]) - np.array([6.0, 6.0, 0.0])
        if sd == {1, -1} and m[2] > top - DEPTH * 1e3 + 1e-6 and abs(m[0] * c + m[1] * s) < 0.5 * LENGTH * 1e3 - 1e-6:
            out.append((a, b))
    return out


def rotation(cell, lams=(LINEAR,), angles=(0.0, 25.0)):
    """P2 on the whole square: the library's snapped cut mesh (`cut_specimen(..., "snap")`, the
    cut faces on the cutting plane) with its tets promoted to P2; lateral faces held in x and y,
    base clamped. Max / mean surface width [mm] per angle and lambda0."""
    sys.path.insert(0, str(HERE))
    import jax

    jax.config.update("jax_enable_x64", True)
    from cut_staircase import path, specimen, surface_measures

    from difftissue.cutting import cut_specimen

    spec = specimen(cell)
    out = {"cell": cell, "rows": []}
    for angle in angles:
        cut = cut_specimen(spec, path(angle), method="snap")
        m = cut.mesh
        X = np.asarray(m.points) * 1e3
        derm = np.asarray(m.region_ids) == m.region_names.index("dermis")
        lo, hi = X.min(axis=0), X.max(axis=0)

        def fixed(Y, lo=lo, hi=hi):
            f = np.zeros(Y.shape, bool)
            side = (np.abs(Y[:, 0] - lo[0]) < 1e-9) | (np.abs(Y[:, 0] - hi[0]) < 1e-9) | (np.abs(Y[:, 1] - lo[1]) < 1e-9) | (np.abs(Y[:, 1] - hi[1]) < 1e-9)
            f[:, 0] |= side
            f[:, 1] |= side
            f[np.abs(Y[:, 2] - lo[2]) < 1e-9] = True
            return f

        side = np.asarray(cut.tet_side)
        prob = P2Problem(X, np.asarray(m.tets), np.where(derm, E_DERMIS * 1e-3, E_FAT * 1e-3), derm, fixed,
                         open_edges=_open_edges(cut, X, angle), minus=side < 0)
        u, prev = None, 1.0
        for lam in lams:
            t0 = time.process_time()
            u, its = prob.continuation(prev, lam, u)
            prev = lam
            x = X + u[: prob.n_vertices]
            a, b = np.asarray(cut.pairs).T
            width = np.linalg.norm(x[a] - x[b], axis=1)
            wmax, wmean = surface_measures(cut, width)
            row = dict(angle=angle, pre_stretch=lam, max_width_mm=wmax, mean_width_mm=wmean, dofs=3 * int(prob.n), newton=its,
                       max_normal_distance_mm=float(cut.quality.max_normal_distance) * 1e3, open_edges=int(prob.n - prob.n_p2), cpu_seconds=time.process_time() - t0, rss_mb=rss_mb())
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
    return out


def order3(f, h):
    """Observed order and Richardson value from three values ``f`` at mesh sizes ``h``
    (experiments/cut_staircase.py's rule; nan order where the increments change sign)."""
    sys.path.insert(0, str(HERE))
    from cut_staircase import _order

    return _order(list(f), list(h))


def no_order_reason(f, h):
    """Why three values ``f`` at sizes ``h`` (coarse to fine) give no observed order in
    `order3` (which searches p in [0.05, 6]): "increments change sign", "increments grow",
    "increments shrink slower than any power of h" (their ratio at or below that of p = 0.05,
    i.e. about ln(h1/h2) / ln(h2/h3)) or "increments shrink faster than h^6". Raises
    ``ValueError`` for a triple that has an observed order."""
    d1, d2 = f[1] - f[0], f[2] - f[1]
    if d1 * d2 <= 0:
        return "increments change sign"
    if abs(d2) >= abs(d1):
        return "increments grow"
    ratio = lambda p: (h[0] ** p - h[1] ** p) / (h[1] ** p - h[2] ** p)  # noqa: E731
    if d1 / d2 <= ratio(0.05):
        return "increments shrink slower than any power of h"
    if d1 / d2 >= ratio(6.0):
        return "increments shrink faster than h^6"
    raise ValueError(f"the increments of {f} at {h} give an observed order; no reason to report")


def _load(name):
    p = RESULTS / name
    return json.loads(p.read_text()) if p.exists() else None


#: P2 files the reference reads (`reference`): cut_convergence_p2.json (levels 2-6), and with
#: ``--table --p2-fine`` also cut_convergence_p2_fine.json (levels 7, 8 of the same grading,
#: kept apart so that the level-6 tables stay reproducible)
P2_FILES = ("cut_convergence_p2.json",)
P2_FINE = "cut_convergence_p2_fine.json"


def reference():
    """Converged P2 max / mean surface width per lambda0 [mm] (aligned cut) from the rows of
    `P2_FILES`: Richardson value of
    the three finest quarter-model levels, its observed order, and the error estimate
    max(|Richardson - finest|, |Richardson - first-order extrapolation of the two finest|) (with the Richardson value of the three coarsest levels alongside
    where there are more than three)."""
    d = {"rows": [r for name in P2_FILES for r in (_load(name) or {"rows": []})["rows"]]}
    out = {}
    for lam in LAMS:
        rows = sorted((r for r in d["rows"] if r["pre_stretch"] == lam), key=lambda r: r["n"])
        for q in ("max_width_mm", "mean_width_mm"):
            f = [r[q] for r in rows]
            h = [1.0 / r["n"] for r in rows]
            if len(f) >= 3:
                p, ext = order3(f[-3:], h[-3:])
            elif len(f) < 2:
                p, ext = float("nan"), float("nan")
            else:  # two levels: first order assumed
                p, ext = float("nan"), f[-1] + (f[-1] - f[-2]) * h[-1] / (h[-2] - h[-1])
            p0, ext0 = order3(f[:3], h[:3]) if len(f) >= 4 else (float("nan"), float("nan"))
            first = f[-1] + (f[-1] - f[-2]) * h[-1] / (h[-2] - h[-1]) if len(f) >= 2 else float("nan")
            err = max(abs(ext - f[-1]), abs(ext - first)) if len(f) >= 3 else abs(ext - f[-1])
            out[(lam, q)] = dict(levels=[r["n"] for r in rows], values=f, order=p, value=ext, error=err, coarse_order=p0, coarse_value=ext0)
    return out


def rotation_ratio():
    """25 deg / 0 deg max and mean surface width of the whole-square P2 on snapped cut meshes,
    per cell size and lambda0: {(lam, quantity): [(cell, ratio), ...]}."""
    d = _load("cut_convergence_rotation.json")
    out = {}
    for run in d or []:
        for lam in sorted({r["pre_stretch"] for r in run["rows"]}):
            for q in ("max_width_mm", "mean_width_mm"):
                v = {r["angle"]: r[q] for r in run["rows"] if r["pre_stretch"] == lam}
                out.setdefault((lam, q), []).append((run["cell"], v[25.0] / v[0.0]))
    return out


#: where the 25 / 0 deg ratio that turns the 0 deg reference into the 25 deg one comes from
#: (``--table --rotation-source``): "conforming" (default), the whole-square P2 on gmsh meshes
#: that follow the cut (experiments/cut_conforming.py: 1.0018 at h_cut = 0.1 mm, converged to
#: about +-0.001), or "snapped", the whole-square P2 on the library's snapped cut meshes
#: (`rotation_ratio`, `ROTATION_CELL`: 0.9835 at 1 mm, 0.9569 at 0.5 mm, an artefact of the
#: snapped 25 deg crack front; docs/dev/cut-openings-finite-strain.md)
ROTATION_SOURCE = "conforming"
#: element size at the cut [m] of the conforming ratio (None: the finest run with h_far 1.5 mm)
CONFORMING_H = None
#: cell size [m] of the snapped ratio (``--rotation-cell``); None: the finest in
#: cut_convergence_rotation.json
ROTATION_CELL = 1e-3


def conforming_ratio():
    """25 deg / 0 deg max and mean surface width of the whole-square P2 on conforming meshes
    (cut_conforming_p2.json, far-field size 1.5 mm), per lambda0 and quantity:
    {(lam, quantity): [(h_cut [m], ratio), ...]}, h_cut decreasing."""
    d = _load("cut_conforming_p2.json") or {"rows": []}
    names = {"max_width_mm": "max_width", "mean_width_mm": "mean_width_trapezoid"}
    by = {}
    for r in d["rows"]:
        if r["h_far_mm"] == 1.5:
            by.setdefault((round(r["pre_stretch"], 9), r["h_cut_mm"]), {})[r["angle"]] = r
    out = {}
    for (lam, h), v in sorted(by.items(), key=lambda kv: (kv[0][0], -kv[0][1])):
        if 0.0 in v and 25.0 in v:
            for q, name in names.items():
                out.setdefault((lam, q), []).append((h * 1e-3, v[25.0][name] / v[0.0][name]))
    return out


def rotation_factor(quantity="max_width_mm"):
    """(size [m], 25/0 deg ratio) of the linear-limit ratio used for the 25 deg reference
    (`ROTATION_SOURCE`; `CONFORMING_H` or `ROTATION_CELL` pick the mesh), or (nan, nan) where
    there is none."""
    if ROTATION_SOURCE == "conforming":
        ratios = conforming_ratio().get((round(LINEAR, 9), quantity), [])
        wanted = CONFORMING_H
    else:
        ratios = rotation_ratio().get((LINEAR, quantity), [])
        wanted = ROTATION_CELL
    if wanted is not None:
        ratios = [(c, x) for c, x in ratios if abs(c - wanted) < 1e-12]
    return ratios[-1] if ratios else (float("nan"), float("nan"))


def rotation_label():
    """Where the 25 deg references' ratio comes from, for the tables' captions."""
    h, x = rotation_factor()
    where = "conforming whole-square P2, h_cut" if ROTATION_SOURCE == "conforming" else "snapped whole-square P2, h"
    return f"the linear-limit 25/0 ratio {x:.4f} ({where} = {h * 1e3:.3g} mm)"


def _springs_runs(model="springs_volume"):
    return sorted((json.loads(p.read_text()) for p in RESULTS.glob(f"cut_convergence_{_tag(model)}_cell*mm.json")), key=lambda d: -d["cell"])


def _tag(model):
    return "springs" if model == "springs_volume" else model.replace("springs_volume", "springs")


def springs_table(quantity="max_width", model="springs_volume"):
    """Markdown rows: springs_volume (staircase) at each cell size against the reference."""
    runs = _springs_runs(model)
    ref = reference()
    q = quantity + "_mm"
    lines = []
    for angle in (0.0, 25.0):
        for lam in LAMS:
            scale = 1.0 / (lam - 1.0) if lam == LINEAR else 1.0
            r = ref[(lam, q)]
            target = r["value"]
            if angle == 25.0:
                target *= rotation_factor(q)[1]
            hs, vals = [], []
            for d in runs:
                hit = [x for x in d["rows"] if x["angle"] == angle and abs(x["pre_stretch"] - lam) < 1e-9]
                if hit:
                    hs.append(d["cell"])
                    vals.append(hit[0][quantity] * 1e3)
            if not vals:
                continue
            err = [v / target - 1.0 for v in vals]
            p_ref = float(np.log(abs(err[-2] / err[-1])) / np.log(hs[-2] / hs[-1])) if len(err) >= 2 and err[-1] * err[-2] > 0 else float("nan")
            if len(vals) >= 3:
                p3, rich = order3(vals[-3:], hs[-3:])
            elif len(vals) == 2 and hs[-2] <= 1.0 + 1e-9:  # two cell sizes <= 1 mm [mm]: springs_volume's second order assumed
                p3, rich = float("nan"), vals[-1] + (vals[-1] - vals[-2]) * hs[-1] ** 2 / (hs[-2] ** 2 - hs[-1] ** 2)
            else:
                p3, rich = float("nan"), float("nan")
            h5 = hs[-1] * (0.05 / abs(err[-1])) ** (1.0 / p_ref) if err and np.isfinite(p_ref) and p_ref > 0 else float("nan")
            lines.append(dict(angle=angle, pre_stretch=lam, reference=target * scale, cells=hs, values=[v * scale for v in vals], errors=err,
                              order_vs_reference=p_ref, order_own=p3, order_assumed=len(vals) == 2 and np.isfinite(rich), richardson=rich * scale, richardson_error=rich / target - 1.0,
                              cell_for_5pct=h5 if abs(err[-1]) > 0.05 else hs[-1]))
    return lines


def markdown(models=("springs_volume", "springs_volume_mesh_lattice")):
    """The tables of docs/experiments.md (max surface width)."""
    ref = reference()
    rot = rotation_ratio()
    lines = ["| λ0 | P2 levels n (quarter): max surface width | observed order | extrapolated (± estimate) | 25° / 0° (whole square, P2, snapped cut) | 25° / 0° (whole square, P2, conforming mesh) |", "|---|---|---|---|---|---|"]
    conf = conforming_ratio()
    for lam in LAMS:
        r = ref[(lam, "max_width_mm")]
        sc = 1.0 / (lam - 1.0) if lam == LINEAR else 1.0
        vals = ", ".join(f"{n}: {v * sc:.4f}" for n, v in zip(r["levels"], r["values"]))
        ratio = ", ".join(f"{x:.4f} (h = {c * 1e3:.3g} mm)" for c, x in rot.get((lam, "max_width_mm"), [])) or "-"
        ratio_c = ", ".join(f"{x:.4f} (h_cut = {c * 1e3:.3g} mm)" for c, x in conf.get((round(lam, 9), "max_width_mm"), [])) or "-"
        o = f"{r['order']:.2f}" if np.isfinite(r["order"]) else ("1 assumed (2 levels)" if len(r["values"]) < 3 else f"none ({no_order_reason(r['values'][-3:], [1.0 / n for n in r['levels'][-3:]])}; 1 assumed)")
        lab = "linear limit" if lam == LINEAR else f"{lam:.2f}"
        lines.append(f"| {lab} | {vals} | {o} | {r['value'] * sc:.4f} ± {r['error'] * sc:.4f} ({100 * r['error'] / r['value']:.1f} %) | {ratio} | {ratio_c} |")
    print("\n".join(lines) + "\n")
    print(f"25° references: the 0° ones times {rotation_label()}\n")
    for model in models:
        if _springs_runs(model):
            print(f"\n{model}\n")
            _springs_markdown(model)


def _springs_markdown(model):
    hs = [d["cell"] for d in _springs_runs(model)]
    lines = ["| cut | λ0 | reference | " + " | ".join(f"h = {h:.3g} mm" for h in hs) + " | own order | extrapolated | h for 5 % |",
             "|---|---|---|" + "---|" * (len(hs) + 3)]
    for ln in springs_table("max_width", model):
        vals = {h: (v, e) for h, v, e in zip(ln["cells"], ln["values"], ln["errors"])}
        cells = " | ".join(f"{vals[h][0]:.4f} ({100 * vals[h][1]:+.1f} %)" if h in vals else "-" for h in hs)
        lab = "linear limit" if ln["pre_stretch"] == LINEAR else f"{ln['pre_stretch']:.2f}"
        o = f"{ln['order_own']:.2f}" if np.isfinite(ln["order_own"]) else "-"
        ex = f"{ln['richardson']:.4f} ({100 * ln['richardson_error']:+.1f} %)" if np.isfinite(ln["richardson"]) else "-"
        if ln["order_assumed"] and np.isfinite(ln["richardson"]):
            ex += ", order 2 assumed"
        if len(ln["cells"]) < len(hs) and abs(ln["errors"][-1]) > 0.05:
            h5 = "-"
        elif abs(ln["errors"][-1]) <= 0.05:
            h5 = "met"
        elif np.isfinite(ln["richardson_error"]) and abs(ln["richardson_error"]) > 0.05:
            h5 = "not by refining"  # the model's own h -> 0 limit misses the reference by more than 5 %
            if ln["order_assumed"]:
                h5 += " (order 2 assumed)"
        else:
            h5 = f"{ln['cell_for_5pct']:.2f} mm" if np.isfinite(ln["cell_for_5pct"]) else "-"
        lines.append(f"| {ln['angle']:g}° | {lab} | {ln['reference']:.4f} | {cells} | {o} | {ex} | {h5} |")
    print("\n".join(lines))


def table():
    ref = reference()
    print("P2 reference (aligned cut, quarter model; widths in mm, per unit pre-strain at lambda0 = 1.001)\n")
    for (lam, q), r in ref.items():
        sc = 1.0 / (lam - 1.0) if lam == LINEAR else 1.0
        vals = ", ".join(f"n={n}: {v * sc:.4f}" for n, v in zip(r["levels"], r["values"]))
        print(f"| {lam} | {q} | {vals} | order {r['order']:.2f} | Richardson {r['value'] * sc:.4f} +- {r['error'] * sc:.4f} "
              f"({100 * r['error'] / r['value']:.2f} %) | coarse triple: order {r['coarse_order']:.2f}, {r['coarse_value'] * sc:.4f} |")
    print("\nrotation ratio 25/0 deg (whole-square P2 on snapped meshes)\n")
    for k, v in rotation_ratio().items():
        print(k, ", ".join(f"h={c * 1e3:.3g} mm: {x:.4f}" for c, x in v))
    print("\nrotation ratio 25/0 deg (whole-square P2 on conforming meshes, experiments/cut_conforming.py)\n")
    for k, v in conforming_ratio().items():
        print(k, ", ".join(f"h_cut={c * 1e3:.3g} mm: {x:.4f}" for c, x in v))
    print(f"25 deg references: the 0 deg ones times {rotation_label()}")
    for quantity in ("max_width", "mean_width"):
        print(f"\nsprings_volume, staircase cut: {quantity}\n")
        for ln in springs_table(quantity):
            vals = " | ".join(f"{v:.4f} ({100 * e:+.1f} %)" for v, e in zip(ln["values"], ln["errors"]))
            print(f"| {ln['angle']:g} | {ln['pre_stretch']} | {ln['reference']:.4f} | {vals} | {ln['order_vs_reference']:.2f} | {ln['order_own']:.2f} | "
                  f"{ln['richardson']:.4f} ({100 * ln['richardson_error']:+.1f} %) | {ln['cell_for_5pct']:.2f} |")


def plot(out=HERE.parent / "docs" / "img" / "cut_convergence.png"):
    """Error of the springs_volume max surface width against the P2 reference over cell size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    for k, angle in enumerate((0.0, 25.0)):
        for ln in springs_table("max_width"):
            if ln["angle"] != angle:
                continue
            lab = "linear limit" if ln["pre_stretch"] == LINEAR else f"lambda0 = {ln['pre_stretch']:.2f}"
            ax[k].plot(ln["cells"], [100 * abs(e) for e in ln["errors"]], "o-", label=lab)
        ax[k].axhline(5.0, color="k", lw=0.8, ls="--")
        ax[k].set_xscale("log")
        ax[k].set_yscale("log")
        ax[k].set_xlabel("cell size h [mm]")
        ax[k].set_title(f"{angle:g} deg cut (staircase)")
    ax[0].set_ylabel("|max surface width error| [%]")
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--springs", type=float, nargs="*", default=[], help="cell sizes [mm]")
    ap.add_argument("--model", default="springs_volume", help="model of --springs (springs_volume, springs_volume_mesh_lattice, "
                    "springs_volume_matched_lattice)")
    ap.add_argument("--lams", type=float, nargs="*", default=None, help="lambda0 values of --springs (default all; the rows "
                    "are merged into the file's other rows)")
    ap.add_argument("--angles", type=float, nargs="*", default=None, help="cut angles [deg] of --springs (default 0 25; merged)")
    ap.add_argument("--newton-log", action="store_true", help="--p2: one line per Newton iteration")
    ap.add_argument("--p2", type=int, nargs="*", default=[], help="quarter-model levels n (e.g. 3 4 6 8)")
    ap.add_argument("--p2-lams", type=float, nargs="*", default=None, help="lambda0 values of --p2 (default all; the continuation "
                    "passes through the ones between)")
    ap.add_argument("--grading", choices=GRADINGS, default="front", help="--p2: the quarter mesh's grading (front: "
                    "cut_convergence_p2.json; front+corner: also towards the max-width corner, cut_convergence_p2_corner.json)")
    ap.add_argument("--q", type=float, default=1.5, help="--p2: the grading exponent (1.5: the files above; else "
                    "_q{q} appended to the name)")
    ap.add_argument("--p2-out", default=None, help="--p2: write into this file of experiments/results/ instead of "
                    "the grading's (diagnostic levels that must not change the reference)")
    ap.add_argument("--full-newton", action="store_true", help="--p2: factorise the tangent at every Newton iteration "
                    "(default: frozen tangent while the residual falls fast)")
    ap.add_argument("--rotation", type=float, nargs="*", default=[], help="cell sizes [mm] of the whole-square P2 (linear limit)")
    ap.add_argument("--rotation-lams", type=float, nargs="*", default=[LINEAR], help="lambda0 values of --rotation")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--p2-fine", action="store_true", help="--table: the reference also from " + P2_FINE)
    ap.add_argument("--rotation-cell", type=float, default=1.0, help="--table: cell size [mm] of the rotation ratio for "
                    "the 25 deg reference (default 1; 0: the finest run)")
    ap.add_argument("--rotation-source", choices=("conforming", "snapped"), default="conforming",
                    help="--table: the 25 deg reference's 25/0 ratio from the conforming meshes (default; the finest "
                    "h_cut) or from the snapped ones (--rotation-cell)")
    ap.add_argument("--plot", action="store_true", help="docs/img/cut_convergence.png")
    a = ap.parse_args()
    P2Problem.log_iterations = a.newton_log
    for c in a.springs:
        t0 = time.process_time()
        name = f"cut_convergence_{_tag(a.model)}_cell{c:.3g}mm.json"
        subset = a.lams is not None or a.angles is not None
        res = springs_cell(c * 1e-3, lams=tuple(a.lams or LAMS), angles=tuple(a.angles or (0.0, 25.0)), model=a.model)
        res["cell"] = c
        res["cpu_seconds_total"] = time.process_time() - t0
        old = _load(name) if subset else None
        if old is not None:  # a subset of the cases: merged into the rows already there (a case given again is replaced)
            new = {(r["angle"], round(r["pre_stretch"], 9)) for r in res["rows"]}
            res["rows"] = [r for r in old["rows"] if (r["angle"], round(r["pre_stretch"], 9)) not in new] + res["rows"]
            res["rows"].sort(key=lambda r: (r["angle"], r["pre_stretch"]))
            res["cpu_seconds_total"] = None  # of several runs
        _write(name, res)
    if a.p2:  # merged into the rows already there, after each lambda0 (a level and lambda0 given again is replaced)
        P2Problem.frozen_tangent = not a.full_newton
        p2_reference(a.p2, lams=tuple(a.p2_lams or LAMS), q=a.q, on_row=lambda out: _merge_p2(out, a.p2_out), grading=a.grading)
    if a.rotation:
        old = _load("cut_convergence_rotation.json") or []
        for c in a.rotation:
            res = rotation(c * 1e-3, lams=tuple(a.rotation_lams))
            res["cell"] = c * 1e-3
            old = [r for r in old if abs(r["cell"] - c * 1e-3) > 1e-12] + [res]
        _write("cut_convergence_rotation.json", sorted(old, key=lambda r: -r["cell"]))
    if a.table:
        ROTATION_CELL = a.rotation_cell * 1e-3 if a.rotation_cell > 0 else None
        ROTATION_SOURCE = a.rotation_source
        P2_FILES = P2_FILES + ((P2_FINE,) if a.p2_fine else ())
        print(f"P2 reference from {', '.join(P2_FILES)}; 25 deg by {rotation_label()}\n")
        table()
        markdown()
    if a.plot:
        plot()
