"""Whether a config can run jobs (``vgripd.vision.readiness``): each rule names its key, the
pipeline raises exactly what ``ready`` raises, and every recipe is judged with its number."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from vgripd.config import Config, config_from_dict, single_camera_problem
from vgripd.errors import ConfigError, NotCalibratedError, NotTaughtError
from vgripd.vision.pipeline import Pipeline
from vgripd.vision.readiness import ready, recipe_readiness

REFERENCE = {"T_base_obj": {"translation_mm": [600.0, 100.0, 10.0]}}


def circles(n: int = 4) -> list[dict[str, Any]]:
    return [{"name": f"c{i}", "kind": "circle", "diameter_mm": 8.0,
             "xyz_mm": [40.0 * (i % 2), 35.0 * (i // 2) + i, 0.0]} for i in range(n)]


def markers(n: int) -> list[dict[str, Any]]:
    return [{"name": f"m{i}", "kind": "aruco", "dictionary": "DICT_4X4_50", "marker_id": i,
             "size_mm": 20.0, "xyz_mm": [50.0 * (i % 2), 45.0 * (i // 2) + i, 0.0]}
            for i in range(n)]


def template(path: str) -> dict[str, Any]:
    return {"name": "t", "kind": "template", "template": path, "size_px": 24,
            "xyz_mm": [20.0, 70.0, 0.0]}


def make(**sections: Any) -> Config:
    return config_from_dict({"camera": {"type": "synthetic", "seed": 1}, **sections})


def mono(**sections: Any) -> Config:
    """The demo cell with its left camera only (a single-camera, PnP, cell)."""
    data = make(**sections).model_dump(mode="json", exclude_none=True)
    for key in ("right", "stereo"):
        data["calibration"].pop(key)
    return config_from_dict(data)


def raised(config: Config, build: Any) -> BaseException:
    with pytest.raises((ConfigError, NotCalibratedError)) as info:
        build(config)
    return info.value


def test_single_camera_with_circle_marks_loads_but_cannot_run() -> None:
    """Not a load rule (a mono cell calibrates its cameras before it has an object), judged
    before a job runs, naming object.features."""
    config = mono(object={"features": circles()}, reference=REFERENCE)
    problem = single_camera_problem(config)
    assert problem.startswith("object.features: single-camera (PnP) mode needs at least 4 "
                              "aruco/template features, the object has 0")
    for build in (ready, Pipeline):
        err = raised(config, build)
        assert type(err) is ConfigError
        assert str(err) == problem


def test_single_camera_rule_holds_only_for_one_camera() -> None:
    assert single_camera_problem(make(object={"features": circles()},
                                      reference=REFERENCE)) == ""  # the stereo demo rig
    assert single_camera_problem(mono(object={"features": markers(4)},
                                      reference=REFERENCE)) == ""
    three = mono(object={"features": [*markers(3), *circles(2)]}, reference=REFERENCE)
    assert "the object has 3" in single_camera_problem(three)
    assert single_camera_problem(config_from_dict({"camera": {"type": "replay",
                                                              "folder": "."}})) == ""


@pytest.mark.parametrize(("sections", "kind", "start"), [
    ({"object": {"features": circles()}}, NotTaughtError, "reference.T_base_obj: object"),
    ({"output": {"mode": "grip"}}, NotCalibratedError,
     'reference.grip: output.mode = "grip" needs the grip pose taught'),
    ({"limits": {"point": "grip"}}, NotCalibratedError,
     'reference.grip: limits.point = "grip" needs the grip pose taught'),
])
def test_what_is_not_taught_is_named_as_the_pipeline_names_it(
        sections: dict[str, Any], kind: type[BaseException], start: str) -> None:
    config = make(**sections)
    errors = [raised(config, build) for build in (ready, Pipeline)]
    assert [type(e) for e in errors] == [kind, kind]
    assert str(errors[0]) == str(errors[1])
    assert str(errors[0]).startswith(start), errors[0]


def test_no_calibration_is_not_calibrated() -> None:
    config = config_from_dict({"camera": {"type": "replay", "folder": "."}})
    err = raised(config, ready)
    assert type(err) is NotCalibratedError
    assert str(err).startswith("camera models: no [calibration] section")


def test_template_files_are_read_and_judged(tmp_path: Path) -> None:
    patch = np.zeros((24, 24), np.uint8)
    patch[6:18, 6:18] = 255
    cv2.imwrite(str(tmp_path / "good.png"), patch)
    (tmp_path / "text.png").write_text("not an image")
    good = ready(make(object={"features": [*circles(), template(str(tmp_path / "good.png"))]},
                      reference=REFERENCE))
    assert list(good.templates) == [4]
    assert np.array_equal(good.templates[4], patch)
    for name, why in (("missing.png", "no such file"), ("text.png", "not an image")):
        path = str(tmp_path / name)
        config = make(object={"features": [*circles(), template(path)]}, reference=REFERENCE)
        err = raised(config, ready)
        assert str(err) == (f"object.features[4].template: cannot read image file {path!r} "
                            f"({why})")


def test_recipes_are_judged_each_with_its_number(tmp_path: Path) -> None:
    config = make(recipes={
        "1": {"name": "untaught", "object": {"features": circles()}},
        "2": {"name": "no grip", "output": {"mode": "grip"}},
        "3": {"name": "fine", "vision": {"min_contrast": 40.0}},
    })
    built, problems, untaught = recipe_readiness(config, ready)
    assert sorted(built) == [0, 3]
    assert sorted(problems) == [1, 2]
    assert problems[1].startswith("reference.T_base_obj:")
    assert problems[2].startswith("reference.grip:")
    assert untaught == {1}
    missing = str(tmp_path / "missing.png")
    bad = make(recipes={"4": {"name": "tagged", "object": {
        "features": [*circles(), template(missing)]}, "reference": REFERENCE}})
    with pytest.raises(ConfigError) as info:
        recipe_readiness(bad, ready)
    assert str(info.value).startswith(
        f"recipes.4.object.features[4].template: cannot read image file {missing!r}")
