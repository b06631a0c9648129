"""The graph's raw vertices and edges: the Python side of the cross-sections (paper §4.1, Fig. 7).

:func:`build_cross_sections` prepares the field and the traced streamlines for the numba kernel
:func:`stages.graph.cross_section._build_sections`, which takes the cross-sections (the vertices; the
module :mod:`stages.graph.cross_section` describes how, and why so), and joins the vertices that follow
each other along a streamline into edges (:func:`streamline_edges`); :class:`RawGraph` holds both for
the clean-up.  This code is kept out of the kernel module: the package ships that module's kernels
compiled, checked against the sha256 of its source, so an edit here does not make them stale.

**Edges** join vertices consecutive along a streamline (sorted by the crossing parameter on it); the
edge keeps the id of (one) streamline it came from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stages.graph.cross_section import _build_sections
from stages.graph.trace import field_on_band


@dataclass
class RawGraph:
    """Cross-section vertices and streamline edges before the clean-up.

    Attributes
    ----------
    xy : numpy.ndarray
        float64 (V, 2) vertex positions (x, y).
    width : numpy.ndarray
        float64 (V,) raw widths (cross-section diameter + one lane spacing).
    root : numpy.ndarray
        complex128 (V,) unit root followed by the cross-section.
    flags : numpy.ndarray
        uint8 (V,), bit 0 = next to singularity.
    member_vertex, member_curve, member_param : numpy.ndarray
        One row per crossing kept in a vertex: vertex id, streamline id, fractional sample index on it.
    edges : numpy.ndarray
        int64 (E, 2) with i < j; ``edge_curve`` int64 (E,) the streamline of each edge.
    n_failed : int
        Stations where no cross-section could be taken (singular or ambiguous roots).
    member_order : numpy.ndarray
        The crossings ordered by streamline, then parameter (:func:`member_order`), sorted once for
        every later walk along the streamlines (millions of rows on a large scan).
    """

    xy: np.ndarray
    width: np.ndarray
    root: np.ndarray
    flags: np.ndarray
    member_vertex: np.ndarray
    member_curve: np.ndarray
    member_param: np.ndarray
    edges: np.ndarray
    edge_curve: np.ndarray
    n_failed: int
    member_order: np.ndarray


def member_order(member_curve: np.ndarray, member_param: np.ndarray) -> np.ndarray:
    """Crossings sorted by streamline id, then by parameter along it (a stable ``lexsort``).

    Parameters
    ----------
    member_curve, member_param : numpy.ndarray
        Crossings: streamline id, parameter (fractional sample index) on the streamline.

    Returns
    -------
    numpy.ndarray
        int64 permutation of the crossings.
    """
    n = len(member_curve)
    if n < 2:
        return np.lexsort((member_param, member_curve))
    # one float64 key (streamline · span + parameter, the parameters being < span) sorted once instead of
    # lexsort's two stable passes: on a page's millions of crossings lexsort cost more than the ink grew
    # (stages/DECISIONS.md, graph).  The key can round distinct neighbours together, and an unstable
    # sort orders equal keys at will, so the order is checked to be lexsort's — the one permutation
    # along which (streamline, parameter, index) strictly increases — and lexsort runs where it is not.
    curve = np.asarray(member_curve)
    param = np.asarray(member_param, np.float64)
    span = np.floor(param.max()) + 1.0
    order = np.argsort(curve * span + param)
    c, p = curve[order], param[order]
    dc, dp = c[1:] - c[:-1], p[1:] - p[:-1]
    if np.all((dc > 0) | ((dc == 0) & ((dp > 0) | ((dp == 0) & (order[1:] > order[:-1]))))):
        return order
    return np.lexsort((member_param, member_curve))


def streamline_edges(member_vertex: np.ndarray, member_curve: np.ndarray,
                     member_param: np.ndarray, order: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Edges between vertices consecutive along a streamline.

    Parameters
    ----------
    member_vertex, member_curve, member_param : numpy.ndarray
        Crossings: vertex id, streamline id, parameter (fractional sample index) on the streamline.
    order : numpy.ndarray, optional
        :func:`member_order` of ``member_curve, member_param`` when already computed.

    Returns
    -------
    edges : numpy.ndarray
        int64 (E, 2), ``i < j``, unique.
    edge_curve : numpy.ndarray
        int64 (E,) a streamline id that produced each edge (the lowest).
    """
    if order is None:
        order = member_order(member_curve, member_param)
    # each temporary is dropped once read: on a page's millions of crossings these sorts were the
    # graph's peak (stages/DECISIONS.md, graph)
    v = member_vertex[order]
    c = member_curve[order]
    link = c[1:] == c[:-1]
    link &= v[1:] != v[:-1]
    a, b, cc = v[:-1][link], v[1:][link], c[:-1][link]
    del v, c, link
    if len(a) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    lo = np.minimum(a, b)
    hi = np.maximum(a, b, out=b)
    del a
    # unique edges, keeping the lowest streamline id: `cc` is already ascending (the crossings are in
    # streamline order), so a stable sort by the edge alone keeps it ascending within each edge (the
    # same permutation as lexsort((cc, e1, e0)), at one int64 key instead of three; the key is one to
    # one with the edge, so equal keys are equal edges)
    key = lo.astype(np.int64) * (int(hi.max()) + 1) + hi
    o = np.argsort(key, kind="stable")
    key = key[o]
    first = np.ones(len(o), bool)
    first[1:] = key[1:] != key[:-1]
    del key
    o = o[first]
    return np.stack([lo[o], hi[o]], axis=1).astype(np.int64), cc[o].astype(np.int64)


def build_cross_sections(c0: np.ndarray, c2: np.ndarray, band: np.ndarray, singular: np.ndarray, lines,
                         **params: float) -> RawGraph:
    """Cross-section vertices along the streamlines and the edges between them: :func:`raw_graph` of
    :func:`take_cross_sections` (arguments as there)."""
    return raw_graph(take_cross_sections(c0, c2, band, singular, lines, **params))


def take_cross_sections(c0: np.ndarray, c2: np.ndarray, band: np.ndarray, singular: np.ndarray, lines,
                        *, step: float, station_spacing: float, cover_factor: float, min_station_gap: float,
                        max_gap: float, max_section_length: float, ambiguity: float, tie: float,
                        lane_pad: float) -> tuple:
    """The cross-sections' kernel alone: vertices across the streamlines and the crossings, no edges.

    Its outputs read nothing of ``lines`` any more, so a caller may drop the samples before
    :func:`raw_graph` sorts the crossings (a page's samples and those sorts were the graph's peak together).

    Parameters
    ----------
    c0, c2, band, singular : numpy.ndarray
        The field (complex (H, W); read as 0 off the band, :func:`stages.graph.trace.field_on_band`),
        the band and the singular pixels.
    lines : stages.graph.trace.Streamlines
        The traced curves with their pixel lookup.
    step : float
        Step of the cross-section traces (px), the tracing step.
    station_spacing : float
        Target distance between consecutive cross-sections along a streamline (px).
    cover_factor : float
        A crossing covers its streamline ± ``cover_factor · station_spacing``.
    min_station_gap : float
        Uncovered stretches shorter than this (px) between covered ones get no cross-section.
    max_gap : float
        Largest gap between consecutive crossings inside one cross-section (px; reference 1).
    max_section_length : float
        Cap on each half of a cross-section (px).
    ambiguity : float
        No cross-section where the two roots are equally aligned with the streamline
        (``||cos u| − |cos v|| < ambiguity``; reference 0.1).
    tie : float
        Root-choice tie margin.
    lane_pad : float
        Width = diameter + ``lane_pad`` × lane spacing (see :mod:`stages.graph.cross_section`).

    Returns
    -------
    tuple
        The kernel's outputs, for :func:`raw_graph`.
    """
    band = np.ascontiguousarray(band, dtype=np.bool_)
    c0 = field_on_band(c0, band)
    c2 = field_on_band(c2, band)
    sx = np.ascontiguousarray(lines.xy[:, 0])
    sy = np.ascontiguousarray(lines.xy[:, 1])
    tx = np.ascontiguousarray(lines.tangent[:, 0])
    ty = np.ascontiguousarray(lines.tangent[:, 1])
    order = np.argsort(-lines.length, kind="stable").astype(np.int64)
    spacing = max(2, int(round(station_spacing / step)))
    return _build_sections(
        c0, c2, band, np.ascontiguousarray(singular, dtype=np.bool_), sx, sy, tx, ty, lines.start, lines.length,
        order, float(step), spacing,
        float(cover_factor * station_spacing / step), max(1, int(round(min_station_gap / step))),
        float(max_gap), max(1, int(math.ceil(max_section_length / step))), float(ambiguity), float(tie),
        float(lane_pad))


def raw_graph(sections: tuple) -> RawGraph:
    """The raw graph of the cross-sections' kernel outputs (:func:`take_cross_sections`): the crossings
    sorted along the streamlines (:func:`member_order`) and the edges between consecutive ones.

    Parameters
    ----------
    sections : tuple
        :func:`take_cross_sections`' outputs.

    Returns
    -------
    RawGraph
    """
    xy, width, root, flags, _seed, mv, mc, mp, n_fail = sections
    # the kernel keeps its vertex and curve ids as int32 (its peak, beside the samples); int64 from here
    mv, mc = mv.astype(np.int64), mc.astype(np.int64)
    order = member_order(mc, mp)
    edges, ecurve = streamline_edges(mv, mc, mp, order)
    return RawGraph(xy=xy, width=width, root=root, flags=flags, member_vertex=mv, member_curve=mc,
                    member_param=mp, edges=edges, edge_curve=ecurve, n_failed=int(n_fail), member_order=order)
