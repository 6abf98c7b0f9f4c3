"""The ``[conveyor]`` section: what the config load refuses (with the field named) and what
``vgripd check`` judges (the belt's motion blur through the calibrated camera)."""

from __future__ import annotations

from typing import Any

import pytest

from vgripd.config import config_from_dict
from vgripd.errors import ConfigError
from vgripd.service.host.commissioning import check_conveyor

BELT: dict[str, Any] = {"counts_per_mm": 30.0, "direction": [1.0, 0.0, 0.0],
                        "origin_mm": [0.0, 0.0, 0.0], "window_mm": [300.0, 800.0],
                        "trigger_distance_mm": 150.0, "speed_mm_s": 500.0}

#: A camera 1000 mm above the belt, looking straight down, f = 2000 px: 1 mm is 2 px.
CAMERA: dict[str, Any] = {
    "calibration": {
        "left": {"fx": 2000.0, "fy": 2000.0, "cx": 640.0, "cy": 512.0, "width": 1280,
                 "height": 1024},
        "hand_eye": {"mounting": "fixed",
                     "T_base_camera": {"translation_mm": [550.0, 0.0, 1000.0],
                                       "rotvec_rad": [3.141592653589793, 0.0, 0.0]}}},
}


def config(**belt: Any) -> Any:
    return config_from_dict({"conveyor": {**BELT, **belt}})


def test_a_good_belt_loads() -> None:
    cfg = config()
    assert cfg.conveyor is not None
    assert cfg.conveyor.latch == "link"
    assert cfg.conveyor.window_points() == [(300.0, 0.0, 0.0), (800.0, 0.0, 0.0)]


@pytest.mark.parametrize(("change", "words"), [
    ({"direction": [1.0, 1.0, 0.0]}, "conveyor.direction .* not a unit vector"),
    ({"direction": [0.8, 0.0, 0.6]}, "leaves the belt plane .* by 36.87 deg"),
    ({"counts_per_mm": 30000.0}, "counts_per_mm 30000 is implausible"),
    ({"counts_per_mm": 0.001}, "counts_per_mm 0.001 is implausible"),
    ({"window_mm": [800.0, 300.0]}, "upstream limit must be below"),
    ({"trigger_distance_mm": 600.0}, "parts would pass between two images"),
    ({"latch": "guess"}, "conveyor.latch"),
])
def test_a_bad_belt_is_refused_naming_the_field(change: dict[str, Any], words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        config(**change)


def test_a_window_outside_the_workspace_is_refused() -> None:
    data = {"conveyor": BELT, "limits": {"workspace_min_mm": [-100, -400, -50],
                                         "workspace_max_mm": [700, 400, 300]}}
    with pytest.raises(ConfigError, match=r"downstream end \[800.0, 0.0, 0.0\] mm lies outside"):
        config_from_dict(data)
    data["limits"]["workspace_max_mm"] = [900, 400, 300]
    assert config_from_dict(data).conveyor is not None


@pytest.mark.parametrize(("exposure_us", "level"), [(2000.0, "ERROR"), (400.0, None)])
def test_motion_blur_above_the_limit_is_an_error(exposure_us: float, level: str | None) -> None:
    """500 mm/s for 2 ms is 1 mm = 2 px (> max_blur_px 1): an error naming the exposure and
    the longest exposure that keeps 1 px; 0.4 ms is 0.4 px: fine."""
    cfg = config_from_dict({**CAMERA, "conveyor": BELT,
                            "camera": {"type": "synthetic", "exposure_us": exposure_us}})
    findings = check_conveyor(cfg)
    assert [f.level for f in findings] == ([level] if level else [])
    if level:
        assert findings[0].key == "camera.exposure_us"
        assert "2.00 px" in findings[0].message
        assert "at most 1000 us" in findings[0].message


def test_blur_without_an_exposure_is_a_warning() -> None:
    cfg = config_from_dict({**CAMERA, "conveyor": BELT, "camera": {"type": "synthetic"}})
    assert [(f.level, f.key) for f in check_conveyor(cfg)] == [("WARNING", "camera.exposure_us")]


@pytest.mark.parametrize("link", [
    {"type": "s7", "host": "127.0.0.1", "db": 10},
    {"type": "modbus_client", "host": "127.0.0.1"},
    {"type": "modbus_server", "host": "127.0.0.1", "port": 1502},
    {"type": "modbus_server", "host": "127.0.0.1", "port": 1502, "map_version": 3},
])
def test_a_register_link_without_the_latch_area_is_refused_naming_its_field(
        link: dict[str, Any]) -> None:
    """A conveyor needs the count with every request: a register link left at map version 3
    (given or the default) is a config error naming ``links[N].map_version``; version 4 loads."""
    other = {"type": "s7", "host": "127.0.0.1", "db": 11, "map_version": 4}
    shown = "3" if "map_version" in link else r"3 \(the default\)"
    with pytest.raises(ConfigError, match=rf"links\[1\]\.map_version = {shown}: the "
                                          rf"{link['type']} link then carries no encoder count"):
        config_from_dict({"conveyor": BELT, "links": [other, link]})
    cfg = config_from_dict({"conveyor": BELT, "links": [other, {**link, "map_version": 4}]})
    assert cfg.conveyor is not None
    # without a belt, version 3 stays what it was: the default
    assert config_from_dict({"links": [link]}).links[0].type == link["type"]


TRAVEL: dict[str, Any] = {**BELT, "trigger": "travel", "latch": "timestamp"}
COUNTING = {"type": "modbus_server", "host": "127.0.0.1", "port": 1502, "map_version": 4}


@pytest.mark.parametrize("link", [
    COUNTING,
    {"type": "modbus_rtu", "device": "/dev/ttyS0", "map_version": 4},
    {"type": "modbus_client", "host": "127.0.0.1", "map_version": 4},
    {"type": "s7", "host": "127.0.0.1", "db": 10, "map_version": 4},
])
def test_triggering_by_travel_loads_with_a_link_that_publishes_the_count(
        link: dict[str, Any]) -> None:
    socket = {"type": "robot_socket", "host": "127.0.0.1", "port": 50100}
    cfg = config_from_dict({"conveyor": TRAVEL, "links": [socket, link]})
    assert cfg.conveyor is not None
    default = config().conveyor
    assert default is not None
    assert (cfg.conveyor.trigger, default.trigger) == ("travel", "request")


@pytest.mark.parametrize("links", [
    [],
    [{"type": "robot_socket", "host": "127.0.0.1", "port": 50100}],
    [{"type": "opcua", "host": "127.0.0.1", "port": 4840}],
    [{"type": "ur_rtde", "host": "127.0.0.1", "map_version": 4}],
])
def test_triggering_by_travel_without_a_link_that_publishes_the_count_is_refused(
        links: list[dict[str, Any]]) -> None:
    with pytest.raises(ConfigError, match=r'conveyor\.trigger = "travel": no link publishes '
                                          r"the belt's encoder count \(links: "
                                          + (r'links\[0\]\.type = "' if links else "none")):
        config_from_dict({"conveyor": TRAVEL, "links": links})


@pytest.mark.parametrize(("change", "words"), [
    ({"latch": "link"}, r'conveyor\.latch = "link" with trigger = "travel": the link publishes '
                        r"the count now"),
    ({"latch": "frame_id"}, r'conveyor\.latch = "frame_id" with trigger = "travel"'),
    ({"encoder_bits": 16, "counts_per_mm": 200.0},
     r"conveyor\.trigger_distance_mm 150 is 30000 counts, not below a quarter of the 16-bit "
     r"counter \(16384\)"),
])
def test_a_travel_trigger_that_cannot_work_is_refused_naming_the_field(
        change: dict[str, Any], words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        config_from_dict({"conveyor": {**TRAVEL, **change}, "links": [COUNTING]})
    # the same belt triggered by requests loads
    assert config_from_dict({"conveyor": {**TRAVEL, **change, "trigger": "request"},
                             "links": [COUNTING]}).conveyor is not None
