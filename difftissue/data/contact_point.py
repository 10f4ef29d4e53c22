"""Contact-point detection on an indentation curve (:func:`find_contact`) and the shift of a
curve to its contact point (:func:`shift_to_contact`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import ContactPointError, DataError
from .curves import _slice_arrays, check_monotonic, ForceDepthCurve


# ============================================================================ contact
#: Contact-point methods of :func:`find_contact`.
CONTACT_METHODS = ("power_law", "ratio_of_variances", "instrument")


@dataclasses.dataclass(frozen=True)
class ContactPoint:
    """A contact point found by :func:`find_contact`.

    Attributes:
        method: the method used.
        depth: contact position in the curve's depth coordinate [m].
        force: baseline force at contact [N] (the fitted baseline for ``power_law``, the
            median of the 50 samples before contact for the other methods).
        index: first sample (in the approach) whose depth stays beyond ``depth``.
        exponent: fitted exponent ``p`` of the contact part (``power_law``), else ``None``.
        baseline_slope: slope of the linear baseline [N/m] (``power_law``; else 0).
        amplitude: ``c`` of ``c (z - z0)^p`` [N/m^p] (``power_law``), else ``None``.
        rms: root-mean-square residual of the fit [N] (``power_law``), else ``None``.
        interval: ``(lo, hi)`` [m], the contact depths whose residual sum of squares is
            within ``4 s^2`` of the best (``s^2`` = residual variance; a rough 2-sigma
            profile interval that assumes white noise), or ``None``.
    """

    method: str
    depth: float
    force: float
    index: int
    exponent: float | None = None
    baseline_slope: float = 0.0
    amplitude: float | None = None
    rms: float | None = None
    interval: tuple[float, float] | None = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _sse_grid(z, F, z0s, ps, sums):
    """Residual sum of squares of ``F ~ a + b z + c (z - z0)_+^p`` for every ``(z0, p)``.

    ``z, F`` are normalized samples; points with ``z <= min(z0s)`` are dropped by the caller
    from ``z, F`` (they only enter ``sums``: (n, Σz, Σz², ΣF, ΣzF, ΣF²) over all points).
    """
    n, Sz, Szz, SF, SzF, SFF = sums
    out = np.empty((len(z0s), len(ps)))
    U0 = np.clip(z[None, :] - z0s[:, None], 0.0, None)
    for j, p in enumerate(ps):
        G = U0**p
        Sg = G.sum(1)
        Szg = G @ z
        Sgg = np.einsum("ij,ij->i", G, G)
        SgF = G @ F
        A = np.empty((len(z0s), 3, 3))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = n, Sz, Sg
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2] = Sz, Szz, Szg
        A[:, 2, 0], A[:, 2, 1], A[:, 2, 2] = Sg, Szg, Sgg
        b = np.stack([np.full(len(z0s), SF), np.full(len(z0s), SzF), SgF], axis=1)
        A[:, 2, 2] += 1e-12 * (1.0 + Sgg)  # ridge: a candidate with no point beyond it
        x = np.linalg.solve(A, b[..., None])[..., 0]
        out[:, j] = SFF - np.einsum("ij,ij->i", x, b)
    return out


def _power_law_contact(z, F, *, exponent, exponent_range):
    n = len(z)
    zm, zs = float(z.mean()), float(np.ptp(z))
    Fm, Fs = float(F.mean()), float(np.ptp(F))
    zc, Fc = (z - zm) / zs, (F - Fm) / Fs
    sums = (n, zc.sum(), zc @ zc, Fc.sum(), zc @ Fc, Fc @ Fc)
    # Search window: from the smallest depth to where the force has made half its rise.
    k = max(5, n // 20)
    f0 = float(np.median(Fc[:k]))
    half = np.flatnonzero(Fc >= f0 + 0.5 * (Fc.max() - f0))
    hi = zc[half[0]] if half.size else zc.max()
    lo = zc.min()
    if exponent is not None:
        pgrid = np.array([float(exponent)])
    else:
        pgrid = np.linspace(exponent_range[0], exponent_range[1], 9)

    # The coarse stage runs on at most ~2000 evenly strided samples (sums rescaled); the
    # refinements use every sample beyond the smallest candidate (the contact region).
    stride = max(1, n // 2000)
    zc_s, Fc_s = zc[::stride], Fc[::stride]
    m = len(zc_s)
    sums_s = (m, zc_s.sum(), zc_s @ zc_s, Fc_s.sum(), zc_s @ Fc_s, Fc_s @ Fc_s)

    def stage(z0s, ps, coarse=False):
        if coarse:
            sel = zc_s > z0s.min()
            return _sse_grid(zc_s[sel], Fc_s[sel], z0s, ps, sums_s)
        sel = zc > z0s.min()
        return _sse_grid(zc[sel], Fc[sel], z0s, ps, sums)

    z0s = np.linspace(lo, hi, 120)
    s = stage(z0s, pgrid, coarse=True)
    i, j = np.unravel_index(np.argmin(s), s.shape)
    z0, p = z0s[i], pgrid[j]
    step = coarse_step = z0s[1] - z0s[0]
    dp = (pgrid[1] - pgrid[0]) if pgrid.size > 1 else 0.0
    for _ in range(3):
        z0s = np.linspace(max(lo, z0 - 2 * step), min(hi, z0 + 2 * step), 41)
        ps = pgrid if exponent is not None else np.unique(np.clip(np.linspace(p - dp, p + dp, 9), *exponent_range))
        s = stage(z0s, ps)
        i, j = np.unravel_index(np.argmin(s), s.shape)
        z0, p = z0s[i], ps[j]
        step, dp = z0s[1] - z0s[0], dp / 4
    smin = float(s.min())
    # Residuals at the optimum; their lag-1 autocorrelation rho inflates the variance of
    # the sum of squares by (1 + rho) / (1 - rho) (AR(1) noise) for the interval below.
    g = np.clip(zc - z0, 0.0, None) ** p
    A = np.stack([np.ones(n), zc, g], axis=1)
    coef, *_ = np.linalg.lstsq(A, Fc, rcond=None)
    res = Fc - A @ coef
    rho = float(np.clip((res[1:] @ res[:-1]) / max(res @ res, 1e-300), 0.0, 0.99))
    var = smin / max(n - 4, 1) * (1.0 + rho) / (1.0 - rho)
    # Profile of the sum of squares over z0 (minimised over p) for the interval.
    span = 2 * coarse_step
    z0s = np.linspace(max(lo, z0 - span), min(hi, z0 + span), 161)
    ps = pgrid if exponent is not None else np.unique(np.clip(np.linspace(p - 0.5, p + 0.5, 21), *exponent_range))
    prof = stage(z0s, ps).min(axis=1)
    ok = z0s[prof <= smin + 4.0 * var]
    interval = (float(ok.min()) * zs + zm, float(ok.max()) * zs + zm) if ok.size else None
    rms = float(np.sqrt(np.mean((A @ coef - Fc) ** 2))) * Fs
    z0_si = float(z0) * zs + zm
    slope = float(coef[1]) * Fs / zs
    force0 = Fm + Fs * (float(coef[0]) + float(coef[1]) * float(z0))
    amplitude = float(coef[2] * Fs / zs**p)
    return z0_si, force0, float(p), slope, amplitude, rms, interval


def _ratio_of_variances(F, window):
    n = len(F)
    N = int(window) if window is not None else max(10, n // 50)
    if n < 2 * N + 2:
        raise ContactPointError(f"the approach has {n} samples, too few for a ratio-of-variances window of {N}")
    c1 = np.concatenate([[0.0], np.cumsum(F)])
    c2 = np.concatenate([[0.0], np.cumsum(F * F)])
    i = np.arange(N, n - N)
    mb = (c1[i] - c1[i - N]) / N
    vb = (c2[i] - c2[i - N]) / N - mb**2
    ma = (c1[i + 1 + N] - c1[i + 1]) / N
    va = (c2[i + 1 + N] - c2[i + 1]) / N - ma**2
    rov = va / np.maximum(vb, 1e-300)
    return int(i[np.argmax(rov)])


def find_contact(
    curve: ForceDepthCurve,
    *,
    method: str = "power_law",
    exponent: float | None = None,
    exponent_range: tuple[float, float] = (1.0, 3.0),
    window: int | None = None,
) -> ContactPoint:
    """Find the contact point of an indentation curve, on its approach segment.

    Methods:

    - ``"power_law"`` (default): least-squares fit of
      ``F(z) = a + b z + c (z - z0)_+^p`` (a linear baseline, to absorb offset and drift,
      plus a power law after contact) over the whole approach. For each ``(z0, p)`` the
      model is linear in ``(a, b, c)``, so the fit is an exact grid search on ``z0`` and
      ``p`` (coarse, then refined twice), no starting guess, no local minima. ``p`` is
      free in ``exponent_range`` (a sphere gives 1.5, a cone 2, a flat punch 1) unless
      ``exponent`` fixes it. It uses every sample, so it is robust to noise, and locates
      the contact where the force starts to rise *in the shape* of the loading curve.
    - ``"ratio_of_variances"`` (Gavara 2016, Sci. Rep. 6:21267): the sample that maximises
      var(next ``window`` forces) / var(previous ``window`` forces). No model, but
      sensitive to the window and to correlated noise; given for comparison.
    - ``"instrument"``: the instrument's own contact (``metadata["instrument"]
      ["contact_depth"]``, from :func:`load_chiaro` with ``depth="raw"``).

    Raises:
        ContactPointError: too few samples, or no force rise above the baseline noise.
    """
    if method not in CONTACT_METHODS:
        raise ContactPointError(f"unknown contact method {method!r}; choose one of {CONTACT_METHODS}")
    seg = curve.approach()
    z, F = seg.depth, seg.force
    n = len(z)
    if n < 20:
        raise ContactPointError(f"the approach segment has {n} samples; at least 20 are needed to find a contact point")
    if method == "instrument":
        inst = curve.metadata.get("instrument", {})
        if "contact_depth" not in inst:
            raise ContactPointError("the curve has no instrument contact point (metadata['instrument']['contact_depth'])")
        z0 = float(inst["contact_depth"])
        idx = _first_beyond(z, z0)
        return ContactPoint("instrument", z0, _force_before(F, idx), idx)
    k = max(5, n // 10)
    noise = 1.4826 * float(np.median(np.abs(np.diff(F[: max(k, 10)]) - np.median(np.diff(F[: max(k, 10)]))))) / math.sqrt(2)
    rise = float(np.max(F[-k:])) - float(np.median(F[:k]))
    if not rise > 10 * noise or np.ptp(z) <= 0:
        raise ContactPointError(
            f"the force rises by {rise:.3g} N over the approach, not clearly above the baseline noise ({noise:.3g} N): "
            f"the curve may not reach contact"
        )
    if method == "ratio_of_variances":
        i = _ratio_of_variances(F, window)
        return ContactPoint("ratio_of_variances", float(z[i]), _force_before(F, i + 1), _first_beyond(z, float(z[i])))
    lo, hi = exponent_range
    if not 0 < lo < hi:
        raise ContactPointError(f"exponent_range must be 0 < lo < hi, got {exponent_range}")
    z0, f0, p, slope, amp, rms, interval = _power_law_contact(z, F, exponent=exponent, exponent_range=(float(lo), float(hi)))
    return ContactPoint("power_law", z0, f0, _first_beyond(z, z0), p, slope, amp, rms, interval)


def _force_before(F, idx: int, n: int = 50) -> float:
    """Median force of the (up to) ``n`` samples before ``idx``: the baseline at contact."""
    seg = np.asarray(F)[max(idx - n, 0) : max(idx, 1)]
    return float(np.median(seg))


def _first_beyond(z, z0) -> int:
    """First index after which ``z`` stays above ``z0``."""
    below = np.flatnonzero(np.asarray(z) <= z0)
    return int(below[-1]) + 1 if below.size else 0


def shift_to_contact(
    curve: ForceDepthCurve,
    contact: ContactPoint | None = None,
    *,
    method: str = "power_law",
    exponent: float | None = None,
    baseline: str = "tilt",
    keep_precontact: bool = False,
    monotonic: bool = False,
    monotonic_tolerance: float = 0.0,
) -> ForceDepthCurve:
    """The approach segment measured from the contact point.

    ``depth - contact.depth`` and ``force - baseline(depth)``, where the baseline is the
    fitted line (``baseline="tilt"``, default: removes offset and drift), the force at
    contact only (``"offset"``), or nothing (``"none"``). Samples before
    ``contact.index`` are dropped unless ``keep_precontact``. ``contact`` defaults to
    :func:`find_contact` with ``method`` and ``exponent``. With ``monotonic``, the result
    must not step back by more than ``monotonic_tolerance`` [m]
    (:class:`~difftissue.errors.NonMonotonicError`).
    """
    if baseline not in ("tilt", "offset", "none"):
        raise DataError(f"baseline must be 'tilt', 'offset' or 'none', got {baseline!r}")
    if contact is None:
        contact = find_contact(curve, method=method, exponent=exponent)
    seg = curve.approach()
    depth = seg.depth - contact.depth
    if baseline == "tilt":
        force = seg.force - (contact.force + contact.baseline_slope * depth)
    elif baseline == "offset":
        force = seg.force - contact.force
    else:
        force = seg.force
    start = 0 if keep_precontact else contact.index
    lines = seg.metadata.get("data_lines")
    meta = {
        **seg.metadata,
        "contact": contact.to_dict(),
        "baseline": baseline,
        "segment": "approach from contact" if not keep_precontact else "approach",
    }
    if lines is not None:
        meta["data_lines"] = np.asarray(lines)[: len(seg)][start:]
    out = ForceDepthCurve(
        depth[start:],
        force[start:],
        None if seg.time is None else seg.time[start:],
        channels=_slice_arrays(seg.channels, slice(start, None)),
        metadata=meta,
    )
    if monotonic:
        check_monotonic(out.depth, tolerance=monotonic_tolerance, what="depth", unit="m", lines=meta.get("data_lines"))
    return out
