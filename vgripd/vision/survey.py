"""Marks found in a stereo pair without an object model, for defining a new object: every
circular mark in both images, paired along the epipolar lines, and every ArUco marker seen once
in each image, paired by its id, and a template taught from a region of the left image, found
once in each image; triangulated and put in the robot base frame; and the judgement of a chosen
layout (enough marks, far enough apart, no symmetry a pose could flip on).

The setup page shows the marks numbered; the integrator ticks those that belong to the object,
whose measured base-frame points become an ``object.definition = "reference"`` model (the object
frame is the base frame at teach time, so no CAD is needed).

Pure functions of images and calibration: no I/O. The daemon runs ``survey_marks`` in its image
helper process.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from vgripd.geometry.stereo import StereoRig
from vgripd.types import FloatArray
from vgripd.vision import features as ft

#: Diameters searched for (px at full resolution) when nothing is known about the marks yet.
SURVEY_DIAMETER_PX = (6.0, 160.0)
#: At least this many marks make an object (a pose needs 3; one more lets a lost mark be
#: survived and the fit be judged).
MIN_MARKS = 3
RECOMMENDED_MARKS = 4
#: Marks closer than this many of their diameters (centre to centre) merge in the image.
MIN_GAP_DIAMETERS = 2.0
#: Two layouts whose pairwise distances differ by less than this (mm) cannot be told apart.
SYMMETRY_TOL_MM = 1.0
#: Permutations tried exhaustively up to this many marks (8! = 40320); beyond, per-mark
#: distance profiles are compared.
EXHAUSTIVE_MAX = 7
#: ArUco dictionaries looked for when the config names none (one of each marker size, and the
#: AprilTag family most printed).
SURVEY_DICTIONARIES = ("DICT_4X4_50", "DICT_5X5_100", "DICT_6X6_250", "DICT_APRILTAG_36h11")
#: A taught template's side (px): smaller has too little to match on, larger is slow to search.
TEMPLATE_SIDE_PX = (12, 400)
#: A region whose grey levels spread less than this (standard deviation) has nothing to match.
TEMPLATE_MIN_STD = 8.0


class TemplateRefused(ValueError):
    """A region that cannot be a template (the text says why and where)."""


@dataclass(frozen=True)
class Mark:
    """One mark seen by both cameras: pixels, base-frame point (mm), diameter (mm)."""

    id: int
    px_left: tuple[float, float]
    px_right: tuple[float, float]
    xyz_base_mm: tuple[float, float, float]
    diameter_mm: float
    epipolar_px: float
    #: ``"circle"``, ``"aruco"`` (then ``diameter_mm`` is the marker's side, and
    #: ``marker_id``/``dictionary`` its identity) or ``"template"`` (``diameter_mm`` the
    #: patch's larger side, ``label`` its name, ``size_px`` that side in pixels).
    kind: str = "circle"
    marker_id: int | None = None
    dictionary: str | None = None
    #: A marker's corners in the left image (px), for drawing it and telling what lies inside.
    outline_left: tuple[tuple[float, float], ...] = ()
    label: str | None = None
    size_px: int = 0
    score: float = 0.0

    @property
    def identified(self) -> bool:
        """Found by an identity of its own (no relabelling can swap it with another mark)."""
        return self.kind != "circle"

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.id, "kind": self.kind, "px_left": list(self.px_left),
            "px_right": list(self.px_right), "xyz_mm": [round(v, 3) for v in self.xyz_base_mm],
            "diameter_mm": round(self.diameter_mm, 2), "epipolar_px": round(self.epipolar_px, 3)}
        if self.kind == "aruco":
            out.update(marker_id=self.marker_id, dictionary=self.dictionary,
                       size_mm=round(self.diameter_mm, 2))
        if self.kind == "template":
            out.update(label=self.label, size_px=self.size_px, score=round(self.score, 3),
                       size_mm=round(self.diameter_mm, 2))
        return out


def survey(left: Any, right: Any, rig: StereoRig, T_base_camera: FloatArray,
           min_contrast: float = 20.0, min_circularity: float = 0.75,
           tolerance_px: float = 2.0, polarity: str = "dark") -> list[Mark]:
    """The marks of ``polarity`` seen in both images, paired one to one along the epipolar
    lines (mutually nearest within ``tolerance_px``), triangulated and in the base frame,
    ordered left to right, top to bottom in the left image."""
    spec = ft.CircleSpec(polarity="bright" if polarity == "bright" else "dark",
                         min_diameter_px=SURVEY_DIAMETER_PX[0],
                         max_diameter_px=SURVEY_DIAMETER_PX[1], min_contrast=min_contrast,
                         min_circularity=min_circularity)
    bl = ft.find_circles(ft.gray_from_image(left), spec)
    br = ft.find_circles(ft.gray_from_image(right), spec)
    if len(bl) == 0 or len(br) == 0:
        return []
    lines = rig.epipolar_lines_right(bl.xy)
    ideal_r = rig.ideal_pixels(rig.right, br.xy)
    dist = np.abs(lines @ np.c_[ideal_r, np.ones(len(ideal_r))].T)  # (nL, nR)
    pairs = [(i, j) for i in range(len(bl)) for j in range(len(br))
             if dist[i, j] <= tolerance_px and int(np.argmin(dist[i])) == j
             and int(np.argmin(dist[:, j])) == i]
    if not pairs:
        return []
    il = np.array([p[0] for p in pairs])
    ir = np.array([p[1] for p in pairs])
    tri = rig.triangulate(bl.xy[il], br.xy[ir])
    pts_cam = np.asarray(tri.points_mm, np.float64)
    pts_base = pts_cam @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]
    fx = float(rig.left.fx)
    order = np.lexsort((bl.xy[il, 0], np.round(bl.xy[il, 1] / 40.0)))
    marks = []
    for k, n in enumerate(order):
        i, j = il[n], ir[n]
        depth = float(pts_cam[n, 2])
        marks.append(Mark(k + 1, (float(bl.xy[i, 0]), float(bl.xy[i, 1])),
                          (float(br.xy[j, 0]), float(br.xy[j, 1])),
                          (float(pts_base[n, 0]), float(pts_base[n, 1]), float(pts_base[n, 2])),
                          float(bl.diameter_px[i]) * depth / fx, float(dist[i, j])))
    return marks


def survey_aruco(left: Any, right: Any, rig: StereoRig, T_base_camera: FloatArray,
                 dictionaries: tuple[str, ...] = SURVEY_DICTIONARIES,
                 tolerance_px: float = 2.0, first_id: int = 1) -> list[Mark]:
    """The ArUco markers of ``dictionaries`` seen once in each image, paired by dictionary and
    id (a pair off its epipolar line by more than ``tolerance_px`` is dropped), their centres
    triangulated and in the base frame, their side measured from the triangulated corners;
    numbered from ``first_id`` in the order of (dictionary, marker id). A quad two
    dictionaries both decode counts for the first."""
    gray_l, gray_r = ft.gray_from_image(left), ft.gray_from_image(right)
    found: list[tuple[str, int, FloatArray, FloatArray, FloatArray, FloatArray]] = []
    taken: list[FloatArray] = []
    for dictionary in dictionaries:
        ml, mr = ft.find_aruco(gray_l, dictionary), ft.find_aruco(gray_r, dictionary)
        for marker_id in sorted(set(ml) & set(mr)):
            a, b = ml[marker_id], mr[marker_id]
            if any(np.linalg.norm(a.centre - c) < 2.0 for c in taken):
                continue
            taken.append(a.centre)
            found.append((dictionary, marker_id, a.centre, b.centre, a.corners, b.corners))
    if not found:
        return []
    centres_l = np.array([f[2] for f in found])
    centres_r = np.array([f[3] for f in found])
    lines = rig.epipolar_lines_right(centres_l)
    ideal_r = rig.ideal_pixels(rig.right, centres_r)
    epi = np.abs(np.sum(lines * np.c_[ideal_r, np.ones(len(ideal_r))], axis=1))
    keep = [k for k in range(len(found)) if epi[k] <= tolerance_px]
    if not keep:
        return []
    centres = np.asarray(rig.triangulate(centres_l[keep], centres_r[keep]).points_mm, np.float64)
    corners_l = np.concatenate([found[k][4] for k in keep])
    corners_r = np.concatenate([found[k][5] for k in keep])
    corners = np.asarray(rig.triangulate(corners_l, corners_r).points_mm,
                         np.float64).reshape(-1, 4, 3)
    base = centres @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]
    marks = []
    for n, k in enumerate(keep):
        dictionary, marker_id, cl, cr, _, _ = found[k]
        side = float(np.mean(np.linalg.norm(corners[n] - np.roll(corners[n], 1, axis=0),
                                            axis=1)))
        marks.append(Mark(first_id + n, (float(cl[0]), float(cl[1])),
                          (float(cr[0]), float(cr[1])),
                          (float(base[n, 0]), float(base[n, 1]), float(base[n, 2])),
                          side, float(epi[k]), "aruco", marker_id, dictionary,
                          tuple((float(x), float(y)) for x, y in found[k][4])))
    return marks


def survey_marks(left: Any, right: Any, rig: StereoRig, T_base_camera: FloatArray,
                 dictionaries: tuple[str, ...] = SURVEY_DICTIONARIES, min_contrast: float = 20.0,
                 min_circularity: float = 0.75, tolerance_px: float = 2.0,
                 polarity: str = "dark") -> list[Mark]:
    """Every mark for a new object: the circles (``survey``) numbered first, then the ArUco
    markers (``survey_aruco``). A dark square of a marker can pass for a circle: a circle whose
    centre lies on a marker is the marker's, not a mark of its own."""
    markers = survey_aruco(left, right, rig, T_base_camera, dictionaries, tolerance_px)
    circles = survey(left, right, rig, T_base_camera, min_contrast, min_circularity,
                     tolerance_px, polarity)
    quads = [np.array(m.outline_left, np.float64) for m in markers]
    circles = [c for c in circles if not any(_inside(q, c.px_left) for q in quads)]
    out = [replace(c, id=k + 1) for k, c in enumerate(circles)]
    out += [replace(m, id=len(out) + k + 1) for k, m in enumerate(markers)]
    return out


def template_patch(image: Any, box: tuple[int, int, int, int]) -> ft.UInt8Image:
    """The region ``box`` (x, y, width, height px of the left image) as a template patch;
    ``TemplateRefused`` when it leaves the image, is too small or too large, or is flat."""
    gray = ft.gray_from_image(np.asarray(image))
    x, y, w, h = (int(round(v)) for v in box)
    lo, hi = TEMPLATE_SIDE_PX
    if not (lo <= w <= hi and lo <= h <= hi):
        raise TemplateRefused(f"region {w}x{h} px: each side {lo} to {hi} px")
    if x < 0 or y < 0 or x + w > gray.shape[1] or y + h > gray.shape[0]:
        raise TemplateRefused(f"region at ({x}, {y}) size {w}x{h} px leaves the "
                              f"{gray.shape[1]}x{gray.shape[0]} image")
    patch = np.ascontiguousarray(gray[y:y + h, x:x + w])
    if float(patch.std()) < TEMPLATE_MIN_STD:
        raise TemplateRefused(f"region at ({x}, {y}) size {w}x{h} px is nearly uniform (grey "
                              f"level spread {patch.std():.1f} < {TEMPLATE_MIN_STD:g}): draw it "
                              "round something with edges")
    return patch


def template_hits(gray: ft.UInt8Image, patch: ft.UInt8Image
                  ) -> tuple[FloatArray, float, float] | None:
    """The best match of ``patch`` (its centre, sub-pixel) and its score, and the best score
    elsewhere (at least half a patch away): a second place the job's finder could take."""
    import cv2

    hit = ft.find_template(gray, patch, -1.0)
    if hit is None:
        return None
    centre, best = hit
    scores = cv2.matchTemplate(gray, patch, cv2.TM_CCOEFF_NORMED)
    h, w = patch.shape
    cx, cy = int(round(centre[0] - (w - 1) / 2.0)), int(round(centre[1] - (h - 1) / 2.0))
    scores[max(0, cy - h // 2):cy + h // 2 + 1, max(0, cx - w // 2):cx + w // 2 + 1] = -1.0
    return centre, best, float(scores.max())


def survey_template(left: Any, right: Any, rig: StereoRig, T_base_camera: FloatArray,
                    patch: ft.UInt8Image, label: str, min_score: float,
                    tolerance_px: float = 2.0, mark_id: int = 1) -> Mark:
    """A template found once in each image (best score at least ``min_score``, no other place
    that reaches it), on the epipolar line of its left match within ``tolerance_px``; its
    centre triangulated into the base frame. ``TemplateRefused`` naming what failed."""
    hits = []
    for side, image in (("left", left), ("right", right)):
        found = template_hits(ft.gray_from_image(np.asarray(image)), patch)
        if found is None or found[1] < min_score:
            best = "none" if found is None else f"{found[1]:.2f}"
            raise TemplateRefused(f"template {label}: not found in the {side} image (best "
                                  f"score {best} < vision.template_min_score {min_score:g})")
        if found[2] >= min_score:
            raise TemplateRefused(f"template {label}: found at two places in the {side} image "
                                  f"(scores {found[1]:.2f} and {found[2]:.2f}, both >= "
                                  f"{min_score:g}): a job could take either; draw a region "
                                  "round something that is there once")
        hits.append(found)
    (cl, score_l, _), (cr, score_r, _) = hits
    line = rig.epipolar_lines_right(cl[None])[0]
    ideal_r = rig.ideal_pixels(rig.right, cr[None])[0]
    epi = abs(float(line @ np.r_[ideal_r, 1.0]))
    if epi > tolerance_px:
        raise TemplateRefused(f"template {label}: the right image's match is {epi:.1f} px off "
                              f"the epipolar line (> {tolerance_px:g}): another place, or a "
                              "region that looks different from the right camera")
    pt = np.asarray(rig.triangulate(cl[None], cr[None]).points_mm, np.float64)[0]
    base = T_base_camera[:3, :3] @ pt + T_base_camera[:3, 3]
    h, w = patch.shape
    side_mm = max(w, h) * float(pt[2]) / float(rig.left.fx)
    x0, y0 = cl[0] - (w - 1) / 2.0, cl[1] - (h - 1) / 2.0
    outline = ((x0, y0), (x0 + w, y0), (x0 + w, y0 + h), (x0, y0 + h))
    return Mark(mark_id, (float(cl[0]), float(cl[1])), (float(cr[0]), float(cr[1])),
                (float(base[0]), float(base[1]), float(base[2])), side_mm, epi, "template",
                outline_left=tuple((float(a), float(b)) for a, b in outline), label=label,
                size_px=max(w, h), score=min(score_l, score_r))


def _inside(quad: FloatArray, point: tuple[float, float]) -> bool:
    """``point`` inside the convex quadrilateral ``quad`` (4, 2) or on its edge."""
    edges = np.roll(quad, -1, axis=0) - quad
    rel = np.asarray(point) - quad
    cross = edges[:, 0] * rel[:, 1] - edges[:, 1] * rel[:, 0]
    return bool(np.all(cross >= 0) or np.all(cross <= 0))


@dataclass(frozen=True)
class LayoutFinding:
    """``level`` ERROR (the object cannot work), WARNING (it may, poorly), or NOTE."""

    level: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {"level": self.level, "message": self.message}


def _symmetric(points: FloatArray, tol_mm: float, fixed: frozenset[int] = frozenset()
               ) -> tuple[int, ...] | None:
    """A relabelling of the points other than the identity that keeps every pairwise distance
    within ``tol_mm`` (the layout looks the same turned or mirrored), or None. The points in
    ``fixed`` carry an identity of their own (ArUco ids) and keep their labels."""
    n = len(points)
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    free = [i for i in range(n) if i not in fixed]
    if len(free) <= EXHAUSTIVE_MAX:
        for order in itertools.permutations(free):
            perm_list = list(range(n))
            for i, p in zip(free, order, strict=True):
                perm_list[i] = p
            perm = tuple(perm_list)
            if perm == tuple(range(n)):
                continue
            if np.max(np.abs(d - d[np.ix_(perm, perm)])) <= tol_mm:
                return perm
        return None
    profiles = np.sort(d, axis=1)
    for a, b in itertools.combinations(free, 2):
        if np.max(np.abs(profiles[a] - profiles[b])) <= tol_mm:
            swap = list(range(n))
            swap[a], swap[b] = b, a
            return tuple(swap)
    return None


def judge_layout(names: list[str], points: FloatArray, diameters_mm: list[float],
                 tol_mm: float = SYMMETRY_TOL_MM,
                 identified: list[bool] | None = None) -> list[LayoutFinding]:
    """What is wrong with an object of these marks (``points`` (n, 3) mm, ``diameters_mm`` a
    circle's diameter or a marker's side): too few, too close to each other, or a layout the
    pose could flip on (pairwise distances that a relabelling keeps; a mark ``identified`` by
    an id of its own, an ArUco marker, keeps its label). Empty: nothing to say."""
    out: list[LayoutFinding] = []
    n = len(names)
    if n < MIN_MARKS:
        return [LayoutFinding("ERROR", f"{n} mark(s) chosen: a pose needs at least "
                                       f"{MIN_MARKS} (better {RECOMMENDED_MARKS} or more)")]
    if n < RECOMMENDED_MARKS:
        out.append(LayoutFinding("WARNING", f"only {n} marks: a job fails whenever one is "
                                            f"hidden; {RECOMMENDED_MARKS} or more are better"))
    pts = np.asarray(points, np.float64)
    for a, b in itertools.combinations(range(n), 2):
        gap = float(np.linalg.norm(pts[a] - pts[b]))
        limit = MIN_GAP_DIAMETERS * max(diameters_mm[a], diameters_mm[b])
        if gap < limit:
            out.append(LayoutFinding("ERROR", f"{names[a]} and {names[b]} are {gap:.1f} mm "
                                              f"apart (centres): under {MIN_GAP_DIAMETERS:g} "
                                              f"diameters ({limit:.1f} mm) they blur into one"))
    fixed = frozenset(i for i, known in enumerate(identified or []) if known)
    perm = _symmetric(pts, tol_mm, fixed)
    if perm is not None:
        moved = [f"{names[i]}->{names[p]}" for i, p in enumerate(perm) if p != i]
        out.append(LayoutFinding("ERROR", f"symmetric layout: relabelling {', '.join(moved)} "
                                          f"keeps every distance within {tol_mm:g} mm, so the "
                                          "pose could come out turned; add or move a mark"))
    return out
