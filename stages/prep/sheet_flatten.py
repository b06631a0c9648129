"""A photographed sheet seen whole, flattened: its four corners found, mapped onto a rectangle.

Used by :func:`~stages.prep.sheet.photographed_sheet` when no cell of the sheet is on the photo's border
(``crop.sheet_flatten``): the corners to under a pixel (:func:`sheet_corners`), the rectangle's
proportions from the camera's focal length (:func:`sheet_aspect`), and the sheet warped through the
corners' homography onto it (:func:`flattened`).

Choices made on purpose
-----------------------
* **A photographed sheet seen whole is flattened** (``crop.sheet_flatten``; not in the references).
  When no cell of the sheet is on the photo's border and its edge is four straight sides, its corners
  are found to under a pixel (lines through the edge's sub-pixel points, each the one most of its side's
  points lie on), and the sheet is mapped through their homography onto a rectangle of its proportions
  (the focal length from EXIF, else from the sides' vanishing points, else a phone's); the drawing is
  that rectangle, upright, and the curves are in its pixels, not the photo's.  Why: a sketch
  photographed at an angle came out in perspective and turned, which no artist wants to edit; on 24
  validation drawings photographed leaning 10-40° back, flattened output scores better than the
  photo-frame output even when that is un-warped with the true camera (stages/DECISIONS.md).  Choice:
  the SVG is the flattened sheet's, not mapped back to the photo (scanner apps do the same), so that the
  drawing's right angles and proportions are kept; ``sheet_flatten=false`` keeps the photo's pixels.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.prep.pixels import blocks, smoothed

#: A sheet seen whole is flattened when its edge is four straight sides: at least this share of the edge's
#: points lie within :data:`SHEET_SIDE_TOLERANCE` of them (a torn or curled sheet is cut out as it is) ...
SHEET_MIN_ON_SIDES = 0.9
#: ... px, or 0.5 % of the sheet's diagonal when larger (the edge is found on the grey smoothed by 1.5 px).
SHEET_SIDE_TOLERANCE = 2.0
#: ... and its corners' angles lie within this many degrees of a right angle (a phone held at up to ~40°).
SHEET_MAX_SKEW = 40.0
#: A flattened sheet's proportions need the camera's focal length, in the photo's longer sides: one found
#: from the sheet's corners outside this range is not trusted (vanishing points nearly at infinity) ...
SHEET_FOCAL_RANGE = (0.3, 5.0)
#: ... and this one is taken instead: a phone's main camera (24-28 mm equivalent on a 4:3 sensor: 0.7-0.8).
SHEET_ASSUMED_FOCAL = 0.75
#: mm: the diagonal of 35-mm film, which an EXIF focal length "in 35-mm film" is relative to.
FILM_35MM_DIAGONAL = 43.27
#: At most this many of the edge's hull vertices are searched for its largest quadrilateral (O(n³): 14 MB).
SHEET_HULL_MAX = 120
#: Lines tried through two of a side's edge points; the one most of them lie on (within 1 px) is fitted.
SHEET_LINE_TRIES = 256
#: px of the flattened sheet's rim left out of the work (its shadowed edge; its corners are found to ~1 px).
SHEET_RIM_PX = 8


def sheet_corners(grey: np.ndarray, sheet: np.ndarray, cell: int, level: float
                  ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
    """The four corners (x, y) of a photographed sheet seen whole, float64 (4, 2), top-left, top-right,
    bottom-right, bottom-left, with the sheet's pixels (bool, a box of the photo) and that box's corner
    (x, y); None when its edge is not four straight sides.

    ``sheet`` is its cells (:func:`~stages.prep.sheet.photographed_sheet`), ``level`` the grey halfway
    between the paper and the ground.  On the grey round the sheet smoothed by 1.5 px, the sheet is the
    region brighter than ``level``, within a cell of its cells, that holds its inner cells (holes filled);
    its edge's points are where the grey crosses ``level`` between two neighbours (sub-pixel).  The largest
    quadrilateral on the points' convex hull gives the four sides; each side's line is then the one through
    two of the points near its middle 80 % that most of them lie on (within 1 px; :data:`SHEET_LINE_TRIES`),
    fitted to those (total least squares), and the corners are where the lines meet.
    The sheet is flattened only when :data:`SHEET_MIN_ON_SIDES` of the edge lies on the sides and the
    corners are within :data:`SHEET_MAX_SKEW` of square.

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) the photograph's grey, 1 = white.
    sheet : numpy.ndarray
        bool (H // cell, W // cell): the sheet's cells, none on the image's border.
    cell : int
        Side of the cells in pixels.
    level : float
        The grey halfway between the paper and the ground.

    Returns
    -------
    tuple or None
        ``(corners, region, corner)``: float64 (4, 2) corners (x, y) in the photo; bool the sheet's pixels
        in a box of the photo; (x, y) of that box's corner.  None when the edge is not four straight sides
        at about right angles.
    """
    from scipy.spatial import ConvexHull, QhullError

    # The sheet's cells and one more all round (none of them off the image: the sheet is seen whole).
    rows, cols = np.flatnonzero(sheet.any(axis=1)), np.flatnonzero(sheet.any(axis=0))
    window = np.s_[rows[0] - 1:rows[-1] + 2, cols[0] - 1:cols[-1] + 2]
    y0, y1, x0, x1 = (rows[0] - 1) * cell, (rows[-1] + 2) * cell, (cols[0] - 1) * cell, (cols[-1] + 2) * cell
    g = smoothed(grey[y0:y1, x0:x1].astype(np.float32), 1.5)
    # Within a cell of the sheet's cells: a lighter desk's bright patches beyond are not the sheet.
    above = (g > level) & blocks(ndimage.binary_dilation(sheet, structure=np.ones((3, 3)))[window], cell, cell)
    labels, n = ndimage.label(above)
    inner = blocks(ndimage.binary_erosion(sheet, structure=np.ones((3, 3)))[window], cell, cell)
    held = np.bincount(labels[inner & above], minlength=n + 1)
    held[0] = 0
    if held.max() == 0:
        return None
    region = ndimage.binary_fill_holes(labels == np.argmax(held))
    # Sub-pixel edge points: between a pixel of the region and its neighbour off it, where the grey
    # crosses the level (linearly).
    points = []
    for axis, step in ((0, 1), (0, -1), (1, 1), (1, -1)):
        here, there = [slice(None), slice(None)], [slice(None), slice(None)]
        here[axis], there[axis] = ((slice(None, -1), slice(1, None)) if step == 1
                                   else (slice(1, None), slice(None, -1)))
        here, there = tuple(here), tuple(there)
        edge = region[here] & ~region[there]
        ga, gb = g[here][edge], g[there][edge]
        yy, xx = np.nonzero(edge)
        if step == -1:
            yy, xx = (yy + 1, xx) if axis == 0 else (yy, xx + 1)
        t = step * np.clip((ga - level) / np.maximum(ga - gb, 1e-6), 0.0, 1.0)
        points.append(np.c_[xx + (t if axis == 1 else 0), yy + (t if axis == 0 else 0)])
    points = np.concatenate(points) + [x0, y0]
    try:
        hull = points[ConvexHull(points).vertices]
    except QhullError:
        return None
    if len(hull) > SHEET_HULL_MAX:     # the largest quadrilateral is found among these in O(n³)
        hull = hull[np.linspace(0, len(hull), SHEET_HULL_MAX, endpoint=False).astype(int)]
    # The largest quadrilateral with corners on the hull: for each diagonal (i, k), the farthest vertex
    # on either side of it.
    d = hull[None] - hull[:, None]                                # d[i, k] = hull[k] − hull[i]
    cross = d[:, :, None, 0] * d[:, None, :, 1] - d[:, :, None, 1] * d[:, None, :, 0]
    i, k = np.unravel_index(np.argmax(cross.max(axis=2) - cross.min(axis=2)), cross.shape[:2])
    quad = hull[[i, np.argmax(cross[i, k]), k, np.argmin(cross[i, k])]]
    diagonal = float(np.hypot(x1 - x0, y1 - y0))
    tolerance = max(SHEET_SIDE_TOLERANCE, 0.005 * diagonal)
    lines = []
    rng = np.random.default_rng(0)      # the same corners for the same photo
    for side in range(4):
        a, b = quad[side], quad[(side + 1) % 4]
        length = float(np.hypot(*(b - a)))
        if length < 4 * cell:
            return None
        u = (b - a) / length
        along, off = (points - a) @ u / length, np.abs((points - a) @ np.array([-u[1], u[0]]))
        near = points[(along > 0.1) & (along < 0.9) & (off < max(4 * tolerance, 0.2 * length))]
        if len(near) < 2 * cell:
            return None
        # The line through two of them that most of them lie on (a torn corner or a finger on the edge
        # bends the hull's quadrilateral there: a least-squares start would follow it) ...
        pairs = rng.integers(0, len(near), (SHEET_LINE_TRIES, 2))
        along_pair = near[pairs[:, 1]] - near[pairs[:, 0]]
        normal = (np.c_[-along_pair[:, 1], along_pair[:, 0]]
                  / np.maximum(np.hypot(along_pair[:, 0], along_pair[:, 1]), 1e-9)[:, None])
        on = np.abs(((near[None] - near[pairs[:, 0]][:, None]) * normal[:, None]).sum(axis=2)) <= 1.0
        near = near[on[np.argmax(on.sum(axis=1))]]
        # ... then fitted to them (total least squares).
        centre = near.mean(axis=0)
        normal = np.linalg.svd(near - centre, full_matrices=False)[2][1]
        lines.append((normal, float(normal @ centre)))
    corners = np.array([np.linalg.solve(np.array([lines[s - 1][0], lines[s][0]]), [lines[s - 1][1], lines[s][1]])
                        for s in range(4)])
    # Distance of every edge point to the nearest side.
    dist = np.full(len(points), np.inf)
    for s in range(4):
        a, b = corners[s], corners[(s + 1) % 4]
        t = np.clip((points - a) @ (b - a) / float((b - a) @ (b - a)), 0.0, 1.0)
        dist = np.minimum(dist, np.hypot(*(points - a - t[:, None] * (b - a)).T))
    if np.mean(dist <= tolerance) < SHEET_MIN_ON_SIDES:
        return None
    sides = np.roll(corners, -1, axis=0) - corners
    cosines = [float(-sides[s - 1] @ sides[s]) / (np.hypot(*sides[s - 1]) * np.hypot(*sides[s])) for s in range(4)]
    if max(abs(np.degrees(np.arcsin(np.clip(cos, -1, 1)))) for cos in cosines) > SHEET_MAX_SKEW:
        return None
    # Top-left first, going round as the photo's top left → top right: the order whose first side points
    # most nearly along +x.
    if sides[0, 0] * sides[1, 1] - sides[0, 1] * sides[1, 0] < 0:
        corners = corners[::-1]
        sides = np.roll(corners, -1, axis=0) - corners
    first = int(np.argmax(sides[:, 0] / np.hypot(sides[:, 0], sides[:, 1])))
    return np.roll(corners, -first, axis=0), region, (int(x0), int(y0))


def flattened(grey: np.ndarray, corners: np.ndarray, region: np.ndarray, corner: tuple[int, int], rim: int,
              focal_35mm: float | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """The sheet whose ``corners`` (top-left, top-right, bottom-right, bottom-left; (x, y) in the photo)
    are given, mapped onto a rectangle of the sheet's proportions (:func:`sheet_aspect`) and of the
    quadrilateral's area (bilinear, through the homography of the four corners), less ``rim`` px all
    round; and the rectangle's (height, width).  The corners are the rectangle's outer pixel corners.
    What lies off the sheet's pixels ``region`` (a box of the photo at ``corner``) inside the rectangle
    (a torn or folded corner, a finger on the edge) takes the grey of the nearest pixel on it.
    ``focal_35mm``: the photo's EXIF focal length (:func:`sheet_aspect`).

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) the photograph's grey, 1 = white.
    corners : numpy.ndarray
        float64 (4, 2) the sheet's corners (x, y) in the photo (:func:`sheet_corners`).
    region : numpy.ndarray
        bool: the sheet's pixels in a box of the photo.
    corner : tuple of int
        (x, y) of that box's corner in the photo.
    rim : int
        Pixels of the rectangle left out all round (:data:`SHEET_RIM_PX`).
    focal_35mm : float or None
        EXIF focal length in 35-mm film terms, mm.

    Returns
    -------
    flat : numpy.ndarray
        (height − 2·rim, width − 2·rim), the dtype of ``grey``: the flattened sheet less its rim.
    shape : tuple of int
        The whole rectangle's (height, width): the drawing's size.
    """
    from skimage.transform import ProjectiveTransform, warp

    aspect = sheet_aspect(corners, grey.shape, focal_35mm)
    xs, ys = corners.T
    area = 0.5 * abs(float(xs @ np.roll(ys, -1) - ys @ np.roll(xs, -1)))
    height = int(round(np.sqrt(area / aspect)))
    width = int(round(height * aspect))
    rect = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64) - 0.5
    # The homography from the rectangle to the photo (8 unknowns, 4 point pairs).
    rows = []
    for (u, v), (x, y) in zip(rect, corners):
        rows += [[u, v, 1, 0, 0, 0, -u * x, -v * x], [0, 0, 0, u, v, 1, -u * y, -v * y]]
    hom = np.append(np.linalg.solve(np.array(rows), corners.ravel()), 1.0).reshape(3, 3)
    # Output pixel (c, r) is the rectangle's (c + rim, r + rim).
    shift = np.array([[1.0, 0, rim], [0, 1.0, rim], [0, 0, 1.0]])
    out = (height - 2 * rim, width - 2 * rim)
    flat = warp(grey, ProjectiveTransform(matrix=hom @ shift), output_shape=out, order=1, mode="edge",
                preserve_range=True).astype(grey.dtype)
    # The sheet's pixels less 2 px (the darker rim of its edge), in the rectangle.
    inside = ndimage.binary_erosion(region, iterations=2).astype(np.float32)
    box = np.array([[1.0, 0, -corner[0]], [0, 1.0, -corner[1]], [0, 0, 1.0]])
    on = warp(inside, ProjectiveTransform(matrix=box @ hom @ shift), output_shape=out, order=1, cval=0.0) > 0.5
    if on.any() and not on.all():
        nearest = ndimage.distance_transform_edt(~on, return_distances=False, return_indices=True)
        flat = flat[nearest[0], nearest[1]]
    return flat, (height, width)


def sheet_aspect(corners: np.ndarray, shape: tuple[int, int], focal_35mm: float | None = None) -> float:
    """Width over height of the rectangle photographed as the quadrilateral ``corners`` (top-left,
    top-right, bottom-right, bottom-left) by a pinhole camera whose centre is the photo's.

    The rectangle's proportions follow from its sides' directions in the camera's frame, which need the
    focal length: the photo's EXIF one (``focal_35mm``, in 35-mm film terms), else the one the sides'
    two vanishing points give (Zhang and He 2007, whiteboard scanning), when it is in
    :data:`SHEET_FOCAL_RANGE` and moving any corner by half a pixel moves it by under 10 % (a sheet
    seen head-on, or only leaned back, has sides parallel in the photo: its vanishing points are at
    infinity), else a phone's, :data:`SHEET_ASSUMED_FOCAL`.  Seen nearly head-on, the proportions hardly
    depend on it.

    Parameters
    ----------
    corners : numpy.ndarray
        float64 (4, 2) the quadrilateral's corners (x, y) in the photo.
    shape : tuple of int
        The photo's (height, width).
    focal_35mm : float or None
        EXIF focal length in 35-mm film terms, mm; None to find it from the corners.

    Returns
    -------
    float
        The rectangle's width / height.
    """
    centre = np.array([0.5 * (shape[1] - 1), 0.5 * (shape[0] - 1)])
    longer = float(max(shape))

    def normals(quad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m1, m2, m4, m3 = (np.append(p - centre, 1.0) for p in quad)     # Zhang's m1, m2 top; m3, m4 bottom
        k2 = np.cross(m1, m4) @ m3 / (np.cross(m2, m4) @ m3)
        k3 = np.cross(m1, m4) @ m2 / (np.cross(m3, m4) @ m2)
        return k2 * m2 - m1, k3 * m3 - m1

    def focal2(n2: np.ndarray, n3: np.ndarray) -> float:
        return -(n2[0] * n3[0] + n2[1] * n3[1]) / (n2[2] * n3[2]) if abs(n2[2] * n3[2]) > 1e-12 else -1.0

    n2, n3 = normals(corners)
    if focal_35mm:
        f2 = (focal_35mm / FILM_35MM_DIAGONAL * float(np.hypot(*shape))) ** 2
    else:
        f2 = focal2(n2, n3)
        low, high = SHEET_FOCAL_RANGE
        moved = [focal2(*normals(corners + np.eye(8)[i].reshape(4, 2) * step)) for i in range(8) for step in (-0.5, 0.5)]
        if not ((low * longer) ** 2 <= f2 <= (high * longer) ** 2
                and all(0.81 * f2 <= f <= 1.21 * f2 for f in moved)):
            f2 = (SHEET_ASSUMED_FOCAL * longer) ** 2
    inv = np.array([1 / f2, 1 / f2, 1.0])
    return float(np.sqrt((n2 * n2) @ inv / ((n3 * n3) @ inv)))
