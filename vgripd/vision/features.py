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

Correspondence:

- ``match_epipolar``: left/right candidate pairs whose right pixel lies within a tolerance of the
  left pixel's epipolar line.
- ``match_model``: which triangulated candidates are which model features, from the distances the
  model fixes (a rigid motion keeps them). Seeds are model triples matched to candidate triples with
  the same three distances; each seed is verified by a rigid fit that must explain further
  candidates; the best hypothesis wins and spurious candidates are left out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.types import FloatArray

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
    """

    polarity: Polarity = "dark"
    min_diameter_px: float = 6.0
    max_diameter_px: float = 200.0
    min_contrast: float = 20.0
    min_circularity: float = 0.6
    downscale: int = 2


@dataclass(frozen=True)
class Blobs:
    """Circle candidates in one image: ``xy`` (N, 2) px, ``diameter_px`` (N,), ``contrast`` (N,)."""

    xy: FloatArray
    diameter_px: FloatArray
    contrast: FloatArray

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def _effective_downscale(spec: CircleSpec) -> int:
    return max(1, min(spec.downscale, int(spec.min_diameter_px // 4)))


def find_circles(gray: UInt8Image, spec: CircleSpec) -> Blobs:
    """Find circular marks and their sub-pixel centres in an 8-bit grey image.

    Marks touching the image border are rejected: a cut mark has a biased centre.
    """
    s = _effective_downscale(spec)
    h, w = gray.shape
    small = (
        cv2.resize(gray, (w // s, h // s), interpolation=cv2.INTER_AREA) if s > 1 else gray
    )
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
    sh, sw = small.shape
    for c in contours:
        area = cv2.contourArea(c)
        if area < 2.0:
            continue
        d_px = 2.0 * np.sqrt(area / np.pi) * s
        if not spec.min_diameter_px * 0.8 <= d_px <= spec.max_diameter_px * 1.2:
            continue
        bx, by, bw, bh = cv2.boundingRect(c)
        if bx <= 0 or by <= 0 or bx + bw >= sw or by + bh >= sh:
            continue
        perimeter = cv2.arcLength(c, True)
        if perimeter <= 0 or 4.0 * np.pi * area / perimeter**2 < spec.min_circularity:
            continue
        m = cv2.moments(c)
        # Centre of the small image's pixel (i, j) in full-resolution coordinates: s*i + (s-1)/2.
        cx = m["m10"] / m["m00"] * s + (s - 1) / 2.0
        cy = m["m01"] / m["m00"] * s + (s - 1) / 2.0
        refined = _refine_centre(gray, cx, cy, d_px, spec.polarity)
        if refined is None:
            continue
        (rx, ry), d_ref, con = refined
        if con < spec.min_contrast:
            continue
        if not spec.min_diameter_px <= d_ref <= spec.max_diameter_px:
            continue
        xs.append((rx, ry))
        diameters.append(d_ref)
        contrasts.append(con)
    return Blobs(
        xy=np.asarray(xs, dtype=np.float64).reshape(-1, 2),
        diameter_px=np.asarray(diameters, dtype=np.float64),
        contrast=np.asarray(contrasts, dtype=np.float64),
    )


def _refine_centre(
    gray: UInt8Image, cx: float, cy: float, d_px: float, polarity: Polarity
) -> tuple[tuple[float, float], float, float] | None:
    """Sub-pixel centre, equivalent diameter (px) and contrast of one mark near (cx, cy).

    In a window of radius 0.75*d + 3 px, each pixel's weight is its "mark fraction"
    (I/B - 1) / (k - 1), clipped to [0, 1]: 1 inside the mark, 0 on the background, partial on
    the blurred rim. B is a plane fitted to the window's corners (uneven light is a gradient at
    this scale; a constant level would pull the centre towards the darker side) and k the
    median ratio I/B in the mark's core: light multiplies mark and background alike, so the
    ratio, unlike a difference, is the same all over the mark. Two passes re-centre the window.
    The contrast returned is |B (k - 1)| in grey levels.
    Returns None when the window leaves the image or the mark has no contrast.
    """
    h, w = gray.shape
    radius = 0.75 * d_px + 3.0
    half = int(np.ceil(radius)) + 2
    sign = -1.0 if polarity == "dark" else 1.0
    ox, oy = cx, cy  # origin of the background plane (image coordinates)
    plane: FloatArray | None = None
    k = contrast = area_px = 0.0
    for _ in range(2):
        ix, iy = int(round(cx)), int(round(cy))
        x0, y0, x1, y1 = ix - half, iy - half, ix + half + 1, iy + half + 1
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            return None
        roi = gray[y0:y1, x0:x1].astype(np.float32)
        xs = np.arange(x0, x1, dtype=np.float32)
        ys = np.arange(y0, y1, dtype=np.float32)
        r2 = (xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2
        inside = r2 <= radius**2
        dx = np.broadcast_to(xs[None, :] - ox, roi.shape)
        dy = np.broadcast_to(ys[:, None] - oy, roi.shape)
        if plane is None:  # fitted once, on the first window; the second one reuses it
            plane = _background_plane(roi, dx, dy, ~inside)
        background = np.maximum(plane[0] + plane[1] * dx + plane[2] * dy, 1.0)
        ratio = roi / background
        if k == 0.0:
            k = float(np.median(ratio[r2 <= (0.3 * d_px) ** 2 + 1.0]))
            contrast = float(plane[0]) * (k - 1.0) * sign
            if contrast <= 0:
                return None
        weight = np.clip((ratio - 1.0) / (k - 1.0), 0.0, 1.0) * inside
        area_px = float(weight.sum())
        if area_px <= 0:
            return None
        cx = float(weight.sum(axis=0) @ xs / area_px)
        cy = float(weight.sum(axis=1) @ ys / area_px)
    return (cx, cy), 2.0 * float(np.sqrt(area_px / np.pi)), contrast


def _background_plane(
    roi: npt.NDArray[np.float32], dx: npt.NDArray[Any], dy: npt.NDArray[Any],
    mask: npt.NDArray[np.bool_],
) -> FloatArray:
    """Coefficients (a, b, c) of the least-squares plane a + b*dx + c*dy through ``roi[mask]``,
    refitted once without the pixels more than 4.5 robust sigmas off (a neighbouring mark in a
    corner). Solved by the 3x3 normal equations (``lstsq`` costs ten times more here)."""
    x, y, z = dx[mask].astype(np.float64), dy[mask].astype(np.float64), roi[mask]
    if x.size < 3:
        return np.array([float(np.median(roi)), 0.0, 0.0])

    def fit(w: FloatArray) -> FloatArray:
        wx, wy = w * x, w * y
        ata = np.array([[w.sum(), wx.sum(), wy.sum()],
                        [wx.sum(), (wx * x).sum(), (wx * y).sum()],
                        [wy.sum(), (wy * x).sum(), (wy * y).sum()]])
        atz = np.array([(w * z).sum(), (wx * z).sum(), (wy * z).sum()])
        return np.asarray(np.linalg.solve(ata, atz), dtype=np.float64)

    coef = fit(np.ones_like(x))
    res = np.abs(z - (coef[0] + coef[1] * x + coef[2] * y))
    good = res < 4.5 * (float(np.median(res)) + 1e-3)
    if good.sum() >= 3 and not good.all():
        coef = fit(good.astype(np.float64))
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


def find_aruco(gray: UInt8Image, dictionary: str) -> dict[int, Marker]:
    """Decode the markers of one dictionary. A marker id seen twice is dropped (no identity)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)
    corners, ids, _ = detector.detectMarkers(gray)
    found: dict[int, Marker] = {}
    seen_twice: set[int] = set()
    if ids is None:
        return found
    for quad, mid in zip(corners, ids.ravel(), strict=True):
        c = np.asarray(quad, dtype=np.float64).reshape(4, 2)
        key = int(mid)
        if key in found:
            seen_twice.add(key)
        found[key] = Marker(key, c, _diagonal_intersection(c))
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


# --------------------------------------------------------------------------- correspondence


def match_epipolar(
    distance_px: FloatArray, tolerance_px: float, plausible: npt.NDArray[np.bool_] | None = None
) -> npt.NDArray[np.intp]:
    """Candidate left/right pairs: every (i, j) whose right pixel j lies within ``tolerance_px``
    of the epipolar line of left pixel i.

    ``distance_px`` is the (nL, nR) matrix of point-to-epipolar-line distances (right image, px);
    ``plausible`` an optional (nL, nR) mask (positive depth, depth within the working range).
    A left candidate may keep several right partners: the model check decides between them.
    Returns (k, 2) indices sorted by left index then distance.
    """
    ok = distance_px <= tolerance_px
    if plausible is not None:
        ok &= plausible
    i, j = np.nonzero(ok)
    order = np.lexsort((distance_px[i, j], i))
    return np.stack([i[order], j[order]], axis=1).astype(np.intp)


@dataclass(frozen=True)
class ModelMatch:
    """Which measured point is which model feature.

    ``assignment`` (n_model,): index into the measured points, -1 where the feature was not
    found. ``T_points_model`` (4, 4): the rigid motion that maps model points onto the measured
    ones (from the winning hypothesis, before any final refit). ``ambiguous``: a second,
    different assignment explains as many features equally well (a symmetric model).
    """

    assignment: npt.NDArray[np.intp]
    T_points_model: FloatArray
    ambiguous: bool

    @property
    def count(self) -> int:
        return int((self.assignment >= 0).sum())


def _pairwise(points: FloatArray) -> FloatArray:
    diff = points[:, None, :] - points[None, :, :]
    return np.asarray(np.sqrt((diff**2).sum(axis=2)), dtype=np.float64)


def kabsch(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rigid T (4, 4) with b ~ R a + t, least squares (SVD); only used to score hypotheses,
    the final pose comes from ``orientation.horn_robust``."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T


def _seed_triples(model: FloatArray, limit: int) -> list[tuple[int, int, int]]:
    """Model triples by decreasing triangle area (well-conditioned seeds first), non-degenerate."""
    scored = []
    for t in combinations(range(model.shape[0]), 3):
        p = model[list(t)]
        area = 0.5 * float(np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0])))
        scored.append((area, t))
    scored.sort(key=lambda s: -s[0])
    top = scored[0][0] if scored else 0.0
    return [t for area, t in scored if area > 1e-3 * top][:limit]


def match_model(
    model: FloatArray,
    points: FloatArray,
    tolerance_mm: float,
    exclusive: Sequence[Sequence[int]] | None = None,
    *,
    max_seeds: int = 12,
    max_hypotheses: int = 4000,
) -> ModelMatch | None:
    """Assign measured 3D points (camera frame) to model points by rigid-distance consistency.

    Parameters
    ----------
    model : (n, 3) model points (object frame, mm).
    points : (m, 3) measured candidates (mm); may contain spurious points and several
        alternatives for one image blob.
    tolerance_mm : how far a measured distance or point may deviate from the model.
    exclusive : per point, the keys it occupies (e.g. its left and right blob ids offset so they
        do not collide); two points sharing a key are never both used.

    A seed maps a model triple (i, j, k) onto a point triple (a, b, c) whose three distances agree
    within ``tolerance_mm``; the rigid motion of the seed carries the whole model onto the points
    and every model point takes the nearest free point within ``tolerance_mm`` (greedy by
    distance). The hypothesis with most features, then least squared error, wins. Seeds are
    tried by decreasing area, at most ``max_seeds`` triples and ``max_hypotheses`` point triples;
    the search stops after a seed whose three features the best hypothesis contains (that seed
    enumerated every hypothesis in which they are visible).
    Returns None when no seed matches at all (fewer than 3 consistent points).
    """
    n, m = model.shape[0], points.shape[0]
    if m < 3 or n < 3:
        return None
    keys = [tuple(k) for k in exclusive] if exclusive is not None else [(i,) for i in range(m)]
    dm = _pairwise(model)
    dp = _pairwise(points)
    best: tuple[int, float, npt.NDArray[np.intp], FloatArray] | None = None
    runner_up: tuple[int, float, npt.NDArray[np.intp], FloatArray] | None = None
    tried = 0

    def conflict(idx: Sequence[int]) -> bool:
        used = [k for i in idx for k in keys[i]]
        return len(used) != len(set(used))

    for i, j, k in _seed_triples(model, max_seeds):
        c_ij = np.abs(dp - dm[i, j]) < tolerance_mm
        c_jk = np.abs(dp - dm[j, k]) < tolerance_mm
        c_ik = np.abs(dp - dm[i, k]) < tolerance_mm
        for a in range(m):
            for b in map(int, np.flatnonzero(c_ij[a])):
                for c in map(int, np.flatnonzero(c_jk[b] & c_ik[a])):
                    if tried >= max_hypotheses:
                        break
                    if conflict((a, b, c)):
                        continue
                    tried += 1
                    T = kabsch(model[[i, j, k]], points[[a, b, c]])
                    assignment, sse = assign_nearest(model, points, T, tolerance_mm, keys)
                    count = int((assignment >= 0).sum())
                    hyp = (count, sse, assignment, T)
                    if best is None or (count, -sse) > (best[0], -best[1]):
                        if best is not None and not np.array_equal(best[2], assignment):
                            runner_up = best
                        best = hyp
                    elif not np.array_equal(best[2], assignment) and (
                        runner_up is None or (count, -sse) > (runner_up[0], -runner_up[1])
                    ):
                        runner_up = hyp
        # This seed enumerated every point triple that (i, j, k) can map to; if the best
        # hypothesis found all three, any better one would also contain them and was seen.
        if best is not None and (best[2][[i, j, k]] >= 0).all():
            break
    if best is None:
        return None
    ambiguous = False
    if runner_up is not None and runner_up[0] == best[0]:
        # A different assignment explaining as many features: ambiguous when it also moves the
        # model somewhere else (not just a swap of two near-coincident candidates).
        shift = _moved(model, best[3], runner_up[3])
        ambiguous = shift > 2.0 * tolerance_mm
    return ModelMatch(assignment=best[2], T_points_model=best[3], ambiguous=ambiguous)


def _moved(model: FloatArray, T1: FloatArray, T2: FloatArray) -> float:
    """Largest displacement (mm) of a model point between two poses."""
    p1 = model @ T1[:3, :3].T + T1[:3, 3]
    p2 = model @ T2[:3, :3].T + T2[:3, 3]
    return float(np.linalg.norm(p1 - p2, axis=1).max())


def assign_nearest(
    model: FloatArray,
    points: FloatArray,
    T: FloatArray,
    tolerance_mm: float,
    keys: Sequence[tuple[int, ...]],
) -> tuple[npt.NDArray[np.intp], float]:
    """Greedy nearest assignment of moved model points to free measured points within tolerance.

    Returns the (n,) assignment (-1 = not found) and the sum of squared distances of the matched.
    """
    moved = model @ T[:3, :3].T + T[:3, 3]
    d = np.sqrt(((moved[:, None, :] - points[None, :, :]) ** 2).sum(axis=2))
    mi, pi = np.nonzero(d < tolerance_mm)
    order = np.argsort(d[mi, pi])
    assignment = np.full(model.shape[0], -1, dtype=np.intp)
    used: set[int] = set()
    sse = 0.0
    for o in order:
        a, p = int(mi[o]), int(pi[o])
        if assignment[a] >= 0 or used.intersection(keys[p]):
            continue
        assignment[a] = p
        used.update(keys[p])
        sse += float(d[a, p] ** 2)
    return assignment, sse

