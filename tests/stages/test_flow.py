"""Tests of the PolyVector flow stage on synthetic drawings with analytic frame fields.

The analytic field of a drawing: on the band of one stroke with unit tangent u, the cross field
p(z) = (z² − u²)(z² − (iu)²) (what the field stage's orthogonal regulariser produces); where two
strokes cross, p(z) = (z² − u²)(z² − v²) with their two tangents, so c2 = −(u² + v²), c0 = u²v².
Beyond the band it is extended like the extension stage does (× 2·L1 distance in a 5 px ring, 0 beyond).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import ndimage as ndi

from stages import flow, synthetic
from stages.artifact import Artifact, unpack_ragged
from stages.config import from_section
from stages.errors import InputError
from stages.flow import kernel

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "flow" / "default.yaml").read_text())


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------

def _nearest_tangent(shape, stroke):
    """Distance from every pixel centre to a polyline and the unit tangent of the nearest segment."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w]
    px, py = xs + 0.5, ys + 0.5
    best = np.full(shape, np.inf)
    tan = np.zeros(shape, complex)
    for a, b in zip(stroke[:-1], stroke[1:]):
        d = b - a
        ll = d @ d
        t = np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / ll, 0, 1)
        dist = np.hypot(px - a[0] - t * d[0], py - a[1] - t * d[1])
        upd = dist < best
        best[upd] = dist[upd]
        tan[upd] = (d[0] + 1j * d[1]) / np.sqrt(ll)
    return best, tan


def analytic_field(drawing: synthetic.Drawing, ring: int = 5, scale: float = 2.0):
    """``c0_ext, c2_ext, mask`` of a synthetic drawing (see the module docstring)."""
    shape = drawing.grey.shape
    half = drawing.width / 2 + 0.5
    ds, ts = map(np.stack, zip(*[_nearest_tangent(shape, np.asarray(s, float)) for s in drawing.strokes]))
    order = np.argsort(ds, axis=0)
    d0 = np.take_along_axis(ds, order[:1], 0)[0]
    u = np.take_along_axis(ts, order[:1], 0)[0]
    if len(ds) > 1:
        d1 = np.take_along_axis(ds, order[1:2], 0)[0]
        u1 = np.take_along_axis(ts, order[1:2], 0)[0]
    else:
        d1, u1 = np.full(shape, np.inf), u
    mask = d0 <= half
    crossing = mask & (d1 <= half) & (np.abs((u * u1.conj()).real) < 0.95)
    v = np.where(crossing, u1, 1j * u)
    c2, c0 = -(u ** 2 + v ** 2), u ** 2 * v ** 2
    dist = ndi.distance_transform_cdt(~mask, metric="taxicab").astype(float)
    yy, xx = np.mgrid[-ring:ring + 1, -ring:ring + 1]
    dil = ndi.binary_dilation(mask, structure=xx * xx + yy * yy <= ring * ring)
    sc = np.where(mask, 1.0, np.where(dil, scale * dist, 0.0))
    return c0 * sc, c2 * sc, mask


def noisy_path(a, b, n=45, noise=0.5, seed=0):
    """A polyline from a to b with i.i.d. normal noise across it (ends exact); its normal and arc lengths."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n)
    nrm = np.array([-(b - a)[1], (b - a)[0]]) / np.linalg.norm(b - a)
    off = rng.normal(0, noise, n)
    off[[0, -1]] = 0
    return a + t[:, None] * (b - a) + off[:, None] * nrm, nrm, t * np.linalg.norm(b - a)


def params(**over) -> flow.FlowConfig:
    cfg = json.loads(json.dumps(CFG))
    cfg.update(over)
    return from_section(flow.FlowConfig, cfg, "flow")


def _run_one(c0, c2, xy, width=3.0, interest=None, **over):
    n = len(xy)
    d = np.full(n, 30.0) if interest is None else interest
    return flow.polyvector_flow(c0, c2, [xy], [np.full(n, width)], [d], params(**over))


def _line_distance(pts, a, nrm):
    return np.abs((np.asarray(pts) - a) @ nrm)


# ---------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------

def test_bilinear_matches_reference_and_its_derivative():
    from stages.geometry import bilinear

    rng = np.random.default_rng(1)
    c0 = rng.normal(size=(7, 9)) + 1j * rng.normal(size=(7, 9))
    c2 = rng.normal(size=(7, 9)) + 1j * rng.normal(size=(7, 9))
    xy = rng.uniform(-1.5, 10.5, size=(200, 2))
    v0, dx0, dy0 = flow.bilinear_with_gradient(c0, xy)
    v2, _, _ = flow.bilinear_with_gradient(c2, xy)
    r0, r2 = bilinear(c0, xy), bilinear(c2, xy)
    np.testing.assert_allclose(v0, r0, atol=1e-12)
    np.testing.assert_allclose(v2, r2, atol=1e-12)
    # Exact derivative of the interpolant (away from the cell borders where it jumps).
    frac = (xy - 0.5) % 1.0
    inner = np.all((frac > 0.01) & (frac < 0.99), axis=1)
    h = 1e-6
    fx = (flow.bilinear_with_gradient(c0, xy + [h, 0])[0] - flow.bilinear_with_gradient(c0, xy - [h, 0])[0]) / (2 * h)
    fy = (flow.bilinear_with_gradient(c0, xy + [0, h])[0] - flow.bilinear_with_gradient(c0, xy - [0, h])[0]) / (2 * h)
    np.testing.assert_allclose(dx0[inner], fx[inner], atol=1e-6)
    np.testing.assert_allclose(dy0[inner], fy[inner], atol=1e-6)


def test_step_scale_is_the_codes_rule():
    d = np.array([0.0, 1.0, 14.9, 15.0, 20.0, 100.0, 299.0, 300.0, 1000.0])
    code = np.where(d < 15, 2.0, np.maximum(0.1, 30.0 / np.maximum(d, 1e-300)))
    np.testing.assert_allclose(flow.step_scale(d, params()), code)


def test_discrete_gradient_is_the_derivative_of_the_reported_energy():
    """The kernel's forces are the exact gradient of the discrete Eq. 6a (with the barrier active)."""
    d = synthetic.cross()
    c0, c2, _ = analytic_field(d)
    a, b = d.strokes[0]
    xy0, nrm, _ = noisy_path(a, b, n=30, noise=0.4, seed=3)
    p = params()
    batch = flow.prepare_paths([xy0], [np.full(30, 3.0)], [np.full(30, 30.0)], p)
    rng = np.random.default_rng(4)
    z = batch.z + (rng.normal(size=len(batch.z)) + 1j * rng.normal(size=len(batch.z))) * 0.6
    z[[0, -1]] = batch.z[[0, -1]]
    fld = kernel._pack_field(c0, c2)
    cen = np.stack([batch.centres.real, batch.centres.imag], 1)
    grad = kernel._discrete_gradient(z, len(z), fld, batch.centres, batch.sigma, batch.rho2, 0, len(cen),
                                   batch.window[0], p.barrier.cutoff ** 2, p.lam, p.eps, batch.home.copy())

    def energy(zz):
        return flow.path_energy(c0, c2, np.stack([zz.real, zz.imag], 1), cen, batch.sigma, p.lam, p.eps,
                                p.barrier.cutoff)

    h = 1e-6
    fd = np.zeros(len(z), complex)
    for j in range(len(z)):
        for unit in (1, 1j):
            e = np.zeros(len(z), complex)
            e[j] = h * unit
            fd[j] += unit * (energy(z + e) - energy(z - e)) / (2 * h)
    assert np.abs(grad).max() > 1.0
    np.testing.assert_allclose(grad, fd, atol=1e-5 * np.abs(grad).max())


def test_safe_radius_guarantees_the_barrier_is_zero():
    xy = np.array([[5.0, 5.0], [15.0, 8.0], [22.0, 3.0]])
    p = params()
    batch = flow.prepare_paths([xy], [np.array([3.0, 6.0, 2.0])], [np.zeros(3)], p)
    cen = np.stack([batch.centres.real, batch.centres.imag], 1)
    assert np.all(batch.rho2 > 0)
    rng = np.random.default_rng(0)
    k = rng.integers(0, len(cen), 2000)
    ang = rng.uniform(0, 2 * np.pi, len(k))
    r = np.sqrt(batch.rho2[k]) * rng.uniform(0, 1, len(k)) ** 0.5
    pts = cen[k] + r[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    d2 = ((pts[:, None] - cen[None]) ** 2).sum(-1)
    s2 = batch.sigma[None] ** 2
    s = np.where(d2 < p.barrier.cutoff ** 2 * s2, np.exp(-0.5 * d2 / s2), 0).sum(1)
    assert s.min() >= 1.0


def test_barrier_centres_are_independent_of_input_density():
    """Eq. 5's S on the initial curve is ≈ √(2π)/spacing however densely the graph sampled the path."""
    a, b = np.array([5.0, 5.0]), np.array([45.0, 17.0])
    p = params()
    for n in (3, 41, 400):
        xy = a + np.linspace(0, 1, n)[:, None] * (b - a)
        batch = flow.prepare_paths([xy], [np.full(n, 3.0)], [np.zeros(n)], p)
        cen = np.stack([batch.centres.real, batch.centres.imag], 1)
        mid = 0.5 * (a + b)
        s = np.exp(-0.5 * ((cen - mid) ** 2).sum(1) / batch.sigma ** 2).sum()
        assert s == pytest.approx(np.sqrt(2 * np.pi) / p.barrier.spacing, rel=0.02)


# ---------------------------------------------------------------------------------------------
# Behaviour of the flow
# ---------------------------------------------------------------------------------------------

def test_flow_lowers_energy_keeps_endpoints_and_reports_eq6a():
    d = synthetic.line(angle=17)
    c0, c2, _ = analytic_field(d)
    a, b = d.strokes[0]
    xy0, nrm, s = noisy_path(a, b, noise=0.5, seed=1)
    res = _run_one(c0, c2, xy0, interest=np.minimum(s, s[-1] - s))
    cv = res.curves[0]
    assert res.energies[0] < 0.9 * res.energies_initial[0]
    np.testing.assert_array_equal(cv[0], xy0[0])
    np.testing.assert_array_equal(cv[-1], xy0[-1])
    # The reported energy is Eq. 6a of the returned curve (brute-force barrier over all centres).
    batch = flow.prepare_paths([xy0], [np.full(len(xy0), 3.0)], [np.zeros(len(xy0))], params())
    cen = np.stack([batch.centres.real, batch.centres.imag], 1)
    p = params()
    ref = flow.path_energy(c0, c2, cv, cen, batch.sigma, p.lam, p.eps, p.barrier.cutoff)
    assert res.energies[0] == pytest.approx(ref, rel=1e-9)
    assert res.failed[0] == 0


def test_energy_never_rises_along_the_flow():
    d = synthetic.vee()
    c0, c2, _ = analytic_field(d)
    s = d.strokes[0]
    xy0 = np.concatenate([s[0] + np.linspace(0, 1, 20)[:-1, None] * (s[1] - s[0]),
                          s[1] + np.linspace(0, 1, 20)[:, None] * (s[2] - s[1])])
    xy0 = xy0 + np.random.default_rng(2).normal(0, 0.4, xy0.shape) * [[0], *[[1]] * (len(xy0) - 2), [0]]
    energies = [_run_one(c0, c2, xy0, iterations=k).energies[0] for k in (0, 5, 20, 100, 400)]
    assert all(e1 <= e0 + 1e-9 for e0, e1 in zip(energies, energies[1:]))


def test_noisy_path_on_17_degree_stroke_ends_within_1px_of_centre_line():
    d = synthetic.line(angle=17)
    c0, c2, _ = analytic_field(d)
    a, b = d.strokes[0]
    xy0, nrm, s = noisy_path(a, b, noise=0.5, seed=7)
    assert _line_distance(xy0, a, nrm).max() > 1.0
    res = _run_one(c0, c2, xy0, interest=np.minimum(s, s[-1] - s))
    dev = _line_distance(res.curves[0], a, nrm)
    assert dev.max() < 1.0
    assert np.sqrt((dev ** 2).mean()) < 0.6 * np.sqrt((_line_distance(xy0, a, nrm) ** 2).mean())


def test_straight_path_through_an_x_stays_straight():
    """At an X the two-root field keeps a path on its own branch (not pulled into the other)."""
    d = synthetic.cross(angle1=10, angle2=70)
    c0, c2, _ = analytic_field(d)
    for k in range(2):
        a, b = d.strokes[k]
        xy0, nrm, s = noisy_path(a, b, noise=0.3, seed=k)
        centre = 0.5 * (a + b)
        res = _run_one(c0, c2, xy0, interest=np.minimum(np.abs(s - s[-1] / 2), np.minimum(s, s[-1] - s)))
        cv = res.curves[0]
        assert _line_distance(cv, a, nrm).max() < 0.5
        near = np.hypot(*(cv - centre).T) < 6
        assert near.sum() > 10 and _line_distance(cv[near], a, nrm).max() < 0.35


def test_many_paths_flow_together_like_one_at_a_time():
    d = synthetic.cross()
    c0, c2, _ = analytic_field(d)
    paths = [noisy_path(*d.strokes[k % 2], noise=0.3, seed=k)[0] for k in range(5)]
    p = params(iterations=200)
    one = [flow.polyvector_flow(c0, c2, [xy], [np.full(len(xy), 3.0)], [np.full(len(xy), 20.0)], p).curves[0]
           for xy in paths]
    together = flow.polyvector_flow(c0, c2, paths, [np.full(len(xy), 3.0) for xy in paths],
                                    [np.full(len(xy), 20.0) for xy in paths], p).curves
    for c1, c2_ in zip(one, together):
        np.testing.assert_allclose(c1, c2_, atol=1e-12)


def test_a_subset_of_the_paths_flows_bit_identically_to_all_of_them():
    """The premise of the engine's per-path memo: a path's result does not depend on the other paths
    (their number, order or position in the packed arrays), to the last bit."""
    d = synthetic.cross()
    c0, c2, _ = analytic_field(d)
    rng = np.random.default_rng(1)
    paths = []
    for k in range(9):
        a, b = (np.asarray(e, float) + rng.normal(0, 1, 2) for e in d.strokes[k % 2])
        paths.append(noisy_path(a, b, n=12 + 9 * k, noise=0.3, seed=k)[0])
    paths.append(np.array([[20.0, 20.0]]))                          # a one-point path among them
    widths = [np.full(len(xy), 2.0 + 0.3 * k) for k, xy in enumerate(paths)]
    interest = [np.linspace(0.5, 45.0, len(xy)) for xy in paths]
    p = params(iterations=120)
    full = flow.polyvector_flow(c0, c2, paths, widths, interest, p)
    sub = [7, 2, 9, 4]
    part = flow.polyvector_flow(c0, c2, [paths[i] for i in sub], [widths[i] for i in sub],
                                [interest[i] for i in sub], p)
    for j, i in enumerate(sub):
        np.testing.assert_array_equal(part.curves[j], full.curves[i])
        for name in ("energies", "energies_initial", "resamples", "rejected", "failed"):
            assert getattr(part, name)[j] == getattr(full, name)[i], name
    # The stage's per-item entry points give run's artifact, byte for byte, from items flowed apart.
    extension = Artifact(arrays={"c0_ext": c0, "c2_ext": c2})
    topo = _topology_artifact(paths[:-1])
    inputs = dict(prep=Artifact(data={"height": 64, "width": 64}), extension=extension, graph=Artifact(), topology=topo)
    cfg = dict(CFG, iterations=120)
    whole = flow.run(cfg, **inputs)
    plan = flow.plan_items(cfg, **inputs)
    results = [None] * len(plan.items)
    for chunk in ([5, 0], [8, 1, 3], [2, 4, 6, 7]):
        for i, r in zip(chunk, flow.run_items(plan, chunk)):
            results[i] = r
    pieced = flow.assemble(plan, results)
    assert pieced.data == whole.data
    for name, a in whole.arrays.items():
        assert pieced.arrays[name].dtype == a.dtype and pieced.arrays[name].tobytes() == a.tobytes()


def test_paths_shared_between_threads_flow_bit_identically_to_one_thread():
    """The flow's threads each run the kernel on their own share of the paths (the kernel releases
    the GIL): any thread count gives the same curves and energies, to the last bit."""
    import numba

    d = synthetic.cross()
    c0, c2, _ = analytic_field(d)
    paths = [noisy_path(*d.strokes[k % 2], n=10 + 7 * k, noise=0.3, seed=k)[0] for k in range(7)]
    widths = [np.full(len(xy), 3.0) for xy in paths]
    interest = [np.linspace(1.0, 30.0, len(xy)) for xy in paths]
    p = params(iterations=150)
    before = numba.get_num_threads()
    runs = []
    try:
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(threads)
            runs.append(flow.polyvector_flow(c0, c2, paths, widths, interest, p))
    finally:
        numba.set_num_threads(before)
    for other in runs[1:]:
        for a, b in zip(runs[0].curves, other.curves):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(runs[0].energies, other.energies)
        np.testing.assert_array_equal(runs[0].rejected, other.rejected)


def test_split_paths_shares_every_path_once_longest_first_and_evenly():
    from stages.flow.stage import split_paths

    sizes = np.array([5, 400, 30, 30, 250, 8, 120, 90, 3])
    shares = split_paths(sizes, 3)
    assert len(shares) == 3
    assert sorted(np.concatenate(shares).tolist()) == list(range(len(sizes)))
    for share in shares:
        assert np.all(np.diff(sizes[share]) <= 0)                  # longest first within a share
    loads = [int(sizes[share].sum()) for share in shares]
    assert max(loads) - min(loads) <= sizes.max()                 # greedy: within one path of even
    assert [s.tolist() for s in split_paths(sizes, 1)] == [np.argsort(-sizes, kind="stable").tolist()]
    assert len(split_paths(sizes[:2], 8)) == 2                     # never more shares than paths


def test_degenerate_paths_are_returned_unchanged():
    c0 = np.zeros((20, 20), complex)
    res = flow.polyvector_flow(c0, c0, [np.array([[3.0, 4.0]]), np.array([[3.0, 4.0], [3.0, 4.0]]),
                                        np.array([[3.0, 4.0], [6.0, 4.0]])],
                               [np.ones(1), np.ones(2), np.ones(2)], [np.zeros(1), np.zeros(2), np.zeros(2)],
                               params(spacing=5.0))
    assert [len(c) for c in res.curves] == [2, 2, 2]
    np.testing.assert_allclose(res.curves[2], [[3, 4], [6, 4]])
    assert np.all(np.isfinite(res.energies))


# ---------------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------------

def _topology_artifact(paths_xy, width=3.0):
    paths = []
    for k, xy in enumerate(paths_xy):
        xy = np.asarray(xy, float)
        s = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        paths.append({"id": k, "component": 0, "vertices": list(range(len(xy))), "xy": xy.tolist(),
                      "widths": [width] * len(xy), "interest_dist": np.minimum(s, s[-1] - s).tolist(),
                      "end_types": [1, 1], "end_keypoints": [2 * k, 2 * k + 1]})
    return Artifact(data={"paths": paths})


def test_run_follows_the_artifact_contract():
    d = synthetic.cross()
    c0, c2, mask = analytic_field(d)
    paths = [noisy_path(*d.strokes[k], noise=0.3, seed=k)[0] for k in range(2)]
    art = flow.run(CFG, prep=Artifact(arrays={"mask": mask}, data={"height": 64, "width": 64}),
                   extension=Artifact(arrays={"c0_ext": c0.astype(np.complex64), "c2_ext": c2.astype(np.complex64)}),
                   graph=Artifact(), topology=_topology_artifact(paths))
    curves = unpack_ragged(art["curve_xy"], art["curve_xy_offsets"])
    assert art["curve_xy"].dtype == np.float64 and art["curve_xy"].shape[1] == 2
    assert len(curves) == 2 and len(art.data["energies"]) == 2 and len(art.data["energies_initial"]) == 2
    for c, xy in zip(curves, paths):
        np.testing.assert_allclose([c[0], c[-1]], [xy[0], xy[-1]])
    assert art.data["failed"] == []
    json.dumps(art.data)


def test_run_with_no_paths_and_bad_input():
    extension = Artifact(arrays={"c0_ext": np.zeros((8, 8), np.complex64), "c2_ext": np.zeros((8, 8), np.complex64)})
    prep = Artifact(data={"height": 8, "width": 8})
    art = flow.run(CFG, prep=prep, extension=extension, graph=Artifact(), topology=Artifact(data={"paths": []}))
    assert len(art["curve_xy_offsets"]) == 1 and art.data["energies"] == []
    bad = _topology_artifact([[[1, 1], [5, 5]]])
    bad.data["paths"][0]["widths"] = [3.0]
    with pytest.raises(InputError):
        flow.run(CFG, prep=prep, extension=extension, graph=Artifact(), topology=bad)
    nan = _topology_artifact([[[1, 1], [np.nan, 5]]])
    with pytest.raises(InputError):
        flow.run(CFG, prep=prep, extension=extension, graph=Artifact(), topology=nan)
    with pytest.raises(InputError):
        flow.run({k: v for k, v in CFG.items() if k != "lam"}, prep=prep, extension=extension, graph=Artifact(),
                 topology=_topology_artifact([]))
    with pytest.raises(InputError):
        flow.run(CFG, prep=prep, graph=Artifact(), topology=_topology_artifact([]))


def test_flowed_topology_paths_stay_in_the_strokes_with_the_real_field():
    """prep → field (real) + synthetic graph → topology → flow on a T: every curve stays on its stroke."""
    pytest.importorskip("stages.topology")
    from synthetic_graph import synthetic_inputs

    from stages import extension as extension_stage
    from stages import field as field_stage
    from stages import prep as prep_stage
    from stages import topology

    d = synthetic.tee()
    cfg = lambda name: yaml.safe_load((ROOT / "conf" / name / "default.yaml").read_text())  # noqa: E731
    P = prep_stage.run(cfg("prep"), image_bytes=d.png_bytes(), image_name="tee")
    F = field_stage.run(cfg("field"), prep=P)
    E = extension_stage.run(cfg("extension"), prep=P, field=F)
    syn = synthetic_inputs(d)
    T = topology.run(cfg("topology"), prep=P, field=F, graph=syn["graph"], keypoints=syn["keypoints"])
    art = flow.run(CFG, prep=P, extension=E, graph=syn["graph"], topology=T)
    curves = unpack_ragged(art["curve_xy"], art["curve_xy_offsets"])
    assert len(curves) == len(T.data["paths"]) > 0
    dist = np.min([synthetic.distance_to_polyline(P["mask"].shape, s) for s in d.strokes], axis=0)
    for c in curves:
        ij = np.clip(np.floor(c[:, ::-1]).astype(int), 0, 63)
        assert dist[ij[:, 0], ij[:, 1]].max() < d.width / 2 + 1.0
    assert all(e1 <= e0 + 1e-9 for e0, e1 in zip(art.data["energies_initial"], art.data["energies"]))


def _real_field(drawing):
    from stages import extension as extension_stage
    from stages import field as field_stage
    from stages import prep as prep_stage

    cfg = lambda name: yaml.safe_load((ROOT / "conf" / name / "default.yaml").read_text())  # noqa: E731
    p = prep_stage.run(cfg("prep"), image_bytes=drawing.png_bytes(), image_name="synthetic")
    e = extension_stage.run(cfg("extension"), prep=p, field=field_stage.run(cfg("field"), prep=p))
    return e["c0_ext"], e["c2_ext"]


def test_with_the_real_field_a_noisy_17_degree_path_is_centred():
    d = synthetic.line(angle=17)
    c0, c2 = _real_field(d)
    a, b = d.strokes[0]
    for seed in range(2):
        xy0, nrm, s = noisy_path(a, b, noise=0.5, seed=seed)
        res = _run_one(c0, c2, xy0, interest=np.minimum(s, s[-1] - s))
        assert _line_distance(res.curves[0], a, nrm).max() < 0.5
        assert res.energies[0] < res.energies_initial[0]


def test_with_the_real_field_a_path_through_an_x_stays_on_its_branch():
    d = synthetic.cross(angle1=10, angle2=70)
    c0, c2 = _real_field(d)
    for k in range(2):
        a, b = d.strokes[k]
        xy0, nrm, s = noisy_path(a, b, noise=0.3, seed=k)
        res = _run_one(c0, c2, xy0, interest=np.minimum(np.abs(s - s[-1] / 2), np.minimum(s, s[-1] - s)))
        assert _line_distance(res.curves[0], a, nrm).max() < 0.5


def test_a_sweeps_next_job_reuses_the_prepared_paths_and_flows_the_same(monkeypatch):
    """The paths prepared for one flow are reused by the next with the same paths and preparation
    settings (a λ sweep's next job); the kernel flows its own copy of the vertices, so the first job's
    settings flowed again give the first job's curves bit for bit. Another spacing prepares anew."""
    from dataclasses import replace

    from stages.flow import paths

    d = synthetic.cross()
    c0, c2, _ = analytic_field(d)
    xys = [noisy_path(a, b, n=30, noise=0.4, seed=k)[0] for k, (a, b) in enumerate(d.strokes)]
    widths, interest = [np.full(30, 3.0)] * len(xys), [np.full(30, 30.0)] * len(xys)
    prepared = []
    original = paths._prepare_all
    monkeypatch.setattr(paths, "_prepare_all", lambda *a: prepared.append(1) or original(*a))
    paths._PREPARED.clear()
    p = params()
    first = flow.polyvector_flow(c0, c2, xys, widths, interest, p)
    other = flow.polyvector_flow(c0, c2, xys, widths, interest, replace(p, lam=p.lam * 4))
    again = flow.polyvector_flow(c0, c2, xys, widths, interest, p)
    assert len(prepared) == 1
    assert all(np.array_equal(a, b) for a, b in zip(first.curves, again.curves))
    assert not all(np.array_equal(a, b) for a, b in zip(first.curves, other.curves))
    flow.polyvector_flow(c0, c2, xys, widths, interest, replace(p, spacing=p.spacing * 1.5))
    assert len(prepared) == 2 and len(paths._PREPARED) == paths.PREPARED_BATCHES
