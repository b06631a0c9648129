"""The keypoint_edits stage: validation of the edits document and its application to detections."""

from __future__ import annotations

import numpy as np
import pytest

from stages.artifact import Artifact
from stages.errors import InputError
from stages.keypoint_edits import run, validate_edits


def _keypoints(h: int = 64, w: int = 80) -> Artifact:
    pts = np.array([[10.5, 10.5], [40.2, 30.7], [70.0, 50.0]], np.float32)
    return Artifact(arrays={"heatmaps": np.zeros((4, h, w), np.float32), "points": pts,
                            "types": np.array([1, 3, 5], np.int8), "scores": np.array([0.9, 0.8, 0.7], np.float32)},
                    data={"points": [], "height": h, "width": w})


CFG = {"match_radius": 3.0}


def test_no_edits_pass_the_detections_through():
    out = run(dict(CFG, edits=None), _keypoints())
    np.testing.assert_array_equal(out["points"], _keypoints()["points"])
    np.testing.assert_array_equal(out["types"], [1, 3, 5])
    assert out.data["edit_counts"] == {"added": 0, "removed": 0, "retyped": 0}
    assert "heatmaps" not in out.arrays  # the page reads the detector's heatmaps; they are not copied


def test_added_removed_retyped_are_applied_by_pixel_coordinates():
    edits = {"format": "polyvec-keypoint-edits", "version": 1, "width": 80, "height": 64,
             "added": [{"x": 20, "y": 5, "type": "junction"}, {"x": 60, "y": 60, "type": 5}],
             "removed": [{"x": 11.0, "y": 9.8}],
             "retyped": [{"x": 69.0, "y": 51.0, "type": "endpoint"}]}
    out = run(dict(CFG, edits=edits), _keypoints())
    np.testing.assert_allclose(out["points"], [[40.2, 30.7], [70.0, 50.0], [20, 5], [60, 60]], atol=1e-5)
    np.testing.assert_array_equal(out["types"], [3, 1, 3, 5])
    np.testing.assert_allclose(out["scores"], [0.8, 0.7, 1.0, 1.0])
    assert out.data["edit_counts"] == {"added": 2, "removed": 1, "retyped": 1}
    assert [p["edited"] for p in out.data["points"]] == ["", "retyped", "added", "added"]
    removed = [e for e in out.data["edits"] if e["op"] == "removed"]
    assert removed == [{"op": "removed", "x": 11.0, "y": 9.8, "type": 1, "keypoint": 0}]


@pytest.mark.parametrize("edits, message", [
    ([], "expected a JSON object"),
    ({"added": [{"x": 1, "y": 2, "type": "tee"}]}, "added[0]: type must be endpoint, junction or corner"),
    ({"added": [{"x": 1, "type": 3}]}, "added[0]: missing 'y'"),
    ({"added": [{"x": 1, "y": 2}]}, "added[0]: missing 'type'"),
    ({"removed": {"x": 1}}, "removed must be a list"),
    ({"moved": []}, "unknown field(s) moved"),
    ({"format": "svg"}, "format must be"),
    ({"width": -3}, "width must be a positive integer"),
])
def test_bad_documents_are_one_line_errors(edits, message):
    with pytest.raises(InputError, match=None) as info:
        validate_edits(edits)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_an_edit_that_matches_no_detection_is_an_error():
    with pytest.raises(InputError, match=r"removed\[0\] at \(30.0, 30.0\): no detected keypoint within 3 px"):
        run(dict(CFG, edits={"removed": [{"x": 30, "y": 30}]}), _keypoints())
    with pytest.raises(InputError, match="already removed"):
        run(dict(CFG, edits={"removed": [{"x": 10, "y": 10}], "retyped": [{"x": 10, "y": 11, "type": 3}]}),
            _keypoints())


def test_edits_for_another_image_size_are_refused():
    with pytest.raises(InputError, match="edits are for a 100×64 drawing, this one is 80×64"):
        run(dict(CFG, edits={"width": 100, "height": 64}), _keypoints())


def test_edits_in_drawing_pixels_land_on_a_supersampled_prep():
    """Thin strokes: prep works at 2x, the keypoints sit at 2x the drawing's pixels; edits do not."""
    kp = _keypoints(h=128, w=160)
    kp.data.update(scale=2, height=64, width=80)      # the drawing's size (prep's data)
    edits = {"format": "polyvec-keypoint-edits", "version": 1, "width": 80, "height": 64,
             "added": [{"x": 20, "y": 5, "type": "junction"}],
             "removed": [{"x": 5.9, "y": 5.0}],         # 10.5/2 = 5.25 (the radius is 3 drawing px)
             "retyped": [{"x": 35.0, "y": 25.0, "type": "endpoint"}]}
    out = run(dict(CFG, edits=edits), kp)
    np.testing.assert_allclose(out["points"], [[40.2, 30.7], [70.0, 50.0], [40, 10]], atol=1e-5)
    np.testing.assert_array_equal(out["types"], [3, 1, 3])
    with pytest.raises(InputError, match="160×128 drawing, this one is 80×64"):
        run(dict(CFG, edits=dict(edits, width=160, height=128)), kp)


def test_edits_in_drawing_pixels_land_on_a_downsampled_prep():
    """Wide strokes: prep works at 1/4 of an odd-sized drawing (ceil: 17 x 21 internal pixels)."""
    kp = _keypoints(h=17, w=21)
    kp.data.update(scale=0.25, height=66, width=83)
    kp.arrays["points"] = np.array([[2.5, 2.5], [10.0, 7.5], [17.5, 12.5]], np.float32)
    edits = {"format": "polyvec-keypoint-edits", "version": 1, "width": 83, "height": 66,
             "added": [{"x": 60, "y": 8, "type": "junction"}],
             "removed": [{"x": 12.0, "y": 8.0}],        # 2.5 x 4 = 10: within the 3-px radius
             "retyped": [{"x": 41.0, "y": 29.0, "type": "corner"}]}
    out = run(dict(CFG, edits=edits), kp)
    np.testing.assert_allclose(out["points"], [[10.0, 7.5], [17.5, 12.5], [15.0, 2.0]], atol=1e-5)
    np.testing.assert_array_equal(out["types"], [5, 5, 3])
    with pytest.raises(InputError, match="84×68 drawing, this one is 83×66"):
        run(dict(CFG, edits=dict(edits, width=84, height=68)), kp)


def test_edits_in_drawing_pixels_land_on_a_cropped_prep():
    """A drawing on a larger page: prep works on its ink's box from (100, 40) at 2x; edits are in the page's pixels."""
    kp = _keypoints(h=128, w=160)
    kp.data.update(scale=2, origin=[100, 40], height=300, width=400)
    edits = {"format": "polyvec-keypoint-edits", "version": 1, "width": 400, "height": 300,
             "added": [{"x": 120, "y": 45, "type": "junction"}],
             "removed": [{"x": 105.9, "y": 45.0}],
             "retyped": [{"x": 135.0, "y": 65.0, "type": "endpoint"}]}
    out = run(dict(CFG, edits=edits), kp)
    np.testing.assert_allclose(out["points"], [[40.2, 30.7], [70.0, 50.0], [40, 10]], atol=1e-5)
    np.testing.assert_array_equal(out["types"], [3, 1, 3])


def test_oracle_edits_swap_the_detected_keypoints_of_a_type_for_the_labels():
    """tests/benchmarks/oracle_keypoints.py: its edits, applied by the stage, leave exactly the labels."""
    from tests.benchmarks.oracle_keypoints import oracle_edits

    kp = _keypoints(80, 80)
    case = {"size": 80, "endpoints": [[5.0, 6.0]], "junctions": [[41.0, 31.0], [12.0, 60.0]], "corners": []}
    junctions = run(dict(CFG, edits=oracle_edits(case, kp["points"], kp["types"], "a.png", ["junction"])), kp)
    np.testing.assert_allclose(junctions["points"], [[10.5, 10.5], [70.0, 50.0], [41, 31], [12, 60]], atol=1e-5)
    np.testing.assert_array_equal(junctions["types"], [1, 5, 3, 3])
    every = run(dict(CFG, edits=oracle_edits(case, kp["points"], kp["types"], "a.png",
                                             ["endpoint", "junction", "corner"])), kp)
    np.testing.assert_allclose(every["points"], [[5, 6], [41, 31], [12, 60]], atol=1e-5)
    np.testing.assert_array_equal(every["types"], [1, 3, 3])
