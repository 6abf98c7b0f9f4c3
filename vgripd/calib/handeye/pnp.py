"""Board poses from the corners: ``T_cam_board`` of each sample, and how well its corners
determine it (the Jacobian the likelihood objective weighs the board poses with)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from vgripd.calib.handeye.refine import (
    BEHIND_PX,
    minimise,
    point_motion_jacobian,
    projection_jacobian,
)
from vgripd.calib.handeye.samples import FloatArray, Sample, label
from vgripd.errors import CalibrationError, ConvergenceError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec, pose_error

#: A second planar pose fitting within this factor of the best (and of 0.1 px) is ambiguous.
AMBIGUITY_RATIO = 2.0


def board_jacobian(obj: FloatArray, px: FloatArray, B: FloatArray, camera: CameraModel,
                   ) -> tuple[FloatArray, FloatArray]:
    """(2N, 6) Jacobian of the projected corners against a small motion of the board in the
    camera frame (rotation rad, translation mm), and the (2N,) residual observed - projected
    at ``B``."""
    pts = obj @ B[:3, :3].T + B[:3, 3]
    J = (projection_jacobian(camera, pts) @ point_motion_jacobian(pts)).reshape(-1, 6)
    return J, (px - camera.project(pts)).ravel()


def corner_jacobians(samples: Sequence[Sample], boards: FloatArray, camera: CameraModel,
                     ) -> tuple[list[FloatArray], float]:
    """Each sample's :func:`board_jacobian` at its board pose (``boards``, (n, 4, 4)) and the
    corner noise (px per coordinate) pooled over every image's own pose fit, which no robot
    error reaches."""
    jacobians, ssr, dof = [], 0.0, 0
    for s, B in zip(samples, boards, strict=True):
        assert s.obj is not None
        assert s.px is not None
        J, r = board_jacobian(s.obj, s.px, B, camera)
        jacobians.append(J)
        ssr += float(r @ r)
        dof += len(r) - 6
    if dof <= 0:
        raise CalibrationError("hand-eye: too few corners per image to weigh the board poses")
    return jacobians, math.sqrt(ssr / dof)


def board_pose(obj: FloatArray, px: FloatArray, camera: CameraModel,
               ) -> tuple[FloatArray, float, bool]:
    """``T_cam_board`` of a planar board (z = 0) from its corners: the better of the two IPPE
    poses (OpenCV, on undistorted coordinates) refined on the pixel error with the camera
    model; returns the pose, its RMS (px) and whether the other pose fits about as well
    (ambiguous)."""
    norm = camera.undistort(px)
    _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        np.ascontiguousarray(obj).reshape(-1, 1, 3), np.ascontiguousarray(norm).reshape(-1, 1, 2),
        np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)

    def residual(state: Sequence[FloatArray]) -> FloatArray:
        pts = obj @ state[0][:3, :3].T + state[0][:3, 3]
        if (pts[:, 2] <= 0).any():
            return np.full(px.size, BEHIND_PX)
        out: FloatArray = (camera.project(pts) - px).ravel()
        return out

    def jacobian(state: Sequence[FloatArray]) -> FloatArray:
        return board_jacobian(obj, px, state[0], camera)[0]

    starts = []
    for rv, tv in zip(rvecs, tvecs, strict=True):
        T0 = make_transform(matrix_from_rotvec(np.ravel(rv)), np.ravel(tv))
        r0 = residual((T0,))
        if not (r0 == BEHIND_PX).all():
            starts.append((math.sqrt(float(r0 @ r0) / len(px)), T0))
    if not starts:
        raise DegenerateInputError("the board lies behind the camera in every candidate pose")
    starts.sort(key=lambda f: f[0])
    # IPPE's poses are near their minima already: refine the better one only, and call the
    # board ambiguous when the other fits about as well even unrefined.
    (T,), _ = minimise(residual, jacobian, (starts[0][1],), ("left",))
    r = residual((T,))
    rms = math.sqrt(float(r @ r) / len(px))
    ambiguous = len(starts) > 1 and pose_error(starts[1][1], T)[1] > 0.1 and (
        starts[1][0] < AMBIGUITY_RATIO * max(rms, 0.1))
    return T, rms, ambiguous


def measure_board_poses(samples: Sequence[Sample], camera: CameraModel) -> list[str]:
    """Fill ``T_cam_board`` of samples that have corners (:func:`board_pose`).

    Returns warnings for ambiguous planar poses; CalibrationError names the sample."""
    warnings = []
    for i, s in enumerate(samples):
        if s.T_cam_board is not None or s.obj is None or s.px is None:
            continue
        try:
            s.T_cam_board, _, ambiguous = board_pose(s.obj, s.px, camera)
        except (DegenerateInputError, ConvergenceError, cv2.error) as err:
            raise CalibrationError(f"hand-eye: {label(samples, i)}: board pose: {err}") from None
        if ambiguous:
            warnings.append(f"{label(samples, i)}: the board pose is ambiguous (board seen "
                            "small or nearly face-on); tilt the board more")
    return warnings
