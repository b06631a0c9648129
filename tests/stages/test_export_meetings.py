"""Export: curves whose ends meet alone are joined (``export.meetings``)."""

from __future__ import annotations

import numpy as np

from stages import export
from test_export import CFG, _cfg, _crossings_between_curves, _inputs, _line, _piece
from test_export import _run_pieces as _run


def _stroke_turning_at_junction_keypoints():
    # One stroke (0,0) -> (40,40) -> (40,0) -> (0,41.3) whose two sharp turns the detector called
    # junctions (type 3) with no third branch there: the first and last legs cross near (20,20).
    a = _piece(1, _line([0, 0], [40, 40]), [1, 3], [0, 1])
    b = _piece(2, _line([40, 0], [40, 40]), [3, 3], [2, 1])          # runs backwards
    c = _piece(3, _line([40, 0], [0, 41.3]), [3, 1], [2, 3])
    return [a, b, c]


def test_ends_that_meet_alone_at_junction_keypoints_make_one_curve_crossing_only_itself():
    pieces = _stroke_turning_at_junction_keypoints()
    assert _crossings_between_curves(pieces) == 1                   # as selected: two curves cross
    out = _run(pieces, CFG)
    assert len(out) == 1 and sorted(out[0]["parts"]) == [100, 101, 102]
    pts = np.asarray(out[0]["points"])
    assert np.hypot(*np.diff(pts, axis=0).T).max() <= 0.6            # continuous, no jump at a joint
    assert _crossings_between_curves(out) == 0
    assert len(_run(pieces, _cfg(meetings={"enabled": False}))) == 3


def test_three_ends_a_passing_curve_or_a_closed_loop_are_left():
    tee = [_piece(1, _line([0, 20], [20, 20]), [1, 3], [0, 1]),
           _piece(2, _line([20, 20], [40, 20]), [3, 1], [1, 2]),
           _piece(3, _line([20, 20], [20, 40]), [3, 1], [1, 3])]
    assert len(_run(tee, CFG)) == len(_run(tee, _cfg(meetings={"enabled": False}))) == 2   # the bar joined, the stem left
    # two ends meeting on a third curve that passes there: a junction, not a continuation
    touch = [_piece(1, _line([0, 0], [20, 20]), [1, 3], [0, 1]),
             _piece(2, _line([20, 20], [40, 0]), [3, 1], [1, 2]),
             _piece(3, _line([0, 21], [40, 21]), [1, 1], [3, 4])]
    assert len(_run(touch, CFG)) == 3
    from stages.export.gaps import join_lone_meetings
    ring = np.array([[20 + 10 * np.cos(t), 20 + 10 * np.sin(t)] for t in np.linspace(0, 2 * np.pi, 64)])
    loop = _piece(1, ring, [3, 3], [1, 1])
    assert len(join_lone_meetings([loop])) == 1


def test_a_junction_the_user_added_keeps_its_curve_ends():
    # The same stroke, its first turn (keypoint 1) a junction the user added in the inspection page:
    # the artist's junction stays a meeting of curve ends; the other turn is still joined.
    pieces = _stroke_turning_at_junction_keypoints()
    inputs = _inputs([p["points"] for p in pieces], list(range(len(pieces))), shape=(48, 48))
    for p, c in zip(inputs["topology"].data["paths"], pieces):
        p["end_types"], p["end_keypoints"] = c["end_types"], c["end_keypoints"]
    inputs["topology"].data["edited_keypoints"] = [1]
    out = export.run(CFG, **inputs).data["curves"]
    assert len(out) == 2
    ends = [np.asarray(c["points"])[k] for c in out for k in (0, -1)]
    assert sum(np.hypot(x - 40, y - 40) < 1.0 for x, y in ends) == 2     # two ends at the added junction
