"""``calibrate_hand_eye``: the pipeline of the package docstring, and its result types."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from vgripd.calib.handeye.likelihood import ROBOT_SIGMA_DEG, ROBOT_SIGMA_MM, Likelihood
from vgripd.calib.handeye.plausibility import (
    HOPELESS_RATIO,
    FitCheck,
    Scorer,
    better_readings,
    exclusion_reading,
)
from vgripd.calib.handeye.pnp import corner_jacobians, measure_board_poses
from vgripd.calib.handeye.refine import Problem, refine
from vgripd.calib.handeye.samples import (
    FloatArray,
    Sample,
    check_mode,
    consensus_board,
    inconsistency,
    label,
    number,
)
from vgripd.calib.handeye.solvers import MIN_SAMPLES, SOLVERS, check_motion, solve_linear
from vgripd.errors import CalibrationError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import check_transform, invert_transform, pose_error

#: What the refinement may minimise (see calibrate_hand_eye).
OBJECTIVES = ("auto", "likelihood", "pixels", "poses", "none")
#: Above this reprojection RMS (px) the pixel objective's result is not trusted: the robot
#: poses (or the intrinsics) carry the larger error.
MAX_PIXEL_RMS = 1.0
#: Estimated robot pose noise (per axis) above which the result warns about the robot poses.
ROBOT_WARN_DEG, ROBOT_WARN_MM = 0.1, 1.0
#: A sample is an outlier when its residual exceeds this multiple of the median ...
OUTLIER_FACTOR = 3.0
#: ... and these floors (px for corner data; deg, mm for pose data).
OUTLIER_FLOOR_PX = 0.5
OUTLIER_FLOOR_DEG = 0.2
OUTLIER_FLOOR_MM = 2.0


@dataclass
class LinearSolution:
    """One linear solver's X, the consensus board pose it implies and its residuals.

    ``rms_px`` is None for pose-only data; ``rotation_deg`` / ``translation_mm`` are the RMS
    over samples of the implied board pose's distance from the consensus. ``error`` says why
    the solver gave no usable answer (then the matrices are NaN).
    """

    T: FloatArray
    T_anchor_board: FloatArray
    rms_px: float | None
    rotation_deg: float
    translation_mm: float
    cost: float
    error: str = ""


@dataclass
class SampleResidual:
    """Residuals of one sample under the final solution."""

    sample: int
    image: str
    rms_px: float | None
    rotation_deg: float
    translation_mm: float
    outlier: bool = False


@dataclass
class Stability:
    """Spread of X over the leave-one-out solutions (against the all-samples solution)."""

    rotation_deg: float  # largest rotation angle between a leave-one-out X and X
    translation_mm: float  # largest translation difference, mm
    rotation_deg_std: float  # RMS of those angles
    translation_mm_std: float  # RMS of those distances
    worst_sample: int  # the sample whose removal moves X most (translation)


@dataclass
class HandEyeResult:
    """Outcome of :func:`calibrate_hand_eye`.

    ``T`` is ``T_flange_camera`` (eye-in-hand) or ``T_base_camera`` (eye-to-hand);
    ``T_anchor_board`` is ``T_base_board`` resp. ``T_flange_board``. ``solver`` is
    "refined-<objective>" (started from ``start``) or, without refinement, the chosen linear
    solver. ``residuals_px`` holds the (N, 2) residuals (observed - projected) per sample
    (corner data).
    """

    mode: str
    T: FloatArray
    T_anchor_board: FloatArray
    solver: str
    start: str
    solvers: dict[str, LinearSolution]
    rms_px: float | None
    per_sample: list[SampleResidual]
    stability: Stability | None
    warnings: list[str] = field(default_factory=list)
    residuals_px: list[FloatArray] = field(default_factory=list)
    #: likelihood objective: the corner noise (px per coordinate, from the images' own pose
    #: fits) and the robot pose noise found most likely (deg, mm per axis); else None
    sigma_px: float | None = None
    robot_sigma: tuple[float, float] | None = None
    #: whether the residuals are within what noise explains (None: not checked)
    check: FitCheck | None = None

    @property
    def robot_sigma_edges(self) -> tuple[str | None, str | None]:
        """:func:`robot_edges` of ``robot_sigma`` ((None, None) without it)."""
        return (None, None) if self.robot_sigma is None else robot_edges(self.robot_sigma)

    @property
    def transform_name(self) -> str:
        return "T_flange_camera" if self.mode == "eye-in-hand" else "T_base_camera"

    @property
    def board_name(self) -> str:
        return "T_base_board" if self.mode == "eye-in-hand" else "T_flange_board"


def robot_edges(robot_sigma: tuple[float, float]) -> tuple[str | None, str | None]:
    """For (deg, mm): "lower" / "upper" when the most likely robot noise is the smallest /
    largest of its search grid (``ROBOT_SIGMA_DEG``, ``ROBOT_SIGMA_MM``: the noise is at most /
    at least that, not that figure), else None."""
    def edge(value: float, grid: Sequence[float]) -> str | None:
        if value <= grid[0]:
            return "lower"
        if value >= grid[-1]:
            return "upper"
        return None

    return edge(robot_sigma[0], ROBOT_SIGMA_DEG), edge(robot_sigma[1], ROBOT_SIGMA_MM)


def robot_noise_text(robot_sigma: tuple[float, float]) -> str:
    """The robot noise found most likely, e.g. "0.3 deg and 3 mm", or at a grid edge
    "0.3 deg and >= 10 mm (at the edge of the search range, ...)"."""
    parts = []
    for value, unit, edge in zip(robot_sigma, ("deg", "mm"), robot_edges(robot_sigma),
                                 strict=True):
        sign = {"upper": ">= ", "lower": "<= "}.get(edge or "", "")
        parts.append(f"{sign}{value:g} {unit}")
    text = " and ".join(parts)
    if any(robot_edges(robot_sigma)):
        text += (f" (at the edge of the search range, {ROBOT_SIGMA_DEG[0]:g}-"
                 f"{ROBOT_SIGMA_DEG[-1]:g} deg and {ROBOT_SIGMA_MM[0]:g}-{ROBOT_SIGMA_MM[-1]:g}"
                 " mm)")
    return text


def _check_samples(samples: Sequence[Sample], camera: CameraModel | None) -> None:
    for i, s in enumerate(samples):
        check = s.T_cam_board if s.T_cam_board is not None else np.eye(4)
        try:
            check_transform(s.T_base_flange, "T_base_flange")
            check_transform(check, "T_cam_board")
        except DegenerateInputError as err:
            raise CalibrationError(f"hand-eye: {label(samples, i)}: {err}") from None
        if s.T_cam_board is None and not (s.has_pixels and camera is not None):
            raise CalibrationError(f"hand-eye: {label(samples, i)}: no board pose, and no "
                                   "corners with intrinsics to measure it")


def calibrate_hand_eye(
    samples: Sequence[Sample],
    mode: str,
    camera: CameraModel | None = None,
    *,
    min_rotation_deg: float = 5.0,
    objective: str = "auto",
    stability: bool = True,
    pose_format: str | None = None,
    refine_refused: bool = True,
) -> HandEyeResult:
    """Solve X from the samples (see the package docstring for the steps).

    Parameters
    ----------
    samples : robot poses with board corners (then ``camera`` is needed) or board poses.
    mode : "eye-in-hand" or "eye-to-hand".
    camera : intrinsics of the images; None when the samples carry board poses only.
    min_rotation_deg : consecutive samples rotating less than this are reported.
    objective : what the refinement minimises: "likelihood" (board poses weighted by their
        pixel uncertainty plus an estimated robot pose noise, :class:`.likelihood.Likelihood`),
        "pixels" (reprojection error of the corners, robot taken as exact), "poses"
        (board-pose residuals, unweighted), "none" (keep the best linear solution) or "auto":
        likelihood with corner data, poses without.
    pose_format : the convention the robot poses were read in (``vgripd.geometry.vendors``),
        if known: the fit check then also tries the same numbers in the other formats.
    refine_refused : False: a fit the check will refuse whatever the refinement does (the
        linear solution already ``HOPELESS_RATIO`` times beyond what noise explains, or
        another reading of the input fitting far better) keeps the linear solution, saving
        the refinement (seconds on such data); the command refines only with ``--force``.

    The result's ``check`` (:mod:`.plausibility`) says whether the residuals are within what
    noise explains and which other reading of the input (pose format, units, pose order,
    mounting) fits far better; a failed check is a warning here, callers decide whether to
    refuse the result (the command does, unless ``--force``).

    Raises
    ------
    CalibrationError
        bad mode, too few samples, no rotation, a sample without corners and board pose,
        every linear solver failing.
    """
    check_mode(mode)
    if objective not in OBJECTIVES:
        raise CalibrationError(f"hand-eye objective {objective!r}: expected one of "
                               f"{', '.join(OBJECTIVES)}")
    _check_samples(samples, camera)
    warnings = check_motion(samples, mode, min_rotation_deg)
    if camera is not None:
        warnings += measure_board_poses(samples, camera)
    problem = Problem(samples, mode, camera)

    solvers = {name: _linear_solution(problem, name) for name in SOLVERS}
    usable = {k: v for k, v in solvers.items() if not v.error}
    if not usable:
        raise CalibrationError("hand-eye: every linear solver failed: " + "; ".join(
            f"{v.error}" for v in solvers.values()))
    warnings += [f"solver {sol.error}" for sol in solvers.values() if sol.error]
    start = min(usable, key=lambda k: usable[k].cost)
    X0, C0 = usable[start].T, usable[start].T_anchor_board
    X, C, solver, converged = X0, C0, start, True
    if objective == "auto":
        objective = "likelihood" if problem.pixels else "poses"
    if objective in ("likelihood", "pixels") and not problem.pixels:
        raise CalibrationError(f"hand-eye objective {objective!r} needs board corners and "
                               "intrinsics; these samples carry board poses only")
    # the fit check's linear part: the given reading and the other readings of the input
    scorer = _scorer(problem, samples, camera)
    given = scorer.linear(samples, mode)
    better = better_readings(scorer, samples, mode, pose_format, given)
    given_ratio = math.inf if given is None else given.ratio
    if not refine_refused and (better or scorer.check(problem, X0, C0).ratio > HOPELESS_RATIO):
        objective = "none"  # refused whatever the refinement does: keep the linear solution
    sigma_px = robot_sigma = likelihood = None
    if objective == "likelihood":
        assert camera is not None
        likelihood = Likelihood.from_corners(problem, samples, camera)
        X, C, converged, robot_sigma = likelihood.solve(X0, C0)
        sigma_px = likelihood.sigma_px
    elif objective == "pixels":
        if problem.cost(X0, C0) == math.inf:
            converged = False  # the check below says why
        else:
            X, C, converged = refine(problem, X0, C0)
            rms = math.sqrt(problem.cost(X, C) / len(problem.px))
            if rms > MAX_PIXEL_RMS:
                warnings.append(
                    f"reprojection RMS {rms:.2f} px with the robot poses taken as exact: far "
                    "above corner noise, so the robot poses (or the intrinsics) carry the "
                    "larger error and the pixel fit bends X to absorb it; use --objective "
                    "likelihood")
    elif objective == "poses":
        X, C, converged = refine(Problem(samples, mode, camera, pixels=False), X0, C0)
    if objective != "none":
        solver = f"refined-{objective}"

    per_sample, residuals_px, rms_px = _per_sample(problem, samples, X, C)
    flagged = [k for k, r in enumerate(per_sample) if r.outlier]
    check = scorer.check(problem, X, C)
    check.linear_ratio, check.better = given_ratio, better
    if check.ratio > check.limit and not check.better:
        left_out = exclusion_reading(scorer, samples, mode, flagged, given)
        if left_out is not None:
            check.better.append(left_out)
    if not check.ok:
        warnings.append("the fit does not explain the data: " + check.residual_text())
    if robot_sigma is not None and check.ok and (
            robot_sigma[0] > ROBOT_WARN_DEG or robot_sigma[1] > ROBOT_WARN_MM):
        warnings.append(
            f"the robot poses disagree with the images by {robot_noise_text(robot_sigma)} per "
            "axis, most likely (robot noise of that size explains the residuals; the corners' "
            f"own noise is {sigma_px:.2f} px): check the robot's accuracy, that each pose was "
            "read after the robot settled, and the intrinsics")
    if not converged and check.ok:
        warnings.append("refinement stopped at its iteration limit; the result may not be "
                        "the best fit")

    outliers = [(k, r) for k, r in enumerate(per_sample) if r.outlier]
    if outliers and check.ok:  # a fit that explains nothing has no outliers to name
        warnings.append(
            "outlier sample(s): " + ", ".join(
                label(samples, k) + (f" {r.rms_px:.2f} px" if r.rms_px is not None else "")
                + f" {r.rotation_deg:.2f} deg {r.translation_mm:.1f} mm" for k, r in outliers)
            + "; check the robot pose and image of each (wrong order, motion blur, pose read "
              "before the robot settled), or solve again without them (--samples FILE "
              f"--exclude {','.join(str(r.sample) for _, r in outliers)})")
    stab = None
    if stability and len(samples) > MIN_SAMPLES and check.ok:
        how = start if objective == "none" else objective
        stab = _leave_one_out(samples, mode, camera, X, C, how, likelihood, robot_sigma)
    return HandEyeResult(mode, X, C, solver, start, solvers, rms_px, per_sample, stab,
                         warnings, residuals_px, sigma_px, robot_sigma, check)


def _scorer(problem: Problem, samples: Sequence[Sample], camera: CameraModel | None,
            ) -> Scorer:
    """The fit check's scorer (:mod:`.plausibility`), with the corners' Jacobians and noise
    when the samples have corners."""
    jacobians, corners_px = None, None
    if problem.pixels:
        assert camera is not None
        jacobians, corners_px = corner_jacobians(samples, problem.B, camera)
    return Scorer(camera, jacobians, corners_px)


def _linear_solution(problem: Problem, name: str) -> LinearSolution:
    nan = np.full((4, 4), np.nan)
    try:
        X = solve_linear(problem.P, problem.B, name)
    except CalibrationError as err:
        return LinearSolution(nan, nan, None, math.nan, math.nan, math.inf, str(err))
    C = consensus_board(problem.P, problem.B, X)
    deg, mm = inconsistency(problem.P, problem.B, X, C)
    cost = problem.cost(X, C)
    rms_px = None
    if problem.pixels:
        rms_px = math.sqrt(cost / len(problem.px)) if math.isfinite(cost) else math.inf
    return LinearSolution(X, C, rms_px, float(np.sqrt((deg**2).mean())),
                          float(np.sqrt((mm**2).mean())), cost)


def _per_sample(problem: Problem, samples: Sequence[Sample], X: FloatArray, C: FloatArray,
                ) -> tuple[list[SampleResidual], list[FloatArray], float | None]:
    deg, mm = inconsistency(problem.P, problem.B, X, C)
    residuals: list[FloatArray] = []
    rms_px = None
    per_rms: list[float | None] = [None] * len(samples)
    if problem.pixels and math.isfinite(problem.cost(X, C)):
        residuals = problem.pixel_residuals((invert_transform(X), C))
        per_rms = [float(np.sqrt((r**2).sum(axis=1).mean())) for r in residuals]
        all_r = np.concatenate(residuals)
        rms_px = float(np.sqrt((all_r**2).sum(axis=1).mean()))
        flags = _outliers(np.array(per_rms, dtype=float), OUTLIER_FLOOR_PX)
    else:  # board poses only, or corners behind the camera (the fit check says so)
        flags = _outliers(deg, OUTLIER_FLOOR_DEG) | _outliers(mm, OUTLIER_FLOOR_MM)
    out = [SampleResidual(number(samples, i), s.image, per_rms[i], float(deg[i]), float(mm[i]),
                          bool(flags[i]))
           for i, s in enumerate(samples)]
    return out, residuals, rms_px


def _outliers(values: FloatArray, floor: float) -> npt.NDArray[np.bool_]:
    """Values above OUTLIER_FACTOR times the median of all and above ``floor``."""
    med = float(np.median(values))
    flags: npt.NDArray[np.bool_] = (values > OUTLIER_FACTOR * med) & (values > floor)
    return flags


def _leave_one_out(samples: Sequence[Sample], mode: str, camera: CameraModel | None,
                   X: FloatArray, C: FloatArray, how: str,
                   likelihood: Likelihood | None = None,
                   robot_sigma: tuple[float, float] | None = None) -> Stability:
    """Re-solve without each sample in turn, the way X was found (``how``: "likelihood" with
    the weights and robot noise found on all samples, "pixels", "poses" or a linear solver's
    name); refinements start from the full solution (one basin, so they converge in a few
    steps)."""
    deg, mm = [], []
    for k in range(len(samples)):
        subset = [s for i, s in enumerate(samples) if i != k]
        problem = Problem(subset, mode, camera, pixels=how in ("pixels", "likelihood"))
        if how == "likelihood":
            assert likelihood is not None
            assert robot_sigma is not None
            Xk = likelihood.without(k, problem).fit(X, C, *robot_sigma)[0]
        elif how in ("pixels", "poses"):
            Xk, _, _ = refine(problem, X, C)
        else:
            Xk = solve_linear(problem.P, problem.B, how)
        dist, angle = pose_error(Xk, X)
        deg.append(angle)
        mm.append(dist)
    d, m = np.array(deg), np.array(mm)
    return Stability(float(d.max()), float(m.max()), float(np.sqrt((d**2).mean())),
                     float(np.sqrt((m**2).mean())), number(samples, int(np.argmax(m))))
