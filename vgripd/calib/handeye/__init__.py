"""Hand-eye calibration: where the camera sits on the robot flange, or in the robot base frame.

Two mountings, one equation. Each sample pairs a robot flange pose ``T_base_flange_i`` (robot
controller) with the pose of a calibration board seen by the camera, ``T_cam_board_i`` (from
the board corners and the intrinsics, or given directly):

- eye-in-hand (camera on the flange, board fixed in the cell): unknown ``X = T_flange_camera``;
  the board pose ``T_base_board = T_base_flange_i @ X @ T_cam_board_i`` is the same for all i.
- eye-to-hand (camera fixed, board carried by the flange): unknown ``X = T_base_camera``;
  ``T_flange_board = T_flange_base_i @ X @ T_cam_board_i`` is the same for all i.

So both are ``T_anchor_board = P_i @ X @ B_i`` with ``B_i = T_cam_board_i`` and
``P_i = T_base_flange_i`` (anchor = base) or ``P_i = T_flange_base_i`` (anchor = flange).
Between two samples this is the classic ``A X = X B`` (``A = P_j^-1 P_i``, ``B = B_j B_i^-1``).
In OpenCV's ``calibrateHandEye`` terms the ``P_i`` are "gripper2base" -- for eye-to-hand that
means the *inverted* robot poses, and what it calls "cam2gripper" is then ``T_base_camera``.

Pipeline of :func:`calibrate_hand_eye` (module in brackets):

1. motion checks on the robot poses [solvers]: no rotation at all is an error; consecutive
   samples that rotate less than ``min_rotation_deg``, and relative rotations all about nearly
   one axis (then the translation of X along that axis is not determined), are warnings;
2. board poses from the corners [pnp], then every linear AX = XB solver (Tsai, Park, Horaud,
   Andreff, Daniilidis) [solvers]; for each, the consensus board pose (chordal mean of the
   ``P_i X B_i``) and its residual [samples];
3. refinement from the linear solution with the lowest residual, over the 12 unknowns (X and
   the board pose, 6 each), by scipy's Levenberg-Marquardt with analytic Jacobians [refine].
   The default objective, ``likelihood`` [likelihood], treats both the images and the robot as
   noisy: each sample's residual is the 6-vector between its measured and predicted board pose,
   weighted by the board pose's covariance from its corners plus the robot pose noise carried
   into the camera frame; the robot noise is the most likely one on a grid. With an exact robot
   this is the pixel objective, with a noisy one it does not bend X to absorb the robot's
   error. Alternatives [refine]: ``pixels`` (reprojection error of every corner through
   :class:`~vgripd.geometry.camera_model.CameraModel`, robot exact), ``poses`` (unweighted
   board-pose residuals: translation mm plus rotation rad times the median camera-board
   distance; the only choice for samples without corners), ``none``;
4. per-sample residuals [calibrate]: reprojection RMS and how far that sample's implied board
   pose ``P_i X B_i`` lies from the consensus (deg, mm); samples far above the median are
   flagged;
5. fit check [plausibility]: the residuals against what noise explains (corner noise plus
   robot poses off by up to 1 deg / 10 mm per axis): the reprojection RMS with the robot taken
   as exact, and the spread of the implied board poses. Beyond ``REFUSE_RATIO`` times that,
   or when another reading of the same input (pose format, units, poses shifted by one, the
   other mounting) fits far better, the result's ``check`` fails and says which reading fits;
   the command refuses such a result unless ``--force``;
6. stability [calibrate]: the refinement repeated leaving out one sample at a time; the spread
   of X (largest and RMS rotation angle in deg and translation in mm against the full
   solution) is what the result would move by if one sample were missing (not for a fit that
   fails the check).

Files [io]: the robot poses file and the samples file. Test data [synth]:
:func:`synthetic_samples`. Rotation and pose-error helpers: ``vgripd.geometry.transforms``.
"""

from __future__ import annotations

from vgripd.calib.handeye.calibrate import (
    MAX_PIXEL_RMS,
    OBJECTIVES,
    HandEyeResult,
    LinearSolution,
    SampleResidual,
    Stability,
    calibrate_hand_eye,
    robot_edges,
    robot_noise_text,
)
from vgripd.calib.handeye.io import SAMPLES_FORMAT, load_samples, read_poses, save_samples
from vgripd.calib.handeye.likelihood import ROBOT_SIGMA_DEG, ROBOT_SIGMA_MM
from vgripd.calib.handeye.plausibility import (
    REFUSE_RATIO,
    ROBOT_BOUND_DEG,
    ROBOT_BOUND_MM,
    FitCheck,
    Reading,
    refusal_lines,
)
from vgripd.calib.handeye.pnp import board_pose, measure_board_poses
from vgripd.calib.handeye.samples import MODES, Sample, anchor_poses, consensus_board
from vgripd.calib.handeye.solvers import MIN_SAMPLES, SOLVERS, check_motion, solve_linear
from vgripd.calib.handeye.synth import synthetic_samples

__all__ = [
    "MAX_PIXEL_RMS",
    "MIN_SAMPLES",
    "MODES",
    "OBJECTIVES",
    "REFUSE_RATIO",
    "ROBOT_BOUND_DEG",
    "ROBOT_BOUND_MM",
    "ROBOT_SIGMA_DEG",
    "ROBOT_SIGMA_MM",
    "SAMPLES_FORMAT",
    "SOLVERS",
    "FitCheck",
    "HandEyeResult",
    "LinearSolution",
    "Reading",
    "Sample",
    "SampleResidual",
    "Stability",
    "anchor_poses",
    "board_pose",
    "calibrate_hand_eye",
    "check_motion",
    "consensus_board",
    "load_samples",
    "measure_board_poses",
    "read_poses",
    "refusal_lines",
    "robot_edges",
    "robot_noise_text",
    "save_samples",
    "solve_linear",
    "synthetic_samples",
]
