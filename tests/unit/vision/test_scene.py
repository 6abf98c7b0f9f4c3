"""Config sections calibration/object/reference and the geometry built from them (vgripd.vision.scene)."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgripd.config import PoseConfig, config_from_dict, load_config
from vgripd.errors import ConfigError, NotCalibratedError
from vgripd.geometry.transforms import pose_error
from vgripd.vision import scene

LEFT = {"fx": 1000.0, "fy": 1000.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
FIXED = {"mounting": "fixed", "T_base_camera": {"translation_mm": [0, 0, 500]}}
FEATS = [
    {"name": n, "xyz_mm": xyz, "kind": "circle", "diameter_mm": 8}
    for n, xyz in [("a", [0, 0, 0]), ("b", [50, 0, 0]), ("c", [0, 30, 5])]
]


def test_empty_config_is_the_demo_stereo_cell() -> None:
    cfg = config_from_dict({})
    left, right = scene.camera_models(cfg)
    assert right is not None
    assert scene.stereo_rig(cfg) is not None
    pts_obj = scene.object_points(cfg)
    assert pts_obj.shape == (6, 3)
    T_base_obj = scene.T_base_obj_ref(cfg)
    T_cam_base = np.linalg.inv(scene.T_base_camera(cfg))
    pts_left = (T_cam_base @ T_base_obj @ np.c_[pts_obj, np.ones(6)].T).T[:, :3]
    T_rl = scene.T_right_left(cfg)
    assert T_rl is not None
    pts_right = (T_rl @ np.c_[pts_left, np.ones(6)].T).T[:, :3]
    # Both cameras look down at the plate from ~690 mm and see every mark well inside the image.
    for model, pts in ((left, pts_left), (right, pts_right)):
        assert np.all((pts[:, 2] > 600) & (pts[:, 2] < 750))
        px = model.project(pts)
        assert np.all((px > 100) & (px < [model.width - 100, model.height - 100]))
    # Baseline ~150 mm, toe-in of a few degrees per camera.
    baseline_mm, toe_in_deg = pose_error(T_rl, np.eye(4))
    assert 140 < baseline_mm < 160
    assert 5 < toe_in_deg < 20


def test_demo_object_has_no_symmetry_ambiguity() -> None:
    pts = scene.object_points(config_from_dict({}))
    d = np.sort([np.linalg.norm(pts[i] - pts[j]) for i, j in itertools.combinations(range(6), 2)])
    assert np.diff(d).min() > 3.0
    assert np.ptp(pts[:, 2]) > 10  # non-planar


@pytest.mark.parametrize(
    ("data", "path"),
    [
        ({"calibration": {"left": {**LEFT, "fx": 0}, "hand_eye": FIXED}}, "calibration.left.fx"),
        ({"calibration": {"left": {**LEFT, "cx": 700}, "hand_eye": FIXED}}, "calibration.left"),
        ({"calibration": {"left": {**LEFT, "dist": [0, 0]}, "hand_eye": FIXED}},
         "calibration.left.dist"),
        ({"calibration": {"left": {**LEFT, "fxx": 1}, "hand_eye": FIXED}}, "calibration.left.fxx"),
        ({"calibration": {"left": LEFT}}, "calibration.hand_eye"),
        ({"calibration": {"left": LEFT, "right": LEFT, "hand_eye": FIXED}}, "calibration"),
        ({"calibration": {"left": LEFT, "hand_eye": {**FIXED, "mounting": "robot"}}},
         "calibration.hand_eye"),
        ({"calibration": {"left": LEFT, "hand_eye": {"mounting": "tripod"}}},
         "calibration.hand_eye.mounting"),
        ({"calibration": {"left": LEFT, "hand_eye": {
            "T_base_camera": {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1.01, 0], [0, 0, 0, 1]]}}}},
         "calibration.hand_eye.T_base_camera.matrix"),
        ({"calibration": {"left": LEFT, "hand_eye": {
            "T_base_camera": {"translation_mm": [0, 0, 1], "matrix": np.eye(4).tolist()}}}},
         "calibration.hand_eye.T_base_camera"),
        ({"calibration": {"left": LEFT, "hand_eye": {"T_base_camera": {"rotvec_rad": [0, 0, 1]}}}},
         "calibration.hand_eye.T_base_camera"),
        ({"object": {"features": FEATS[:2]}}, "object.features"),
        ({"object": {"features": [*FEATS, FEATS[0]]}}, "object.features"),
        ({"object": {"features": [*FEATS[:2], {**FEATS[2], "diameter_mm": -1}]}},
         "object.features.2.circle.diameter_mm"),
        ({"object": {"features": [*FEATS[:2], {**FEATS[2], "kind": "blob"}]}}, "object.features.2"),
        ({"object": {"features": [*FEATS[:2], {"name": "m", "xyz_mm": [0, 0, 0], "kind": "aruco",
                                                 "marker_id": 3, "size_mm": 20, "dictionary": "4x4"}]}},
         "object.features.2.aruco.dictionary"),
        ({"object": {"definition": "reference", "features": FEATS},
          "reference": {"T_base_obj": {"translation_mm": [0, 0, 0]}}}, "reference.T_base_obj"),
    ],
)
def test_config_errors_name_the_field_path(data: dict[str, Any], path: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "cell.toml")
    assert f"cell.toml: {path}" in str(info.value) or f"{path} " in str(info.value)


@pytest.mark.parametrize("rotvec", [[0, 0, 0], [0.1, -0.2, 0.3], [np.pi, 0, 0], [0, 3.1, 0.2]])
def test_pose_forms_agree_with_opencv_and_scipy(rotvec: list[float]) -> None:
    T = scene.matrix_from_pose(PoseConfig(translation_mm=(1, -2, 3), rotvec_rad=tuple(rotvec)))
    np.testing.assert_allclose(T[:3, :3], cv2.Rodrigues(np.array(rotvec, float))[0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(T[:3, 3], [1, -2, 3])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    again = scene.matrix_from_pose(PoseConfig(matrix=tuple(map(tuple, T.tolist()))))
    np.testing.assert_allclose(again, T, atol=1e-15)


def test_single_camera_has_no_rig_and_real_camera_needs_calibration() -> None:
    mono = config_from_dict({"calibration": {"left": LEFT, "hand_eye": FIXED}})
    assert scene.camera_models(mono)[1] is None
    assert scene.stereo_rig(mono) is None
    assert scene.T_right_left(mono) is None

    real = config_from_dict({"camera": {"type": "opencv", "left": 0}})
    assert real.calibration is None
    for fn in (scene.camera_models, scene.stereo_rig, scene.T_base_camera):
        with pytest.raises(NotCalibratedError, match="no \\[calibration\\]"):
            fn(real)


def test_robot_mounted_camera_chains_the_flange_pose() -> None:
    T_fc = {"translation_mm": [0, 50, 80], "rotvec_rad": [0, 0, 0.5]}
    cfg = config_from_dict({"calibration": {
        "left": LEFT, "hand_eye": {"mounting": "robot", "T_flange_camera": T_fc}}})
    T_bf = scene.matrix_from_pose(PoseConfig(translation_mm=(400, 0, 600), rotvec_rad=(3.0, 0, 0)))
    expected = T_bf @ scene.matrix_from_pose(PoseConfig.model_validate(T_fc))
    np.testing.assert_allclose(scene.T_base_camera(cfg, T_bf), expected, atol=1e-12)
    with pytest.raises(NotCalibratedError, match="flange pose"):
        scene.T_base_camera(cfg)


def test_reference_definitions() -> None:
    by_ref = config_from_dict({"object": {"definition": "reference", "features": FEATS}})
    np.testing.assert_array_equal(scene.T_base_obj_ref(by_ref), np.eye(4))
    assert scene.feature_names(by_ref) == ("a", "b", "c")

    untaught = config_from_dict({"object": {"features": FEATS}})
    with pytest.raises(NotCalibratedError, match="reference.T_base_obj"):
        scene.T_base_obj_ref(untaught)

    taught = config_from_dict({"object": {"features": FEATS},
                               "reference": {"T_base_obj": {"translation_mm": [5, 6, 7]}}})
    np.testing.assert_array_equal(scene.T_base_obj_ref(taught)[:3, 3], [5, 6, 7])


def test_toml_file_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(
        """
[camera]
type = "replay"
folder = "x"

[calibration.left]
fx = 1200.5
fy = 1201.0
cx = 640
cy = 480
dist = [-0.1, 0.05, 0.0, 0.0, 0.0]
width = 1280
height = 960

[calibration.hand_eye]
mounting = "robot"
T_flange_camera = { translation_mm = [0, 60, 90], rotvec_rad = [0, 0, 1.5708] }

[object]
name = "bracket"
definition = "cad"

[[object.features]]
name = "hole1"
xyz_mm = [0, 0, 0]
kind = "circle"
diameter_mm = 6

[[object.features]]
name = "tag"
xyz_mm = [40, 0, 0]
kind = "aruco"
marker_id = 7
size_mm = 20

[[object.features]]
name = "corner"
xyz_mm = [0, 30, 10]
kind = "template"
template = "corner.png"
size_px = 48

[reference]
T_base_obj = { matrix = [[1, 0, 0, 500], [0, 1, 0, 20], [0, 0, 1, 0], [0, 0, 0, 1]] }
""",
        encoding="utf-8",
    )
    cfg = load_config(path)
    left, right = scene.camera_models(cfg)
    assert (left.fx, left.dist[0], right) == (1200.5, -0.1, None)
    assert [f.kind for f in cfg.object.features] == ["circle", "aruco", "template"]
    np.testing.assert_array_equal(scene.T_base_obj_ref(cfg)[:3, 3], [500, 20, 0])
