"""Correspondence: which measured points are which, for the finders' output
(``vgripd.vision.features``).

- ``match_epipolar``: left/right candidate pairs whose right pixel lies within a tolerance of the
  left pixel's epipolar line.
- ``match_model``: which triangulated candidates are which model features, from the distances the
  model fixes (a rigid motion keeps them). Hypothesise and verify over every model triangle: seeds
  are model triples matched to candidate triples with the same three distances, each seed's rigid
  motion is scored by the further candidates it explains, the best pose wins and spurious
  candidates are left out; a rival pose scoring about as well, or a match that the spurious points
  would make by chance, is reported as ambiguous. The work is bounded and stops early once nothing
  unseen could rival the winner.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np
import numpy.typing as npt

from vgripd.types import FloatArray


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
    """Which measured point is which model feature, and how sure that is.

    ``assignment`` (n_model,): index into the measured points, -1 where the feature was not
    found. ``T_points_model`` (4, 4): the rigid motion that maps model points onto the measured
    ones, least squares over the assigned features (the pipeline fits again, robustly and with
    the circle-centre bias removed). ``rms_mm``: RMS distance of the assigned points from the
    moved model. ``score``: the support of the pose, sum over the assigned features of
    ``max(0, 1 - (d / s)**2)`` with ``s = score_scale(...)`` (a feature exactly in place counts
    1, one at ``s`` or further 0). ``rival``: the score of the best hypothesis whose pose
    differs materially from the winner's (0 when there is none; when no hypothesis fits within
    ``max_rms_mm``, winner and rival are compared by feature counts instead). ``complete``: the
    search saw every hypothesis that could come within ``AMBIGUITY_MARGIN`` of the winner
    (False only when the work bound stopped it first). ``nfa``: expected number of equally good
    hypotheses that the unused (spurious) points would make by chance (``_Search.chance``).
    ``ambiguous``: a rival comes within the margin, the search is incomplete, or ``nfa >= 1``:
    the winner cannot be told from another pose or from a coincidence of clutter.
    ``hypotheses``: how many were scored.
    """

    assignment: npt.NDArray[np.intp]
    T_points_model: FloatArray
    ambiguous: bool
    rms_mm: float = 0.0
    score: float = 0.0
    rival: float = 0.0
    complete: bool = True
    hypotheses: int = 0
    nfa: float = 0.0

    @property
    def count(self) -> int:
        return int((self.assignment >= 0).sum())


#: A rival pose scoring within this of the winner makes the match ambiguous: the winner must
#: explain at least half a feature more (one more mark in place, or the same marks clearly
#: closer: three marks at 0.33 of the score scale score 0.33 less than three in place).
AMBIGUITY_MARGIN = 0.5

#: Seed triangles (model triples) thinner than this share of the tolerance are not used: the
#: rotation about their long side is not determined by the points.
MIN_SEED_ALTITUDE = 0.5

#: Seeds scored together (bounds the (h, n, m) distance arrays of the bulk scoring).
_CHUNK = 1024


def score_scale(tolerance_mm: float, max_rms_mm: float) -> float:
    """Distance (mm) at which a feature stops adding to a hypothesis' score: the tolerance, or
    twice the RMS the fit check accepts when that is tighter. A feature at a fifth of it scores
    0.96, at half of it 0.75; a clutter blob that merely falls within a 3 mm tolerance of
    where a mark should be adds little against marks fitted to a tenth of a millimetre."""
    return min(tolerance_mm, 2.0 * max_rms_mm)


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


def _kabsch_many(
    a: FloatArray, b: FloatArray, w: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """Weighted ``kabsch`` of many point sets at once: model points a (h, k, 3) (or one set
    (k, 3) for all) onto b (h, k, 3) with weights w (h, k) (None: all 1). Returns rotations
    (h, 3, 3) and translations (h, 3); a set with fewer than three weighted points gets some
    finite motion (the callers score it, they do not trust it)."""
    a = np.broadcast_to(a, b.shape)
    if w is None:
        w = np.ones(b.shape[:2])
    sw = np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    ca = (w[..., None] * a).sum(axis=1) / sw
    cb = (w[..., None] * b).sum(axis=1) / sw
    cov = np.einsum("hk,hki,hkj->hij", w, a - ca[:, None, :], b - cb[:, None, :])
    u, _, vt = np.linalg.svd(cov)
    v = np.swapaxes(vt, 1, 2).copy()
    ut = np.swapaxes(u, 1, 2)
    d = np.sign(np.linalg.det(v @ ut))
    v[:, :, 2] *= np.where(d == 0, 1.0, d)[:, None]
    R = v @ ut
    return R, cb - np.einsum("hij,hj->hi", R, ca)


def _transform(R: FloatArray, t: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _spread_order(model: FloatArray) -> list[int]:
    """Model indices, the two farthest apart first, then each time the point farthest from
    those already taken: the first triples span the layout and make well-conditioned seeds."""
    d = _pairwise(model)
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)
    order = [int(i), int(j)]
    rest = [r for r in range(model.shape[0]) if r not in order]
    while rest:
        k = max(rest, key=lambda r: float(d[r, order].min()))
        order.append(k)
        rest.remove(k)
    return order


def _altitudes(model: FloatArray) -> FloatArray:
    """(n, n, n): smallest altitude of every model triangle (twice its area over its longest
    side; 0 for a repeated point)."""
    e = model[None, :, :] - model[:, None, :]  # e[i, j] = p_j - p_i
    area2 = np.linalg.norm(np.cross(e[:, :, None, :], e[:, None, :, :]), axis=3)
    d = np.linalg.norm(e, axis=2)
    longest = np.maximum(np.maximum(d[:, :, None], d[:, None, :]), d[None, :, :])
    return np.asarray(np.where(longest > 0, area2 / np.where(longest > 0, longest, 1.0), 0.0))


@dataclass(frozen=True)
class _Hypothesis:
    assignment: npt.NDArray[np.intp]
    T: FloatArray
    rms: float
    score: float

    @property
    def count(self) -> int:
        return int((self.assignment >= 0).sum())


class _Search:
    """State of one ``match_model`` search (see there)."""

    def __init__(self, model: FloatArray, points: FloatArray, tolerance_mm: float,
                 keys: Sequence[tuple[int, ...]], max_rms_mm: float) -> None:
        self.model, self.points, self.tol, self.keys = model, points, tolerance_mm, keys
        self.max_rms = max_rms_mm
        self.scale = score_scale(tolerance_mm, max_rms_mm)
        n, m = model.shape[0], points.shape[0]
        # Two points may be used together unless they are one point or share a key.
        owners: dict[int, list[int]] = {}
        for row, ks in enumerate(keys):
            for key in ks:
                owners.setdefault(key, []).append(row)
        together = ~np.eye(m, dtype=bool)
        for group in owners.values():
            if len(group) > 1:
                together[np.ix_(group, group)] = False
        self.dp = np.where(together, _pairwise(points), np.inf)
        self.dm = _pairwise(model)
        # compat[i, j, a, b]: points a, b are as far apart as model points i, j (row i filled
        # when a seed first uses feature i: all marks visible, three rows).
        self.compat = np.empty((n, n, m, m), dtype=bool)
        self.filled = np.zeros(n, dtype=bool)
        self.seedable = _altitudes(model) >= MIN_SEED_ALTITUDE * tolerance_mm
        self.p2 = (points**2).sum(axis=1)
        # Hypotheses explaining more than their seed, verified one by one.
        self.full: list[_Hypothesis] = []
        self.seen: set[tuple[int, ...]] = set()
        self.covered: set[tuple[tuple[int, int], ...]] = set()  # seeds inside self.full
        # Bare triangles: seeds that explain nothing beyond their three points (most seeds in
        # clutter), kept in bulk as chunks of (features, points, R, t, RMS, score).
        self.bare: list[tuple[npt.NDArray[Any], ...]] = []
        self.best = 0.0  # score of the best hypothesis within max_rms_mm
        self.verified = 0
        self.seeds = 0

    def stage_seeds(self, triples: npt.NDArray[np.intp]
                    ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
        """Every point triple with the distances of one of the model ``triples`` (t, 3):
        the seeds' model triples (h, 3) and point triples (h, 3)."""
        I, J, K = triples.T
        for i in map(int, np.unique(triples)):
            if not self.filled[i]:
                self.compat[i] = np.abs(self.dp[None] - self.dm[i][:, None, None]) < self.tol
                self.filled[i] = True
        p, a, b = np.nonzero(self.compat[I, J])
        e, c = np.nonzero(self.compat[J[p], K[p], b] & self.compat[I[p], K[p], a])
        return triples[p[e]], np.stack([a[e], b[e], c], axis=1)

    def _nearest(self, moved: FloatArray) -> tuple[npt.NDArray[np.intp], FloatArray]:
        """Nearest point (h, n) to each moved model point and its squared distance."""
        d2 = (moved**2).sum(axis=2)[:, :, None] + self.p2 - 2.0 * moved @ self.points.T
        near = np.argmin(d2, axis=2)
        return near, np.take_along_axis(d2, near[:, :, None], axis=2)[:, :, 0]

    def stage(self, feats: npt.NDArray[np.intp], pts: npt.NDArray[np.intp],
              max_hypotheses: int) -> bool:
        """Score a stage's seeds in bulk, keep the bare triangles, verify the rest (most
        features first). False when the work bound was reached."""
        found: list[tuple[int, float, tuple[tuple[int, int], ...], FloatArray, FloatArray]] = []
        tol2 = self.tol**2
        for start in range(0, feats.shape[0], _CHUNK):
            f, q = feats[start : start + _CHUNK], pts[start : start + _CHUNK]
            # A fourth feature needs a point at its three model distances from the seed's
            # points (within the tolerance): seeds without one are bare triangles, found
            # from the distance table alone (most seeds in clutter).
            fourth = (self.compat[f[:, 0], :, q[:, 0], :] & self.compat[f[:, 1], :, q[:, 1], :]
                      & self.compat[f[:, 2], :, q[:, 2], :]).any(axis=(1, 2))
            if not fourth.all():
                self._bare(f[~fourth], q[~fourth])
                f, q = f[fourth], q[fourth]
                if not f.size:
                    continue
            R, t = _kabsch_many(self.model[f], self.points[q])
            moved = np.einsum("hij,nj->hni", R, self.model) + t[:, None, :]
            own2 = ((np.take_along_axis(moved, f[:, :, None], axis=1)
                     - self.points[q]) ** 2).sum(axis=2)
            # Features within the tolerance of a point, at the seed's motion or after one refit
            # on those points (a thin seed's motion is only as good as its three points): an
            # upper estimate of the score verification can find (it ignores shared blobs).
            near, d2 = self._nearest(moved)
            close = d2 < tol2
            count = close.sum(axis=1)
            R2, t2 = R.copy(), t.copy()
            wide = (d2 < 4.0 * tol2).sum(axis=1)
            redo = np.flatnonzero((wide > count) & (wide >= max(4.0, self.best - AMBIGUITY_MARGIN)))
            if redo.size:
                Rr, tr = _kabsch_many(self.model, self.points[near[redo]],
                                      close[redo].astype(np.float64))
                moved2 = np.einsum("hij,nj->hni", Rr, self.model) + tr[:, None, :]
                count2 = (self._nearest(moved2)[1] < tol2).sum(axis=1)
                better = count2 > count[redo]
                R2[redo[better]], t2[redo[better]] = Rr[better], tr[better]
                count[redo[better]] = count2[better]
            bare = count <= 3
            if bare.any():
                self._bare(f[bare], q[bare], R[bare], t[bare], own2[bare])
            for h in np.flatnonzero(~bare):
                seed = tuple(sorted(zip(map(int, f[h]), map(int, q[h]), strict=True)))
                found.append((int(count[h]), float(own2[h].sum()), seed, R2[h], t2[h]))
        found.sort(key=lambda x: (-x[0], x[1]))
        for count_h, _, seed, R_h, t_h in found:
            if count_h < self.best - AMBIGUITY_MARGIN:
                break  # cannot win, nor come within the margin of the best
            if seed in self.covered:
                continue  # part of a hypothesis already verified: it would repeat it
            if self.verified >= max_hypotheses:
                return False
            self.verified += 1
            self.verify(_transform(R_h, t_h))
        return True

    def _bare(self, f: npt.NDArray[np.intp], q: npt.NDArray[np.intp],
              R: FloatArray | None = None, t: FloatArray | None = None,
              own2: FloatArray | None = None) -> None:
        """Keep seeds (f, q) as bare triangles (their motion and residuals computed here
        unless given)."""
        if R is None or t is None or own2 is None:
            R, t = _kabsch_many(self.model[f], self.points[q])
            moved = np.einsum("hij,hkj->hki", R, self.model[f]) + t[:, None, :]
            own2 = ((moved - self.points[q]) ** 2).sum(axis=2)
        rms = np.sqrt(own2.mean(axis=1))
        score = np.clip(1.0 - own2 / self.scale**2, 0.0, None).sum(axis=1)
        self.bare.append((f, q, R, t, rms, score))
        valid = rms <= self.max_rms
        if valid.any():
            self.best = max(self.best, float(score[valid].max()))

    def verify(self, T: FloatArray) -> None:
        hyp = _verify(self.model, self.points, T, self.tol, self.keys, self.max_rms, self.scale)
        if hyp is None:
            return
        assigned = tuple(int(x) for x in hyp.assignment)
        if assigned in self.seen:
            return
        self.seen.add(assigned)
        self.full.append(hyp)
        inliers = [(f, q) for f, q in enumerate(assigned) if q >= 0]
        self.covered.update(combinations(inliers, 3))
        if hyp.rms <= self.max_rms:
            self.best = max(self.best, hyp.score)

    def result(self, complete: bool) -> ModelMatch | None:
        n = self.model.shape[0]
        if self.bare:
            f, q, R, t, rms, score = (np.concatenate(c) for c in zip(*self.bare, strict=True))
        else:
            f = q = np.zeros((0, 3), dtype=np.intp)
            R, t, rms, score = np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0)
        if not self.full and not rms.size:
            return None
        ok = rms <= self.max_rms
        hyps = [h for h in self.full if h.rms <= self.max_rms]
        if hyps or ok.any():
            # Valid hypotheses (RMS within the fit check) compete by score.
            value, bare_value, margin = (lambda h: h.score), score, AMBIGUITY_MARGIN
        else:
            # Nothing fits within the limit: the most features (then the least RMS) is kept for
            # the residual check to judge; another pose with as many makes it ambiguous.
            hyps, ok = list(self.full), np.ones_like(ok)
            value, bare_value, margin = (lambda h: float(h.count)), np.full(rms.shape, 3.0), 0.0
        best = max(hyps, key=lambda h: (value(h), -h.rms), default=None)
        if ok.any():
            i = int(np.argmax(np.where(ok, bare_value - 1e-9 * rms, -np.inf)))
            if best is None or bare_value[i] > value(best):
                assignment = np.full(n, -1, dtype=np.intp)
                assignment[f[i]] = q[i]
                best = _Hypothesis(assignment, _transform(R[i], t[i]), float(rms[i]),
                                   float(score[i]))
        assert best is not None
        # A rival: another pose (the model moves by more than the tolerance), not the same pose
        # with one alternative candidate swapped in.
        rival = max((value(h) for h in hyps
                     if h is not best and _moved(self.model, best.T, h.T) > self.tol),
                    default=0.0)
        close = ok & (bare_value >= value(best) - margin)
        if close.any():
            here = self.model @ best.T[:3, :3].T + best.T[:3, 3]
            there = np.einsum("hij,nj->hni", R[close], self.model) + t[close][:, None, :]
            other = np.linalg.norm(there - here, axis=2).max(axis=1) > self.tol
            if other.any():
                rival = max(rival, float(bare_value[close][other].max()))
        nfa = self.chance(best)
        return ModelMatch(
            assignment=best.assignment,
            T_points_model=best.T,
            ambiguous=rival >= value(best) - margin or not complete or nfa >= 1.0,
            rms_mm=best.rms,
            score=best.score,
            rival=rival,
            complete=complete,
            hypotheses=self.verified + int(rms.size),
            nfa=nfa,
        )

    def chance(self, best: _Hypothesis) -> float:
        """Expected number of hypotheses as good as ``best`` made by the unused points alone
        (a contrario; under 1: ``best`` is not a coincidence of clutter).

        Three features of ``best`` (its best-fitting) are taken as the seed; each further
        feature at residual d is a hit a spurious point makes by chance with probability
        ``F(d) = rho pi d^2``, rho the density of the unused candidates over the disc the
        model covers (R + tolerance around its centroid; points near a plate lie near a plane,
        so an area density is the conservative choice). The number of trials is the seeds
        tried times the ways of choosing the further features among the n - 3 others.
        Three-feature hypotheses have nothing to test: 0.
        """
        sel = np.flatnonzero(best.assignment >= 0)
        extra = sel.size - 3
        if extra <= 0:
            return 0.0
        moved = self.model @ best.T[:3, :3].T + best.T[:3, 3]
        res = np.sort(np.linalg.norm(moved[sel] - self.points[best.assignment[sel]], axis=1))
        centre = moved.mean(axis=0)
        radius = float(np.linalg.norm(moved - centre, axis=1).max()) + self.tol
        unused = np.ones(self.points.shape[0], dtype=bool)
        unused[best.assignment[sel]] = False
        near = np.linalg.norm(self.points[unused] - centre, axis=1) <= radius
        rho = float(near.sum()) / (np.pi * radius**2)
        hits = np.minimum(1.0, rho * np.pi * res[3:] ** 2)
        trials = max(self.seeds, 1) * math.comb(self.model.shape[0] - 3, extra)
        return float(trials * np.prod(hits))


def match_model(
    model: FloatArray,
    points: FloatArray,
    tolerance_mm: float,
    exclusive: Sequence[Sequence[int]] | None = None,
    *,
    max_rms_mm: float = float("inf"),
    max_hypotheses: int = 200,
    max_seeds: int = 20_000,
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
    max_rms_mm : a hypothesis whose fitted RMS exceeds this is not a valid pose: it neither
        wins over a valid one nor makes it ambiguous (the pipeline passes
        ``vision.max_fit_rms_mm``, the same bound its residual check applies).
    max_hypotheses, max_seeds : the work bound: hypotheses verified one by one, seeds scored
        in bulk. A search stopped by it is ``complete`` only if what it did not see could not
        have come within the margin of the winner; otherwise it is ``ambiguous``.

    Hypothesise and verify. A seed maps a model triple (i, j, k) onto a point triple (a, b, c)
    whose three distances agree within ``tolerance_mm``; its rigid motion carries the whole
    model onto the points. Seeds are scored in bulk (features within the tolerance, at the
    seed's motion and after one refit); those explaining nothing beyond their own three points
    are bare triangles, scored as they are. The others are verified, most features first: every
    model point takes the nearest free point within the tolerance (greedy by distance), the
    motion is fitted to those points and the assignment redone until it settles, and a gross
    outlier that alone lifts the RMS over ``max_rms_mm`` is dropped. Each hypothesis scores
    ``sum(max(0, 1 - (d / s)**2))`` over its features, ``s = score_scale(tolerance_mm,
    max_rms_mm)`` (the truncated quadratic of MSAC): more marks win, and a coincidence of
    clutter blobs that only falls within the tolerance weighs less than marks in place. The
    winner is ambiguous when a materially different pose scores within ``AMBIGUITY_MARGIN`` of
    it.

    Seeds come from *every* model triple, in stages: with the model points in a spread order
    o_0, o_1, ..., stage r tries the triples of {o_0..o_r} that contain o_r. After stage r each
    hypothesis with three features among o_0..o_r has been seen, so an unseen one scores at
    most n - r + 1; the search stops as soon as the best valid score minus the margin exceeds
    that. All marks visible: one triple; k of n visible: the triples of about n - k + 4 points.
    Seeds already contained in a verified hypothesis, or that cannot come within the margin of
    the best, are not verified.

    Returns None when no seed matches at all (fewer than 3 consistent points).
    """
    n, m = model.shape[0], points.shape[0]
    if m < 3 or n < 3:
        return None
    keys = [tuple(k) for k in exclusive] if exclusive is not None else [(i,) for i in range(m)]
    search = _Search(model, points, tolerance_mm, keys, max_rms_mm)
    order = _spread_order(model)
    done = 1  # stages whose seeds have all been tried (stage 1: no triple yet)
    for r in range(2, n):
        k = order[r]
        triples = np.array([(i, j, k) for i, j in combinations(order[:r], 2)
                            if search.seedable[i, j, k]], dtype=np.intp).reshape(-1, 3)
        feats, pts = search.stage_seeds(triples)
        room = max(0, max_seeds - search.seeds)
        search.seeds += min(room, feats.shape[0])
        if not search.stage(feats[:room], pts[:room], max_hypotheses) or room < feats.shape[0]:
            break  # the work bound: this stage is unfinished
        done = r
        # Every hypothesis with three features among order[:r + 1] has been seen.
        if search.best - AMBIGUITY_MARGIN > n - r + 1:
            break
    return search.result(
        complete=done == n - 1 or search.best - AMBIGUITY_MARGIN > n - done + 1)


def _verify(
    model: FloatArray,
    points: FloatArray,
    T: FloatArray,
    tolerance_mm: float,
    keys: Sequence[tuple[int, ...]],
    max_rms_mm: float = float("inf"),
    scale_mm: float | None = None,
) -> _Hypothesis | None:
    """Refine a seed's motion: assign, fit to the assigned points, assign again, until the
    assignment settles (at most four rounds). Then, while the RMS exceeds ``max_rms_mm``, gross
    outliers (e.g. a blob that happens to lie within the tolerance of a hidden mark's place)
    are dropped; uniformly high residuals (a drifted calibration) are left for the residual
    check. None when fewer than 3 features are explained."""
    assignment, _ = assign_nearest(model, points, T, tolerance_mm, keys)
    for _ in range(4):
        sel = np.flatnonzero(assignment >= 0)
        if sel.size < 3:
            return None
        T = kabsch(model[sel], points[assignment[sel]])
        again, _ = assign_nearest(model, points, T, tolerance_mm, keys)
        if np.array_equal(again, assignment):
            break
        assignment = again
    scale = tolerance_mm if scale_mm is None else scale_mm
    hyp = _fitted(model, points, assignment, scale)
    if hyp is None:
        return None
    # Gross outliers: the worst point goes when the rest then fits within the limit, or at
    # least halves the RMS (several blobs in hidden marks' places); a uniform misfit (each
    # removal helps a little) keeps every point and is judged by the residual check.
    best = hyp
    while best.rms > max_rms_mm and best.count > 3:
        res = np.linalg.norm(
            model @ best.T[:3, :3].T + best.T[:3, 3] - points[np.maximum(best.assignment, 0)],
            axis=1)
        res[best.assignment < 0] = -1.0
        trimmed = best.assignment.copy()
        trimmed[int(np.argmax(res))] = -1
        lighter = _fitted(model, points, trimmed, scale)
        if lighter is None or not (lighter.rms <= max_rms_mm or lighter.rms <= 0.5 * best.rms):
            break
        best = lighter
    return best if best.rms <= max_rms_mm else hyp


def _fitted(
    model: FloatArray, points: FloatArray, assignment: npt.NDArray[np.intp], scale_mm: float
) -> _Hypothesis | None:
    """The rigid fit of the assigned features, its RMS and score (``score_scale``); None under
    3 features."""
    sel = np.flatnonzero(assignment >= 0)
    if sel.size < 3:
        return None
    T = kabsch(model[sel], points[assignment[sel]])
    moved = model[sel] @ T[:3, :3].T + T[:3, 3]
    d2 = np.sum((moved - points[assignment[sel]]) ** 2, axis=1)
    score = float(np.clip(1.0 - d2 / scale_mm**2, 0.0, None).sum())
    return _Hypothesis(assignment, T, float(np.sqrt(np.mean(d2))), score)


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
    order = np.argsort(d[mi, pi], kind="stable")
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
