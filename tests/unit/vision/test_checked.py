"""The daemon's pipeline (``vgripd.vision.checked``): a failed job's diagnosis names what
``vgripd check`` names, on rendered scenes where the images alone do not tell."""

from __future__ import annotations

import copy
from typing import Any

from tests.unit.vision.test_diagnosis import grab, make_config
from vgripd.config import Config, config_from_dict
from vgripd.service.host.commissioning import check_scene
from vgripd.types import ImagePair, Status
from vgripd.vision.checked import CheckedPipeline
from vgripd.vision.pipeline import Pipeline


def at_distance(z_mm: float, **vision: Any) -> Config:
    """The synthetic plate with the camera ``z_mm`` above the base (about as far from it)."""
    data = copy.deepcopy(make_config().model_dump(mode="json", exclude_none=True))
    data["calibration"]["hand_eye"]["T_base_camera"]["translation_mm"][2] = z_mm
    data["vision"].update(vision)
    return config_from_dict(data)


async def test_a_working_distance_that_excludes_a_far_object_is_named_at_run_time() -> None:
    # The object 1 m away, vision.working_distance_mm [100, 400]: the marks are too small to
    # be candidates at all; the images alone blame the camera ("no mark-like blob").
    config = at_distance(1000.0, working_distance_mm=[100.0, 400.0])
    pair = await grab(config)
    plain = Pipeline(config).process(pair, 1)
    assert plain.status is Status.NOT_FOUND
    assert plain.diagnosis is not None
    assert all(c.key != "vision.working_distance_mm" for c in plain.diagnosis.causes)
    assert any(f.key == "vision.working_distance_mm" and f.level == "ERROR"
               for f in check_scene(config))

    result = CheckedPipeline(config).process(pair, 1)
    assert result.status is Status.NOT_FOUND
    d = result.diagnosis
    assert d is not None
    assert d.top is not None
    assert d.top.key == "vision.working_distance_mm", d.lines()
    assert "[100, 400]" in d.top.reason
    assert "vgripd check" in d.top.reason
    assert "vision.working_distance_mm" in d.summary()
    assert len({c.key for c in d.causes}) == len(d.causes)  # one cause per key


async def test_a_good_job_and_the_image_causes_are_unchanged() -> None:
    config = at_distance(700.0)
    pair = await grab(config)
    assert CheckedPipeline(config).process(pair, 1).status is Status.OK
    # check finds nothing wrong with the config: the job's own cause stays on top.
    data = copy.deepcopy(config.model_dump(mode="json", exclude_none=True))
    for f in data["object"]["features"]:
        f["polarity"] = "bright"
    wrong = config_from_dict(data)
    d = CheckedPipeline(wrong).process(pair, 1).diagnosis
    assert d is not None
    assert d.top is not None
    assert d.top.key == "object.features[*].polarity"


def test_cameras_swapped_across_rigs_are_named() -> None:
    """north_left's and south_left's images exchanged (rigs north and south of the sample
    two-rig cell, rendered): NOT_FOUND, and the cause names the two cameras."""
    from tests.unit.vision.test_views_locator import config as two_rigs
    from tests.unit.vision.test_views_locator import grab as grab_views

    cfg = two_rigs()
    pair = grab_views(cfg, 1)[0]
    views = list(pair.views)
    views[0], views[2] = views[2], views[0]
    swapped = ImagePair.of_views(views, pair.t_mono_ns)
    plain = Pipeline(cfg).process(swapped, 1)
    assert plain.status is Status.NOT_FOUND
    assert plain.diagnosis is not None
    assert not any("swapped" in c.reason for c in plain.diagnosis.causes)

    result = CheckedPipeline(cfg).process(swapped, 1)
    assert result.status is Status.NOT_FOUND  # the job itself is not rescued
    d = result.diagnosis
    assert d is not None
    assert d.top is not None
    assert d.top.key == "calibration.cameras"
    assert "north_left and south_left look swapped" in d.top.reason
    # The cell as wired: OK, and nothing probed.
    assert CheckedPipeline(cfg).process(pair, 2).status is Status.OK
