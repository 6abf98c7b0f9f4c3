"""Why a job found no valid pose: what each stage saw, and the likely causes.

Very different mistakes end with the same check message ("0 feature(s) matched, need at least
3"): marks of the other polarity, a ``vision.working_distance_mm`` that excludes the object, the
stereo transform given the wrong way round, a wrong hand-eye. A failed job therefore carries a
:class:`Diagnosis` (``JobResult.diagnosis``):

- per image: circle candidates kept, and dropped by size, contrast, circularity or the image
  border (recorded by ``features.find_circles`` as it goes, so the success path pays nothing
  for it), plus the marks of the *other* polarity that would have passed every filter (a second
  run of the finder, made only for a failed job);
- stereo: epipolar pairs, and (when pairing fails) how many left marks would find a partner
  with ``T_right_left`` inverted; paired points in front of both cameras and those outside the
  working distance;
- the model search: hypotheses tried and features explained;
- the likely causes, strongest first, each naming the config key to check and saying why in
  one line (:data:`Cause`).

The rules follow the chain: the earliest stage that lost the marks is the likeliest culprit.
``vgripd.vision.pipeline.diagnose`` runs the whole pipeline on one pair and always returns a
diagnosis (for ``vgripd check`` and commissioning); ``Pipeline.process`` attaches one to failed
jobs only.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np

from vgripd.config import CircleFeature, Config
from vgripd.errors import VgripError
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import invert_transform, rotation_angle
from vgripd.types import Status
from vgripd.vision import features as ft
from vgripd.vision.found import Found
from vgripd.vision.jobstate import PipelineView as Pipeline
from vgripd.vision.jobstate import Trace, _Job

#: Statuses whose jobs get a diagnosis: the images were usable but no valid pose came out.
DIAGNOSED = frozenset({Status.NOT_FOUND, Status.PARTIAL, Status.AMBIGUOUS,
                       Status.RESIDUAL_TOO_HIGH, Status.OUT_OF_LIMITS, Status.OUT_OF_WORKSPACE})

#: What a candidate blob's ``reason`` can be: kept and used for the pose, or why it was not.
CANDIDATE_REASONS = ("used", "model", "depth", "epipolar", "kept", *ft.REJECT_REASONS,
                     "polarity")


class Cause(NamedTuple):
    """A likely cause: the config ``key`` to check and a one-line ``reason``."""

    key: str
    reason: str

    def __str__(self) -> str:
        return f"{self.key}: {self.reason}"


class Candidate(NamedTuple):
    """A blob in one image and what became of it (``CANDIDATE_REASONS``); ``label`` is the
    short text drawn beside it (e.g. ``"contrast 18"``)."""

    x: float
    y: float
    diameter_px: float
    reason: str
    label: str


@dataclass(frozen=True)
class ImageStage:
    """The finders in one image.

    ``found``: circle candidates that passed every filter; ``identified``: ArUco/template
    features found; ``rejected``: dropped circle candidates by reason (``REJECT_REASONS``);
    ``opposite_polarity``: blobs of the other polarity that would have passed (-1: not probed);
    ``low_contrast``: blobs that would pass at a third of ``vision.min_contrast`` (-1: not
    probed); ``candidates``: every blob with its fate, for the annotated images.
    """

    side: str
    found: int
    identified: int
    rejected: dict[str, int]
    opposite_polarity: int = -1
    low_contrast: int = -1
    candidates: tuple[Candidate, ...] = ()


@dataclass(frozen=True)
class Diagnosis:
    """What each stage of one job saw, and the likely causes (strongest first).

    ``pairs``: left/right pairs along the epipolar lines (identified features included);
    ``paired_left``: left circle candidates with at least one partner; ``paired_inverted``:
    the same with ``T_right_left`` inverted (None: not probed); ``triangulated``: pairs in front
    of both cameras; ``outside_working_distance``: of those, outside
    ``vision.working_distance_mm``; ``depth_mm``: their depth range (None without any);
    ``hypotheses``: model hypotheses scored; ``best_explained``: features the best match
    assigned; ``used``: features in the final fit. Stereo counts are None for a mono job.
    """

    status: str
    images: tuple[ImageStage, ...]
    pairs: int | None = None
    paired_left: int | None = None
    paired_inverted: int | None = None
    triangulated: int | None = None
    outside_working_distance: int | None = None
    depth_mm: tuple[float, float] | None = None
    hypotheses: int = 0
    best_explained: int = 0
    used: int = 0
    causes: tuple[Cause, ...] = ()

    @property
    def top(self) -> Cause | None:
        return self.causes[0] if self.causes else None

    def summary(self) -> str:
        """One line: the top cause with its key, or what the stages saw when there is none."""
        if self.top is not None:
            return f"likely cause: {self.top}"
        return "no likely cause found; " + self.counts_line()

    def counts_line(self) -> str:
        parts = []
        for st in self.images:
            rej = ", ".join(f"{n} {r}" for r, n in st.rejected.items() if n)
            parts.append(f"{st.side} {st.found} found" + (f" ({rej} rejected)" if rej else ""))
        if self.pairs is not None:
            parts.append(f"{self.pairs} epipolar pairs")
        if self.triangulated is not None:
            parts.append(f"{self.triangulated} triangulated, {self.outside_working_distance} "
                         "outside the working distance")
        parts.append(f"{self.best_explained} matched to the model ({self.hypotheses} "
                     "hypotheses)")
        return "; ".join(parts)

    def lines(self) -> list[str]:
        """The "why" block of ``vgripd locate``: per stage, then the causes."""
        out = []
        for st in self.images:
            rej = ", ".join(f"{r} {n}" for r, n in st.rejected.items() if n) or "none"
            line = f"  {st.side + ':':7} {st.found} mark(s) found; rejected: {rej}"
            if st.identified:
                line += f"; {st.identified} identified (ArUco/template)"
            if st.opposite_polarity > 0:
                line += f"; {st.opposite_polarity} of the other polarity would pass"
            if st.low_contrast > 0:
                line += f"; {st.low_contrast} would pass at a third of min_contrast"
            out.append(line)
        if self.pairs is not None:
            line = (f"  stereo:  {self.pairs} epipolar pair(s), {self.paired_left} left "
                    "mark(s) paired")
            if self.paired_inverted is not None:
                line += f" ({self.paired_inverted} with T_right_left inverted)"
            out.append(line)
        if self.triangulated is not None:
            depth = ("" if self.depth_mm is None else
                     f" at {self.depth_mm[0]:.0f}..{self.depth_mm[1]:.0f} mm")
            out.append(f"  depth:   {self.triangulated} triangulated{depth}, "
                       f"{self.outside_working_distance} outside vision.working_distance_mm")
        out.append(f"  model:   {self.hypotheses} hypotheses, best explains "
                   f"{self.best_explained}; {self.used} used in the fit")
        if self.causes:
            out.append("likely causes:")
            out.extend(f"  {i}. {c}" for i, c in enumerate(self.causes, 1))
        else:
            out.append("likely causes: none found")
        return out

    def as_dict(self) -> dict[str, Any]:
        """JSON data (candidates left out: they are for the annotated images)."""
        return {
            "summary": self.summary(),
            "causes": [{"key": c.key, "reason": c.reason} for c in self.causes],
            "images": [{"side": s.side, "found": s.found, "identified": s.identified,
                        "rejected": dict(s.rejected), "opposite_polarity": s.opposite_polarity,
                        "low_contrast": s.low_contrast} for s in self.images],
            "pairs": self.pairs,
            "paired_left": self.paired_left,
            "paired_inverted": self.paired_inverted,
            "triangulated": self.triangulated,
            "outside_working_distance": self.outside_working_distance,
            "depth_mm": None if self.depth_mm is None else list(self.depth_mm),
            "hypotheses": self.hypotheses,
            "best_explained": self.best_explained,
            "used": self.used,
        }


# --------------------------------------------------------------------------- public API


# --------------------------------------------------------------------------- the rules


def explain(pipeline: Pipeline, job: _Job, status: Status, message: str) -> Diagnosis:
    """The diagnosis of one job from its trace (``Pipeline.process_with_points`` calls it)."""
    trace = job.trace
    if pipeline.multi is not None:
        return _explain_multi(pipeline, job, status, message)
    finders = [pipeline.find_left, pipeline.find_right]
    failed = not status.pose_valid
    stereo = len(trace.found) == 2 and pipeline.rig is not None
    # Per blob of each image: what became of it after the finder (left/right index -> reason).
    fate = _pair_fates(pipeline, trace) if stereo else [{}, {}]
    images = []
    for k, found in enumerate(trace.found):
        finder = finders[k]
        gray = trace.grays[k]
        assert finder is not None
        assert gray is not None
        images.append(_image_stage(("left", "right")[k], found, finder.specs, gray, fate[k],
                                   probe=failed))
    d = Diagnosis(status=status.name, images=tuple(images), used=len(job.used))
    if trace.assignment is not None:
        d = replace(d, best_explained=int((trace.assignment >= 0).sum()))
    d = replace(d, hypotheses=trace.hypotheses)
    paired_inverted = None
    if stereo:
        d = _stereo_counts(pipeline, trace, d)
        enough = min(len(f.circles) for f in trace.found) >= 3
        if failed and enough and d.paired_left is not None and d.paired_left < 3:
            paired_inverted = _paired(pipeline, trace, inverted=True)[0]
            d = replace(d, paired_inverted=paired_inverted)
    if not failed:
        return d
    causes: list[tuple[float, Cause]] = []
    causes += _image_causes(pipeline, trace, d)
    if stereo:
        causes += _stereo_causes(pipeline, trace, d)
    causes += _gate_causes(pipeline, job, status, message, d)
    if len(trace.found) == 1 and pipeline.rig is not None and _circle_features(pipeline.config):
        causes.append((75.0, Cause(
            "camera", "a stereo cell was given one image: circle marks carry no identity in "
            "one image, give the right image too")))
    return replace(d, causes=_ranked(causes))


def _ranked(causes: list[tuple[float, Cause]]) -> tuple[Cause, ...]:
    """Causes strongest first, one per config key."""
    causes.sort(key=lambda sc: -sc[0])
    seen: set[str] = set()
    ordered = []
    for _, c in causes:
        if c.key not in seen:
            seen.add(c.key)
            ordered.append(c)
    return tuple(ordered)


def _explain_multi(pipeline: Pipeline, job: _Job, status: Status, message: str) -> Diagnosis:
    """The diagnosis of a multi-camera job: the finders in every camera (named), and causes
    that name the camera's own config entry (``calibration.cameras.<j>``).

    Beyond the image causes of one camera (polarity, contrast, size, circularity), a camera
    that found fewer marks than it sees at the found pose (or, without a pose, at the taught
    reference) is named with both counts, and a rig the consistency check named points at the
    pose of its worst camera."""
    multi = pipeline.multi
    assert multi is not None
    trace = job.trace
    failed = not status.pose_valid
    images = []
    for j, found in enumerate(trace.found):
        gray = trace.grays[j]
        assert gray is not None
        images.append(_image_stage(multi.names[j], found, pipeline.finders[j].specs, gray, {},
                                   probe=failed))
    d = Diagnosis(status=status.name, images=tuple(images), used=len(job.used),
                  best_explained=len(job.used))
    if not failed:
        return d
    causes = _image_causes(pipeline, trace, d, cams=list(multi.cameras),
                           finders=list(pipeline.finders))
    T = job.T_base_obj if job.T_base_obj is not None else pipeline.T_base_obj_ref
    try:
        view = multi.view(trace.T_base_flange)
        sees = multi.visible(view, T).sum(axis=0)
    except VgripError:  # robot-mounted cameras: where they were is not kept in the trace
        sees = None
    where = "at the found pose" if job.T_base_obj is not None else "at the taught reference"
    if sees is not None:
        for j, st in enumerate(d.images):
            if sees[j] >= 3 and st.found + st.identified < min(3, int(sees[j])):
                causes.append((65.0 + sees[j] - st.found, Cause(
                    f"calibration.cameras.{j}",
                    f"camera {multi.names[j]} found {st.found} mark(s) but sees {sees[j]} "
                    f"{where}: is it aimed at the object, in focus, and its image the one "
                    "given for it (image order = calibration.cameras order)?")))
    for name in trace.odd:
        members = next((m for g, m in multi.groups if g == name), ())
        # Under the other rigs' pose (``rest_px``) the camera that moved stands out; under
        # the joint pose (``reprojection_px``) its partner shares the error.
        errors = [(job.residuals.get(f"camera.{multi.names[j]}.rest_px",
                                     job.residuals.get(
                                         f"camera.{multi.names[j]}.reprojection_px", 0.0)), j)
                  for j in members]
        if not errors:
            continue
        rms, j = max(errors)
        mounted = pipeline.config.calibration
        kind = ("T_flange_camera" if mounted is not None and mounted.cameras is not None
                and mounted.cameras[j].mounting == "robot" else "T_base_camera")
        causes.append((90.0, Cause(
            f"calibration.cameras.{j}.{kind}",
            f"rig {name} disagrees with the others (its worst camera {multi.names[j]}, "
            f"{rms:.2f} px RMS): that camera moved since calibration, recalibrate it "
            "(vgripd calibrate cameras)")))
    if status is Status.AMBIGUOUS:
        causes.append((50.0, Cause(
            "object.features",
            "two poses explain the marks about equally well: make the marks' pairwise "
            "distances differ by a few mm, or remove clutter near the object")))
    elif status is Status.RESIDUAL_TOO_HIGH and not trace.odd:
        causes.append((55.0, Cause(
            "calibration.cameras",
            f"{message}: no single rig stands out: the model's xyz_mm, or several cameras' "
            "calibration")))
    elif status in (Status.PARTIAL, Status.NOT_FOUND):
        seen_by = [j for j, n in enumerate(trace.camera_marks) if n]
        causes.append((30.0, Cause(
            "object.features",
            f"{len(job.used)} mark(s) located from {len(seen_by)} camera(s); marks "
            f"{' '.join(job.missing) or '-'} not located: each needs two cameras (or one, "
            "once three marks fix the pose)")))
    elif status in (Status.OUT_OF_LIMITS, Status.OUT_OF_WORKSPACE):
        causes.append((40.0, Cause(
            "limits.max_translation_mm" if status is Status.OUT_OF_LIMITS
            else "limits.workspace_min_mm",
            f"{message}: the object may really lie there; else reference.T_base_obj or "
            "calibration.cameras (the base frame of every camera) is off")))
    return replace(d, causes=_ranked(causes))


def _image_stage(side: str, found: Found, specs: list[ft.CircleSpec], gray: ft.UInt8Image,
                 fate: dict[int, str], probe: bool) -> ImageStage:
    counts: Counter[str] = Counter({r: 0 for r in ft.REJECT_REASONS})
    candidates: list[Candidate] = []
    row = 0
    for blobs in found.blobs:
        for (x, y), dia in zip(blobs.xy, blobs.diameter_px, strict=True):
            reason = fate.get(row, "kept")
            candidates.append(Candidate(float(x), float(y), float(dia), reason,
                                        "" if reason in ("used", "kept") else reason))
            row += 1
        for r in blobs.rejected:
            counts[r.reason] += 1
            candidates.append(Candidate(r.x, r.y, r.diameter_px, r.reason, _label(r)))
    opposite = low = -1
    if probe and specs:
        opposite = 0
        for spec in specs:
            other: ft.Polarity = "bright" if spec.polarity == "dark" else "dark"
            blobs = ft.find_circles(gray, replace(spec, polarity=other))
            opposite += len(blobs)
            candidates += [Candidate(float(x), float(y), float(dia), "polarity", other)
                           for (x, y), dia in zip(blobs.xy, blobs.diameter_px, strict=True)]
        if len(found.circles) + counts["contrast"] < 3:
            low = sum(len(ft.find_circles(gray, replace(s, min_contrast=s.min_contrast / 3)))
                      for s in specs)
    return ImageStage(side, len(found.circles), len(found.identified), dict(counts),
                      opposite, low, tuple(candidates))


def _label(r: ft.Rejected) -> str:
    if r.reason == "size":
        return f"size {r.value:.0f}px"
    if r.reason == "contrast":
        return f"contrast {r.value:.0f}"
    if r.reason == "circularity":
        return f"round {r.value:.2f}"
    return r.reason


def _pair_fates(pipeline: Pipeline, trace: Trace) -> list[dict[int, str]]:
    """Per image, circle index -> "used" / "model" / "depth" / "epipolar"."""
    nl, nr = len(trace.found[0].circles), len(trace.found[1].circles)
    rank = {"epipolar": 0, "depth": 1, "model": 2, "used": 3}
    fates: list[dict[int, str]] = [dict.fromkeys(range(nl), "epipolar"),
                                   dict.fromkeys(range(nr), "epipolar")]
    if trace.pairs is None or trace.depth_mm is None or trace.in_front is None:
        return fates
    near, far = pipeline.config.vision.working_distance_mm
    assigned = set() if trace.assignment is None else set(trace.assignment[trace.assignment >= 0])
    for k, (i, j) in enumerate(trace.pairs):
        row = trace.first_circle_row + k
        z = trace.depth_mm[row]
        if not (trace.in_front[row] and near <= z <= far):
            fate = "depth"
        else:
            fate = "used" if row in assigned else "model"
        for side, idx in ((0, int(i)), (1, int(j))):
            if rank[fate] > rank[fates[side][idx]]:
                fates[side][idx] = fate
    return fates


def _stereo_counts(pipeline: Pipeline, trace: Trace, d: Diagnosis) -> Diagnosis:
    n_fixed = trace.first_circle_row
    pairs = trace.pairs if trace.pairs is not None else np.zeros((0, 2), dtype=np.intp)
    d = replace(d, pairs=n_fixed + len(pairs),
                paired_left=len(np.unique(pairs[:, 0])) if len(pairs) else 0)
    if trace.depth_mm is not None and trace.in_front is not None:
        near, far = pipeline.config.vision.working_distance_mm
        z = trace.depth_mm[trace.in_front]
        outside = int(((z < near) | (z > far)).sum())
        d = replace(d, triangulated=int(z.size), outside_working_distance=outside,
                    depth_mm=(float(z.min()), float(z.max())) if z.size else None)
    return d


def _paired(pipeline: Pipeline, trace: Trace, inverted: bool) -> tuple[int, float]:
    """Left circle candidates with a right partner within the epipolar tolerance (with
    ``T_right_left`` inverted when asked), and the median distance (px) of each left
    candidate's nearest right one from its line."""
    rig = pipeline.rig
    left, right = trace.found[0].circles, trace.found[1].circles
    if rig is None or not len(left) or not len(right):
        return 0, float("inf")
    if inverted:
        try:
            rig = StereoRig(rig.left, rig.right, invert_transform(rig.T_right_left))
        except VgripError:
            return 0, float("inf")
    lines = rig.epipolar_lines_right(left)
    ideal = rig.ideal_pixels(rig.right, right)
    dist = np.abs(lines[:, :2] @ ideal.T + lines[:, 2:3]).min(axis=1)
    tol = pipeline.config.vision.epipolar_tolerance_px
    return int((dist <= tol).sum()), float(np.median(dist))


def _circle_features(config: Config) -> list[tuple[int, CircleFeature]]:
    return [(i, f) for i, f in enumerate(config.object.features) if isinstance(f, CircleFeature)]


def _feature_key(config: Config, field_name: str, polarity: str | None = None) -> str:
    """``object.features[i].field`` for one feature, ``object.features[*].field`` for all."""
    circles = _circle_features(config)
    sel = [i for i, f in circles if polarity is None or f.polarity == polarity]
    if len(sel) == 1 and len(config.object.features) > 1:
        return f"object.features[{sel[0]}].{field_name}"
    return f"object.features[*].{field_name}"


def _image_causes(pipeline: Pipeline, trace: Trace, d: Diagnosis, cams: list[Any] | None = None,
                  finders: list[Any] | None = None) -> list[tuple[float, Cause]]:
    """Causes seen in single images (``cams``/``finders`` per image: default the stereo
    pair's)."""
    config = pipeline.config
    vision = config.vision
    circles = _circle_features(config)
    if not circles:
        return []
    need = min(3, len(circles))
    out: list[tuple[float, Cause]] = []
    if cams is None or finders is None:
        cams = [pipeline.left, pipeline.right]
        finders = [pipeline.find_left, pipeline.find_right]
    for k, st in enumerate(d.images):
        short = st.found < need  # this image lost the job
        lacking = st.found < len(circles)
        if not lacking:
            continue
        weight = 1.0 if short else 0.3
        polarities = sorted({f.polarity for _, f in circles})
        if st.opposite_polarity >= max(3 if short else 1, 2 * st.found):
            pol = polarities[0] if len(polarities) == 1 else "dark/bright"
            other = {"dark": "bright", "bright": "dark"}.get(pol, "the other polarity")
            out.append((100 * weight + st.opposite_polarity, Cause(
                _feature_key(config, "polarity"),
                f"{st.side} image: {st.found} {pol} mark(s) found but {st.opposite_polarity} "
                f"{other} one(s) would pass every filter: are the marks {other}?")))
        rejected = st.rejected
        total = sum(rejected.values())
        cam = cams[k]
        finder = finders[k]
        blobs = [r for b in trace.found[k].blobs for r in b.rejected]
        n_con = rejected.get("contrast", 0)
        if (n_con >= (3 if short else 1) and 2 * n_con >= total) or st.low_contrast >= 3:
            values = [r.value for r in blobs if r.reason == "contrast"]
            if values:
                what = (f"{n_con} blob(s) rejected for contrast (median {np.median(values):.0f} "
                        f"grey levels < vision.min_contrast {vision.min_contrast:g})")
            else:
                what = (f"no blob stands out by vision.min_contrast {vision.min_contrast:g} "
                        f"but {st.low_contrast} would at a third of it")
            out.append((80 * weight + n_con, Cause(
                "vision.min_contrast",
                f"{st.side} image: {what}: lower it, or improve the lighting/exposure")))
        n_size = rejected.get("size", 0)
        if n_size >= (3 if short else 1) and 2 * n_size >= total and cam is not None:
            sizes = np.array([r.value for r in blobs if r.reason == "size"])
            size = float(np.median(sizes))
            diameters = [f.diameter_mm for _, f in circles]
            dia = float(np.median(diameters))
            z = cam.fx * dia / size
            near, far = vision.working_distance_mm
            lo = max(3.0, cam.fx * min(diameters) / far)
            hi = cam.fx * max(diameters) / near
            if not near <= z <= far:
                cause = Cause("vision.working_distance_mm",
                              f"{st.side} image: {n_size} blob(s) rejected by size: about "
                              f"{size:.0f} px across, which {dia:g} mm marks are at about "
                              f"{z:.0f} mm, outside vision.working_distance_mm "
                              f"[{near:g}, {far:g}] (searched {lo:.0f}..{hi:.0f} px)")
            else:
                cause = Cause(_feature_key(config, "diameter_mm"),
                              f"{st.side} image: {n_size} blob(s) rejected by size: about "
                              f"{size:.0f} px across, outside the {lo:.0f}..{hi:.0f} px that "
                              f"{dia:g} mm marks make within vision.working_distance_mm: check "
                              "the marks' diameter_mm")
            out.append((85 * weight + n_size, cause))
        n_round = rejected.get("circularity", 0)
        if n_round >= (3 if short else 1) and 2 * n_round >= total:
            out.append((60 * weight + n_round, Cause(
                "vision.min_circularity",
                f"{st.side} image: {n_round} blob(s) rejected as not round enough "
                f"(< vision.min_circularity {vision.min_circularity:g}): strong tilt, blur, "
                "or marks touching something")))
        if short and total + st.found + max(st.opposite_polarity, 0) + max(st.low_contrast, 0) \
                == 0 and finder is not None:
            out.append((40, Cause(
                "camera", f"{st.side} image: no mark-like blob at all: is the object in view, "
                "in focus and lit?")))
    return out


def _stereo_causes(pipeline: Pipeline, trace: Trace, d: Diagnosis) -> list[tuple[float, Cause]]:
    vision = pipeline.config.vision
    out: list[tuple[float, Cause]] = []
    nl, nr = (len(f.circles) for f in trace.found)
    if min(nl, nr) >= 3 and d.paired_left is not None and d.paired_left < 3:
        inv = d.paired_inverted or 0
        _, off = _paired(pipeline, trace, inverted=False)
        tol = vision.epipolar_tolerance_px
        if inv >= 3 and inv >= 2 * d.paired_left + 1:
            out.append((95.0, Cause(
                "calibration.stereo.T_right_left",
                f"{nl} and {nr} marks found, but only {d.paired_left} left mark(s) have a "
                f"partner on their epipolar line, {inv} with T_right_left inverted: it looks "
                "inverted (it is the pose of the left camera in the right camera frame, "
                "X_R = R X_L + t, as stereoCalibrate gives it)")))
        elif off <= 5 * tol:
            out.append((70.0, Cause(
                "calibration.stereo.T_right_left",
                f"marks lie about {off:.1f} px from their epipolar lines (tolerance "
                f"vision.epipolar_tolerance_px {tol:g}): the rig has moved since it was "
                "calibrated: recalibrate it")))
        else:
            out.append((70.0, Cause(
                "calibration.stereo.T_right_left",
                f"{nl} and {nr} marks found, but only {d.paired_left} left mark(s) pair along "
                f"the epipolar lines (median {off:.0f} px off): the stereo calibration does "
                "not fit these cameras (another rig? left and right swapped?)")))
    if d.triangulated is not None and d.outside_working_distance is not None:
        inside = d.triangulated - d.outside_working_distance
        if d.outside_working_distance >= 3 and inside < 3 and d.depth_mm is not None:
            near, far = vision.working_distance_mm
            out.append((90.0, Cause(
                "vision.working_distance_mm",
                f"{d.outside_working_distance} of {d.triangulated} paired points triangulate at "
                f"{d.depth_mm[0]:.0f}..{d.depth_mm[1]:.0f} mm, outside "
                f"vision.working_distance_mm [{near:g}, {far:g}]")))
        elif inside >= 3 and d.best_explained < 3:
            out.append((50.0, Cause(
                _feature_key(pipeline.config, "xyz_mm"),
                f"{inside} points triangulated within the working distance but no three match "
                f"the model's distances within vision.model_tolerance_mm "
                f"{vision.model_tolerance_mm:g} ({d.hypotheses} hypotheses tried): check the "
                "marks' xyz_mm (object frame, mm) and the stereo calibration")))
    return out


def _gate_causes(pipeline: Pipeline, job: _Job, status: Status, message: str,
                 d: Diagnosis) -> list[tuple[float, Cause]]:
    config = pipeline.config
    vision = config.vision
    out: list[tuple[float, Cause]] = []
    fit = job.residuals.get("fit_rms_mm", 0.0)
    if status in (Status.OUT_OF_LIMITS, Status.OUT_OF_WORKSPACE) and job.T_base_obj is not None:
        centre = pipeline.model.mean(axis=0)
        ref = pipeline.T_base_obj_ref
        moved = float(np.linalg.norm((job.T_base_obj[:3, :3] - ref[:3, :3]) @ centre
                                     + job.T_base_obj[:3, 3] - ref[:3, 3]))
        turn = float(np.degrees(rotation_angle(job.T_base_obj[:3, :3] @ ref[:3, :3].T)))
        view = _reference_in_view(pipeline)
        hint = "" if view else "; with this hand-eye the taught reference is not even in view"
        key = ("calibration.hand_eye.T_base_camera"
               if config.calibration is not None
               and config.calibration.hand_eye.mounting == "fixed"
               else "calibration.hand_eye.T_flange_camera")
        limits = config.limits
        # Far beyond the limits (or the reference out of view): a calibration, not a part
        # that slid a little too far.
        far = (not view or moved > 2 * limits.max_translation_mm
               or turn > 2 * limits.max_rotation_deg)
        if not far:
            out.append((40.0, Cause(
                "limits.max_translation_mm" if status is Status.OUT_OF_LIMITS
                else "limits.workspace_min_mm",
                f"the object is found with a good fit just outside the limits ({message}): "
                "it may really lie there")))
        out.append(((85.0 if far else 35.0) + (10.0 if not view else 0.0), Cause(
            key,
            f"the marks fit the model (RMS {fit:.2f} mm) but the object is {moved:.0f} mm and "
            f"{turn:.0f} deg from reference.T_base_obj{hint}: if it lies at its taught place, "
            "the hand-eye calibration is wrong")))
        out.append((30.0, Cause(
            "reference.T_base_obj",
            f"or the reference was taught elsewhere ({status.name}: {message})")))
    elif status is Status.RESIDUAL_TOO_HIGH:
        if fit > vision.max_fit_rms_mm:
            out.append((60.0, Cause(
                _feature_key(config, "xyz_mm"),
                f"the found marks fit the model only to {fit:.2f} mm RMS (> "
                "vision.max_fit_rms_mm): the model's xyz_mm or the stereo calibration is off")))
        else:
            out.append((60.0, Cause(
                "calibration.left",
                f"{message}: the camera calibration (intrinsics, distortion) does not fit")))
    elif status is Status.AMBIGUOUS:
        out.append((50.0, Cause(
            "object.features",
            "two poses explain the marks about equally well: make the marks' pairwise "
            "distances differ by a few mm, or remove clutter near the object")))
    elif status in (Status.PARTIAL, Status.NOT_FOUND) and job.missing and d.best_explained >= 3:
        out.append((20.0, Cause(
            "object.features",
            f"marks {' '.join(job.missing)} not found: covered, out of view or rejected "
            "(see the image counts)")))
    return out


def _reference_in_view(pipeline: Pipeline) -> bool:
    """Whether the model at the taught reference projects into the left image (fixed camera;
    True when that cannot be said)."""
    T_base_camera = getattr(pipeline, "fixed_T_base_camera", None)
    if T_base_camera is None:
        return True
    T = invert_transform(T_base_camera) @ pipeline.T_base_obj_ref
    pts = pipeline.model @ T[:3, :3].T + T[:3, 3]
    if (pts[:, 2] <= 0).any():
        return False
    try:
        px = pipeline.left.project(pts)
    except VgripError:
        return False
    cam = pipeline.left
    return bool(((px >= -0.5) & (px <= [cam.width - 0.5, cam.height - 0.5])).all())


__all__ = ["CANDIDATE_REASONS", "DIAGNOSED", "Candidate", "Cause", "Diagnosis", "ImageStage",
           "Trace", "explain"]
