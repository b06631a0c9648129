"""Tests of the keypoint stage: labelling rules, targets, loss, NMS, training, shipped model."""

from __future__ import annotations

import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image

from stages import synthetic
from stages.artifact import Artifact
from stages.errors import InputError
from stages.evaluate.keypoints import f1_authors, match_keypoints, read_pts
from stages.keypoints import PACKAGED_WEIGHTS, STAGE_VERSION, VIEWS, load_model, render_keypoints, run
from stages.keypoints.inference import (_tile_starts, dilate_band, find_keypoints, network_input, predict_heatmaps,
                                        predict_views)
from stages.keypoints.network import KeypointNet, NetConfig, fold_batch_norms
from stages.keypoints.training.generator import drawing_from_strokes, generate, render_strokes
from stages.keypoints.training.human_strokes import read_quickdraw_ndjson, read_svg_strokes
from stages.keypoints.training.labels import label_keypoints
from stages.keypoints.training.targets import asymmetric_l1, gaussian_heatmaps, keypoint_loss
from tests.conftest import train_configs

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT / ".." / "shared"
CONF = ROOT / "conf"
GENERATOR, RULES = train_configs()
TINY_NET = NetConfig(stem_mid=4, level_channels=(4, 8, 8, 8), bottleneck_blocks=1, negative_slope=0.1, class_width=0,
                     class_dilations=(1,))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _cfg() -> dict:
    return yaml.safe_load((CONF / "keypoints" / "default.yaml").read_text())


def _labels(drawing):
    return label_keypoints(drawing.strokes, [drawing.width] * len(drawing.strokes), RULES)


# --- labelling rules (metrics.md §4.2) ---------------------------------------------------------


def test_line_has_two_endpoints():
    pts, types = _labels(synthetic.line())
    assert sorted(types.tolist()) == [1, 1]
    s = synthetic.line().strokes[0]
    assert np.allclose(np.sort(pts[:, 0]), np.sort(s[:, 0]), atol=1e-6)


def test_cross_has_one_junction_and_four_ends():
    d = synthetic.cross()
    pts, types = _labels(d)
    assert (types == 3).sum() == 1 and (types == 1).sum() == 4
    assert np.allclose(pts[types == 3][0], [32, 32], atol=0.6)


def test_near_parallel_crossing_is_not_a_junction():
    pts, types = _labels(synthetic.cross(angle1=10, angle2=30, length=50))
    assert (types == 3).sum() == 0


def test_crossing_angle_of_the_labels_is_a_rule_of_its_own():
    """A 28° crossing: no junction by the reference's 37° (validation cases, realvec_dev), a junction by
    the acceptance scorer's 20°, which the shipped network was trained with (MODEL_CARD, phase 19g)."""
    d = synthetic.cross(angle1=10, angle2=38, length=60)
    _, reference = label_keypoints(d.strokes, [d.width] * 2, RULES)
    pts, scorer = label_keypoints(d.strokes, [d.width] * 2, replace(RULES, crossing_min_deg=20.0))
    assert RULES.crossing_min_deg == 37.0
    assert (reference == 3).sum() == 0
    assert (scorer == 3).sum() == 1 and np.allclose(pts[scorer == 3][0], [32, 32], atol=1.0)


def test_an_end_on_its_own_stroke_is_a_junction_only_by_the_reference_rule():
    """A hook whose end curls back onto its own stroke: a T by §4.2 (``own_stroke_tee``), a free end
    for the acceptance scorer (an end beside its own curve has valence 1)."""
    t = np.linspace(0, 1, 60)
    ang = np.linspace(0, 1.5 * np.pi, 60)
    hook = np.vstack([np.c_[10 + 60 * t, np.full_like(t, 40.0)], np.c_[70 + 12 * np.sin(ang), 28 + 12 * np.cos(ang)],
                      [[58.0, 40.0]]])
    assert RULES.own_stroke_tee
    _, ref = label_keypoints([hook], [3.0], RULES)
    pts, off = label_keypoints([hook], [3.0], replace(RULES, own_stroke_tee=False))
    assert sorted(ref.tolist()) == [1, 3] and sorted(off.tolist()) == [1, 1]
    assert np.allclose(sorted(pts[:, 0]), [10.0, 58.0], atol=0.5)


def test_vee_has_one_corner():
    d = synthetic.vee()
    pts, types = _labels(d)
    assert (types == 5).sum() == 1 and (types == 1).sum() == 2
    assert np.allclose(pts[types == 5][0], d.strokes[0][1], atol=1.0)


def test_gentle_bend_is_not_a_corner():
    pts, types = _labels(synthetic.vee(opening=150))  # turning 30°
    assert (types == 5).sum() == 0


def test_tee_end_on_a_stroke_is_a_junction():
    d = synthetic.tee()
    pts, types = _labels(d)
    assert sorted(types.tolist()) == [1, 1, 1, 3]


def test_wye_and_closed_loop():
    _, types = _labels(synthetic.wye())
    assert sorted(types.tolist()) == [1, 1, 1, 3]
    _, types = _labels(synthetic.circle())
    assert len(types) == 0


def test_two_strokes_meeting_end_to_end():
    a = np.array([[10.0, 40.0], [30.0, 40.0]])
    bent = [a, np.array([[30.0, 40.0], [30.0, 15.0]])]
    straight = [a, np.array([[30.0, 40.0], [55.0, 40.0]])]
    _, t_bent = label_keypoints(bent, [3, 3], RULES)
    _, t_straight = label_keypoints(straight, [3, 3], RULES)
    assert sorted(t_bent.tolist()) == [1, 1, 5]
    assert sorted(t_straight.tolist()) == [1, 1]


def test_generator_is_deterministic_and_labelled():
    cfg = GENERATOR
    a = generate(np.random.default_rng(3), cfg, RULES)
    b = generate(np.random.default_rng(3), cfg, RULES)
    assert np.array_equal(a.grey, b.grey) and np.array_equal(a.points, b.points)
    assert a.grey.dtype == np.float32 and a.grey.min() >= 0 and a.grey.max() <= 1
    assert len(a.points) == len(a.types) > 0
    h, w = a.grey.shape
    assert (a.points >= 0).all() and (a.points[:, 0] < w).all() and (a.points[:, 1] < h).all()


def test_render_strokes_width():
    ink = render_strokes((40, 40), [np.array([[5.0, 20.0], [35.0, 20.0]])], [np.array([4.0, 4.0])])
    assert np.isclose(ink[:, 20].sum(), 4.0, atol=0.05)


# --- targets and loss -------------------------------------------------------------------------


def test_gaussian_heatmaps():
    hm = gaussian_heatmaps((32, 40), np.array([[10.5, 8.5], [30.5, 20.5]]), np.array([1, 5]), 2.0)
    assert hm.shape == (4, 32, 40)
    assert hm[0, 8, 10] == pytest.approx(1.0) and hm[1, 8, 10] == pytest.approx(1.0)
    assert hm[3, 20, 30] == pytest.approx(1.0) and hm[2].max() == 0
    assert hm[0, 8, 12] == pytest.approx(np.exp(-4 / 8), rel=1e-5)


def test_asymmetric_loss_penalises_misses_more():
    t = torch.zeros(1)
    assert float(asymmetric_l1(torch.ones(1) * 0.5, t)) == pytest.approx(0.3)
    assert float(asymmetric_l1(-torch.ones(1) * 0.5, t)) == pytest.approx(0.5)


def test_network_and_loss_shapes():
    net = KeypointNet(TINY_NET)
    x = torch.rand(2, 1, 32, 48)
    final, inter = net(x)
    assert final.shape == (2, 4, 32, 48)
    assert [i.shape[-2:] for i in inter] == [(8, 12), (16, 24)]
    target = torch.zeros(2, 4, 32, 48)
    band = torch.zeros(2, 1, 32, 48)
    band[..., 10:20, :] = 1
    loss, parts = keypoint_loss(final, inter, target, band, (1, .2, .2, .2, .4, .6))
    assert loss.ndim == 0 and set(parts) == {"h1", "h2", "h3", "h4", "h5", "h6"}
    # Outside the band nothing counts.
    final2 = final.detach().clone()
    final2[..., :10, :] = 5.0
    loss2, _ = keypoint_loss(final2, [i.detach() for i in inter], target, band, (1, .2, .2, .2, .4, .6))
    assert float(loss2) == pytest.approx(float(loss.detach()), rel=1e-5)


# --- inference ---------------------------------------------------------------------------------


def test_nms_threshold_distance_and_types():
    hm = np.zeros((4, 30, 30), np.float32)
    hm[:, :, :] = 0.0
    hm[0] = gaussian_heatmaps((30, 30), np.array([[5.5, 5.5], [8.5, 5.5]]), np.array([1, 1]), 1.0)[0]
    hm[0, 5, 8] = 0.9  # a weaker peak 3 px from the first
    hm[0, 20, 20] = 0.4  # an isolated peak below threshold
    hm[2, 5, 5] = 0.8  # class: junction at the first peak
    pts, types, scores = find_keypoints(hm, 0.5, 4, subpixel=False)
    assert len(pts) == 1 and np.allclose(pts[0], [5.5, 5.5]) and types[0] == 3
    pts, _, _ = find_keypoints(hm, 0.5, 2, subpixel=False)
    assert len(pts) == 2
    band = np.zeros((30, 30), bool)
    assert len(find_keypoints(hm, 0.5, 2, band=band)[0]) == 0


def test_local_peaks_are_the_peaks_skimage_finds():
    """The keypoints' NMS (written so that the keypoints process imports no skimage or scipy.spatial)
    gives skimage's peak_local_max points in its order: plateaus and ties, constant images, one-pixel
    and one-row images, thresholds met exactly, spacings 1–8, sparse and smooth maps."""
    from scipy import ndimage
    from skimage.feature import peak_local_max

    from stages.keypoints.inference import local_peaks

    rng = np.random.default_rng(0)
    cases = 0
    for t in range(400):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        kind = t % 5
        if kind == 0:
            img = rng.random((h, w)).astype(np.float32)
        elif kind == 1:
            img = (np.round(rng.random((h, w)) * 4) / 4).astype(np.float32)   # plateaus, values equal to 0.5
        elif kind == 2:
            img = np.full((h, w), rng.choice([0.0, 0.7]), np.float32)
        elif kind == 3:
            img = ndimage.gaussian_filter(rng.random((h, w)), rng.uniform(0.5, 3)).astype(np.float32)
            img /= max(float(img.max()), 1e-9)
        else:
            img = ((rng.random((h, w)) < 0.05) * rng.random((h, w))).astype(np.float32)
        for md in (1, 2, 3, 5, 8):   # 8: past MAX_WINDOW_LOOKUP, the KD-tree's neighbours
            thr = float(rng.choice([0.0, 0.3, 0.5]))
            want = peak_local_max(img, min_distance=md, threshold_abs=thr, exclude_border=False)
            got = local_peaks(img, md, thr)
            assert got.shape == want.shape and np.array_equal(got, want), (t, md, thr)
            cases += int(len(want) > 0)
    assert cases > 600

def test_junction_threshold_keeps_weaker_junctions_only():
    from stages.keypoints import keypoints_from_heatmaps

    hm = np.zeros((4, 40, 40), np.float32)
    for (y, x), h1, cls in (((5, 5), 0.45, 2), ((20, 20), 0.45, 1), ((30, 8), 0.8, 1), ((8, 30), 0.35, 2)):
        hm[0, y, x] = h1
        hm[cls, y, x] = 0.9  # class channel 1 = endpoint, 2 = junction
    cfg = dict(_cfg(), typing="argmax", subpixel=False, restrict_to_band=False)

    def kept(**over):
        _, pts, types, scores = keypoints_from_heatmaps(dict(cfg, **over), hm, None)
        return sorted((int(p[0]), int(p[1]), int(t)) for p, t in zip(pts, types))

    assert kept() == [(8, 30, 1)]  # junction_threshold null: one threshold (0.5) for every type
    assert kept(junction_threshold=0.4) == [(5, 5, 3), (8, 30, 1)]  # the 0.45 junction, not the 0.45 end
    assert kept(junction_threshold=0.3) == [(5, 5, 3), (8, 30, 1), (30, 8, 3)]
    assert kept(threshold=0.4, junction_threshold=0.6) == [(8, 30, 1), (20, 20, 1)]  # stricter on junctions
    with pytest.raises(InputError, match="junction_threshold"):
        from stages.config import from_section
        from stages.keypoints import KeypointsConfig
        from_section(KeypointsConfig, dict(_cfg(), junction_threshold=1.5), "keypoints")


def test_subpixel_refinement():
    hm = np.zeros((4, 20, 20), np.float32)
    hm[0] = gaussian_heatmaps((20, 20), np.array([[10.2, 7.8]]), np.array([1]), 2.0)[0]
    pts, _, _ = find_keypoints(hm, 0.5, 1, subpixel=True)
    assert np.allclose(pts[0], [10.2, 7.8], atol=0.1)


def test_network_input_normalisation():
    grey = np.ones((20, 20), np.float32)
    grey[5:8, :] = 0.4
    x = network_input(grey, 0.5)
    assert x.dtype == np.float32 and x.max() == pytest.approx(1.0) and x[0, 0] == 0.0


def test_tiles_blend_without_seams():
    torch.manual_seed(0)
    net = KeypointNet(TINY_NET).eval()
    x = network_input(synthetic.tee(size=100).grey, 0.5)
    whole = predict_heatmaps(net, x, 4096, 64)
    tiled = predict_heatmaps(net, x, 64, 32)
    assert whole.shape == tiled.shape == (4,) + x.shape
    assert np.abs(whole - tiled).max() < 0.05
    # H1 alone (an ensemble member's pass) is the full pass's H1, whole and tiled
    for tile, full in ((4096, whole), (64, tiled)):
        h1 = predict_heatmaps(net, x, tile, 32 if tile == 64 else 64, detection_only=True)
        assert h1.shape == (1,) + x.shape
        np.testing.assert_allclose(h1[0], full[0], atol=1e-5)


def test_tiles_without_band_are_skipped_and_change_no_kept_pixel():
    torch.manual_seed(0)
    net = KeypointNet(TINY_NET).eval()
    grey = np.ones((200, 200), np.float32)
    grey[150:154, 20:180] = 0.0          # one stroke near the bottom: the top tiles hold no band
    x = network_input(grey, 0.5)
    needed = dilate_band(grey < 0.65, 3)
    calls = []
    counting = KeypointNet(TINY_NET).eval()
    counting.load_state_dict(net.state_dict())
    counting.forward = (lambda f: (lambda t: (calls.append(t.shape), f(t))[1]))(counting.forward)
    full = predict_heatmaps(net, x, 64, 16)
    skipped = predict_heatmaps(counting, x, 64, 16, needed=needed)
    assert 0 < len(calls) < len(_tile_starts(x.shape[0] + 8, 64, 48)) * len(_tile_starts(x.shape[1] + 8, 64, 48))
    np.testing.assert_array_equal(skipped[:, needed], full[:, needed])
    assert not skipped[:, :96].any()      # rows that only skipped tiles cover are 0
    # single_pass_max: up to it the drawing runs whole, as with a tile that large
    whole = predict_heatmaps(net, x, 64, 16, single_pass_max=256)
    np.testing.assert_array_equal(whole, predict_heatmaps(net, x, 4096, 16))


def test_run_artifact_contract():
    d = synthetic.cross(size=48)
    prep = Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={})
    a = run(_cfg(), prep=prep)
    assert a["heatmaps"].shape == (4, 48, 48) and a["heatmaps"].dtype == np.float32
    assert a["points"].dtype == np.float32 and a["points"].shape[1:] == (2,)
    assert a["types"].dtype == np.int8 and a["scores"].dtype == np.float32
    assert len(a.data["points"]) == len(a["points"])
    assert set(a["types"].tolist()) <= {1, 3, 5}
    assert STAGE_VERSION.startswith("8+") and a.data["weights"] and a.data["scale"] == 1
    assert (a.data["height"], a.data["width"]) == (48, 48)        # the drawing's size, for the edits
    assert torch.get_num_threads() == 1
    img = render_keypoints(d.grey, a["heatmaps"], a["points"], a["types"])
    assert img.shape == (48, 48, 3) and img.dtype == np.uint8


def test_a_mosaic_of_far_apart_parts_runs_the_network_on_each_piece_alone():
    """prep laid two far-apart drawings side by side (``pieces``): the network runs on each piece's
    window, never on the paper between them, and finds there what it finds on that drawing alone; the
    artifact keeps the pieces, so keypoint edits map through them."""
    a, b = synthetic.cross(size=48), synthetic.line(size=48, angle=23.0, length=30.0, width=3.0)
    grey = np.ones((48, 120), np.float32)
    grey[:, :48], grey[:, 72:] = a.grey, b.grey
    pieces = [[0, 0, 300, 10, 48, 48], [72, 0, 20, 500, 48, 48]]
    prep = Artifact(arrays={"grey": grey, "mask": grey < 0.65}, data={"pieces": pieces, "height": 600, "width": 400})
    model, _ = load_model("packaged")
    calls = []
    forward = model.forward
    model.forward = lambda t: (calls.append(tuple(t.shape[-2:])), forward(t))[1]
    try:
        art = run(_cfg(), prep=prep)
    finally:
        del model.forward
    assert calls == [(56, 56), (56, 56)]         # each 48-px piece, padded to the network's multiple
    assert art.data["pieces"] == pieces and (art.data["height"], art.data["width"]) == (600, 400)
    assert not art["heatmaps"][:, :, 48:72].any()
    for d, x0 in ((a, 0), (b, 72)):
        alone = run(_cfg(), prep=Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={}))
        mine = art["points"][(art["points"][:, 0] >= x0) & (art["points"][:, 0] < x0 + 48)]
        assert len(alone["points"]) > 0
        np.testing.assert_allclose(np.sort(mine - [x0, 0], axis=0), np.sort(alone["points"], axis=0), atol=1e-4)


def test_detection_ensemble_averages_h1_and_keeps_class_maps():
    """``detection_ensemble: [packaged_procedural]`` averages H1 of the main and the procedural network;
    the class maps (which the typing perceptron reads) stay the main network's; the default, ``[]``, is
    the main one alone (one pass: phase 16 alone ties the pair, MODEL_CARD)."""
    d = synthetic.cross(size=64)
    prep = Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={})
    cfg = _cfg()
    assert cfg["detection_ensemble"] == []
    both = run(dict(cfg, detection_ensemble=["packaged_procedural"]), prep=prep)
    main = run(cfg, prep=prep)
    other = run(dict(cfg, weights="packaged_procedural", detection_ensemble=[]), prep=prep)
    np.testing.assert_array_equal(both["heatmaps"][1:], main["heatmaps"][1:])
    lo = np.minimum(main["heatmaps"][0], other["heatmaps"][0]) - 1e-5
    hi = np.maximum(main["heatmaps"][0], other["heatmaps"][0]) + 1e-5
    assert np.all((both["heatmaps"][0] >= lo) & (both["heatmaps"][0] <= hi))
    assert not np.allclose(both["heatmaps"][0], main["heatmaps"][0], atol=1e-3)
    assert "keypoints_procedural.pt@" in both.data["weights"]
    with pytest.raises(InputError, match="no such file"):
        run(dict(cfg, detection_ensemble=["/nonexistent/net.pt"]), prep=prep)


class _PositionNet(torch.nn.Module):
    """Not equivariant at all: its four maps are the input and fixed ramps across the image."""

    multiple = 8

    def forward(self, a):
        h, w = a.shape[-2:]
        yy = torch.arange(h, dtype=a.dtype)[:, None].expand(h, w)
        xx = torch.arange(w, dtype=a.dtype)[None, :].expand(h, w)
        return (torch.stack([a[0, 0], xx, yy, xx * yy])[None],)


@pytest.mark.parametrize("view", sorted(VIEWS))
def test_each_test_time_view_is_mapped_back_onto_the_drawing(view):
    """A view's output comes back in the drawing's frame: the input channel is the drawing itself; the
    ramps (which a view turns) average with their mapped-back mirror images. Non-square, with tiles."""
    x = np.random.default_rng(0).random((37, 53)).astype(np.float32)
    for tile, single in ((512, 1024), (24, 24)):            # one pass, and overlapping tiles
        plain = predict_heatmaps(_PositionNet(), x, tile, 8, single_pass_max=single)
        both = predict_views(_PositionNet(), x, [view], tile, 8, single_pass_max=single)
        np.testing.assert_allclose(both[0], x, atol=1e-5)                          # the drawing, mapped back
        mirrored = VIEWS[view](predict_heatmaps(_PositionNet(), np.ascontiguousarray(VIEWS[view](x)), tile, 8,
                                                single_pass_max=single))
        np.testing.assert_allclose(both, (plain + mirrored) / 2, atol=1e-4)
        assert not np.allclose(both[1:], plain[1:])                               # the ramps did turn
    np.testing.assert_array_equal(predict_views(_PositionNet(), x, [], 512, 8), predict_heatmaps(_PositionNet(), x, 512, 8))


def test_test_time_views_in_the_stage_and_bad_names():
    """``test_time_views: [transpose]`` averages the drawing's and its transpose's heatmaps (the default,
    ``[]``, one pass); unknown or repeated names are one clear error."""
    d = synthetic.cross(size=64)
    prep = Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={})
    cfg = _cfg()
    assert cfg["test_time_views"] == []
    main = run(cfg, prep=prep)
    both = run(dict(cfg, test_time_views=["transpose"]), prep=prep)
    assert not np.allclose(both["heatmaps"], main["heatmaps"], atol=1e-4)
    assert len(both["points"]) == len(main["points"])          # the cross's four ends and its junction
    for bad in (["mirror"], ["flip_x", "flip_x"]):
        with pytest.raises(InputError, match="test_time_views"):
            run(dict(cfg, test_time_views=bad), prep=prep)


def test_weights_load_on_cpu():
    model, name = load_model("packaged")
    assert next(model.parameters()).device.type == "cpu"
    if PACKAGED_WEIGHTS.is_file():
        assert name.startswith("keypoints.pt@") and name.split("@")[1] in STAGE_VERSION


def test_loaded_networks_have_their_batch_norms_folded():
    # Inference runs the folded network (a third fewer passes over full-resolution tensors); the
    # heatmaps must be those of the network as trained, up to float rounding.
    from torch import nn

    model, _ = load_model("packaged")
    assert not any(isinstance(m, nn.BatchNorm2d) for m in model.modules())
    ckpt = torch.load(PACKAGED_WEIGHTS, map_location="cpu", weights_only=True)
    plain = KeypointNet(model.cfg)
    plain.load_state_dict({k: v.float() for k, v in ckpt["state_dict"].items()})
    plain.eval()
    x = torch.from_numpy(network_input(synthetic.tee(size=96).grey, 0.5))[None, None]
    with torch.inference_mode():
        assert torch.allclose(model(x)[0], plain(x)[0], atol=1e-4)
    with pytest.raises(ValueError, match="eval mode"):
        fold_batch_norms(KeypointNet(model.cfg))


def test_pointwise_convolutions_by_onednn_match_conv2d_and_fall_back():
    # The loaded network runs its 1×1 convolutions (but the one-channel ones) through oneDNN; the
    # result is conv2d's up to rounding, and under bf16 autocast or with gradients conv2d itself runs.
    from torch import nn

    from stages.keypoints.network import ChannelScale, OneDNNPointwise, use_onednn_pointwise

    model, _ = load_model("packaged")
    swapped = [m for m in model.modules() if isinstance(m, OneDNNPointwise)]
    scales = [m for m in model.modules() if isinstance(m, ChannelScale)]
    plain_1x1 = [m for m in model.modules() if isinstance(m, nn.Conv2d) and m.kernel_size == (1, 1)]
    assert len(swapped) > 10 and len(scales) == 2 and not plain_1x1   # the stem's two from the drawing
    torch.manual_seed(0)
    conv = nn.Conv2d(12, 5, 1)
    pw = use_onednn_pointwise(nn.Sequential(conv))[0]
    assert isinstance(pw, OneDNNPointwise) and pw.weight is conv.weight
    x = torch.randn(1, 12, 40, 56).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        ref = nn.functional.conv2d(x, conv.weight, conv.bias)
        assert torch.allclose(pw(x), ref, atol=1e-5) and torch.allclose(pw(x.contiguous()), ref, atol=1e-5)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert pw(x.bfloat16()).dtype == torch.bfloat16
    y = pw(x.requires_grad_())
    y.sum().backward()
    assert x.grad is not None and torch.allclose(y, ref, atol=1e-5)


def test_one_channel_pointwise_convolution_is_a_channels_last_scaling():
    # The stem's 1×1 convolutions from the drawing: conv2d's values, written channels-last (what the next
    # 3×3 convolution reads without a reorder); conv2d itself under autocast or with gradients.
    from torch import nn

    from stages.keypoints.network import ChannelScale, use_onednn_pointwise

    torch.manual_seed(1)
    conv = nn.Conv2d(1, 6, 1)
    cs = use_onednn_pointwise(nn.Sequential(conv))[0]
    assert isinstance(cs, ChannelScale)
    x = torch.randn(2, 1, 30, 44)
    with torch.inference_mode():
        ref = nn.functional.conv2d(x, conv.weight, conv.bias)
        y = cs(x)
        assert y.is_contiguous(memory_format=torch.channels_last) and torch.allclose(y, ref, atol=1e-6)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert cs(x).dtype == torch.bfloat16
    y = cs(x.requires_grad_())
    y.sum().backward()
    assert x.grad is not None and torch.allclose(y, ref, atol=1e-6)


def test_concatenations_are_fused_part_by_part():
    # PartwiseFuse: conv(cat(parts)) as a sum over the parts, for the stem (1×1) and the decoder (3×3 +
    # LeakyReLU); the loaded network uses it at every concatenation and never concatenates.
    from torch import nn

    from stages.keypoints.network import PartwiseFuse, ResNeXtModule, _Up

    torch.manual_seed(2)
    for k, act in ((1, []), (3, [nn.LeakyReLU(0.1)])):
        conv = nn.Conv2d(10, 4, k, padding=k // 2)
        seq = nn.Sequential(conv, nn.Identity(), *act)
        fuse = PartwiseFuse(seq, [6, 4])
        parts = [torch.randn(1, 6, 21, 17).contiguous(memory_format=torch.channels_last), torch.randn(1, 4, 21, 17)]
        with torch.inference_mode():
            ref = seq(torch.cat(parts, 1))
            assert torch.allclose(fuse(parts), ref, atol=1e-5)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                assert torch.allclose(fuse(parts).float(), ref, atol=0.1)
        assert torch.allclose(fuse(parts), ref, atol=1e-5)   # with gradients: conv2d's path
    with pytest.raises(ValueError, match="folded"):
        PartwiseFuse(nn.Sequential(nn.Conv2d(4, 2, 1), nn.BatchNorm2d(2)), [2, 2])
    with pytest.raises(ValueError, match="channels"):
        PartwiseFuse(nn.Sequential(nn.Conv2d(4, 2, 1)), [2, 3])
    model, _ = load_model("packaged")
    fusing = [m for m in model.modules() if isinstance(m, (ResNeXtModule, _Up))]
    assert len(fusing) == 1 + model.cfg.depth and all(isinstance(m.fuse, PartwiseFuse) for m in fusing)
    cats = []
    original = torch.cat
    try:
        torch.cat = lambda parts, *a, **kw: cats.append(sum(t.shape[1] for t in parts)) or original(parts, *a, **kw)
        with torch.inference_mode():
            model(torch.zeros(1, 1, 32, 32))
    finally:
        torch.cat = original
    assert cats == [4]   # only the four output maps


@pytest.mark.skipif(not PACKAGED_WEIGHTS.is_file(), reason="no shipped weights yet")
def test_shipped_model_finds_both_ends_of_a_stroke():
    d = synthetic.line(size=96, angle=23.0, length=60.0, width=3.0)
    prep = Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={})
    a = run(_cfg(), prep=prep)
    gt = np.array([k[:2] for k in d.keypoints])
    m = match_keypoints(gt, np.array([1, 1]), a["points"], a["types"], 5.0)
    assert m.tp == 2 and m.correct_type == 2


@pytest.mark.skipif(not PACKAGED_WEIGHTS.is_file(), reason="no shipped weights yet")
def test_shipped_model_gives_no_corner_on_thin_aliased_smooth_curves():
    """Thin (1–2.2 px) grey ink with hard or coarse anti-aliasing (generator.thin_prob): the aliasing
    staircase of smooth ellipses and an arc must not read as corners, nor as any other keypoint."""
    from stages import prep as prep_stage

    t, u = np.linspace(0, 2 * np.pi, 700), np.linspace(0, 1, 300)
    pcfg = yaml.safe_load((CONF / "prep" / "default.yaml").read_text())
    spurious = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        strokes = [np.stack([300 + rng.uniform(150, 230) * np.cos(t), 330 + rng.uniform(110, 170) * np.sin(t)], 1),
                   np.stack([200 + rng.uniform(50, 80) * np.cos(t), 140 + rng.uniform(40, 70) * np.sin(t)], 1),
                   np.stack([420 + 140 * u, 230 - rng.uniform(30, 90) * np.sin(np.pi * u)], 1)]
        s = drawing_from_strokes(rng, strokes, (600, 600), replace(GENERATOR, thin_prob=1.0), RULES)
        png = Image.fromarray((s.grey * 255).round().astype(np.uint8))
        buf = io.BytesIO()
        png.save(buf, format="PNG")
        a = run(_cfg(), prep=prep_stage.run(pcfg, image_bytes=buf.getvalue(), image_name="thin.png"))
        assert 5 not in s.types.tolist()
        for q, ty in zip(a["points"], a["types"]):
            if np.min(np.hypot(*(s.points - q).T)) > 6:
                spurious.append((seed, int(ty), q.round().tolist()))
    assert not spurious


# --- metrics -----------------------------------------------------------------------------------


def test_authors_f1_and_matching():
    gt = np.array([[10.0, 10.0], [50.0, 50.0]])
    assert f1_authors(gt, gt, 100) == 1.0
    assert f1_authors(gt, np.zeros((0, 2)), 100) == 0.0
    assert f1_authors(np.zeros((0, 2)), gt, 100) == 0.5
    # One prediction between two close GT points satisfies both in the authors' F1 but not 1-to-1.
    gt2 = np.array([[10.0, 10.0], [11.0, 10.0]])
    assert f1_authors(gt2, np.array([[10.5, 10.0]]), 100) == 1.0
    m = match_keypoints(gt2, np.array([1, 3]), np.array([[10.5, 10.0]]), np.array([3]), 5)
    assert (m.tp, m.fp, m.fn) == (1, 0, 1)
    assert read_pts("2 \n3.0 4.0 5.0\n1 2 1\n")[0].tolist() == [[4.5, 3.5], [2.5, 1.5]]


# --- training ----------------------------------------------------------------------------------


def test_training_smoke_loss_decreases(tmp_path):
    from pipeline.train import compose_plain
    from stages.keypoints.training import train

    cfg = compose_plain(CONF, [
        f"train.out_dir={tmp_path}", "train.steps=12", "train.batch_size=4", "train.num_workers=0",
        "train.crop_schedule=[[0,48]]", "train.val.count=1", "train.val.vector_count=0", "train.val.every=1000",
        "train.checkpoint_every=6", "train.log_every=1000", "train.lr=0.003", "train.crops_per_image=4",
        "train.network.level_channels=[4,8,8,8]", "train.network.stem_mid=4",
        "train.network.bottleneck_blocks=1"])
    cfg["train"]["seed"] = 1
    torch.manual_seed(0)
    rec = train(cfg)
    assert rec["steps"] == 12 and (tmp_path / "keypoints.pt").is_file() and (tmp_path / "last.pt").is_file()
    model, _ = load_model(tmp_path / "keypoints.pt")
    assert isinstance(model, KeypointNet)
    # keypoints.weights may name the training checkpoint too (to score it before exporting)
    resumed, _ = load_model(tmp_path / "last.pt")
    for k, v in model.state_dict().items():
        assert torch.allclose(v.float(), resumed.state_dict()[k].float(), atol=2e-3, rtol=2e-3), k
    torch.save({"network": {}, "weights": {}}, tmp_path / "other.pt")
    with pytest.raises(InputError, match="not a polyvec-train checkpoint"):
        load_model(tmp_path / "other.pt")
    curve = rec["loss_curve"]
    assert len(curve) == 12 and np.mean(curve[-3:]) < np.mean(curve[:3])


def test_legacy_network_config_rebuilds_the_first_head():
    # Checkpoints without the class-branch keys must load with the first model's head.
    legacy = {"stem_mid": 4, "level_channels": [4, 8, 8, 8], "bottleneck_blocks": 1, "negative_slope": 0.1}
    cfg = NetConfig.from_dict(legacy)
    assert (cfg.class_width, cfg.class_dilations) == (0, (1,))
    names = [k for k in KeypointNet(cfg).state_dict() if k.startswith("class_head.")]
    assert {k.split(".")[1] for k in names} == {"0", "1"}
    wide = NetConfig.from_dict(legacy | {"class_width": 6, "class_dilations": [1, 2]})
    assert NetConfig.from_dict(wide.to_dict()) == wide
    out, _ = KeypointNet(wide)(torch.zeros(1, 1, 32, 32))
    assert out.shape == (1, 4, 32, 32)


_TINY = ["train.network.level_channels=[4,8,8,8]", "train.network.stem_mid=4", "train.network.bottleneck_blocks=1",
         "train.val.count=1", "train.val.vector_count=0", "train.num_workers=0"]


def _tiny_detector(tmp_path: Path, steps: int, class_overrides: list[str]) -> Path:
    """A tiny detector trained for ``steps`` steps (tests of the class branch's re-training); its weights."""
    from pipeline.train import compose_plain
    from stages.keypoints.training import train

    train(compose_plain(CONF, _TINY + [
        f"train.out_dir={tmp_path / 'base'}", f"train.steps={steps}", "train.batch_size=2",
        "train.crop_schedule=[[0,48]]", "train.val.every=1000", "train.log_every=1000"] + class_overrides))
    return tmp_path / "base" / "keypoints.pt"


def test_class_branch_training_keeps_detection(tmp_path):
    from pipeline.train import compose_plain
    from stages.keypoints.training import train_class_branch

    _tiny_detector(tmp_path, 2, ["train.network.class_width=0", "train.network.class_dilations=[1]"])
    cfg = compose_plain(CONF, _TINY + [
        f"train.out_dir={tmp_path / 'cb'}", f"train.init_weights={tmp_path / 'base' / 'keypoints.pt'}",
        "train.network.class_width=6", "train.network.class_dilations=[1,2]",
        "train.class_branch.drawings=3", "train.class_branch.val_drawings=1", "train.class_branch.epochs=2",
        "train.class_branch.patch=13", "train.class_branch.supervised_margin=3"])
    rec = train_class_branch(cfg)
    assert rec["keypoints"] > 0 and len(rec["history"]) == 2
    old, _ = load_model(tmp_path / "base" / "keypoints.pt")
    new, _ = load_model(tmp_path / "cb" / "keypoints.pt")
    assert new.cfg.class_dilations == (1, 2)
    x = torch.from_numpy(network_input(synthetic.tee(size=64).grey, 0.5))[None, None]
    with torch.inference_mode():
        h_old, h_new = old(x)[0], new(x)[0]
    # The detector is frozen: H1 is unchanged, only the class maps differ.
    assert torch.equal(h_old[:, 0], h_new[:, 0])
    assert not torch.equal(h_old[:, 1:], h_new[:, 1:])


def test_distilled_class_branch_keeps_detection_and_learns_the_teachers_maps(tmp_path):
    """``train.class_branch.distill``: a narrower class branch trained on the teacher's own class maps
    around its detections; the trunk and H1 are the teacher's, and the student's loss falls."""
    from pipeline.train import compose_plain
    from stages.keypoints.training import train_class_branch
    from stages.keypoints.training.class_branch import distill_patches

    teacher_path = _tiny_detector(tmp_path, 3, ["train.network.class_width=6", "train.network.class_dilations=[1,2]"])
    cfg = compose_plain(CONF, _TINY + [
        f"train.out_dir={tmp_path / 'cb'}", f"train.init_weights={teacher_path}", "train.vector_prob=0",
        "train.network.class_width=3", "train.network.class_dilations=[1,2]",
        "train.class_branch.distill=true", "train.class_branch.peak_threshold=-1",
        "train.class_branch.drawings=2", "train.class_branch.val_drawings=1", "train.class_branch.epochs=4",
        "train.class_branch.lr=0.02", "train.class_branch.patch=13", "train.class_branch.supervised_margin=4"])
    teacher, _ = load_model(teacher_path)
    feats, targets = distill_patches(teacher, cfg, 1, 5, 13, 4)
    assert feats.shape[1:] == (4, 13, 13) and targets.shape == (len(feats), 3, 5, 5)
    # The targets are the teacher's own class maps on the centre of each feature patch.
    with torch.inference_mode():
        again = torch.tanh(teacher.class_head(feats[:4].float()))[:, :, 4:9, 4:9]
    # (float16 storage: ≤ 2.5e-4 apart; the maps one pixel off differ by ~1e-3 even in this tiny network)
    assert torch.allclose(again, targets[:4].float(), rtol=0, atol=4e-4)
    rec = train_class_branch(cfg)
    assert rec["mode"] == "class_branch_distill" and rec["patches"] > 0 and len(rec["history"]) == 4
    assert rec["history"][-1]["loss"] < rec["history"][0]["loss"]
    new, _ = load_model(tmp_path / "cb" / "keypoints.pt")
    assert new.cfg.class_width == 3
    x = torch.from_numpy(network_input(synthetic.tee(size=64).grey, 0.5))[None, None]
    with torch.inference_mode():
        h_old, h_new = teacher(x)[0], new(x)[0]
    assert torch.equal(h_old[:, 0], h_new[:, 0])


def test_widening_the_shipped_network_keeps_its_heatmaps():
    """training/widen.py: the shipped network embedded in a wider one computes the same H1..H6 (eval
    mode); a change other than width is refused."""
    from stages.keypoints.training.widen import can_widen, widen

    ck = torch.load(PACKAGED_WEIGHTS, map_location="cpu", weights_only=False)
    old_cfg = NetConfig.from_dict(ck["network"])
    old = KeypointNet(old_cfg)
    old.load_state_dict({k: v.float() for k, v in ck["state_dict"].items()})
    wide_cfg = replace(old_cfg, stem_mid=old_cfg.stem_mid + 4,
                       level_channels=tuple(c + (4 if k else 3) for k, c in enumerate(old_cfg.level_channels)))
    wide = KeypointNet(wide_cfg)
    wide.load_state_dict(widen(ck["state_dict"], old_cfg, wide_cfg))
    old.eval(), wide.eval()
    x = torch.from_numpy(network_input(synthetic.tee(size=96).grey, 0.5))[None, None]
    with torch.inference_mode():
        (a, ai), (b, bi) = old(x), wide(x)
    # float32 sums over the wider convolutions run in another order: up to ~1e-5 apart (maps in [-1, 1]);
    # a widening that changed the function would be off by orders of magnitude more.
    assert torch.allclose(a, b, atol=1e-4) and all(torch.allclose(p, q, atol=1e-4) for p, q in zip(ai, bi))
    # The new channels are live (random fan-in), so training can grow them.
    assert wide.stem.fuse[0].weight[old_cfg.level_channels[0]:].abs().sum() > 0
    assert not can_widen(old_cfg, replace(old_cfg, bottleneck_blocks=old_cfg.bottleneck_blocks + 1))
    assert not can_widen(wide_cfg, old_cfg)
    with pytest.raises(ValueError, match="not a widening"):
        widen(ck["state_dict"], wide_cfg, old_cfg)


def test_training_warm_starts_a_wider_network_from_a_narrow_checkpoint(tmp_path):
    """``polyvec-train train.init_weights=<narrow> train.network.level_channels=<wider>`` widens the
    checkpoint; a checkpoint of another layout is one clear error."""
    from pipeline.train import compose_plain
    from stages.keypoints.training import train

    small = ["train.network.stem_mid=4", "train.network.bottleneck_blocks=1", "train.val.count=1",
             "train.val.vector_count=0", "train.num_workers=0", "train.steps=1", "train.batch_size=2",
             "train.crop_schedule=[[0,48]]", "train.val.every=1000", "train.log_every=1000"]
    train(compose_plain(CONF, small + ["train.network.level_channels=[4,8,8,8]",
                                       f"train.out_dir={tmp_path / 'narrow'}"]))
    narrow = tmp_path / "narrow" / "keypoints.pt"
    rec = train(compose_plain(CONF, small + ["train.network.level_channels=[6,12,16,16]",
                                             f"train.init_weights={narrow}", f"train.out_dir={tmp_path / 'wide'}"]))
    assert rec["widened_from"]["level_channels"] == [4, 8, 8, 8]
    model, _ = load_model(tmp_path / "wide" / "keypoints.pt")
    assert model.cfg.level_channels == (6, 12, 16, 16)
    with pytest.raises(SystemExit, match="neither equals nor widens"):
        train(compose_plain(CONF, small + ["train.network.level_channels=[4,8,8,8]", "train.network.bottleneck_blocks=2",
                                           f"train.init_weights={narrow}", f"train.out_dir={tmp_path / 'deep'}"]))


# --- readers (need ../shared) ------------------------------------------------------------------


@pytest.mark.shared
def test_readers_on_shared_vector_data():
    vec = SHARED / "data" / "vector"
    if not vec.is_dir():
        pytest.skip("../shared absent")
    drawings = read_quickdraw_ndjson(vec / "quickdraw" / "cat.ndjson", limit=2)
    assert len(drawings) == 2 and all(s.shape[1] == 2 for s in drawings[0])
    strokes, size = read_svg_strokes(vec / "creative" / "test_50.svg")
    assert len(strokes) > 3 and size[0] > 0
    allp = np.concatenate(strokes)
    assert allp.min() > -1 and allp.max() < max(size) + 1
    angel = sorted((vec / "tu_berlin" / "angel").glob("*.svg"))[0]
    strokes, size = read_svg_strokes(angel)
    allp = np.concatenate(strokes)
    assert len(strokes) > 1 and allp.min() > -5 and allp.max() < max(size) + 5


def test_eval_keypoints_cli_scores_a_folder(tmp_path):
    """``python -m pipeline.eval_keypoints DIR`` scores drawings against their JSON keypoints, with the
    config's detection ensemble by default (none), the named networks with ``--ensemble W…`` and the
    main network alone with a bare ``--ensemble``."""
    from PIL import Image

    from pipeline.eval_keypoints import main

    d = synthetic.cross(size=96, length=70.0)
    Image.fromarray((d.grey * 255).round().astype(np.uint8)).save(tmp_path / "x.png")
    ends = [p.tolist() for s in d.strokes for p in (s[0], s[-1])]
    centre = np.mean([s.mean(0) for s in d.strokes], 0).tolist()
    (tmp_path / "x.json").write_text(json.dumps({"endpoints": ends, "junctions": [centre], "corners": []}))
    for extra, procedural in (([], False), (["--ensemble", "packaged_procedural"], True), (["--ensemble"], False)):
        out = tmp_path / f"kp{len(extra)}.json"
        assert main([str(tmp_path), "--json", str(out), *extra]) == 0
        s = json.loads(out.read_text())["summary"]
        assert s["cases"] == 1 and 0.0 <= s["f1_matched_pooled"] <= 1.0
        assert ("keypoints_procedural.pt@" in s["weights"]) == procedural
        assert s["test_time_views"] == []
    out = tmp_path / "views.json"
    assert main([str(tmp_path), "--json", str(out), "--views", "transpose"]) == 0
    assert json.loads(out.read_text())["summary"]["test_time_views"] == ["transpose"]
    assert main([str(tmp_path), "--views", "mirror"]) == 2                   # one line, no traceback
    assert main([str(tmp_path / "missing")]) == 2


def test_eval_keypoints_can_label_crossings_from_the_scorers_angle(tmp_path, capsys):
    """``--crossing-angle 20`` scores against labels made again from the case's strokes: a 30° crossing,
    which the case's own (37°) labels leave out, becomes a ground-truth junction; a case without
    strokes is one line."""
    from PIL import Image

    from pipeline.eval_keypoints import main

    d = synthetic.cross(size=96, angle1=10.0, angle2=40.0, length=70.0)
    Image.fromarray((d.grey * 255).round().astype(np.uint8)).save(tmp_path / "x.png")
    ends = [p.tolist() for s in d.strokes for p in (s[0], s[-1])]
    case = {"strokes": [s.tolist() for s in d.strokes], "width": d.width, "endpoints": ends, "junctions": [],
            "corners": []}
    (tmp_path / "x.json").write_text(json.dumps(case))
    n_gt = {}
    for angle in (None, 37, 20):
        out = tmp_path / f"kp{angle}.json"
        assert main([str(tmp_path), "--json", str(out)] + ([] if angle is None else ["--crossing-angle", str(angle)])) == 0
        res = json.loads(out.read_text())
        n_gt[angle] = res["cases"][0]["n_gt"]
        assert res["summary"]["labels"] == ("case" if angle is None else f"relabelled, crossings from {angle}°")
    assert n_gt == {None: 4, 37: 4, 20: 5}
    (tmp_path / "x.json").write_text(json.dumps({"endpoints": ends, "junctions": [], "corners": []}))
    capsys.readouterr()
    assert main([str(tmp_path), "--crossing-angle", "20"]) == 2
    assert "needs the case's vector strokes" in capsys.readouterr().err


def test_missing_packaged_weights_are_an_error_not_a_random_network(tmp_path, monkeypatch):
    """A deleted weights file must stop the stage: a randomly initialised network gives plausible nonsense."""
    import stages.keypoints.stage as kp

    monkeypatch.setitem(kp._PACKAGED_NETWORKS, "packaged", tmp_path / "keypoints.pt")
    monkeypatch.setattr(kp, "_MODELS", {})
    with pytest.raises(InputError, match="packaged weights file .* is missing"):
        load_model("packaged")


def test_bf16_arithmetic_finds_the_fp32_keypoints():
    """keypoints.precision=bf16 (bfloat16 autocast): the same keypoints as fp32 on the bundled example
    drawing, within a pixel and of the same types; the artifact says which arithmetic ran."""
    from stages import prep as prep_stage
    from stages.keypoints.inference import use_bf16

    png = synthetic.example_drawing().png_bytes()
    p = prep_stage.run(yaml.safe_load((CONF / "prep" / "default.yaml").read_text()), png)
    fp32 = run(dict(_cfg(), precision="fp32"), prep=p)
    bf16 = run(dict(_cfg(), precision="bf16"), prep=p)
    assert (fp32.data["precision"], bf16.data["precision"]) == ("fp32", "bf16")
    assert np.abs(fp32["heatmaps"] - bf16["heatmaps"]).max() > 0      # it did run in bf16
    assert len(fp32["points"]) == len(bf16["points"]) > 5
    d = np.linalg.norm(fp32["points"][:, None] - bf16["points"][None], axis=2)
    nearest = d.argmin(1)
    assert d.min(1).max() < 1.0 and np.array_equal(fp32["types"], bf16["types"][nearest])
    auto = run(dict(_cfg(), precision="auto"), prep=p)
    assert auto.data["precision"] == ("bf16" if use_bf16("auto") else "fp32")
    with pytest.raises(InputError, match="precision"):
        run(dict(_cfg(), precision="half"), prep=p)
