"""The image processing application: feature finders and correspondence.

Finders (one per feature kind) return pixel positions in float image coordinates with OpenCV's
origin (the centre of the top-left pixel is (0, 0), x to the right, y down):

- ``find_circles``: dark or bright circular marks or holes. Blobs are found on an image reduced
  by an integer factor (cheap), against a local background (morphological black-hat/top-hat, so
  uneven light does not matter), filtered by size and circularity; each centre is then refined at
  full resolution as the centroid of the background-corrected "darkness fraction" in a small window.
  That centroid is unbiased under blur (blur is symmetric) and uses every pixel of the mark.
- ``find_aruco``: ArUco/AprilTag markers (``cv2.aruco.ArucoDetector``); the identity comes from the
  id and the centre is the intersection of the diagonals (the projection of the square's centre
  under perspective, unlike the mean of the corners).
- ``find_template``: a taught patch by normalised cross-correlation, sub-pixel peak by a quadratic
  fit of the 3x3 score neighbourhood.

Correspondence (``match_epipolar``, ``match_model``, ``assign_nearest``) is
``vgripd.vision.correspondence``; its names are re-exported here for the callers that use
``features.match_model`` and the like.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.types import FloatArray
from vgripd.vision.correspondence import (
    AMBIGUITY_MARGIN,
    MIN_SEED_ALTITUDE,
    ModelMatch,
    assign_nearest,
    kabsch,
    match_epipolar,
    match_model,
    score_scale,
)
from vgripd.vision.touching import split_touching

__all__ = [  # the finders, and correspondence's names callers reach through ``features``
    "AMBIGUITY_MARGIN", "MIN_SEED_ALTITUDE", "REJECT_REASONS", "Blobs", "CircleSpec", "Marker",
    "ModelMatch", "Polarity", "Rejected", "UInt8Image", "aruco_dictionary", "assign_nearest",
    "find_aruco", "find_aruco_all", "find_circles", "find_template", "gray_from_image", "kabsch",
    "match_epipolar", "match_model", "score_scale",
]

Polarity = Literal["dark", "bright"]
UInt8Image = npt.NDArray[np.uint8]


def gray_from_image(image: npt.NDArray[Any]) -> UInt8Image:
    """An 8-bit grey view/copy of a driver image (grey (H, W) or BGR (H, W, 3)).

    Raises ``ValueError`` naming the shape or dtype when the array is not an 8-bit image.
    """
    if image.dtype != np.uint8:
        raise ValueError(f"image dtype {image.dtype} is not uint8")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    raise ValueError(f"image shape {image.shape} is neither (H, W) nor (H, W, 3)")


# --------------------------------------------------------------------------- circles


@dataclass(frozen=True)
class CircleSpec:
    """What a circular mark looks like in the image.

    ``min_diameter_px``/``max_diameter_px``: accepted equivalent diameters at full resolution.
    ``min_contrast``: grey levels between the mark and its local background.
    ``min_circularity``: 4*pi*area/perimeter**2 of the blob outline (1 for a disc; an ellipse seen
    at 60 deg tilt is about 0.9; pixelation lowers small blobs to about 0.7).
    ``downscale``: the detection step works on the image reduced by this factor; it is lowered
    automatically so that the smallest mark keeps at least 4 px across.
    ``separate_neighbours``: marks closer than their refinement windows (touching plates of a
    pallet) each keep only the pixels nearer to their own coarse centre; on for pick lists
    (``picking.max_objects > 1``), off for one object, whose results it leaves as they were.
    """

    polarity: Polarity = "dark"
    min_diameter_px: float = 6.0
    max_diameter_px: float = 200.0
    min_contrast: float = 20.0
    min_circularity: float = 0.6
    downscale: int = 2
    separate_neighbours: bool = False


class Rejected(NamedTuple):
    """A blob the circle finder dropped, and why: ``reason`` is one of ``REJECT_REASONS`` and
    ``value`` the figure that failed (diameter px, contrast in grey levels, circularity; 0 for
    ``border``). ``x``, ``y`` px (full resolution), ``diameter_px`` its equivalent diameter."""

    x: float
    y: float
    diameter_px: float
    reason: str
    value: float


#: Why ``find_circles`` drops a blob: its size is outside the spec's diameter range, its contrast
#: under ``min_contrast``, its outline not round enough, or it touches the image border.
REJECT_REASONS = ("size", "contrast", "circularity", "border")


@dataclass(frozen=True)
class Blobs:
    """Circle candidates in one image: ``xy`` (N, 2) px, ``diameter_px`` (N,), ``contrast`` (N,).

    ``rejected``: the blobs dropped on the way, with the reason (for the diagnosis of a failed
    job, ``vgripd.vision.diagnosis``). Specks of noise under 40 % of the smallest diameter
    searched for are not candidates and are not listed.
    """

    xy: FloatArray
    diameter_px: FloatArray
    contrast: FloatArray
    rejected: tuple[Rejected, ...] = ()

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def _effective_downscale(spec: CircleSpec) -> int:
    return max(1, min(spec.downscale, int(spec.min_diameter_px // 4)))


def shrink(gray: UInt8Image, s: int) -> UInt8Image:
    """``gray`` reduced by the integer factor ``s``, each pixel the mean of an s x s block
    (``INTER_AREA``). A power of two that divides both sides is halved step by step with
    ``INTER_LINEAR``, which at exactly half the size averages 2 x 2 pixels: the same mean
    (within one grey level of rounding) at a fifth of the time on a 5 MP image."""
    h, w = gray.shape
    out: Any = gray
    if s & (s - 1) == 0 and h % s == 0 and w % s == 0:
        while s > 1:
            h, w, s = h // 2, w // 2, s // 2
            out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
    elif s > 1:
        out = cv2.resize(gray, (w // s, h // s), interpolation=cv2.INTER_AREA)
    return out


def find_circles(gray: UInt8Image, spec: CircleSpec) -> Blobs:
    """Find circular marks and their sub-pixel centres in an 8-bit grey image.

    Marks touching the image border are rejected: a cut mark has a biased centre.
    """
    s = _effective_downscale(spec)
    h, w = gray.shape
    small = shrink(gray, s)
    # Local contrast: black-hat (closing - image) keeps dark structures smaller than the kernel
    # and removes the slowly varying background; top-hat does the same for bright marks.
    k = int(np.ceil(spec.max_diameter_px / s * 1.3)) | 1
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    op = cv2.MORPH_BLACKHAT if spec.polarity == "dark" else cv2.MORPH_TOPHAT
    contrast = cv2.morphologyEx(small, op, kernel)
    otsu, _ = cv2.threshold(contrast, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    level = max(spec.min_contrast / 2.0, float(otsu))
    _, mask = cv2.threshold(contrast, level, 255, cv2.THRESH_BINARY)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)

    xs: list[tuple[float, float]] = []
    diameters: list[float] = []
    contrasts: list[float] = []
    rejected: list[Rejected] = []
    sh, sw = small.shape
    speck = 0.4 * spec.min_diameter_px
    candidates: list[tuple[float, float, float]] = []  # coarse centre (px) and diameter

    def drop(c: Any, d_px: float, reason: str, value: float) -> None:
        # Only on the way out of the loop: costs nothing for the blobs that are kept.
        bx, by, bw, bh = cv2.boundingRect(c)
        rejected.append(Rejected((bx + 0.5 * bw) * s - 0.5, (by + 0.5 * bh) * s - 0.5, d_px,
                                 reason, value))

    for c in contours:
        area = cv2.contourArea(c)
        if area < 2.0:
            continue
        d_px = 2.0 * np.sqrt(area / np.pi) * s
        too_big = d_px > spec.max_diameter_px * 1.2
        if d_px < spec.min_diameter_px * 0.8 or (too_big and not spec.separate_neighbours):
            if d_px >= speck:
                drop(c, d_px, "size", d_px)
            continue
        bx, by, bw, bh = cv2.boundingRect(c)
        if bx <= 0 or by <= 0 or bx + bw >= sw or by + bh >= sh:
            drop(c, d_px, "border", 0.0)
            continue
        if spec.separate_neighbours:
            # Marks of touching plates merged into one blob (round enough to pass as one
            # mark, or not): each disc becomes a candidate of its own.
            parts = _touching_parts(c, s, spec)
            if parts:
                candidates += parts
                continue
            if too_big:
                drop(c, d_px, "size", d_px)
                continue
        perimeter = cv2.arcLength(c, True)
        circularity = 4.0 * np.pi * area / perimeter**2 if perimeter > 0 else 0.0
        if circularity < spec.min_circularity:
            drop(c, d_px, "circularity", circularity)
            continue
        m = cv2.moments(c)
        # Centre of the small image's pixel (i, j) in full-resolution coordinates: s*i + (s-1)/2.
        cx = m["m10"] / m["m00"] * s + (s - 1) / 2.0
        cy = m["m01"] / m["m00"] * s + (s - 1) / 2.0
        candidates.append((cx, cy, d_px))

    coarse = np.array(candidates).reshape(-1, 3)
    for index, (cx, cy, d_px) in enumerate(candidates):
        # Marks so close that one's refinement window reaches into the other (touching
        # plates of a pallet): each keeps only the pixels nearer to its own rim.
        reach = np.hypot(coarse[:, 0] - cx, coarse[:, 1] - cy) < 2.0 * d_px + 10.0
        reach[index] = False
        if not spec.separate_neighbours:
            reach[:] = False
        refined = _refine_centre(gray, cx, cy, d_px, spec.polarity, coarse[reach])
        if refined is None:
            # The refinement window left the image, or the mark has no contrast at all.
            half = int(np.ceil(0.75 * d_px + 3.0)) + 2
            near_edge = min(cx, cy, w - 1 - cx, h - 1 - cy) < half + 1
            rejected.append(Rejected(cx, cy, d_px, "border" if near_edge else "contrast", 0.0))
            continue
        (rx, ry), d_ref, con = refined
        if con < spec.min_contrast:
            rejected.append(Rejected(rx, ry, d_ref, "contrast", con))
            continue
        if not spec.min_diameter_px <= d_ref <= spec.max_diameter_px:
            rejected.append(Rejected(rx, ry, d_ref, "size", d_ref))
            continue
        xs.append((rx, ry))
        diameters.append(d_ref)
        contrasts.append(con)
    return Blobs(
        xy=np.asarray(xs, dtype=np.float64).reshape(-1, 2),
        diameter_px=np.asarray(diameters, dtype=np.float64),
        contrast=np.asarray(contrasts, dtype=np.float64),
        rejected=tuple(rejected),
    )


def _touching_parts(contour: Any, s: int, spec: CircleSpec) -> list[tuple[float, float, float]]:
    """The discs of one blob that holds several (``touching.split_touching``: marks of two
    plates that touch in the image), as coarse candidates (full-resolution centre px,
    diameter px); empty when the blob is one disc or not made of discs."""
    bx, by, bw, bh = cv2.boundingRect(contour)
    mask = np.zeros((bh, bw), np.uint8)
    cv2.drawContours(mask, [contour], -1, 255, thickness=cv2.FILLED, offset=(-bx, -by))
    discs = split_touching(mask, 0.4 * spec.min_diameter_px / s - 1.0,
                           0.6 * spec.max_diameter_px / s + 1.0)
    return [((bx + x) * s + (s - 1) / 2.0, (by + y) * s + (s - 1) / 2.0, 2.0 * r * s)
            for x, y, r in discs]


def _refine_centre(
    gray: UInt8Image, cx: float, cy: float, d_px: float, polarity: Polarity,
    neighbours: FloatArray | None = None,
) -> tuple[tuple[float, float], float, float] | None:
    """Sub-pixel centre, equivalent diameter (px) and contrast of one mark near (cx, cy).

    In a window of radius 0.75*d + 3 px, each pixel's weight is its "mark fraction"
    (I/B - 1) / (k - 1), clipped to [0, 1]: 1 inside the mark, 0 on the background, partial on
    the blurred rim. B is a plane fitted to the window's corners (uneven light is a gradient at
    this scale; a constant level would pull the centre towards the darker side) and k the
    median ratio I/B in the mark's core: light multiplies mark and background alike, so the
    ratio, unlike a difference, is the same all over the mark. Two passes re-centre the window.
    The contrast returned is |B (k - 1)| in grey levels.
    ``neighbours`` (k, 2): coarse centres of other marks whose window overlaps this one; the
    pixels nearer to one of them than to this mark's coarse centre take no part (neither in the
    background plane nor in the centroid). Without neighbours nothing changes. (k, 3): coarse
    centres and diameters; the pixels then part along the power line of the two rims
    (``|p - c| - d / 2`` compared) rather than the bisector of the centres, so that a large
    mark touching a small one keeps its own rim.
    Returns None when the window leaves the image or the mark has no contrast.
    """
    h, w = gray.shape
    radius = 0.75 * d_px + 3.0
    half = int(np.ceil(radius)) + 2
    sign = -1.0 if polarity == "dark" else 1.0
    ox, oy = cx, cy  # origin of the background plane (image coordinates)
    plane: FloatArray | None = None
    k = contrast = area_px = 0.0
    core2 = (0.3 * d_px) ** 2 + 1.0
    for _ in range(2):
        ix, iy = int(round(cx)), int(round(cy))
        x0, y0, x1, y1 = ix - half, iy - half, ix + half + 1, iy + half + 1
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            return None
        roi = gray[y0:y1, x0:x1].astype(np.float32)
        xs = np.arange(x0, x1, dtype=np.float32)
        ys = np.arange(y0, y1, dtype=np.float32)
        r2 = np.add.outer((ys - cy) ** 2, (xs - cx) ** 2)
        inside = r2 <= radius**2
        mine: npt.NDArray[np.bool_] | None = None
        if neighbours is not None and len(neighbours):
            mine = np.ones_like(inside)
            own2 = np.add.outer((ys - oy) ** 2, (xs - ox) ** 2)
            if neighbours.shape[1] == 2:
                for nx, ny in neighbours:
                    mine &= own2 <= np.add.outer((ys - ny) ** 2, (xs - nx) ** 2)
            else:
                own = np.sqrt(own2) - 0.5 * d_px
                for nx, ny, nd in neighbours:
                    mine &= own <= np.sqrt(np.add.outer((ys - ny) ** 2, (xs - nx) ** 2)) - 0.5 * nd
            inside &= mine
        dx, dy = xs - ox, ys - oy
        if plane is None:  # fitted once, on the first window; the second one reuses it
            plane = _background_plane(roi, dx, dy, ~inside if mine is None else ~inside & mine)
        background = np.add.outer(plane[2] * dy, plane[1] * dx)
        background += plane[0]
        ratio = roi / np.maximum(background, 1.0)
        if k == 0.0:
            k = _median(ratio[r2 <= core2])
            contrast = float(plane[0]) * (k - 1.0) * sign
            if contrast <= 0:
                return None
        weight = ratio - 1.0
        weight *= 1.0 / (k - 1.0)
        np.clip(weight, 0.0, 1.0, out=weight)
        weight *= inside
        area_px = float(weight.sum())
        if area_px <= 0:
            return None
        cx = float(weight.sum(axis=0) @ xs / area_px)
        cy = float(weight.sum(axis=1) @ ys / area_px)
    return (cx, cy), 2.0 * float(np.sqrt(area_px / np.pi)), contrast


def _median(values: npt.NDArray[Any]) -> float:
    """``np.median`` of a 1-D array, by one partition (without its per-call overhead, which
    is most of the cost at the sizes of a refinement window)."""
    n = values.size
    if n == 0:
        return float("nan")
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return 0.5 * (float(part[half - 1]) + float(part[half]))


def _background_plane(
    roi: npt.NDArray[np.float32], dx: npt.NDArray[Any], dy: npt.NDArray[Any],
    mask: npt.NDArray[np.bool_],
) -> FloatArray:
    """Coefficients (a, b, c) of the least-squares plane a + b*dx + c*dy through ``roi[mask]``
    (``dx`` the window's columns, ``dy`` its rows, relative to the plane's origin), refitted
    once without the pixels more than 4.5 robust sigmas off (a neighbouring mark in a corner).
    Solved by the 3x3 normal equations (``lstsq`` costs ten times more here)."""
    rows, cols = np.nonzero(mask)
    if rows.size < 3:
        return np.array([float(np.median(roi)), 0.0, 0.0])
    design = np.empty((rows.size, 3))
    design[:, 0] = 1.0
    design[:, 1] = dx[cols]
    design[:, 2] = dy[rows]
    z = roi[rows, cols].astype(np.float64)

    def fit(a: FloatArray, b: FloatArray) -> FloatArray:
        return np.asarray(np.linalg.solve(a.T @ a, a.T @ b), dtype=np.float64)

    coef = fit(design, z)
    res = np.abs(z - design @ coef)
    good = res < 4.5 * (_median(res) + 1e-3)
    if good.sum() >= 3 and not good.all():
        coef = fit(design[good], z[good])
    return coef


# --------------------------------------------------------------------------- aruco


@dataclass(frozen=True)
class Marker:
    """One decoded marker: ``corners`` (4, 2) px in the dictionary's order, ``centre`` (2,) px."""

    marker_id: int
    corners: FloatArray
    centre: FloatArray


def aruco_dictionary(name: str) -> Any:
    """The OpenCV dictionary for a name such as ``"DICT_4X4_50"`` or ``"4X4_50"``."""
    key = name.upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    try:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))
    except AttributeError:
        raise ValueError(f"unknown ArUco dictionary {name!r}") from None


def _diagonal_intersection(c: FloatArray) -> FloatArray:
    """Intersection of the diagonals c0-c2 and c1-c3 of a quadrilateral (4, 2)."""
    d1, d2 = c[2] - c[0], c[3] - c[1]
    a = np.array([[d1[0], -d2[0]], [d1[1], -d2[1]]])
    if abs(np.linalg.det(a)) < 1e-9:
        return np.asarray(c.mean(axis=0), dtype=np.float64)
    t = np.linalg.solve(a, c[1] - c[0])[0]
    return np.asarray(c[0] + t * d1, dtype=np.float64)


def find_aruco_all(gray: UInt8Image, dictionary: str) -> list[Marker]:
    """Every decoded marker of one dictionary, an id as often as it is seen (pick lists: the
    same markers on every object)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None:
        return []
    out = []
    for quad, mid in zip(corners, ids.ravel(), strict=True):
        c = np.asarray(quad, dtype=np.float64).reshape(4, 2)
        out.append(Marker(int(mid), c, _diagonal_intersection(c)))
    return out


def find_aruco(gray: UInt8Image, dictionary: str) -> dict[int, Marker]:
    """Decode the markers of one dictionary. A marker id seen twice is dropped (no identity)."""
    found: dict[int, Marker] = {}
    seen_twice: set[int] = set()
    for marker in find_aruco_all(gray, dictionary):
        if marker.marker_id in found:
            seen_twice.add(marker.marker_id)
        found[marker.marker_id] = marker
    for key in seen_twice:
        del found[key]
    return found


# --------------------------------------------------------------------------- template


def find_template(
    gray: UInt8Image, template: UInt8Image, min_score: float
) -> tuple[FloatArray, float] | None:
    """Best match of a taught patch by normalised cross-correlation (TM_CCOEFF_NORMED).

    Returns the sub-pixel position of the template's centre ((w-1)/2, (h-1)/2 in the patch) and
    the score, or None when the best score is under ``min_score``. The sub-pixel offset is the
    vertex of a parabola through the peak and its two neighbours, per axis.
    """
    th, tw = template.shape
    if gray.shape[0] < th or gray.shape[1] < tw:
        return None
    scores = cv2.matchTemplate(gray, template, cv2.TM_CCOEFF_NORMED)
    _, best, _, (px, py) = cv2.minMaxLoc(scores)
    if best < min_score:
        return None

    def vertex(m: float, c: float, p: float) -> float:
        den = m - 2.0 * c + p
        return 0.0 if den >= 0 else float(np.clip(0.5 * (m - p) / den, -0.5, 0.5))

    dx = dy = 0.0
    if 0 < px < scores.shape[1] - 1:
        dx = vertex(scores[py, px - 1], scores[py, px], scores[py, px + 1])
    if 0 < py < scores.shape[0] - 1:
        dy = vertex(scores[py - 1, px], scores[py, px], scores[py + 1, px])
    centre = np.array([px + dx + (tw - 1) / 2.0, py + dy + (th - 1) / 2.0])
    return centre, float(best)
