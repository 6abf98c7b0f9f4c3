"""``vision.views``: the config rules and the cell it expands to (``scene.views_config``),
the camera poses of the views checked against scipy's rotations as an independent oracle."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from vgripd.config import config_from_dict
from vgripd.errors import ConfigError, NotCalibratedError
from vgripd.vision import scene

LEFT = {"fx": 1000.0, "fy": 1000.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
T_FC = {"translation_mm": [10.0, 60.0, 120.0], "rotvec_rad": [0.02, -0.01, 0.3]}
ROBOT = {"mounting": "robot", "T_flange_camera": T_FC}
MARKERS = {"name": "tag_plate", "definition": "cad", "features": [
    {"name": f"t{i}", "xyz_mm": [x, y, 0.0], "kind": "aruco", "marker_id": i,
     "dictionary": "DICT_4X4_50", "size_mm": 20.0}
    for i, (x, y) in enumerate([(-60.0, -40.0), (60.0, -40.0), (60.0, 40.0), (-60.0, 45.0)])]}


def cfg(views: int = 3, **vision: Any) -> Any:
    return config_from_dict({"calibration": {"left": LEFT, "hand_eye": ROBOT},
                             "vision": {"views": views, **vision}})


@pytest.mark.parametrize(("calibration", "extra", "why"), [
    ({"left": LEFT, "hand_eye": {"mounting": "fixed",
                                 "T_base_camera": {"translation_mm": [0, 0, 900]}}}, {},
     'mounting is "fixed"'),
    ({"left": LEFT, "right": LEFT, "hand_eye": ROBOT,
      "stereo": {"T_right_left": {"translation_mm": [-100, 0, 0]}}}, {},
     "calibration.right is set"),
    # ArUco markers: a pick list's marks for one camera, so the views rule is what refuses
    ({"left": LEFT, "hand_eye": ROBOT}, {"picking": {"max_objects": 3}, "object": MARKERS},
     "max_objects"),
])
def test_views_need_one_robot_mounted_camera(calibration: dict[str, Any],
                                             extra: dict[str, Any], why: str) -> None:
    with pytest.raises(ConfigError, match=f"vision.views = 2 needs one robot-mounted camera.*"
                       f"{why}"):
        config_from_dict({"calibration": calibration, "vision": {"views": 2}, **extra})


def test_view_poses_count_must_match_views_and_views_are_1_to_8() -> None:
    with pytest.raises(ConfigError, match="vision: .*view_poses has 1 poses for views = 3"):
        cfg(3, view_poses=[{"translation_mm": [0, 0, 0]}])
    with pytest.raises(ConfigError, match="vision.views"):
        cfg(9)
    with pytest.raises(ConfigError, match="vision.view_timeout_s"):
        cfg(2, view_timeout_s=0)


def test_one_view_is_the_config_itself() -> None:
    one = cfg(1)
    assert scene.views_config(one) is one


def test_views_expand_to_a_cell_of_robot_mounted_views() -> None:
    cell = scene.views_config(cfg(3))
    assert scene.camera_names(cell) == ("view1", "view2", "view3")
    assert cell.vision.views == 1
    assert all(c.mounting == "robot" for c in cell.calibration.cameras)
    assert scene.camera_groups(cell) == (("view1", (0,)), ("view2", (1,)), ("view3", (2,)))
    with pytest.raises(NotCalibratedError, match="2 flange poses came with the images of 3"):
        scene.T_base_cameras(cell, np.stack([np.eye(4)] * 2))


def _pose(rotvec: list[float], t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


rotvecs = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)
points = st.lists(st.floats(-2000.0, 2000.0), min_size=3, max_size=3)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(rotvecs, points), min_size=2, max_size=8))
def test_each_view_is_seen_through_its_own_flange_pose(flanges: list[Any]) -> None:
    """Camera k = flange k @ T_flange_camera, composed here with scipy, never mixed up."""
    cell = scene.views_config(cfg(len(flanges)))
    stack = np.stack([_pose(r, t) for r, t in flanges])
    T_fc = _pose(T_FC["rotvec_rad"], T_FC["translation_mm"])
    np.testing.assert_allclose(scene.T_base_cameras(cell, stack), stack @ T_fc, atol=1e-8)


def test_views_refuse_a_link_that_cannot_capture() -> None:
    """opcua and robot_socket have no CAPTURE: in a views cell they could only be refused."""
    with pytest.raises(ConfigError, match='links.1..type = "robot_socket" cannot send CAPTURE.*'
                       "use modbus_client, modbus_rtu, modbus_server, s7, ur_rtde"):
        config_from_dict({"calibration": {"left": LEFT, "hand_eye": ROBOT},
                          "vision": {"views": 2},
                          "links": [{"type": "modbus_server"}, {"type": "robot_socket"}]})
    config_from_dict({"calibration": {"left": LEFT, "hand_eye": ROBOT}, "vision": {"views": 1},
                      "links": [{"type": "robot_socket"}]})
