"""``[calibration]``: the cameras' intrinsics, the stereo rig, the hand-eye pose or a
multi-camera cell's cameras and rigs; ``[calibration_walk]`` (how the robot moves in a walked
hand-eye calibration); and the embedded demo cell's calibration."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator

from vgripd.config.common import Model, PoseConfig


class CalibrationWalkConfig(Model):
    """How the robot programs move in a walked hand-eye calibration (docs/calibration-handeye.md,
    "Walked calibration"): ``vgripd robot-program`` writes these into each brand's walk routine
    (vgripd commands no motion). The defaults are the UR RTDE routine's (robots/urscript)."""

    speed_mm_s: float = Field(default=50.0, gt=0, le=250.0)  # linear, flange; <= 250: T1 speed
    settle_s: float = Field(default=1.0, ge=0, le=60.0)  # standstill before the image


class IntrinsicsConfig(Model):
    """One camera: pinhole + Brown distortion in OpenCV order (= Bouguet ``kc``), pixels.

    ``dist = [k1, k2, p1, p2, k3]``; ``skew`` is the x-axis shear in px (Bouguet
    ``alpha_c * fc[0]``), 0 for square-pixel sensors.
    """

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    skew: float = 0.0
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = Field(gt=0)
    height: int = Field(gt=0)

    @model_validator(mode="after")
    def _principal_point_inside(self) -> IntrinsicsConfig:
        if not (0 <= self.cx < self.width and 0 <= self.cy < self.height):
            raise ValueError(
                f"principal point ({self.cx}, {self.cy}) lies outside the "
                f"{self.width}x{self.height} image"
            )
        return self


class StereoConfig(Model):
    """The rig: ``T_right_left`` = pose of the left camera in the right camera frame
    (Bouguet/OpenCV ``stereoCalibrate``: ``X_R = R X_L + T``)."""

    T_right_left: PoseConfig

    @model_validator(mode="after")
    def _has_a_baseline(self) -> StereoConfig:
        baseline = math.dist(self.T_right_left.translation(), (0.0, 0.0, 0.0))
        if baseline < MIN_BASELINE_MM:
            raise ValueError(f"T_right_left: baseline {baseline:.3g} mm: the two cameras are at "
                             f"one place, nothing to triangulate (at least {MIN_BASELINE_MM:g} "
                             "mm; a calibration file copied over the wrong one?)")
        return self


class HandEyeConfig(Model):
    """Where the (left) camera is: fixed in the cell or carried by the robot.

    ``mounting = "fixed"`` needs ``T_base_camera`` (camera in the robot base frame);
    ``mounting = "robot"`` needs ``T_flange_camera`` (camera in the flange frame; the flange pose
    at capture then comes with each image).
    """

    mounting: Literal["fixed", "robot"] = "fixed"
    T_base_camera: PoseConfig | None = None
    T_flange_camera: PoseConfig | None = None

    @model_validator(mode="after")
    def _pose_matches_mounting(self) -> HandEyeConfig:
        need, other = (
            ("T_base_camera", "T_flange_camera")
            if self.mounting == "fixed"
            else ("T_flange_camera", "T_base_camera")
        )
        if getattr(self, need) is None:
            raise ValueError(f'mounting = "{self.mounting}" needs {need}')
        if getattr(self, other) is not None:
            raise ValueError(f'mounting = "{self.mounting}" takes {need}, not {other}')
        return self


#: Names of cameras and rigs: they become keys of residuals (``rig.<name>.reprojection_px``)
#: and of messages, so plain lower-case words.
NAME_PATTERN = r"^[a-z0-9_]+$"

#: How many cameras one cell may have (``calibration.cameras``).
MAX_CAMERAS = 8
#: Two cameras closer than this are one place (a pose copied twice): no baseline between them.
MIN_BASELINE_MM = 1.0


class CameraEntryConfig(Model):
    """One camera of a multi-camera cell: its intrinsics and where it is.

    ``mounting = "fixed"`` needs ``T_base_camera`` (the camera in the robot base frame);
    ``mounting = "robot"`` needs ``T_flange_camera`` (the camera on the flange; the flange pose
    comes with each acquisition). Same meaning as ``calibration.hand_eye``, per camera.
    """

    name: str = Field(pattern=NAME_PATTERN, max_length=32)
    intrinsics: IntrinsicsConfig
    mounting: Literal["fixed", "robot"] = "fixed"
    T_base_camera: PoseConfig | None = None
    T_flange_camera: PoseConfig | None = None

    @model_validator(mode="after")
    def _pose_matches_mounting(self) -> CameraEntryConfig:
        HandEyeConfig(mounting=self.mounting, T_base_camera=self.T_base_camera,
                      T_flange_camera=self.T_flange_camera)
        return self

    def hand_eye(self) -> HandEyeConfig:
        """This camera's pose as the single-camera ``calibration.hand_eye`` section."""
        return HandEyeConfig(mounting=self.mounting, T_base_camera=self.T_base_camera,
                             T_flange_camera=self.T_flange_camera)


class RigConfig(Model):
    """A named group of cameras (usually a stereo pair on one side of the object).

    Rigs do not change the fit (one pose over all marks of all cameras); they name the groups
    whose residuals are reported apart and which the consistency check can blame (a camera
    moved, a rig knocked). A camera belongs to at most one rig; one in no rig is a group of
    its own, named after the camera.
    """

    name: str = Field(pattern=NAME_PATTERN, max_length=32)
    cameras: tuple[str, ...] = Field(min_length=1)


_PLACEHOLDER_INTRINSICS = IntrinsicsConfig(fx=1, fy=1, cx=0, cy=0, width=1, height=1)
_PLACEHOLDER_HAND_EYE = HandEyeConfig(T_base_camera=PoseConfig(translation_mm=(0, 0, 0)))


class CalibrationConfig(Model):
    """Intrinsics of one or two cameras, the stereo rig and the hand-eye pose; or N cameras.

    Without ``right`` (and ``stereo``) the job runs in single-camera (PnP) mode.

    ``cameras`` (2..8 entries) makes a multi-camera cell (docs/multicamera.md): every camera
    has its own pose in the base frame or on the flange, ``rigs`` group them. Then ``right``,
    ``stereo`` and ``hand_eye`` must not be given, and ``left`` / ``hand_eye`` are filled in
    from the first camera, so that single-camera tools (commissioning, teach) see camera 0 as
    "the" camera. (A ``left`` / ``hand_eye`` equal to camera 0 is accepted, so that a dumped
    config loads again.)
    """

    left: IntrinsicsConfig
    right: IntrinsicsConfig | None = None
    stereo: StereoConfig | None = None
    hand_eye: HandEyeConfig
    cameras: tuple[CameraEntryConfig, ...] | None = None
    rigs: tuple[RigConfig, ...] = ()

    @model_validator(mode="before")
    @classmethod
    def _left_from_first_camera(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not data.get("cameras"):
            return data
        data = dict(data)
        first = data["cameras"][0] if isinstance(data["cameras"], list | tuple) else None
        try:
            first = CameraEntryConfig.model_validate(first)
        except ValidationError:
            # The field validation reports calibration.cameras.0 and fails the whole config;
            # placeholders keep it from also calling left and hand_eye missing.
            data.setdefault("left", _PLACEHOLDER_INTRINSICS)
            data.setdefault("hand_eye", _PLACEHOLDER_HAND_EYE)
            return data
        for key in ("right", "stereo"):
            if data.get(key) is not None:
                raise ValueError(f"calibration.{key} is not used with calibration.cameras: "
                                 f"remove it (a pair is two entries of calibration.cameras)")
        derived = {"left": first.intrinsics, "hand_eye": first.hand_eye()}
        for key, value in derived.items():
            given = data.get(key)
            if given is None:
                data[key] = value
                continue
            given_model = type(value).model_validate(given) if isinstance(given, dict) else given
            if given_model != value:
                raise ValueError(
                    f"calibration.{key} is not used with calibration.cameras and differs from "
                    f"the first camera ({first.name!r}): remove calibration.{key}")
        return data

    @model_validator(mode="after")
    def _stereo_complete(self) -> CalibrationConfig:
        if (self.right is None) != (self.stereo is None):
            raise ValueError("calibration.right and calibration.stereo go together")
        return self

    @model_validator(mode="after")
    def _cameras_and_rigs(self) -> CalibrationConfig:
        if self.cameras is None:
            if self.rigs:
                raise ValueError("calibration.rigs needs calibration.cameras")
            return self
        n = len(self.cameras)
        if not 2 <= n <= MAX_CAMERAS:
            raise ValueError(f"calibration.cameras: a multi-camera cell has 2 to {MAX_CAMERAS} "
                             f"cameras, got {n} (one or two cameras: use calibration.left/right)")
        names: dict[str, int] = {}
        for i, cam in enumerate(self.cameras):
            if cam.name in names:
                raise ValueError(f"calibration.cameras.{i}.name: {cam.name!r} is already the "
                                 f"name of calibration.cameras.{names[cam.name]}")
            names[cam.name] = i
        owner: dict[str, str] = {}
        rig_names: set[str] = set()
        for i, rig in enumerate(self.rigs):
            where = f"calibration.rigs.{i}"
            if rig.name in rig_names:
                raise ValueError(f"{where}.name: duplicate rig name {rig.name!r}")
            if rig.name in names:
                raise ValueError(f"{where}.name: {rig.name!r} is also a camera's name (a camera "
                                 "outside every rig is reported under its own name)")
            rig_names.add(rig.name)
            for j, cam_name in enumerate(rig.cameras):
                if cam_name not in names:
                    raise ValueError(f"{where}.cameras.{j}: no camera named {cam_name!r} in "
                                     f"calibration.cameras (known: {', '.join(names)})")
                if cam_name in owner:
                    raise ValueError(f"{where}.cameras.{j}: camera {cam_name!r} is already in "
                                     f"rig {owner[cam_name]!r} (a camera is in one rig at most)")
                owner[cam_name] = rig.name
        self._cameras_apart()
        return self

    def _cameras_apart(self) -> None:
        """Two fixed cameras at one place: a pose pasted twice; the pair between them has no
        baseline to triangulate on. (Cameras on the flange may share a pose: the views of one
        camera that the robot moves between them, docs/multicamera.md.)"""
        assert self.cameras is not None
        seen: dict[int, tuple[float, float, float]] = {}
        for i, cam in enumerate(self.cameras):
            if cam.mounting != "fixed" or cam.T_base_camera is None:
                continue
            here = cam.T_base_camera.translation()
            for j, there in seen.items():
                if math.dist(here, there) < MIN_BASELINE_MM:
                    raise ValueError(
                        f"calibration.cameras.{i}.T_base_camera: {math.dist(here, there):.3g} mm "
                        f"from calibration.cameras.{j} ({self.cameras[j].name!r}): two fixed "
                        f"cameras at one place (at least {MIN_BASELINE_MM:g} mm apart; a pose "
                        "pasted twice?)")
            seen[i] = here

    def camera_groups(self) -> tuple[tuple[str, tuple[int, ...]], ...]:
        """``(group name, camera indices)`` of a multi-camera cell: the rigs in config order,
        then every camera outside all rigs as a group of its own; () without cameras."""
        if self.cameras is None:
            return ()
        index = {cam.name: i for i, cam in enumerate(self.cameras)}
        groups = [(rig.name, tuple(index[c] for c in rig.cameras)) for rig in self.rigs]
        grouped = {i for _, members in groups for i in members}
        groups += [(cam.name, (i,)) for i, cam in enumerate(self.cameras) if i not in grouped]
        return tuple(groups)


# The embedded demo cell: two 1280x1024 cameras with 16 mm lenses (fx ~ 1800 px), 150 mm
# baseline, each toed in by 6 deg, ~690 mm above a 160 x 120 mm plate with six dark 10 mm marks
# (two on bosses 12 and 20 mm high; all pairwise distances differ by > 4 mm, so no symmetry).
DEMO_CALIBRATION = CalibrationConfig(
    left=IntrinsicsConfig(
        fx=1805.2, fy=1804.6, cx=641.3, cy=508.9, dist=(-0.08, 0.11, 0.0004, -0.0003, 0.0),
        width=1280, height=1024,
    ),
    right=IntrinsicsConfig(
        fx=1798.7, fy=1799.5, cx=636.8, cy=514.2, dist=(-0.075, 0.095, -0.0002, 0.0005, 0.0),
        width=1280, height=1024,
    ),
    stereo=StereoConfig(
        T_right_left=PoseConfig(
            translation_mm=(-149.18, 0.35, 15.68), rotvec_rad=(0.0021, 0.20944, -0.0032)
        )
    ),
    hand_eye=HandEyeConfig(
        mounting="fixed",
        T_base_camera=PoseConfig(
            translation_mm=(525.0, 100.0, 700.0), rotvec_rad=(3.13729, 0.0, 0.16442)
        ),
    ),
)
