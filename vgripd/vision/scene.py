"""Geometry objects built from the configuration: cameras, rig, hand-eye chain, object, reference.

Pure functions, no I/O. The config has already checked shapes and bounds; what can still be
wrong here (a missing section, a model that rejects the numbers) is a ``NotCalibratedError``
naming the config section, so that a job ends with status NOT_CALIBRATED instead of crashing.

Frames: ``base`` (robot base), ``flange`` (robot flange), ``camera`` (the left camera, the
reference camera of a stereo rig), ``obj`` (the object's model frame). Millimetres, radians.
"""

from __future__ import annotations

import numpy as np

from vgripd.config import CameraEntryConfig, Config, IntrinsicsConfig, PoseConfig
from vgripd.errors import NotCalibratedError, NotTaughtError, VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
from vgripd.types import FloatArray


def matrix_from_pose(pose: PoseConfig) -> FloatArray:
    """The (4, 4) float64 transform a ``PoseConfig`` describes (either of its two forms)."""
    if pose.matrix is not None:
        T = np.array(pose.matrix, dtype=np.float64)
        T[3] = (0.0, 0.0, 0.0, 1.0)  # the config accepted it within ROTATION_TOL
        return T
    assert pose.translation_mm is not None  # guaranteed by PoseConfig's validator
    rotvec = pose.rotvec_rad if pose.rotvec_rad is not None else (0.0, 0.0, 0.0)
    return make_transform(matrix_from_rotvec(np.asarray(rotvec, dtype=np.float64)),
                          np.asarray(pose.translation_mm, dtype=np.float64))


def _calibration(cfg: Config, what: str) -> None:
    if cfg.calibration is None:
        raise NotCalibratedError(
            f"{what}: no [calibration] section (camera type {cfg.camera.type!r} is not the "
            "synthetic demo, so the embedded demo calibration does not apply)"
        )


def _camera_model(section: IntrinsicsConfig, where: str) -> CameraModel:
    try:
        return CameraModel(
            fx=section.fx, fy=section.fy, cx=section.cx, cy=section.cy, skew=section.skew,
            dist=section.dist, width=section.width, height=section.height,
        )
    except VgripError as err:
        raise NotCalibratedError(f"{where}: {err}") from None


def camera_models(cfg: Config) -> tuple[CameraModel, CameraModel | None]:
    """``(left, right)`` camera models; ``right`` is None in single-camera (PnP) mode."""
    _calibration(cfg, "camera models")
    assert cfg.calibration is not None
    left = _camera_model(cfg.calibration.left, "calibration.left")
    if cfg.calibration.right is None:
        return left, None
    return left, _camera_model(cfg.calibration.right, "calibration.right")


def T_right_left(cfg: Config) -> FloatArray | None:
    """Pose of the left camera in the right camera frame (``X_R = R X_L + T``), or None (mono)."""
    _calibration(cfg, "stereo rig")
    assert cfg.calibration is not None
    if cfg.calibration.stereo is None:
        return None
    return matrix_from_pose(cfg.calibration.stereo.T_right_left)


def stereo_rig(cfg: Config) -> StereoRig | None:
    """The calibrated stereo rig, or None when only the left camera is configured."""
    left, right = camera_models(cfg)
    T = T_right_left(cfg)
    if right is None or T is None:
        return None
    try:
        return StereoRig(left, right, T)
    except VgripError as err:
        raise NotCalibratedError(f"calibration.stereo: {err}") from None


def T_base_camera(cfg: Config, T_base_flange: FloatArray | None = None) -> FloatArray:
    """Pose of the (left) camera in the robot base frame at capture time.

    Parameters
    ----------
    T_base_flange : (4, 4) flange pose at capture (mm); required for robot-mounted cameras
        (``ImagePair.T_base_flange``), ignored for fixed ones.
    """
    _calibration(cfg, "hand-eye")
    assert cfg.calibration is not None
    hand_eye = cfg.calibration.hand_eye
    if hand_eye.mounting == "fixed":
        assert hand_eye.T_base_camera is not None
        return matrix_from_pose(hand_eye.T_base_camera)
    assert hand_eye.T_flange_camera is not None
    if T_base_flange is None:
        raise NotCalibratedError(
            "calibration.hand_eye: the camera is robot-mounted but no flange pose came with "
            "the image (the camera driver must deliver T_base_flange)"
        )
    flange = np.asarray(T_base_flange, dtype=np.float64)
    if flange.shape != (4, 4) or not np.all(np.isfinite(flange)):
        raise NotCalibratedError(f"flange pose at capture is not a finite 4x4 matrix: {flange!r}")
    return flange @ matrix_from_pose(hand_eye.T_flange_camera)


def feature_names(cfg: Config) -> tuple[str, ...]:
    """Names of the object's features, in config order (the row order of ``object_points``)."""
    return tuple(f.name for f in cfg.object.features)


def object_points(cfg: Config) -> FloatArray:
    """(n, 3) feature points in mm: object frame (``cad``) or base frame at teach time
    (``reference``), rows in the order of ``feature_names``."""
    return np.array([f.xyz_mm for f in cfg.object.features], dtype=np.float64)


def model_points(cfg: Config) -> FloatArray:
    """(n, 3) mm model points in feature order: ``reference.points_mm`` when taught (``reference``
    definition), else the features' ``xyz_mm`` (``object_points``)."""
    taught = cfg.reference.points_mm
    if cfg.object.definition == "reference" and taught is not None:
        return np.array([taught[name] for name in feature_names(cfg)], dtype=np.float64)
    return object_points(cfg)


def T_base_obj_ref(cfg: Config) -> FloatArray:
    """The taught reference pose of the object in the base frame (4, 4).

    Identity for ``object.definition = "reference"`` (the model points *are* base-frame points
    at the reference), so that ``T_offset = T_base_obj @ inv(T_base_obj_ref)`` holds for both.
    """
    if cfg.object.definition == "reference":
        return np.eye(4)
    if cfg.reference.T_base_obj is None:
        raise NotTaughtError(
            f"reference.T_base_obj: object {cfg.object.name!r} has no taught reference pose yet"
        )
    return matrix_from_pose(cfg.reference.T_base_obj)


# --- multi-camera cells (calibration.cameras; docs/multicamera.md) ---------------------------


def is_multi_camera(cfg: Config) -> bool:
    """True for a cell configured with ``calibration.cameras`` (2..8 cameras)."""
    return cfg.calibration is not None and cfg.calibration.cameras is not None


def _cameras(cfg: Config) -> tuple[CameraEntryConfig, ...]:
    _calibration(cfg, "multi-camera cell")
    assert cfg.calibration is not None
    if cfg.calibration.cameras is None:
        raise NotCalibratedError("calibration.cameras: not a multi-camera cell")
    return cfg.calibration.cameras


def camera_names(cfg: Config) -> tuple[str, ...]:
    """Names of the cameras of a multi-camera cell, in config order (the image order)."""
    return tuple(cam.name for cam in _cameras(cfg))


def multi_camera_models(cfg: Config) -> tuple[CameraModel, ...]:
    """Camera models of a multi-camera cell, in config order."""
    return tuple(_camera_model(cam.intrinsics, f"calibration.cameras.{i}.intrinsics")
                 for i, cam in enumerate(_cameras(cfg)))


def T_base_cameras(cfg: Config, T_base_flange: FloatArray | None = None) -> FloatArray:
    """(N, 4, 4) poses of the cameras of a multi-camera cell in the base frame at capture.

    ``T_base_flange`` is needed when any camera is robot-mounted (as for
    :func:`T_base_camera`); fixed cameras ignore it. A (N, 4, 4) stack gives each camera its
    own flange pose: the views of one robot-mounted camera (:func:`views_config`).
    """
    cameras = _cameras(cfg)
    if T_base_flange is not None and np.ndim(T_base_flange) == 3:
        if len(T_base_flange) != len(cameras):
            raise NotCalibratedError(f"{len(T_base_flange)} flange poses came with the images "
                                     f"of {len(cameras)} cameras (views)")
        flanges: list[FloatArray | None] = list(T_base_flange)
    else:
        flanges = [T_base_flange] * len(cameras)
    out = []
    for i, (cam, T_base_flange) in enumerate(zip(cameras, flanges, strict=True)):
        if cam.mounting == "fixed":
            assert cam.T_base_camera is not None
            out.append(matrix_from_pose(cam.T_base_camera))
            continue
        assert cam.T_flange_camera is not None
        if T_base_flange is None:
            raise NotCalibratedError(
                f"calibration.cameras.{i} ({cam.name!r}) is robot-mounted but no flange pose "
                "came with the images (the camera driver must deliver T_base_flange)")
        flange = np.asarray(T_base_flange, dtype=np.float64)
        if flange.shape != (4, 4) or not np.all(np.isfinite(flange)):
            raise NotCalibratedError(
                f"flange pose at capture is not a finite 4x4 matrix: {flange!r}")
        out.append(flange @ matrix_from_pose(cam.T_flange_camera))
    return np.array(out)


def views_config(cfg: Config) -> Config:
    """A cell of ``vision.views`` > 1 as the multi-camera cell it is: its one robot-mounted
    camera repeated as cameras ``view1`` .. ``viewN``, each seen through its own flange pose
    (an (N, 4, 4) ``ImagePair.T_base_flange``). The fit, the residuals per view (each view is
    a group of its own) and the disagreeing-view check are then the multi-camera path's.
    Other configs come back unchanged."""
    if cfg.vision.views == 1:
        return cfg
    _calibration(cfg, "views")
    assert cfg.calibration is not None
    cal = cfg.calibration
    cameras = tuple(CameraEntryConfig(name=f"view{k + 1}", intrinsics=cal.left,
                                      mounting="robot",
                                      T_flange_camera=cal.hand_eye.T_flange_camera)
                    for k in range(cfg.vision.views))
    data = cfg.model_dump(mode="json", exclude_none=True)
    data["calibration"] = {"cameras": [c.model_dump(mode="json", exclude_none=True)
                                       for c in cameras]}
    data["vision"]["views"] = 1  # the expanded cell takes its N images at once
    data["vision"].pop("view_poses", None)
    return Config.model_validate(data)


def camera_groups(cfg: Config) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """``(rig name, camera indices)``: the configured rigs, then each camera outside every rig
    as a group of its own (``CalibrationConfig.camera_groups``)."""
    _cameras(cfg)
    assert cfg.calibration is not None
    return cfg.calibration.camera_groups()


def feature_normals(cfg: Config) -> FloatArray:
    """(n, 3) unit outward normals of the features (object frame), NaN rows where a feature
    has no ``normal`` (seen from both sides), rows in the order of ``feature_names``."""
    out = np.full((len(cfg.object.features), 3), np.nan)
    for i, f in enumerate(cfg.object.features):
        if f.normal is not None:
            v = np.asarray(f.normal, dtype=np.float64)
            out[i] = v / np.linalg.norm(v)
    return out
