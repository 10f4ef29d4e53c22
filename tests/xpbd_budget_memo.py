"""Test helper: within one test, an XPBD export repeated with the same inputs reuses the XPBD
runs of the first.

The refusal tests export the same document at the same saturated budget twice: once to see it
refused, once with ``approximate=True`` to see the miss written. Both calls run the same search
(the budget's factor, then smaller ``dt`` until one reaches 2 %), i.e. the same
:func:`difftissue.export.budget.xpbd_budget_reactions` runs, 60 of them, XPBD to rest each.
That function is deterministic (a function of the document's numbers, the boundary
conditions, the factor, ``dt``, ``tol`` and the frame limit), so the second call can take the
first one's answers: everything else of the exporter (the reference solves, the secant
search, the message, the notes) runs again. Nothing is shared between tests.
"""

from __future__ import annotations

import hashlib

import numpy as np

import difftissue.export.budget as _budget


def _feed(h, obj) -> None:
    """Feed ``obj`` (dicts, lists, tuples, arrays, scalars, None, str) into ``h`` by value."""
    if isinstance(obj, dict):
        h.update(b"{")
        for k in sorted(obj):
            h.update(repr(k).encode())
            _feed(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)) and not all(isinstance(v, (int, float, bool, np.number)) for v in obj):
        h.update(b"[")
        for v in obj:
            _feed(h, v)
        h.update(b"]")
    elif obj is None or isinstance(obj, str):
        h.update(repr(obj).encode())
    else:  # an array, a list of numbers or a number: shape, dtype and bytes
        a = np.ascontiguousarray(np.asarray(obj))
        h.update(f"{a.shape}{a.dtype.str}".encode())
        h.update(a.tobytes())


def remember_xpbd_budget_runs(monkeypatch) -> dict:
    """Replace ``difftissue.export.budget.xpbd_budget_reactions`` (what the exporter calls) for
    the rest of the test by a version that runs XPBD once per distinct input and returns the
    stored result (copied) for a repeated one. Returns the counts ``{"runs": ..., "reused": ...}``.
    A direct call of the function imported into a test module is not affected (it stays an
    independent run)."""
    real = _budget.xpbd_budget_reactions
    memo: dict = {}
    count = {"runs": 0, "reused": 0}

    def remembered(doc, fixed, prescribed, observe, fractions, **kw):
        h = hashlib.sha256()
        _feed(h, [{k: doc[k] for k in ("specimen", "per_tet", "setting")}, fixed, prescribed, observe,
                  [float(f) for f in fractions], kw])
        key = h.hexdigest()
        if key in memo:
            count["reused"] += 1
        else:
            count["runs"] += 1
            memo[key] = real(doc, fixed, prescribed, observe, fractions, **kw)
        reactions, rested = memo[key]
        return np.array(reactions, copy=True), rested

    monkeypatch.setattr(_budget, "xpbd_budget_reactions", remembered)
    return count
