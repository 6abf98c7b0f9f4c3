"""Several identical objects in one cloud of measured points: which points belong together.

A pallet of identical plates gives the stereo chain one cloud of triangulated marks, six per
plate, plus whatever the epipolar pairing made of neighbouring marks on the same image row.
``correspondence.match_model`` finds *one* object and calls a second pose that scores as well
"ambiguous": with identical plates that second pose is simply the next plate. This module
finds them all (docs/picklists.md, "Finding the instances"):

1. **Hypothesise.** For every usable model triangle (thin ones are skipped, as in
   ``match_model``) every point triple with the same three distances (within the tolerance) is
   a seed; a seed already explained by a verified hypothesis is skipped, so a plate with all
   its marks costs one verification, not twenty. A plate with a mark missing is still seeded by
   the triangles of its visible marks.
2. **Verify** each seed with ``correspondence._verify``: assign the nearest free point to each model
   point, refit, repeat until it settles, drop gross outliers. Score = the MSAC support of
   ``match_model`` (a mark in place counts 1).
3. **Select**, best score first. A hypothesis that uses a point (or an image blob, through
   the ``keys``) already claimed by an accepted instance is verified again on the free points
   only and goes back into the queue with its new score: two plates that touch, or a
   hypothesis that straddles two plates, never become one merged pose; the plate explained
   better keeps the contested marks and the other is judged on what remains.
4. **Ambiguity** per instance: a hypothesis that shares points with an accepted instance,
   still holds up on the points not claimed by the others, puts the object somewhere else
   (the model moves by more than the tolerance) and scores within ``AMBIGUITY_MARGIN`` makes
   that instance ambiguous (a symmetric subset of marks, or too few marks to tell).

Pure numpy on points; the pipeline fits each instance again (robustly, circle bias removed).
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from vgripd.errors import GeometryError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.orientation import pnp
from vgripd.types import FloatArray
from vgripd.vision.correspondence import (
    AMBIGUITY_MARGIN,
    MIN_SEED_ALTITUDE,
    _altitudes,
    _Hypothesis,
    _kabsch_many,
    _moved,
    _pairwise,
    _spread_order,
    _verify,
    kabsch,
    score_scale,
)

#: Hypotheses verified one by one at most, per candidate point (each costs one small
#: assignment): a pallet needs about two per point, spurious pairings included.
MAX_VERIFIED_PER_POINT = 50

#: Instances accepted at most (the config's ``picking.max_objects`` is at most 64).
MAX_INSTANCES = 256


@dataclass(frozen=True)
class InstanceMatch:
    """One object instance: which measured point is which model feature.

    ``assignment`` (n_model,): row into the measured points, -1 where the feature was not found.
    ``T_points_model``: rigid motion of the model onto the points (least squares over the
    assigned ones). ``score``: MSAC support (``correspondence.score_scale``), at most n_model.
    ``rival``: score of the best other pose for some of the same points (0: none).
    """

    assignment: npt.NDArray[np.intp]
    T_points_model: FloatArray
    rms_mm: float
    score: float
    ambiguous: bool = False
    rival: float = 0.0

    @property
    def count(self) -> int:
        return int((self.assignment >= 0).sum())


@dataclass(frozen=True)
class Grouping:
    """The instances (best score first) and the work done: seeds found, hypotheses verified,
    and whether the work bound stopped the search (``complete`` False)."""

    instances: tuple[InstanceMatch, ...]
    seeds: int
    verified: int
    complete: bool


class _Pool:
    """The verified hypotheses and the seeds they already explain."""

    def __init__(self, model: FloatArray, points: FloatArray, tolerance_mm: float,
                 keys: Sequence[tuple[int, ...]], max_rms_mm: float) -> None:
        self.model, self.points, self.tol, self.keys = model, points, tolerance_mm, keys
        self.max_rms = max_rms_mm
        self.scale = score_scale(tolerance_mm, max_rms_mm)
        self.centre = model.mean(axis=0)
        radius = float(np.linalg.norm(model - self.centre, axis=1).max())
        self.reach2 = (radius + 4.0 * tolerance_mm) ** 2
        self.hyps: list[_Hypothesis] = []
        self.seen: set[tuple[int, ...]] = set()
        self.covered: set[tuple[tuple[int, int], ...]] = set()
        self.verified = 0

    def verify(self, T: FloatArray, free: npt.NDArray[np.bool_] | None = None
               ) -> _Hypothesis | None:
        """``correspondence._verify`` of the motion ``T`` on the (``free``) points near the moved
        model; None under three features.

        Only the points within reach of the object can take part (the refits move it by a few
        tolerances at most), so the verification runs on those: a pallet's cost then grows
        with its number of plates, not with its square."""
        self.verified += 1
        centre = T[:3, :3] @ self.centre + T[:3, 3]
        near = np.sum((self.points - centre) ** 2, axis=1) <= self.reach2
        if free is not None:
            near &= free
        rows = np.flatnonzero(near)
        if rows.size < 3:
            return None
        hyp = _verify(self.model, self.points[rows], T, self.tol,
                      [self.keys[int(r)] for r in rows], self.max_rms, self.scale)
        if hyp is None:
            return None
        assignment = np.where(hyp.assignment >= 0, rows[np.maximum(hyp.assignment, 0)], -1)
        return _Hypothesis(assignment, hyp.T, hyp.rms, hyp.score)

    def add(self, hyp: _Hypothesis) -> None:
        assigned = tuple(int(x) for x in hyp.assignment)
        if assigned in self.seen:
            return
        self.seen.add(assigned)
        self.hyps.append(hyp)
        inliers = [(f, q) for f, q in enumerate(assigned) if q >= 0]
        self.covered.update(combinations(inliers, 3))


def _exclusive_distances(points: FloatArray, keys: Sequence[tuple[int, ...]]) -> FloatArray:
    """Pairwise distances, infinite between a point and itself and between two points that
    share a key (two pairings of one image blob are never one object's two marks)."""
    m = points.shape[0]
    owners: dict[int, list[int]] = {}
    for row, ks in enumerate(keys):
        for key in ks:
            owners.setdefault(key, []).append(row)
    together = ~np.eye(m, dtype=bool)
    for group in owners.values():
        if len(group) > 1:
            together[np.ix_(group, group)] = False
    return np.where(together, _pairwise(points), np.inf)


def _seeds(dm: FloatArray, dp: FloatArray, triple: tuple[int, int, int], tol: float
           ) -> npt.NDArray[np.intp]:
    """Point triples (h, 3) whose distances match the model triangle ``triple``."""
    i, j, k = triple
    ij = np.abs(dp - dm[i, j]) < tol
    jk = np.abs(dp - dm[j, k]) < tol
    ik = np.abs(dp - dm[i, k]) < tol
    a, b = np.nonzero(ij)
    if not a.size:
        return np.zeros((0, 3), dtype=np.intp)
    e, c = np.nonzero(jk[b] & ik[a])
    return np.stack([a[e], b[e], c], axis=1).astype(np.intp)


def find_instances(
    model: FloatArray,
    points: FloatArray,
    tolerance_mm: float,
    keys: Sequence[Sequence[int]] | None = None,
    *,
    max_rms_mm: float = float("inf"),
    max_verified: int | None = None,
    max_instances: int = MAX_INSTANCES,
) -> Grouping:
    """Every instance of ``model`` among ``points`` (module docstring).

    Parameters
    ----------
    model : (n, 3) model points (mm).
    points : (m, 3) measured candidates (mm), several objects' marks, spurious points and
        alternative pairings of one blob (``keys``).
    tolerance_mm : how far a measured distance or point may deviate from the model.
    keys : per point the keys it occupies (left and right blob ids); two points sharing a key
        are never both used, by one instance or by two.
    max_rms_mm : the fit check (``vision.max_fit_rms_mm``): it sets the score scale; an
        instance over it is still returned (the residual check judges it).
    max_verified : the work bound (default ``MAX_VERIFIED_PER_POINT`` per point); a search
        stopped by it is not ``complete``.
    """
    n, m = model.shape[0], points.shape[0]
    if m < 3 or n < 3:
        return Grouping((), 0, 0, True)
    key_list = ([tuple(k) for k in keys] if keys is not None
                else [(i,) for i in range(m)])
    pool = _Pool(model, points, tolerance_mm, key_list, max_rms_mm)
    if max_verified is None:
        max_verified = MAX_VERIFIED_PER_POINT * m
    dp = _exclusive_distances(points, key_list)
    dm = _pairwise(model)
    seedable = _altitudes(model) >= MIN_SEED_ALTITUDE * tolerance_mm
    order = _spread_order(model)
    # Well-spread triangles first: they make the best-conditioned seeds.
    triples = [(i, j, k) for r in range(2, n) for i, j in combinations(order[:r], 2)
               for k in (order[r],) if seedable[i, j, k]]
    seeds = 0
    complete = True
    # Bare triangles (nothing but their own three points near the moved model) are verified
    # last, and only when a point of theirs is not already explained by a plate of four or
    # more marks: on a pallet most seeds are such triangles across neighbouring plates, and
    # each cost a verification and a re-verification in the selection (docs/picklists.md,
    # "Finding the instances").
    deferred: list[tuple[tuple[tuple[int, int], ...], tuple[int, int, int],
                         tuple[int, int, int]]] = []
    tree = cKDTree(points)
    for triple in triples:
        found = _seeds(dm, dp, triple, tolerance_mm)
        seeds += found.shape[0]
        named = [tuple(sorted(zip(triple, map(int, f), strict=True))) for f in found]
        fresh = [i for i, seed in enumerate(named) if seed not in pool.covered]
        found = found[fresh]
        bare = _bare(model, points, tree, model[list(triple)], found, tolerance_mm)
        for i, (a, b, c), is_bare in zip(fresh, found, bare, strict=True):
            seed = named[i]
            if seed in pool.covered:
                continue
            if is_bare:
                deferred.append((seed, triple, (int(a), int(b), int(c))))
                continue
            if pool.verified >= max_verified:
                complete = False
                break
            hyp = pool.verify(kabsch(model[list(triple)], points[[a, b, c]]))
            if hyp is not None:
                pool.add(hyp)
        if not complete:
            break
    if complete:
        explained = _explained(pool)
        for seed, triple, rows in deferred:
            if seed in pool.covered or all(q in explained for q in rows):
                continue
            if pool.verified >= max_verified:
                complete = False
                break
            hyp = pool.verify(kabsch(model[list(triple)], points[list(rows)]))
            if hyp is not None:
                pool.add(hyp)
    accepted = _select(pool, max_instances)
    return Grouping(tuple(_judge(pool, accepted)), seeds, pool.verified, complete)


def _bare(model: FloatArray, points: FloatArray, tree: cKDTree, seed_model: FloatArray,
          found: npt.NDArray[np.intp], tolerance_mm: float) -> npt.NDArray[np.bool_]:
    """(h,) per seed of ``found`` (h, 3): no model point but the seed's three comes within
    the tolerance of a measured point at the seed's motion (a bare triangle, at least before a
    refit; a plate's own well-spread seeds find its other marks at once). ``tree``: the
    points' k-d tree."""
    if not found.size:
        return np.zeros(0, dtype=bool)
    R, t = _kabsch_many(seed_model, points[found])
    moved = np.einsum("hij,nj->hni", R, model) + t[:, None, :]
    dist, _ = tree.query(moved.reshape(-1, 3), distance_upper_bound=tolerance_mm)
    near = np.isfinite(dist).reshape(moved.shape[:2])
    return np.asarray(near.sum(axis=1) <= 3)


def _explained(pool: _Pool) -> set[int]:
    """Points that share an image blob (a key) with a verified hypothesis of four or more
    features that fits within the limit and scores more than a bare triangle could come within
    ``AMBIGUITY_MARGIN`` of: a bare triangle made only of such points can neither be selected
    (its blobs are taken by a better instance) nor make one of those ambiguous. The shared
    blob covers the other epipolar pairings of a plate's marks, too."""
    keys: set[int] = set()
    for hyp in pool.hyps:
        if hyp.count >= 4 and hyp.rms <= pool.max_rms and hyp.score > 3.0 + AMBIGUITY_MARGIN:
            keys |= _claims(hyp, pool.keys)
    return {row for row, ks in enumerate(pool.keys) if keys.intersection(ks)}


def _claims(hyp: _Hypothesis, keys: Sequence[tuple[int, ...]]) -> set[int]:
    return {k for q in hyp.assignment if q >= 0 for k in keys[int(q)]}


def _blocked_by(claimed: set[int], owners: dict[int, list[int]], m: int
                ) -> npt.NDArray[np.bool_]:
    """Rows (m,) that share a key with ``claimed``."""
    blocked = np.zeros(m, dtype=bool)
    for key in claimed:
        blocked[owners.get(key, [])] = True
    return blocked


def _owners(keys: Sequence[tuple[int, ...]]) -> dict[int, list[int]]:
    owners: dict[int, list[int]] = {}
    for row, ks in enumerate(keys):
        for key in ks:
            owners.setdefault(key, []).append(row)
    return owners


def _select(pool: _Pool, max_instances: int) -> list[_Hypothesis]:
    """Best score first; a hypothesis touching claimed points is verified again on the free
    points and requeued (never merged with the instance that claimed them)."""
    keys = pool.keys
    owners = _owners(keys)
    blocked = np.zeros(pool.points.shape[0], dtype=bool)
    heap = [(-h.score, h.rms, i, h) for i, h in enumerate(pool.hyps)]
    heapq.heapify(heap)
    tie = len(heap)
    accepted: list[_Hypothesis] = []
    while heap and len(accepted) < max_instances:
        _, _, _, hyp = heapq.heappop(heap)
        rows = hyp.assignment[hyp.assignment >= 0]
        if not blocked[rows].any():
            accepted.append(hyp)
            blocked |= _blocked_by(_claims(hyp, keys), owners, blocked.size)
            continue
        again = pool.verify(hyp.T, ~blocked)
        if again is not None:
            tie += 1
            heapq.heappush(heap, (-again.score, again.rms, tie, again))
    return accepted


def _judge(pool: _Pool, accepted: list[_Hypothesis]) -> list[InstanceMatch]:
    """Each accepted hypothesis as an instance, with its rival (module docstring, step 4)."""
    keys = pool.keys
    owners = _owners(keys)
    m = pool.points.shape[0]
    claims = [_claims(h, keys) for h in accepted]
    # Per hypothesis of the pool: the keys it uses (computed once).
    pool_claims = [_claims(h, keys) for h in pool.hyps]
    out: list[InstanceMatch] = []
    for idx, hyp in enumerate(accepted):
        others = set().union(*(c for j, c in enumerate(claims) if j != idx))
        free: npt.NDArray[np.bool_] | None = None
        rival = 0.0
        for other, used in zip(pool.hyps, pool_claims, strict=True):
            if other is hyp or other.score < hyp.score - AMBIGUITY_MARGIN - 1.0:
                continue
            if not used & claims[idx]:
                continue
            if _moved(pool.model, hyp.T, other.T) <= pool.tol:
                continue
            if used & others:
                if free is None:
                    free = ~_blocked_by(others, owners, m)
                again = pool.verify(other.T, free)
            else:
                again = other
            if again is None or _moved(pool.model, hyp.T, again.T) <= pool.tol:
                continue
            valid = again.rms <= pool.max_rms or hyp.rms > pool.max_rms
            if valid:
                rival = max(rival, again.score)
        out.append(InstanceMatch(
            assignment=hyp.assignment, T_points_model=hyp.T, rms_mm=hyp.rms,
            score=hyp.score, ambiguous=rival >= hyp.score - AMBIGUITY_MARGIN, rival=rival))
    return out


# --------------------------------------------------------------------------- one camera

@dataclass(frozen=True)
class MonoInstance:
    """One instance among identified detections in one image: ``assignment`` (n_model,) index
    into the detections (-1: not seen), ``T_cam_obj`` from PnP, its reprojection RMS (px)."""

    assignment: npt.NDArray[np.intp]
    T_cam_obj: FloatArray
    rms_px: float
    ambiguous: bool

    @property
    def count(self) -> int:
        return int((self.assignment >= 0).sum())


def find_instances_mono(
    model: FloatArray,
    feature: npt.NDArray[np.intp],
    px: FloatArray,
    side_px: FloatArray,
    size_mm: FloatArray,
    camera: CameraModel,
    tolerance_px: float,
    *,
    min_count: int = 4,
) -> list[MonoInstance]:
    """Every instance of an object of identified markers repeated on identical objects, seen by
    one camera (``feature[i]``: the model feature of detection i, ``px[i]`` its centre,
    ``side_px[i]`` its mean side; ``size_mm`` per model feature).

    A marker's identity says which feature it is, not which object it belongs to. Two
    detections of different features whose image distance fits the model distance at the
    first one's scale (``side_px / size_mm``, within 40 %) seed a similarity of the model's xy
    plane onto the image (both handednesses: the plate may be seen from either side of its
    frame); the nearest detection of each further feature within a third of the smallest model
    distance joins, PnP on the group gives the pose, and every feature is assigned again to the
    nearest detection within ``tolerance_px`` of its projection and PnP repeated. Groups are
    accepted most features first, then lowest RMS; one that shares a detection with an accepted
    group is assigned again on the free detections (never merged).
    """
    k, n = px.shape[0], model.shape[0]
    if k < min_count:
        return []
    by_feature = [np.flatnonzero(feature == f) for f in range(n)]
    xy = model[:, :2]
    dm = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    spacing = float(dm[dm > 0].min()) if (dm > 0).any() else 1.0
    hyps: dict[tuple[int, ...], MonoInstance] = {}
    # Detection pairs inside a hypothesis already found: seeding from them again finds the
    # same group (each PnP costs milliseconds; a plate of five markers has twenty such pairs).
    covered: set[tuple[int, int]] = set()
    for a in range(k):
        fa = int(feature[a])
        scale = side_px[a] / size_mm[fa]
        for b in range(k):
            fb = int(feature[b])
            if fb == fa or dm[fa, fb] <= 0 or (min(a, b), max(a, b)) in covered:
                continue
            d = float(np.linalg.norm(px[b] - px[a]))
            if not 0.6 * dm[fa, fb] * scale <= d <= 1.4 * dm[fa, fb] * scale:
                continue
            vm = complex(*(xy[fb] - xy[fa]))
            vp = complex(*(px[b] - px[a]))
            for mirror in (False, True):
                z = vp / (vm.conjugate() if mirror else vm)
                rel = xy - xy[fa]
                w = rel[:, 0] - 1j * rel[:, 1] if mirror else rel[:, 0] + 1j * rel[:, 1]
                pred = complex(*px[a]) + z * w
                guess = np.stack([pred.real, pred.imag], axis=1)
                assignment = _nearest_detections(guess, px, by_feature,
                                                 spacing * abs(z) / 3.0)
                hyp = _mono_fit(model, px, assignment, camera, by_feature, tolerance_px,
                                min_count)
                if hyp is not None:
                    hyps.setdefault(tuple(int(x) for x in hyp.assignment), hyp)
                    group = sorted(int(x) for x in hyp.assignment if x >= 0)
                    covered.update(combinations(group, 2))
                    if (min(a, b), max(a, b)) in covered:
                        break  # this seed's other handedness: the same pair, covered
    return _select_mono(list(hyps.values()), model, px, camera, by_feature, tolerance_px,
                        min_count)


def _nearest_detections(guess: FloatArray, px: FloatArray,
                        by_feature: list[npt.NDArray[np.intp]], radius_px: float,
                        free: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.intp]:
    """Per model feature, the nearest (free) detection of that feature within ``radius_px`` of
    its predicted pixel, -1 if none."""
    out = np.full(len(by_feature), -1, dtype=np.intp)
    for f, rows in enumerate(by_feature):
        if free is not None:
            rows = rows[free[rows]]
        if not rows.size:
            continue
        d = np.linalg.norm(px[rows] - guess[f], axis=1)
        j = int(np.argmin(d))
        if d[j] <= radius_px:
            out[f] = rows[j]
    return out


def _mono_fit(model: FloatArray, px: FloatArray, assignment: npt.NDArray[np.intp],
              camera: CameraModel, by_feature: list[npt.NDArray[np.intp]],
              tolerance_px: float, min_count: int,
              free: npt.NDArray[np.bool_] | None = None) -> MonoInstance | None:
    """PnP on the assigned features, reassignment within ``tolerance_px`` of the projections,
    PnP again; None under ``min_count`` features or when PnP refuses the points."""
    for _ in range(2):
        sel = np.flatnonzero(assignment >= 0)
        if sel.size < min_count:
            return None
        try:
            result = pnp(model[sel], px[assignment[sel]], camera)
        except GeometryError:
            return None
        T = result.T_cam_obj
        cam_pts = model @ T[:3, :3].T + T[:3, 3]
        if (cam_pts[:, 2] <= 0).any():
            return None
        again = _nearest_detections(camera.project(cam_pts), px, by_feature, tolerance_px,
                                    free)
        if np.array_equal(again, assignment):
            break
        assignment = again
    sel = np.flatnonzero(assignment >= 0)
    if sel.size < min_count:
        return None
    return MonoInstance(assignment, T, float(result.rms_px), bool(result.ambiguous))


def _select_mono(hyps: list[MonoInstance], model: FloatArray, px: FloatArray,
                 camera: CameraModel, by_feature: list[npt.NDArray[np.intp]],
                 tolerance_px: float, min_count: int) -> list[MonoInstance]:
    heap = [(-h.count, h.rms_px, i, h) for i, h in enumerate(hyps)]
    heapq.heapify(heap)
    tie = len(heap)
    used = np.zeros(px.shape[0], dtype=bool)
    accepted: list[MonoInstance] = []
    while heap and len(accepted) < MAX_INSTANCES:
        _, _, _, hyp = heapq.heappop(heap)
        rows = hyp.assignment[hyp.assignment >= 0]
        if not used[rows].any():
            accepted.append(hyp)
            used[rows] = True
            continue
        free = ~used
        start = hyp.assignment.copy()
        start[(start >= 0) & ~free[np.maximum(start, 0)]] = -1
        again = _mono_fit(model, px, start, camera, by_feature, tolerance_px, min_count, free)
        if again is not None:
            tie += 1
            heapq.heappush(heap, (-again.count, again.rms_px, tie, again))
    return accepted
