"""Does the fit explain the data? The check that refuses a hand-eye result whose residuals are
far beyond what noise can cause, and the search for the reading of the input that the data
do fit (another pose format, other length units, the poses out of step with the images, the
other mounting).

What noise explains. With board corners: the corners' own noise (each image's pose fit,
which no robot error reaches) plus robot poses off by up to ``ROBOT_BOUND_DEG`` /
``ROBOT_BOUND_MM`` per axis (the top of the likelihood objective's search range), carried
into the image through each board pose's pixel Jacobian; the check compares the reprojection
RMS with the robot poses taken as exact against the RMS those two would give. Without corners
(board poses only): the same robot error carried into the implied board pose ``P_i X B_i``
(rotation, and translation with the rotation's lever arm), against its RMS spread.

The robot's rotation error turns about the flange; its lever arm (the flange's distance from
the board) comes from the fit, which is wrong when the input is: it is counted as at most the
camera's distance from the board, so that a wrong fit cannot explain itself by a huge arm.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from vgripd.calib.handeye.likelihood import ROBOT_SIGMA_DEG, ROBOT_SIGMA_MM
from vgripd.calib.handeye.refine import Problem
from vgripd.calib.handeye.samples import (
    MODES,
    FloatArray,
    Sample,
    consensus_board,
    inconsistency,
)
from vgripd.calib.handeye.solvers import MIN_SAMPLES, solve_linear
from vgripd.errors import CalibrationError, ConversionError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import adjoint, invert_transform, make_transform
from vgripd.geometry.vendors import (
    VENDORS,
    convention,
    transform_from_vendor,
    vendor_from_transform,
)

#: Robot pose error (one sigma per axis, flange frame) that the check lets explain residuals:
#: the top of the likelihood objective's robot-noise grid.
ROBOT_BOUND_DEG, ROBOT_BOUND_MM = ROBOT_SIGMA_DEG[-1], ROBOT_SIGMA_MM[-1]
#: A fit is refused when a residual exceeds this multiple of what noise explains. Measured
#: (docs/calibration-handeye.md): the right input 0.24-0.29 on real data (ViSP, Tabb), <= 0.41
#: on synthetic sets with the robot off by up to 0.3 deg / 3 mm per axis (<= 0.90 at the grid
#: top, 1 deg / 10 mm); a wrong pose format, pose order or mounting 5.4 and up: 1.5 is the
#: geometric middle of 0.41 and 5.4. Units slips give 1.9 and up (and are named by the
#: reading that fits, below).
REFUSE_RATIO = 1.5
#: A linear solution this far beyond is refused whatever a refinement would do (measured: the
#: right input <= 0.9 even with the robot off by 1 deg / 10 mm per axis, wrong input >= 5.4).
HOPELESS_RATIO = 3.0 * REFUSE_RATIO
#: Another reading of the input is named as the likely cause (and the fit refused) when its
#: residual ratio is within REFUSE_RATIO and at most 1 / BETTER_FACTOR of the given reading's.
BETTER_FACTOR = 3.0
#: Length-unit slips tried: (factor on the robot translations, what it means).
UNIT_SLIPS = ((1000.0, "m"), (0.001, "mm"))
#: A fit that fails is tried without its flagged outliers, without each sample (up to
#: MAX_SINGLES_SAMPLES samples) and without each pair (a swapped pair of lines; up to
#: MAX_PAIRS_SAMPLES samples).
MAX_SINGLES_SAMPLES = 30
MAX_PAIRS_SAMPLES = 15


@dataclass
class Reading:
    """Another reading of the input that the data fit far better than the one given."""

    cause: str  # "the pose format", "the units", "the pose order", "the mounting", "bad samples"
    change: str  # what to change, e.g. "--pose-format kuka"
    ratio: float  # residual / what noise explains, at this reading's linear solution
    residual: str  # the residual, e.g. "6.2 px" or "0.4 deg, 5.1 mm"


@dataclass
class FitCheck:
    """The residuals of the final fit against what noise explains (module docstring).

    Always the pose consistency: the RMS over samples of how far each sample's implied board
    pose lies from the consensus (``rotation_deg``, ``translation_mm``) against what the
    robot error gives (``expected_deg``, ``expected_mm``); with board corners also the
    reprojection RMS with the robot poses taken as exact (``rms_px``, inf when the fit puts
    the board behind the camera) against ``expected_px`` (corner noise ``corners_px`` plus
    the robot error). ``ratio`` is the largest residual / expected, ``limit`` the largest
    accepted; ``better`` the readings of the input that fit far better, compared at the
    linear solutions (``linear_ratio``: the given reading's there).
    """

    rotation_deg: float
    translation_mm: float
    expected_deg: float
    expected_mm: float
    rms_px: float | None = None
    expected_px: float | None = None
    corners_px: float | None = None
    limit: float = REFUSE_RATIO
    linear_ratio: float = math.nan
    better: list[Reading] = field(default_factory=list)

    @property
    def pixels(self) -> bool:
        return self.rms_px is not None

    @property
    def pose_ratio(self) -> float:
        return max(self.rotation_deg / self.expected_deg,
                   self.translation_mm / self.expected_mm)

    @property
    def pixel_ratio(self) -> float | None:
        if self.rms_px is None or self.expected_px is None:
            return None
        return self.rms_px / self.expected_px

    @property
    def ratio(self) -> float:
        px = self.pixel_ratio
        return self.pose_ratio if px is None else max(px, self.pose_ratio)

    @property
    def behind(self) -> bool:
        """The fit puts board corners behind the camera."""
        return self.rms_px is not None and math.isinf(self.rms_px)

    @property
    def ok(self) -> bool:
        return self.ratio <= self.limit and not self.better

    def residual(self) -> str:
        """The residual in a few words: "356 px; 31 deg, 154 mm"."""
        poses = f"{self.rotation_deg:.2g} deg, {self.translation_mm:.3g} mm"
        if self.behind:
            return f"board behind the camera; {poses}"
        return poses if self.rms_px is None else f"{self.rms_px:.3g} px; {poses}"

    def residual_text(self) -> str:
        """The residuals against what noise explains, a sentence or two."""
        robot = (f"robot poses off by up to {ROBOT_BOUND_DEG:g} deg and {ROBOT_BOUND_MM:g} mm "
                 "per axis")
        parts = []
        if self.behind:
            parts.append("the fit puts the board behind the camera (the robot poses cannot be "
                         "those of these images as read)")
        elif self.rms_px is not None:
            parts.append(
                f"reprojection RMS {self.rms_px:.3g} px with the robot poses taken as exact, "
                f"where the corners' own noise is {self.corners_px:.2f} px and it plus {robot} "
                f"would give about {self.expected_px:.3g} px ({self.pixel_ratio:.2g}x that)")
        parts.append(
            f"the board poses the samples imply disagree by {self.rotation_deg:.3g} deg and "
            f"{self.translation_mm:.3g} mm RMS, where "
            + ("that robot error" if parts and not self.behind else robot)
            + f" would give about {self.expected_deg:.2g} deg and {self.expected_mm:.3g} mm "
            f"({self.pose_ratio:.2g}x that)")
        return "; ".join(parts) + f". The limit is {self.limit:g}x."


class Scorer:
    """Fit checks of (X, C) on a set of samples, or on other readings of it: ``jacobians``
    (each sample's :func:`.pnp.board_jacobian`, in order) and ``corners_px`` (the pooled
    corner noise) are computed once; None for board-pose-only samples."""

    def __init__(self, camera: CameraModel | None, jacobians: Sequence[FloatArray] | None,
                 corners_px: float | None):
        self.camera = camera
        self.jacobians = None if jacobians is None else list(jacobians)
        self.corners_px = corners_px
        self.robot = np.array([math.radians(ROBOT_BOUND_DEG)] * 3 + [ROBOT_BOUND_MM] * 3) ** 2

    def check(self, problem: Problem, X: FloatArray, C: FloatArray,
              jacobians: Sequence[FloatArray] | None = None) -> FitCheck:
        """The residuals of (X, C) on ``problem`` against what noise explains.

        ``jacobians``: the corner Jacobians of ``problem``'s samples in order (default: all
        of the scorer's)."""
        deg, mm = inconsistency(problem.P, problem.B, X, C)
        # the robot error carried into the implied board pose P_i X B_i, its rotation turning
        # about the flange (lever arm: the board's distance from it, at most the camera's)
        if problem.mode == "eye-in-hand":
            arm = np.linalg.norm((X @ problem.B)[:, :3, 3], axis=1)
        else:
            arm = np.full(len(problem.B), float(np.linalg.norm(C[:3, 3])))
        arm = np.minimum(arm, np.linalg.norm(problem.B[:, :3, 3], axis=1))
        bound_rad = math.radians(ROBOT_BOUND_DEG)
        exp_mm = math.sqrt(float(np.mean(3.0 * ROBOT_BOUND_MM**2 + 2.0 * bound_rad**2 * arm**2)))
        check = FitCheck(_rms(deg), _rms(mm), math.sqrt(3.0) * ROBOT_BOUND_DEG, exp_mm)
        jac = self.jacobians if jacobians is None else list(jacobians)
        if problem.pixels and jac is not None and self.corners_px is not None:
            check.rms_px, check.expected_px = self._pixels(problem, X, C, jac)
            check.corners_px = self.corners_px
        return check

    def _pixels(self, problem: Problem, X: FloatArray, C: FloatArray,
                jacobians: Sequence[FloatArray]) -> tuple[float, float]:
        """Reprojection RMS (robot exact; inf: behind the camera) and the RMS expected."""
        assert self.corners_px is not None
        n_px = len(problem.px)
        cost = problem.cost(X, C)
        rms = math.sqrt(cost / n_px) if math.isfinite(cost) else math.inf
        # T_cam_flange of each sample (eye-in-hand the same for all), its origin (the flange,
        # about which the robot's rotation error turns) kept within the board's distance
        Y = invert_transform(X)
        F = np.broadcast_to(Y, problem.Q.shape) if problem.mode == "eye-in-hand" else Y @ problem.Q
        robot_px2 = 0.0
        for J, Fi, Bi, s_obj in zip(jacobians, F, problem.B, _centres(problem), strict=True):
            centre = Bi[:3, :3] @ s_obj + Bi[:3, 3]
            arm = Fi[:3, 3] - centre
            limit = float(np.linalg.norm(centre))
            length = float(np.linalg.norm(arm))
            origin = centre + arm * min(1.0, limit / length) if length > 0 else Fi[:3, 3]
            JA = J @ adjoint(make_transform(Fi[:3, :3], origin))
            robot_px2 += float((JA**2).sum(axis=0) @ self.robot)
        return rms, math.sqrt((robot_px2 + 2.0 * n_px * self.corners_px**2) / n_px)

    def linear(self, samples: Sequence[Sample], mode: str,
               jacobians: Sequence[FloatArray] | None = None) -> FitCheck | None:
        """The check at the best linear solution (Park, else Tsai) of ``samples`` read in
        ``mode``; None when neither solves."""
        problem = Problem(samples, mode, self.camera)
        for method in ("park", "tsai"):
            try:
                X = solve_linear(problem.P, problem.B, method)
            except CalibrationError:
                continue
            return self.check(problem, X, consensus_board(problem.P, problem.B, X), jacobians)
        return None


def _rms(values: FloatArray) -> float:
    return float(np.sqrt(np.mean(values**2)))


def _centres(problem: Problem) -> list[FloatArray]:
    """Each sample's board centre (mean of its corners' board points)."""
    starts = np.cumsum([0, *problem.counts])
    return [problem.obj[a:b].mean(axis=0) for a, b in zip(starts[:-1], starts[1:], strict=True)]


def other_readings(samples: Sequence[Sample], mode: str, pose_format: str | None,
                   ) -> Iterator[tuple[str, str, list[Sample], str, list[int]]]:
    """Other ways to read the same input: (cause, change, samples, mode, images kept).

    The robot poses in every other pose format with as many numbers (from ``pose_format``'s
    numbers of each pose), with the translations x1000 and /1000, one pose later and one
    earlier than the images (``images kept``: indices of the samples whose images are used),
    and the other mounting."""
    poses = [np.asarray(s.T_base_flange, dtype=np.float64) for s in samples]
    every = list(range(len(samples)))

    def paired(new: Sequence[FloatArray], images: Sequence[int] = every) -> list[Sample]:
        return [Sample(T, samples[k].T_cam_board, samples[k].image, samples[k].obj,
                       samples[k].px, samples[k].number) for T, k in zip(new, images, strict=True)]

    if pose_format is not None:
        for change, read in _format_readings(poses, pose_format):
            yield "the pose format", change, paired(read), mode, every
    unit = "" if pose_format is None else convention(pose_format).length_unit
    for factor, meant in UNIT_SLIPS:
        if unit == meant:
            continue  # the format's own unit: not a slip
        scaled = [make_transform(T[:3, :3], T[:3, 3] * factor) for T in poses]
        expects = f" where --pose-format {pose_format} expects {unit}" if unit else ""
        yield ("the units", f"the robot positions x{factor:g} (the poses file holds {meant}"
               f"{expects})", paired(scaled), mode, every)
    if len(samples) - 1 >= MIN_SAMPLES:
        yield ("the pose order", "each image with the pose one line later in the poses file",
               paired(poses[1:], every[:-1]), mode, every[:-1])
        yield ("the pose order", "each image with the pose one line earlier in the poses file",
               paired(poses[:-1], every[1:]), mode, every[1:])
    other = next(m for m in MODES if m != mode)
    yield "the mounting", f"--mode {other}", paired(poses), other, every


def _format_readings(poses: Sequence[FloatArray], pose_format: str,
                     ) -> Iterator[tuple[str, list[FloatArray]]]:
    """The poses' numbers in ``pose_format`` read as each other format with as many numbers
    (one of each set of identical conventions): ("--pose-format NAME ...", poses)."""
    given = convention(pose_format)

    def key(name: str) -> tuple[str, str, str, str]:
        c = convention(name)
        return c.length_unit, c.rotation, c.angle_unit, c.euler_seq

    sized = [n for n in VENDORS if len(convention(n).fields) == len(given.fields)]
    seen = {key(given.name)}
    numbers = [vendor_from_transform(given.name, T) for T in poses]
    for name in sized:
        if key(name) in seen:
            continue
        seen.add(key(name))
        try:
            read = [transform_from_vendor(name, v) for v in numbers]
        except ConversionError:
            continue
        same = [n for n in sized if n != name and key(n) == key(name)]
        alias = f" (or {', '.join(same)}: the same convention)" if same else ""
        yield f"--pose-format {name}{alias}", read


def better_readings(scorer: Scorer, samples: Sequence[Sample], mode: str,
                    pose_format: str | None, given: FitCheck | None) -> list[Reading]:
    """The readings of :func:`other_readings` that fit far better than the given one (ratio
    within REFUSE_RATIO and at most 1 / BETTER_FACTOR of ``given``'s, the given reading's
    check at its linear solution), best first."""
    base = math.inf if given is None else given.ratio
    out = []
    for cause, change, subset, other_mode, kept in other_readings(samples, mode, pose_format):
        reading = _reading(scorer, subset, other_mode, kept, base, cause, change)
        if reading is not None:
            out.append(reading)
    out.sort(key=lambda r: r.ratio)
    return out


def _reading(scorer: Scorer, subset: Sequence[Sample], mode: str, kept: Sequence[int],
             base: float, cause: str, change: str) -> Reading | None:
    """The reading when it fits far better than ``base`` (else None)."""
    jac = None if scorer.jacobians is None else [scorer.jacobians[k] for k in kept]
    check = scorer.linear(subset, mode, jac)
    if check is None or not math.isfinite(check.ratio):
        return None
    if check.ratio <= REFUSE_RATIO and check.ratio * BETTER_FACTOR <= base:
        return Reading(cause, change, check.ratio, check.residual())
    return None


def exclusion_reading(scorer: Scorer, samples: Sequence[Sample], mode: str,
                      flagged: Sequence[int], given: FitCheck | None) -> Reading | None:
    """For a fit that fails the check: the fewest samples without which the rest fit far
    better (as :func:`better_readings`), tried among the ``flagged`` outliers together, each
    sample alone and each pair (up to ``MAX_SINGLES_SAMPLES`` / ``MAX_PAIRS_SAMPLES``
    samples); None when none do."""
    n = len(samples)
    base = math.inf if given is None else given.ratio
    tries: list[tuple[int, ...]] = []
    if flagged and len(flagged) <= n // 3:
        tries.append(tuple(flagged))
    if n <= MAX_SINGLES_SAMPLES:
        tries += [(k,) for k in range(n)]
    if n <= MAX_PAIRS_SAMPLES:
        tries += list(itertools.combinations(range(n), 2))
    best: Reading | None = None
    best_size = 0
    for left_out in sorted(set(tries), key=len):
        if best is not None and len(left_out) > best_size:
            break  # fewer samples left out wins
        kept = [k for k in range(n) if k not in left_out]
        if len(kept) <= MIN_SAMPLES:
            continue
        numbers = ",".join(str(k if samples[k].number is None else samples[k].number)
                           for k in left_out)
        reading = _reading(scorer, [samples[k] for k in kept], mode, kept, base,
                           "bad samples (a wrong pose line, swapped lines, a pose read before "
                           "the robot settled)", f"--exclude {numbers}")
        if reading is not None and (best is None or reading.ratio < best.ratio):
            best, best_size = reading, len(left_out)
    return best


def refusal_lines(check: FitCheck, mode: str, pose_format: str | None) -> list[str]:
    """Why the fit is refused and what to check, the reading that fits far better (if one
    does) first: lines for a message."""
    lines = ["the fit does not explain the data: " + check.residual_text()]
    if check.better:
        best = check.better[0]
        lines.append(f"Most likely {best.cause}: the data fit with {best.change} (residual "
                     f"{best.residual}, {best.ratio:.2g}x what noise explains)" + "".join(
                         f"; or with {r.change} ({r.residual})" for r in check.better[1:3])
                     + ".")
        head = "Other causes to check: "
    else:
        tried = "pose format, units" if pose_format else "units"
        head = (f"No other {tried}, shift by one, mounting or a sample or two left out fits "
                "either. Check: ")
    fmt = (f"--pose-format {pose_format} ({convention(pose_format).summary}): is that how the "
           "controller wrote them?") if pose_format else (
               "the convention the robot poses were read in (--pose-format when the samples "
               "were made)")
    unit = (f"the units (--pose-format {pose_format} expects positions in "
            f"{convention(pose_format).length_unit})" if pose_format
            else "the units of the robot positions (the samples hold mm)")
    causes = [
        f"the pose format, {fmt}",
        unit,
        "the pose order (one pose per image, in image order: a missing, extra or swapped line "
        "shifts them; leave a bad sample out with --exclude)",
        f"the mounting, --mode {mode} (eye-in-hand: camera on the flange; eye-to-hand: camera "
        "fixed, board on the flange)",
        "the intrinsics and the board spec",
    ]
    lines.append(head + "; ".join(causes) + ".")
    return lines
