"""The offset limits judge what a user means (docs/pipeline.md, "Limits"): how far a point of the
object moved (its origin, the mark centroid, the taught grip or a configured point) and the
angle it turned, not the length of the base-frame offset's translation, which adds the lever
arm of every rotation about the robot base.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from vgripd.config import Config, config_from_dict
from vgripd.errors import ConfigError, NotCalibratedError
from vgripd.geometry.transforms import invert_transform, make_transform, matrix_from_rotvec
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.types import Status
from vgripd.vision.pipeline import Pipeline
from vgripd.vision.pose_checks import Measurement, check_pose, displacement_mm, limit_point

REF_T = (600.0, 100.0, 10.0)  # the demo cell's taught reference
REF_ROT = (0.0, 0.0, 0.05)
GOOD = {"fit_rms_mm": 0.01, "reprojection_px": 0.02, "epipolar_px": 0.01}


def make_config(**sections: Any) -> Config:
    data: dict[str, Any] = {"camera": {"type": "synthetic", "seed": 3}}
    data.update(sections)
    return config_from_dict(data)


def T_ref() -> np.ndarray:
    return make_transform(matrix_from_rotvec(np.array(REF_ROT)), np.array(REF_T))


def turned_about_own_origin(rotvec: tuple[float, float, float],
                            shift: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The reference object turned by ``rotvec`` (base-frame axis) about its own origin, then
    shifted: ``T_base_obj``."""
    ref = T_ref()
    R = matrix_from_rotvec(np.array(rotvec)) @ ref[:3, :3]
    return make_transform(R, ref[:3, 3] + np.array(shift))


def judge(config: Config, T_base_obj: np.ndarray) -> tuple[Status, str]:
    pipeline = Pipeline(config)
    m = Measurement(found=6, needed=4, T_base_obj=T_base_obj,
                    offset=T_base_obj @ invert_transform(pipeline.T_base_obj_ref),
                    residuals=GOOD, limit_point=pipeline.limit_point,
                    limit_point_name=pipeline.limit_point_name)
    return check_pose(m, config.vision, config.limits)


def test_a_plate_turned_about_itself_far_from_the_base_is_within_the_limits() -> None:
    # 5 deg about base z through the object origin (608 mm from the base) plus 10 mm: the
    # base-frame offset's translation is the lever arm, 2 * 608 * sin(2.5 deg) = 53 mm over
    # the 50 mm limit, yet the plate moved 10 mm.
    T = turned_about_own_origin((0.0, 0.0, np.radians(5.0)), (8.0, -6.0, 0.0))
    offset = T @ invert_transform(T_ref())
    assert np.linalg.norm(offset[:3, 3]) > 50.0
    assert displacement_mm(T, offset) == pytest.approx(10.0, abs=1e-9)
    status, message = judge(make_config(), T)
    assert status is Status.OK, message


def test_a_real_80_mm_displacement_is_out_of_limits_naming_the_quantity() -> None:
    T = turned_about_own_origin((0.0, 0.0, 0.0), (80.0, 0.0, 0.0))
    status, message = judge(make_config(), T)
    assert status is Status.OUT_OF_LIMITS
    assert message == ("offset translation: object origin moved 80.00 mm > "
                       "limits.max_translation_mm 50")


def test_the_rotation_limit_is_the_angle_the_object_turned() -> None:
    T = turned_about_own_origin((np.radians(12.0), 0.0, 0.0))
    status, message = judge(make_config(), T)
    assert status is Status.OUT_OF_LIMITS
    assert message == "offset rotation: object turned 12.00 deg > limits.max_rotation_deg 10"
    status, _ = judge(make_config(), turned_about_own_origin((np.radians(9.0), 0.0, 0.0)))
    assert status is Status.OK


GRIP = {"translation_mm": [REF_T[0], REF_T[1], REF_T[2] + 150.0],
        "rotvec_rad": [np.pi, 0.0, 0.0]}


def test_the_grip_point_variant_limits_where_the_gripper_goes() -> None:
    # Tilted 6 deg about base x through the object origin: the origin stays, the grip 150 mm
    # above it moves 2 * 150 * sin(3 deg) = 15.7 mm.
    T = turned_about_own_origin((np.radians(6.0), 0.0, 0.0))
    limits = {"max_translation_mm": 12.0}
    assert judge(make_config(limits=limits, reference={
        "T_base_obj": {"translation_mm": REF_T, "rotvec_rad": REF_ROT}, "grip": GRIP}), T)[0] \
        is Status.OK
    status, message = judge(make_config(limits={**limits, "point": "grip"}, reference={
        "T_base_obj": {"translation_mm": REF_T, "rotvec_rad": REF_ROT}, "grip": GRIP}), T)
    assert status is Status.OUT_OF_LIMITS
    moved = 2 * 150.0 * np.sin(np.radians(3.0))
    assert message.startswith(f"offset translation: grip point moved {moved:.2f} mm > "
                              "limits.max_translation_mm 12")
    # The same point given in the object frame.
    p = invert_transform(T_ref()) @ np.array([*GRIP["translation_mm"], 1.0])
    config = make_config(limits={**limits, "point_mm": p[:3].tolist()})
    status, message = judge(config, T)
    assert status is Status.OUT_OF_LIMITS
    assert f"limits.point_mm [0.0, 0.0, 150.0] moved {moved:.2f} mm" in message


def test_grip_point_needs_a_taught_grip_and_point_forms_exclude_each_other() -> None:
    with pytest.raises(NotCalibratedError, match=r'reference\.grip: limits\.point = "grip"'):
        Pipeline(make_config(limits={"point": "grip"}))
    with pytest.raises(ConfigError, match="either point or point_mm"):
        make_config(limits={"point": "origin", "point_mm": [0, 0, 0]})


def test_reference_defined_objects_default_to_the_mark_centroid() -> None:
    # With object.definition = "reference" the object frame is the base frame at teach time:
    # its origin is the robot base, so the origin would carry the whole lever arm again.
    features = [{"name": f"m{i}", "kind": "circle", "xyz_mm": xyz, "diameter_mm": 10.0}
                for i, xyz in enumerate([(540.0, 130.0, 10.0), (535.0, 56.0, 10.0),
                                         (585.0, 145.0, 10.0), (570.0, 85.0, 10.0)])]
    config = make_config(object={"definition": "reference", "features": features})
    model = np.array([f["xyz_mm"] for f in features])
    point, name = limit_point(config, model, np.eye(4))
    assert name == "mark centroid"
    assert point == pytest.approx(model.mean(axis=0))
    c = model.mean(axis=0)
    turn = matrix_from_rotvec(np.array([0.0, 0.0, np.radians(6.0)]))
    T = make_transform(turn, c - turn @ c)  # turned 6 deg about the centroid
    status, message = judge(config, T)
    assert np.linalg.norm(T[:3, 3]) > 50.0
    assert status is Status.OK, message


async def test_a_synthetic_scene_turned_about_the_object_passes_the_limits() -> None:
    # End to end: images of the demo plate turned 5 deg about its own origin.
    pose = {"translation_mm": list(REF_T), "rotvec_rad": [0.0, 0.0, 0.05 + np.radians(5.0)]}
    config = make_config(camera={"type": "synthetic", "seed": 3, "pose": pose})
    cls = load_class(CAMERAS, "camera", "synthetic")
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    await camera.open()
    try:
        pair = await camera.grab(30.0)
    finally:
        await camera.close()
    result = Pipeline(config).process(pair, 1)
    assert result.offset is not None
    assert np.linalg.norm(result.offset[:3, 3]) > 50.0
    assert result.status is Status.OK, result.message
