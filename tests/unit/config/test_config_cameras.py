"""calibration.cameras / calibration.rigs (multi-camera cells) and feature normals: accepted
shapes, refusals naming the field, the first camera standing in for ``left``, and the scene
helpers built from them."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from vgripd.config import config_from_dict
from vgripd.errors import ConfigError, NotCalibratedError
from vgripd.vision import scene

INTR = {"fx": 1000.0, "fy": 1000.0, "cx": 640.0, "cy": 512.0, "width": 1280, "height": 1024}


def _cams(n: int) -> list[dict[str, Any]]:
    return [{"name": f"cam{i}", "intrinsics": dict(INTR, fx=1000.0 + i),
             "T_base_camera": {"translation_mm": [100.0 * i, 0.0, 800.0],
                               "rotvec_rad": [np.pi, 0.0, 0.0]}} for i in range(n)]


def _cfg(**calibration: Any) -> Any:
    return config_from_dict({"calibration": calibration})


def test_cameras_and_rigs_load_and_first_camera_stands_in_for_left() -> None:
    cfg = _cfg(cameras=_cams(4), rigs=[{"name": "north", "cameras": ["cam1", "cam0"]}])
    cal = cfg.calibration
    assert cal is not None
    assert cal.cameras is not None
    assert cal.left == cal.cameras[0].intrinsics
    assert cal.hand_eye.T_base_camera == cal.cameras[0].T_base_camera
    assert cal.right is None
    assert cal.stereo is None
    assert cal.camera_groups() == (("north", (1, 0)), ("cam2", (2,)), ("cam3", (3,)))
    assert scene.is_multi_camera(cfg)
    assert scene.camera_names(cfg) == ("cam0", "cam1", "cam2", "cam3")
    assert [m.fx for m in scene.multi_camera_models(cfg)] == [1000.0, 1001.0, 1002.0, 1003.0]
    T = scene.T_base_cameras(cfg)
    assert T.shape == (4, 4, 4)
    np.testing.assert_allclose(T[:, :3, 3], [[0, 0, 800], [100, 0, 800], [200, 0, 800],
                                             [300, 0, 800]])


def test_a_dumped_multi_camera_config_loads_again() -> None:
    cfg = _cfg(cameras=_cams(3), rigs=[{"name": "r", "cameras": ["cam0", "cam1"]}])
    again = config_from_dict(cfg.model_dump(mode="json", exclude_none=True))
    assert again == cfg


@pytest.mark.parametrize(("calibration", "expected"), [
    ({"cameras": _cams(1)}, "2 to 8 cameras, got 1"),
    ({"cameras": _cams(9)}, "2 to 8 cameras, got 9"),
    ({"cameras": [*_cams(2), _cams(1)[0]]}, "calibration.cameras.2.name: 'cam0' is already"),
    ({"cameras": _cams(2), "rigs": [{"name": "r", "cameras": ["nope"]}]},
     "calibration.rigs.0.cameras.0: no camera named 'nope'"),
    ({"cameras": _cams(3), "rigs": [{"name": "a", "cameras": ["cam0"]},
                                    {"name": "b", "cameras": ["cam1", "cam0"]}]},
     "calibration.rigs.1.cameras.1: camera 'cam0' is already in rig 'a'"),
    ({"cameras": _cams(2), "rigs": [{"name": "a", "cameras": ["cam0"]},
                                    {"name": "a", "cameras": ["cam1"]}]},
     "calibration.rigs.1.name: duplicate rig name 'a'"),
    ({"cameras": _cams(2), "rigs": [{"name": "cam1", "cameras": ["cam0"]}]},
     "calibration.rigs.0.name: 'cam1' is also a camera's name"),
    ({"cameras": _cams(2), "rigs": [{"name": "a", "cameras": []}]},
     "calibration.rigs.0.cameras: Tuple should have at least 1 item"),
    ({"cameras": _cams(2), "right": INTR}, "calibration.right is not used with"),
    ({"cameras": _cams(2), "left": dict(INTR, fx=5.0)},
     "calibration.left is not used with calibration.cameras and differs"),
    ({"cameras": [dict(_cams(1)[0], name="North")] + _cams(2)[1:]},
     "calibration.cameras.0.name: String should match pattern"),
    ({"cameras": [dict(_cams(1)[0], mounting="robot")] + _cams(2)[1:]},
     'calibration.cameras.0: Value error, mounting = "robot" needs T_flange_camera'),
    ({"cameras": _cams(2)[:1] + [dict(_cams(2)[1], intrinsics=dict(INTR, fx=-1))]},
     "calibration.cameras.1.intrinsics.fx: Input should be greater than 0"),
    ({"left": INTR, "hand_eye": {"T_base_camera": {"translation_mm": [0, 0, 0]}},
      "rigs": [{"name": "a", "cameras": ["x"]}]}, "calibration.rigs needs calibration.cameras"),
])
def test_bad_camera_sections_are_refused_naming_the_field(
        calibration: dict[str, Any], expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        _cfg(**calibration)
    assert expected in str(err.value)
    # One error, not a cascade (a bad first camera does not also make left "missing").
    assert "left: Field required" not in str(err.value)


def _pasted(i: int, j: int, matrix: bool = False) -> list[dict[str, Any]]:
    """Four cameras, camera j's pose pasted over camera i's (a matrix with ``matrix``)."""
    cams = _cams(4)
    cams[i] = dict(cams[i], T_base_camera=cams[j]["T_base_camera"])
    if matrix:
        t = cams[j]["T_base_camera"]["translation_mm"]
        cams[i]["T_base_camera"] = {"matrix": [[1, 0, 0, t[0]], [0, -1, 0, t[1] + 0.4],
                                               [0, 0, -1, t[2]], [0, 0, 0, 1]]}
    return cams


@pytest.mark.parametrize(("cams", "expected"), [
    (_pasted(2, 0), "calibration.cameras.2.T_base_camera: 0 mm from calibration.cameras.0 "
                    "('cam0'): two fixed cameras at one place"),
    (_pasted(3, 1, matrix=True), "calibration.cameras.3.T_base_camera: 0.4 mm from "
                                 "calibration.cameras.1 ('cam1')"),
])
def test_two_cameras_at_one_place_are_refused_naming_the_second(
        cams: list[dict[str, Any]], expected: str) -> None:
    """A pose pasted twice leaves a pair with no baseline: refused at load (``vgripd check``
    and the config transaction say so), not a worker that cannot build its locator."""
    with pytest.raises(ConfigError) as err:
        _cfg(cameras=cams)
    assert expected in str(err.value)


def test_cameras_on_the_flange_may_share_a_pose() -> None:
    """A fixed camera and one on the flange with equal numbers are in different frames, and
    cameras on the flange at one pose are the views of one camera the robot moves."""
    cams = _cams(3)
    for i in (1, 2):
        cams[i] = {"name": f"view{i}", "intrinsics": INTR, "mounting": "robot",
                   "T_flange_camera": cams[0]["T_base_camera"]}
    assert _cfg(cameras=cams).calibration.cameras is not None


@pytest.mark.parametrize("t", [[0.0, 0.0, 0.0], [0.3, -0.2, 0.5]])
def test_a_stereo_pair_without_a_baseline_is_refused(t: list[float]) -> None:
    with pytest.raises(ConfigError, match=r"calibration.stereo: Value error, T_right_left: "
                                          r"baseline .* mm: the two cameras are at one place"):
        _cfg(left=INTR, right=INTR, stereo={"T_right_left": {"translation_mm": t}},
             hand_eye={"T_base_camera": {"translation_mm": [0, 0, 800]}})


def test_robot_mounted_camera_needs_the_flange_pose() -> None:
    cams = _cams(2)
    cams[1] = {"name": "hand", "intrinsics": INTR, "mounting": "robot",
               "T_flange_camera": {"translation_mm": [0, 50, 100]}}
    cfg = _cfg(cameras=cams)
    with pytest.raises(NotCalibratedError, match=r"calibration.cameras.1 \('hand'\)"):
        scene.T_base_cameras(cfg)
    flange = np.eye(4)
    flange[:3, 3] = (400.0, 0.0, 300.0)
    T = scene.T_base_cameras(cfg, flange)
    np.testing.assert_allclose(T[1][:3, 3], [400.0, 50.0, 400.0])


def test_single_pair_config_is_not_multi_camera() -> None:
    cfg = config_from_dict({})
    assert not scene.is_multi_camera(cfg)
    with pytest.raises(NotCalibratedError, match="not a multi-camera cell"):
        scene.camera_names(cfg)


def test_feature_normals_optional_normalised_and_nonzero() -> None:
    feats = [{"name": "a", "kind": "circle", "xyz_mm": [0, 0, 0], "diameter_mm": 5,
              "normal": [0, 0, -2]},
             {"name": "b", "kind": "circle", "xyz_mm": [50, 0, 0], "diameter_mm": 5},
             {"name": "c", "kind": "circle", "xyz_mm": [0, 40, 0], "diameter_mm": 5}]
    cfg = config_from_dict({"object": {"features": feats}})
    n = scene.feature_normals(cfg)
    np.testing.assert_allclose(n[0], [0, 0, -1])
    assert np.isnan(n[1:]).all()
    feats[0]["normal"] = [0, 0, 0]
    with pytest.raises(ConfigError, match=r"object.features.0.circle.normal: Value error, "
                                          r"normal must be a non-zero vector"):
        config_from_dict({"object": {"features": feats}})
