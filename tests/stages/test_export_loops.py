"""Export: a loop whose seam came out as two overlapping tails is closed (``export.loops``)."""

from __future__ import annotations

import numpy as np

from test_export import CFG, _cfg, _piece
from test_export import _run_pieces as _run


def _ring(start_deg: float, end_deg: float, r: float = 12.0, c=(24.0, 24.0), wobble: float = 0.0) -> np.ndarray:
    t = np.radians(np.linspace(start_deg, end_deg, 120))
    rad = r + wobble * np.linspace(-1, 1, len(t))                    # the tails pass each other
    return np.stack([c[0] + rad * np.cos(t), c[1] + rad * np.sin(t)], 1)


def _free_ends(curves) -> int:
    n = 0
    for c in curves:
        p = np.asarray(c["points"])
        n += 0 if np.hypot(*(p[0] - p[-1])) <= 1e-6 else 2
    return n


def test_a_loop_cut_at_a_synthetic_end_with_crossing_tails_is_closed():
    # An eye drawn as one closed stroke, cut at a synthetic vertex; the flow pushed the ends 25° past
    # each other (a tick on a smooth stretch, two free ends): one closed curve, no tails left.
    seam = _piece(1, _ring(-10, 375, wobble=0.8), [0, 0], [-1, -1])
    out = _run([seam], CFG)
    assert len(out) == 1 and _free_ends(out) == 0
    pts = np.asarray(out[0]["points"])
    ang = np.degrees(np.arctan2(pts[:, 1] - 24, pts[:, 0] - 24)) % 360
    assert np.ptp(np.unwrap(np.radians(ang))) < np.radians(362)     # the overlap is cut, not kept
    assert _free_ends(_run([seam], _cfg(loops=dict(CFG["loops"], enabled=False)))) == 2


def test_ends_at_keypoints_and_open_hooks_are_left():
    # An "o" whose pen start and end overlap at endpoint keypoints: the drawing says "end" there.
    drawn = _piece(1, _ring(-10, 375, wobble=0.8), [1, 1], [0, 1])
    assert _free_ends(_run([drawn], CFG)) == 2
    # A "c" open by more than the meeting radius: no seam.
    hook = _piece(1, _ring(30, 330), [0, 0], [-1, -1])
    assert _free_ends(_run([hook], CFG)) == 2
