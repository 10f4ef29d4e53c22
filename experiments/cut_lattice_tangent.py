"""The homogenised cell at the pre-stretched state: why the lattices open a cut less than the
neo-Hookean, and the tangent-matched lattice's class factors (docs/dev/cut-openings-finite-strain.md,
sections 1 and 5).

Modes (dermis E = 200 kPa, nu = 0.45, 1 mm cubes; plane stress: the thickness stretch free):

tangent      fem_neo_hookean, springs_volume, springs_volume_mesh_lattice at each lambda0: tension
             P_xx, thickness stretch, first-Piola tangent A = d2psi/dF2 about the mesh state
             (in-plane moduli condensed over F_zz, transverse shear), the strain a cut face
             releases, and the orthotropic crack-opening factor T sqrt(...) of the incremental
             moduli.
attribution  that crack factor with one quantity of a lattice swapped for the neo-Hookean's
             (the tangent numbers of the page's table, kPa).
match        the class factors (in-plane edges, out-of-plane edges, in-plane face diagonals,
             out-of-plane face diagonals[, volume term]) of the mesh lattice that make the cell
             carry the neo-Hookean's (P_xx, A_xxxx, A_xxyy, A_xyxy[, A_xzxz]) at lambda0:
             --classes 4 (fsolve, volume term unchanged) or 5 (least squares, the design option).
path         the same 5-factor match by Newton continuation in lambda0 from --lams[0] down to
             --lams[-1] (the cell written with the library's own kernels, jit-compiled once),
             with the condition number of the match, the factors' linear extrapolation to
             lambda0 = 1 and that limit lattice's linear moduli against the neo-Hookean's.
design       the tension-exact match that tends to the default lattice (section 7): four spring-class
             factors and the lattice's own pre-stretch s (rest state the cube shrunk by 1/s) matching
             the neo-Hookean's (P_xx, A_xxxx, A_xxyy, A_xyxy, A_xzxz) exactly, by Newton
             continuation from lambda0 = 1 (where the default lattice solves it); --scan adds the
             member nearest the default lattice over a volume-term factor.
screen       the 5-factor lattice on the 1 mm / 0.5 mm staircase cut (0 deg), FACTORS given on
             the command line: the screen run before the library had the option (a
             SpringVolumeModel subclass patched into Incision); `--factors 1 1 1 1 1` must give
             springs_volume_mesh_lattice's width; --lattice-stretch s for a design row.

Run:  python experiments/cut_lattice_tangent.py tangent --lams 1.05 1.10 1.15
      python experiments/cut_lattice_tangent.py match --classes 5 --lams 1.15
      python experiments/cut_lattice_tangent.py path --lams 1.15 1.0025 --step 0.0025
      python experiments/cut_lattice_tangent.py screen --cell 1 --lam 1.15 --factors 0.393 1.6536 0.8749 0.9743 0.4605
      python experiments/cut_lattice_tangent.py design --lams 1.0025 1.005 1.02 1.05 1.10 1.15 --scan
      python experiments/cut_lattice_tangent.py screen --cell 0.5 --lam 1.15 --factors 0.39958 1.64911 0.91091 1.01403 1 --lattice-stretch 1.133663
Uses difftissue.constitutive's private one-cell helpers (_unit_cell, _energy_density): the
model's own energy on one cell, nothing of its formulas repeated.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
E_DERMIS, NU = 2e5, 0.45
KINDS = ("fem_neo_hookean", "springs_volume", "springs_volume_mesh_lattice")


def _jax():
    import jax

    jax.config.update("jax_enable_x64", True)
    return jax


def _skin():
    from difftissue.materials import Material

    return Material(E_DERMIS, NU)


def classes(model, X):
    """``(S, 4)`` indicator of each spring's class (in-plane edge, out-of-plane edge, in-plane
    face diagonal, out-of-plane face diagonal) from its direction in the mesh ``X``."""
    d = X[model.springs[:, 1]] - X[model.springs[:, 0]]
    nz = np.abs(d) > 1e-12 * np.abs(d).max()
    edge, inpl = nz.sum(1) == 1, ~nz[:, 2]
    return np.stack([edge & inpl, edge & ~inpl, ~edge & inpl, ~edge & ~inpl], 1).astype(float)


def density(kind, lam):
    """``psi(c, F)`` [Pa] of the cell of ``kind`` pre-stretched by ``lam``, with class factors
    ``c`` (4 or 5 entries; ignored for the continuum) on a springs model."""
    _jax()
    import equinox as eqx
    import jax.numpy as jnp
    import jax.numpy as jnp

    from difftissue.constitutive import _cell_shape, _checked, _energy_density, _unit_cell
    from difftissue.materials import lame_parameters

    skin = _skin()
    shape = _cell_shape(kind, (1e-3,) * 3 if kind.startswith("springs") else None)
    mat = _checked(kind, shape, skin.replace(pre_stretch=lam))
    if not kind.startswith("springs"):
        return lambda c, F: _energy_density(kind, shape, mat, F)
    model, X, V = _unit_cell(kind, shape)
    C = classes(model, X)
    lm, mu = (float(v) for v in lame_parameters(E_DERMIS, NU))

    def psi(c, F):
        m = eqx.tree_at(lambda m: m.spring_factors, model, jnp.asarray(model.spring_factors) * (C @ c[:4]))
        e = m.energy(jnp.asarray(X) @ F.T, mat) / V
        if len(c) > 4:  # the cell volume term 0.5 (lam - mu) (det F - lam0^-2)^2 lam0^2 per mesh volume, scaled by c[4]
            e = e + (c[4] - 1.0) * 0.5 * (lm - mu) * (jnp.linalg.det(F) - lam**-2) ** 2 * lam**2
        return e

    return psi


def state(psi, c, lo=0.3, hi=3.0):
    """Plane-stress state at the mesh: ``(moduli (P_xx, K_xxxx, K_xxyy, K_xyxy, A_xzxz) [Pa],
    thickness stretch, full tangent A (9, 9) [Pa], P (3, 3) [Pa])``; K condensed over F_zz."""
    jax = _jax()
    import jax.numpy as jnp
    from scipy.optimize import brentq

    dz = jax.jit(lambda z: jax.grad(psi, 1)(c, jnp.diag(jnp.stack([1.0, 1.0, z])))[2, 2])
    lz = brentq(lambda z: float(dz(z)), lo, hi)
    F0 = jnp.diag(jnp.array([1.0, 1.0, lz]))
    P = np.asarray(jax.grad(psi, 1)(c, F0))
    A = np.asarray(jax.hessian(psi, 1)(c, F0)).reshape(9, 9)  # index 3 i + j: F_ij
    ip = [0, 1, 3, 4]
    K = A[np.ix_(ip, ip)] - np.outer(A[ip, 8], A[8, ip]) / A[8, 8]
    return np.array([P[0, 0], K[0, 0], K[0, 3], K[1, 1], A[2, 2]]), lz, A, P


def crack_factor(T, a, b, g, a22=None):
    """``T sqrt(a11 a22 / 2 (sqrt(a22 / a11) + (2 a12 + a66) / (2 a11)))``: the orthotropic
    plane-stress crack-opening compliance of the incremental moduli times the tension."""
    S = np.linalg.inv([[a, b], [b, a if a22 is None else a22]])
    a11, a22_, a12, a66 = S[0, 0], S[1, 1], S[0, 1], 1.0 / g
    return T * np.sqrt(a11 * a22_ / 2 * (np.sqrt(a22_ / a11) + (2 * a12 + a66) / (2 * a11)))


def tangent(lams):
    jax = _jax()
    import jax.numpy as jnp
    from scipy.optimize import brentq

    out = {}
    for lam in lams:
        print(f"\nlambda0 = {lam}")
        for kind in KINDS:
            psi = density(kind, lam)
            c = jnp.ones(4)
            m, lz, A, P = state(psi, c, 0.5, 1.5)
            dy = jax.jit(lambda sy, z: jax.grad(psi, 1)(c, jnp.diag(jnp.stack([1.0, sy, z]))))

            def Ty(sy):
                z = brentq(lambda z: float(dy(sy, z)[2, 2]), 0.5, 1.6)
                return float(dy(sy, z)[1, 1])

            s_star = brentq(Ty, 0.6, 1.0)  # y unloaded to zero traction, x held at the mesh
            ss = np.linspace(s_star, 1.0, 41)
            W = np.trapezoid([Ty(s) for s in ss], ss)
            r = dict(T=m[0], Axx=m[1], Axy=m[2], G=m[3], Axz=A[2, 2], Azx=A[6, 6], relax=1 - s_star, W=W, crack=crack_factor(*m[:4]))
            out[(lam, kind)] = r
            nh = out[(lam, KINDS[0])]
            rel = lambda k: f"{r[k]/1e3:9.2f} ({100*(r[k]/nh[k]-1):+5.1f}%)"  # noqa: E731
            print(f" {kind:28s} P_xx={rel('T')} lz={lz:.4f} A_xxxx={rel('Axx')} A_xxyy={rel('Axy')} A_xyxy={rel('G')} "
                  f"A_xzxz={rel('Axz')} A_zxzx={rel('Azx')} relax={r['relax']:.4f} W={rel('W')} "
                  f"crack={r['crack']:.4f} ({100*(r['crack']/nh['crack']-1):+.1f}%)", flush=True)
    return out


# (T, A_xxxx, A_xxyy, A_xyxy) [kPa] of the page's table (output of `tangent`)
TABLE = {
    1.05: {"nh": (15.76, 211.66, 89.49, 68.97), "sv": (15.30, 214.72, 69.80, 73.70), "ml": (16.27, 221.29, 80.69, 73.44)},
    1.10: {"nh": (27.59, 181.59, 71.25, 68.97), "sv": (25.98, 192.65, 37.55, 78.50), "ml": (29.30, 199.85, 54.55, 77.54)},
    1.15: {"nh": (36.54, 158.38, 56.98, 68.97), "sv": (33.57, 182.94, 15.80, 83.35), "ml": (39.86, 185.39, 34.00, 81.34)},
}


def attribution():
    names = ("T", "A_xxxx", "A_xxyy", "A_xyxy")
    for lam, d in TABLE.items():
        nh = crack_factor(*d["nh"])
        for k in ("sv", "ml"):
            base = crack_factor(*d[k])
            out = [f"{lam} {k}: {100*(base/nh-1):+.1f}%"]
            for i, n in enumerate(names):
                v = list(d[k])
                v[i] = d["nh"][i]
                out.append(f"{n}->NH {100*(crack_factor(*v)/nh-1):+.1f}%")
            print("  ".join(out))


def match(lams, n_classes=5, start=None):
    """Class factors matching the neo-Hookean's (P_xx, K_xxxx, K_xxyy, K_xyxy[, A_xzxz]) at each lambda0."""
    import jax.numpy as jnp
    from scipy.optimize import fsolve, least_squares

    rows = []
    for lam in lams:
        nh, lz_nh, A_nh, _ = state(density("fem_neo_hookean", lam), jnp.ones(n_classes))
        psi = density("springs_volume_mesh_lattice", lam)
        ml, lz_ml, _, _ = state(psi, jnp.ones(n_classes))
        target = nh[:n_classes]

        def resid(c):
            try:
                return state(psi, jnp.asarray(c))[0][:n_classes] / target - 1.0
            except ValueError:  # no thickness stretch in the bracket
                return np.full(n_classes, 10.0)

        x0 = np.ones(n_classes) if start is None else np.asarray(start, dtype=float)
        if n_classes == 4:
            sol = fsolve(resid, x0, xtol=1e-10)
            info = f"residual {np.round(resid(sol), 6)}"
        else:
            r = least_squares(resid, x0, bounds=(0.05, 4.0), xtol=1e-12, ftol=1e-12)
            sol, info = r.x, f"status {r.status}, cost {r.cost:.2e}, residual {np.round(r.fun, 6)}"
        got, lz, A, _ = state(psi, jnp.asarray(sol))
        print(f"lambda0={lam}: NH (T, A_xxxx, A_xxyy, A_xyxy, A_xzxz) kPa = {np.round(nh/1e3, 2)}, lz={lz_nh:.4f}; "
              f"mesh lattice {np.round(ml/1e3, 2)} lz={lz_ml:.4f}")
        print(f"  class factors {np.round(sol, 4)}  {info}")
        print(f"  matched {np.round(got/1e3, 3)} lz={lz:.4f}; A_xzxz {A[2,2]/1e3:.2f} (NH {A_nh[2,2]/1e3:.2f}), "
              f"A_zxzx {A[6,6]/1e3:.2f} (NH {A_nh[6,6]/1e3:.2f})", flush=True)
        rows.append(dict(pre_stretch=lam, factors=sol.tolist(), thickness_stretch=lz, thickness_stretch_nh=lz_nh))
    return rows


def _cell_kernels():
    """``(psi_lat, psi_nh, moduli, mu)`` of the one-cube cell (1 mm, the dermis):
    ``psi_lat(c, F, l0)`` the mesh lattice's energy density [Pa] with class factors ``c`` (four
    spring classes and the volume term) and its rest state the cube shrunk by ``1/l0`` in x and
    y; ``psi_nh(F, l0)`` the neo-Hookean's at pre-stretch ``l0``; ``moduli(dens, lz)`` the
    out-of-plane stress ``P_zz`` and ``(P_xx, K_xxxx, K_xxyy, K_xyxy, A_xzxz)`` [Pa] at
    ``F = diag(1, 1, lz)`` (K condensed over F_zz). Through the library's kernels
    (``cubic_spring_energy``, ``_cell_volume_energy``, ``neo_hookean_energy_density``)."""
    jax = _jax()
    import jax.numpy as jnp

    from difftissue.energies.fem import neo_hookean_energy_density
    from difftissue.energies.springs import cubic_spring_energy
    from difftissue.materials import lame_parameters
    from difftissue.mesh import _CUBE_CORNERS, _CUBE_DIAGONALS, _CUBE_EDGES
    from difftissue.models import _cell_spring_factors, _cell_volume_energy

    lm, mu = (float(v) for v in lame_parameters(E_DERMIS, NU))
    X = _CUBE_CORNERS.astype(float)
    pairs = np.array(list(_CUBE_EDGES) + list(_CUBE_DIAGONALS))
    g = _cell_spring_factors(np.ones((1, 3)))[0]
    d = X[pairs[:, 1]] - X[pairs[:, 0]]
    nz = np.abs(d) > 1e-12
    edge, inpl = nz.sum(1) == 1, ~nz[:, 2]
    CL = np.stack([edge & inpl, edge & ~inpl, ~edge & inpl, ~edge & ~inpl], 1).astype(float)

    def psi_lat(c, F, l0):
        x = jnp.asarray(X) @ F.T
        L0 = jnp.linalg.norm(jnp.asarray(d) * jnp.stack([1 / l0, 1 / l0, 1.0]), axis=1)
        k = mu * jnp.asarray(g) * (jnp.asarray(CL) @ c[:4])
        e = jnp.sum(jax.vmap(cubic_spring_energy)(x[pairs[:, 0]], x[pairs[:, 1]], L0, k, 0.0 * k))
        return e + _cell_volume_energy(x, 1.0 / l0**2, c[4] * (lm - mu))

    def psi_nh(F, l0):
        return neo_hookean_energy_density(F @ jnp.diag(jnp.stack([l0, l0, 1.0])), lm, mu) / l0**2

    def moduli(dens, lz):
        F0 = jnp.diag(jnp.stack([1.0, 1.0, lz]))
        P, A = jax.grad(dens)(F0), jax.hessian(dens)(F0).reshape(9, 9)
        ip = jnp.array([0, 1, 3, 4])
        K = A[jnp.ix_(ip, ip)] - jnp.outer(A[ip, 8], A[8, ip]) / A[8, 8]
        return P[2, 2], jnp.stack([P[0, 0], K[0, 0], K[0, 3], K[1, 1], A[2, 2]])

    return psi_lat, psi_nh, moduli, mu


def _nh_target(psi_nh, moduli, l0):
    """The neo-Hookean's thickness stretch at ``P_zz = 0`` (40 Newton steps from 1) and its
    tension and moduli there (``_cell_kernels``' ``moduli``) at pre-stretch ``l0``."""
    import jax
    import jax.numpy as jnp

    fz = lambda z: moduli(lambda F: psi_nh(F, l0), z)[0]  # noqa: E731
    # a loop, not 40 unrolled steps: traced and compiled once (the unrolled form took ~1 min to trace and compile)
    z = jax.lax.fori_loop(0, 40, lambda _, z: z - fz(z) / jax.grad(fz)(z), jnp.asarray(1.0))
    return z, moduli(lambda F: psi_nh(F, l0), z)[1]


def path(lam_hi, lam_lo, step, start=(0.393, 1.6536, 0.8749, 0.9743, 0.4605, 0.8281), match_thickness=False):
    """Newton continuation of the 5-factor match (unknowns: the factors and the thickness
    stretch; equations: P_zz = 0 and the five moduli) from ``lam_hi`` down to ``lam_lo``.

    The cell: the 24 springs of one 1 mm cube (factors ``_cell_spring_factors`` times the class
    factor, rest lengths of the cube shrunk by 1/lambda0 in x and y, cubic coefficient 0) and its
    volume term, through the library's kernels (``cubic_spring_energy``, ``_cell_volume_energy``);
    checked against ``constitutive``'s one-cell model at ``start`` (the page's 1.15 factors).

    ``match_thickness``: the thickness stretch is the neo-Hookean's (not an unknown), so six
    equations (P_zz = 0 there and the five moduli) on the five factors, solved by Gauss-Newton
    (least squares, unweighted, each residual / mu)."""
    jax = _jax()
    import jax.numpy as jnp

    psi_lat, psi_nh, moduli, mu = _cell_kernels()

    def resid(y, l0, target, zn):
        pzz, m = moduli(lambda F: psi_lat(y[:5], F, l0), zn if match_thickness else y[5])
        return jnp.concatenate([jnp.stack([pzz]), m - target]) / mu

    def solve(J, r):
        return jnp.linalg.lstsq(J, r)[0] if match_thickness else jnp.linalg.solve(J, r)

    @jax.jit
    def newton(y, l0):
        z, target = _nh_target(psi_nh, moduli, l0)

        def step(_, y):  # each change limited to 0.02: stays on the branch of the start
            return y - jnp.clip(solve(jax.jacfwd(resid)(y, l0, target, z), resid(y, l0, target, z)), -0.02, 0.02)

        y = jax.lax.fori_loop(0, 40, step, y)  # a loop, not 40 unrolled steps: traced and compiled once
        J = jax.jacfwd(resid)(y, l0, target, z)
        r = resid(y, l0, target, z)
        return y, r, z, jnp.linalg.cond(J)

    y = jnp.asarray(start if not match_thickness else start[:5], dtype=float)
    check = density("springs_volume_mesh_lattice", lam_hi)
    F = jnp.diag(jnp.array([1.01, 0.99, float(y[5])])) + 0.01 * jnp.eye(3)[::-1]
    ref = float(check(y[:5], F))
    assert abs(float(psi_lat(y[:5], F, lam_hi)) - ref) <= 1e-10 * abs(ref), "cell energy differs from the model's"
    rows = []
    for i, l0 in enumerate(np.round(np.arange(lam_hi, lam_lo - 1e-9, -step), 6)):
        for _ in range(4 if i == 0 else 1):  # the first point from a distant start: more limited steps
            y, r, zn, cond = newton(y, float(l0))
        lz = float(zn) if match_thickness else float(y[5])
        rows.append(dict(pre_stretch=float(l0), factors=np.asarray(y[:5]).tolist(), thickness_stretch=lz,
                         thickness_stretch_nh=float(zn), residual=np.asarray(r).tolist(), condition=float(cond)))
        print(f"lambda0={l0:.4f}: factors {np.round(np.asarray(y[:5]), 4)} lz={lz:.4f} (NH {float(zn):.4f}) "
              f"r/mu (P_zz, P_xx, K11, K12, K66, A_xzxz)={np.round(np.asarray(r), 5)} cond={float(cond):.2e}", flush=True)
    if len(rows) >= 2:
        (a, b) = rows[-2], rows[-1]
        lim = np.asarray(b["factors"]) + (np.asarray(b["factors"]) - np.asarray(a["factors"])) * (b["pre_stretch"] - 1.0) / (a["pre_stretch"] - b["pre_stretch"])
        print(f"linear extrapolation to lambda0 = 1: {np.round(lim, 4)}")
        An = np.asarray(jax.hessian(lambda F: psi_nh(F, 1.0))(jnp.eye(3))).reshape(9, 9)
        A = np.asarray(jax.hessian(lambda F: psi_lat(jnp.asarray(lim), F, 1.0))(jnp.eye(3))).reshape(9, 9)
        names = {"C11": (0, 0), "C33": (8, 8), "C12": (0, 4), "C13": (0, 8), "C66": (1, 1), "C44 (A_xzxz)": (2, 2)}
        print("its linear moduli [kPa] (neo-Hookean): " + ", ".join(f"{k} {A[i, j]/1e3:.2f} ({An[i, j]/1e3:.2f})" for k, (i, j) in names.items()))
        ip = [0, 1, 3, 4]
        cond = lambda M: M[np.ix_(ip, ip)] - np.outer(M[ip, 8], M[8, ip]) / M[8, 8]  # noqa: E731
        K, Kn = cond(A), cond(An)
        print(f"plane stress: K11 {K[0, 0]/1e3:.2f} ({Kn[0, 0]/1e3:.2f}), K12 {K[0, 3]/1e3:.2f} ({Kn[0, 3]/1e3:.2f})")
    return rows


def design(lams, step=0.005, scan=True):
    """The tension-exact tangent match with a sixth unknown: the lattice's own pre-stretch ``s``
    (its rest state the cube shrunk by ``1/s`` in x and y, the neo-Hookean's stays ``1/lambda0``).

    Unknowns ``(c_1..c_4, s, lz)`` (four spring-class factors, ``s``, the thickness stretch) at a
    given volume-term factor ``v``; equations: ``P_zz = 0`` and the neo-Hookean's ``(P_xx,
    K_xxxx, K_xxyy, K_xyxy, A_xzxz)`` at ``lambda0``. Square and regular at ``lambda0 = 1``
    (there ``dP_xx/dc = 0`` and ``dP_xx/ds = K_xxxx + K_xxyy``), so its solution tends to the
    default lattice, ``(c, s) -> (1, 1)``. Design S: ``v = 1``. Design M (``scan``): the member
    of the one-parameter family in ``v`` nearest the default lattice, min ``|(c, v) - 1|``
    (at ``lambda0 = 1`` the family is section 6's: out-of-plane edges against the volume term,
    whose nearest member is ``c = 1``). Newton continuation from ``lambda0 = 1`` (the default
    lattice is the exact solution there) up to ``max(lams)`` in steps ``step``; rows at ``lams``."""
    jax = _jax()
    import jax.numpy as jnp

    psi_lat, psi_nh, moduli, mu = _cell_kernels()

    def resid(y, l0, target, v):
        c = jnp.concatenate([y[:4], jnp.stack([v])])
        pzz, m = moduli(lambda F: psi_lat(c, F, y[4]), y[5])
        return jnp.concatenate([jnp.stack([pzz]), m - target]) / mu

    @jax.jit
    def newton(y, l0, v):
        z, target = _nh_target(psi_nh, moduli, l0)

        def step(_, y):  # each change limited to 0.02: stays on the branch of the start
            return y - jnp.clip(jnp.linalg.solve(jax.jacfwd(resid)(y, l0, target, v), resid(y, l0, target, v)), -0.02, 0.02)

        y = jax.lax.fori_loop(0, 30, step, y)  # a loop, not 30 unrolled steps: traced and compiled once
        J = jax.jacfwd(resid)(y, l0, target, v)
        return y, resid(y, l0, target, v), z, jnp.linalg.cond(J)

    def row(y, r, z, cond, l0, v, label):
        c = np.concatenate([np.asarray(y[:4]), [v]])
        d = dict(design=label, pre_stretch=float(l0), factors=c.tolist(), lattice_stretch=float(y[4]), thickness_stretch=float(y[5]),
                 thickness_stretch_nh=float(z), residual=np.asarray(r).tolist(), condition=float(cond), distance=float(np.linalg.norm(c - 1)))
        print(f"{label} lambda0={l0:.4f}: factors {np.round(c, 4)} s={d['lattice_stretch']:.5f} (s/lambda0-1={d['lattice_stretch']/l0-1:+.5f}) "
              f"lz={d['thickness_stretch']:.4f} (NH {float(z):.4f}) |c-1|={d['distance']:.4f} max|r|/mu={np.abs(np.asarray(r)).max():.1e} "
              f"cond={float(cond):.1e}", flush=True)
        return d

    y = jnp.ones(6)
    rows, top = [], max(lams)
    marks = {round(float(l), 6) for l in lams}
    for l0 in np.round(np.arange(1.0, top + 1e-9, step), 6):
        y, r, z, cond = newton(y, float(l0), 1.0)
        if round(float(l0), 6) not in marks:
            continue
        rows.append(row(y, r, z, cond, l0, 1.0, "S"))
        if not scan:
            continue
        dist = {}
        for sign in (-1, 1):  # continuation in v from the v = 1 solution
            yv = y
            for v in np.round(1.0 + sign * np.arange(0.0, 0.8 + 1e-9, 0.02), 6):
                if v <= 0.05:
                    break
                yv, rv, _, _ = newton(yv, float(l0), float(v))
                if np.abs(np.asarray(rv)).max() > 1e-9 or np.any(np.asarray(yv[:4]) <= 0):
                    break
                dist[float(v)] = (float(np.linalg.norm(np.concatenate([np.asarray(yv[:4]), [v]]) - 1)), yv)
        vs = np.array(sorted(dist))
        k = int(np.argmin([dist[v][0] for v in vs]))
        if 0 < k < len(vs) - 1:  # parabola through the three grid points around the minimum
            a, b, cc = vs[k - 1:k + 2]
            fa, fb, fc = (dist[v][0] ** 2 for v in (a, b, cc))
            vstar = b - 0.5 * ((b - a) ** 2 * (fb - fc) - (b - cc) ** 2 * (fb - fa)) / ((b - a) * (fb - fc) - (b - cc) * (fb - fa))
        else:
            vstar = vs[k]
        ym, rm, zm, cm = newton(dist[vs[k]][1], float(l0), float(vstar))
        rows.append(row(ym, rm, zm, cm, l0, float(vstar), "M"))
    return rows


def screen(cell, lam, factors, angle=0.0, lattice_stretch=None):
    """Max surface width [mm] of the mesh lattice with its dermis classes scaled by ``factors``
    (5: four spring classes and the volume term) on the staircase cut; ``lattice_stretch``: the
    dermis lattice's own pre-stretch ``s`` (rest lengths and rest volumes of the cube shrunk by
    ``1/s`` in x and y; None: ``lambda0``, design ``design``'s sixth unknown)."""
    _jax()
    import equinox as eqx
    import jax.numpy as jnp

    import difftissue.incision as inc_mod
    from difftissue.cutting import cut_specimen
    from difftissue.incision import Incision, IncisionOptions
    from difftissue.models import SpringVolumeModel

    sys.path.insert(0, str(HERE))
    from cut_staircase import path, specimen, surface_measures

    class Scaled(SpringVolumeModel):
        cell_bulk_factor: np.ndarray

        def __init__(self, mesh, c, region="dermis"):
            super().__init__(mesh, pre_stretch_lattice="mesh")
            r = list(mesh.region_names).index(region)
            p = np.asarray(mesh.points)
            d = p[self.springs[:, 1]] - p[self.springs[:, 0]]
            nz = np.abs(d) > 1e-12 * np.abs(d).max()
            edge, inpl = nz.sum(1) == 1, ~nz[:, 2]
            C = np.stack([edge & inpl, edge & ~inpl, ~edge & inpl, ~edge & ~inpl], 1).astype(float)
            self.spring_factors = self.spring_factors * np.where(self.spring_regions == r, C @ np.asarray(c[:4]), 1.0)
            self.cell_bulk_factor = np.where(self.cell_regions == r, c[4], 1.0)

        def spring_parameters(self, material):
            rest, k, a = super().spring_parameters(material)
            if lattice_stretch is None:
                return rest, k, a
            r = list(self.region_names).index("dermis")  # a = 0 (b = 0, checked below): no rest length in it
            own = self.rest_lengths * jnp.sqrt(1.0 + self.spring_in_plane * (lattice_stretch**-2 - 1.0))
            return jnp.where(jnp.asarray(self.spring_regions) == r, own, rest), k, a

        def cell_rest_volumes(self, material):
            v = super().cell_rest_volumes(material)
            if lattice_stretch is None:
                return v
            on = jnp.asarray(self.cell_regions) == list(self.region_names).index("dermis")
            return jnp.where(on, jnp.asarray(self.cell_volumes) / lattice_stretch**2, v)

        def terms(self, material):
            t = super().terms(material)
            return (t[0], eqx.tree_at(lambda e: e.params[1], t[1], t[1].params[1] * self.cell_bulk_factor))

    if lattice_stretch is not None and _skin().cubic_coefficient != 0.0:
        raise ValueError("--lattice-stretch: the screen's rest-length override assumes a cubic coefficient of 0")
    spec = specimen(cell * 1e-3)
    cut = cut_specimen(spec, path(angle), method="staircase")
    inc_mod.make_model = lambda mesh, kind: Scaled(mesh, factors)  # the screen's patch (no library option then)
    t0 = time.process_time()
    inc = Incision(cut, model="springs_volume_mesh_lattice", fitted_regions=("dermis",),
                   options=IncisionOptions(scalpel_steps=1, linear_solver="sparse"))
    res = inc.solve(_skin().replace(pre_stretch=lam))
    wmax, wmean = surface_measures(cut, res.opening.width)
    row = dict(cell_mm=cell, angle=angle, pre_stretch=lam, factors=list(factors), lattice_stretch=lattice_stretch, max_width_mm=wmax * 1e3,
               mean_width_mm=wmean * 1e3, cpu_seconds=time.process_time() - t0)
    print(json.dumps(row), flush=True)
    return row


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=("tangent", "attribution", "match", "path", "design", "screen"))
    ap.add_argument("--lams", type=float, nargs="*", default=[1.05, 1.10, 1.15], help="pre-stretches (tangent, match)")
    ap.add_argument("--classes", type=int, choices=(4, 5), default=5, help="match: 4 spring classes, or 4 + the volume term")
    ap.add_argument("--start", type=float, nargs="*", default=None, help="match: starting factors (default ones)")
    ap.add_argument("--match-thickness", action="store_true", help="path: the neo-Hookean's thickness stretch too "
                    "(six equations, least squares)")
    ap.add_argument("--scan", action="store_true", help="design: also the member nearest the default lattice over the "
                    "volume-term factor (design M)")
    ap.add_argument("--step", type=float, default=0.0025, help="path: continuation step in lambda0")
    ap.add_argument("--cell", type=float, default=1.0, help="screen: cell size [mm] (1, 0.5)")
    ap.add_argument("--lam", type=float, default=1.15, help="screen: pre-stretch")
    ap.add_argument("--angle", type=float, default=0.0, help="screen: cut angle [deg]")
    ap.add_argument("--lattice-stretch", type=float, default=None, help="screen: the dermis lattice's own pre-stretch s "
                    "(default lambda0)")
    ap.add_argument("--factors", type=float, nargs=5, default=[0.393, 1.6536, 0.8749, 0.9743, 0.4605], help="screen: class factors")
    a = ap.parse_args()
    if a.mode == "tangent":
        tangent(a.lams)
    elif a.mode == "attribution":
        attribution()
    elif a.mode == "match":
        match(a.lams, a.classes, a.start)
    elif a.mode == "design":
        design(a.lams, a.step, scan=a.scan)
    elif a.mode == "path":
        path(max(a.lams), min(a.lams), a.step, match_thickness=a.match_thickness)
    else:
        screen(a.cell, a.lam, a.factors, a.angle, a.lattice_stretch)
