"""What finding the object needs of its features, judged by the config when it is loaded (no
pipeline built): one kind of mark per pick-list setup, ArUco ids unique per dictionary and
dictionaries OpenCV knows. Each refusal names its field, also inside a recipe (``recipes.N.``)."""

from __future__ import annotations

import copy
from typing import Any

import cv2
import pytest

from vgripd.config import config_from_dict
from vgripd.config.objects import ARUCO_DICTIONARIES
from vgripd.errors import ConfigError

DEMO = config_from_dict({}).model_dump(exclude_none=True, exclude={"recipes", "about"})


def aruco(name: str, marker_id: int, dictionary: str = "DICT_4X4_50",
          x_mm: float = 0.0) -> dict[str, Any]:
    return {"name": name, "xyz_mm": [x_mm, 0.0, 0.0], "kind": "aruco", "marker_id": marker_id,
            "dictionary": dictionary, "size_mm": 20.0}


def cell(**changes: Any) -> dict[str, Any]:
    """The demo cell (stereo, six circle marks, taught) with ``changes`` applied per section."""
    data = copy.deepcopy(DEMO)
    for section, value in changes.items():
        data[section] = value
    return data


def refused(data: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "cell.toml")
    return str(info.value).splitlines()


def with_markers(*markers: dict[str, Any]) -> dict[str, Any]:
    return {**DEMO["object"], "features": [*DEMO["object"]["features"], *markers]}


def test_an_uncalibrated_cell_is_not_judged_on_its_features() -> None:
    """Without a calibration no camera setup is known: its jobs answer NOT_CALIBRATED."""
    config = config_from_dict(cell(calibration=None, camera={"type": "opencv"},
                                   picking={"max_objects": 3},
                                   object=with_markers(aruco("t", 3))))
    assert config.calibration is None


def test_pick_lists_need_one_kind_of_mark_for_the_camera_setup() -> None:
    assert refused(cell(picking={"max_objects": 3}, object=with_markers(aruco("t", 3)))) == [
        "cell.toml: picking.max_objects > 1 needs a stereo rig and an object of circle marks "
        "only, or a single camera and an object of ArUco markers only (docs/picklists.md)"]
    assert config_from_dict(cell(picking={"max_objects": 3}))


def test_an_aruco_id_twice_in_one_dictionary_is_refused() -> None:
    object_ = with_markers(aruco("t", 3), aruco("u", 3, x_mm=5.0), aruco("v", 3, "DICT_5X5_50"))
    assert refused(cell(object=object_)) == [
        "cell.toml: object.features[7]: marker id 3 of DICT_4X4_50 is used twice"]


def test_an_unknown_dictionary_is_refused() -> None:
    assert refused(cell(object=with_markers(aruco("t", 3, "DICT_9X9_1")))) == [
        "cell.toml: object.features[6].dictionary: unknown ArUco dictionary 'DICT_9X9_1'"]


def test_every_problem_is_named_at_once() -> None:
    object_ = with_markers(aruco("t", 3), aruco("u", 3, x_mm=5.0), aruco("w", 4, "DICT_9X9_1"))
    assert refused(cell(object=object_, picking={"max_objects": 2})) == [
        "cell.toml: picking.max_objects > 1 needs a stereo rig and an object of circle marks "
        "only, or a single camera and an object of ArUco markers only (docs/picklists.md)",
        "cell.toml: object.features[7]: marker id 3 of DICT_4X4_50 is used twice",
        "cell.toml: object.features[8].dictionary: unknown ArUco dictionary 'DICT_9X9_1'"]


def test_a_recipe_is_refused_with_its_own_path_even_when_untaught() -> None:
    """A recipe with its own object has no taught reference; the duplicate id is still named
    (before, the missing reference hid it)."""
    object_ = with_markers(aruco("t", 3), aruco("u", 3, x_mm=5.0))
    data = cell(recipes={"2": {"name": "b", "object": object_}})
    assert refused(data) == [
        "cell.toml: recipes.2.object.features[7]: marker id 3 of DICT_4X4_50 is used twice"]


def test_the_dictionaries_are_opencvs() -> None:
    opencv = {name.upper() for name in dir(cv2.aruco) if name.startswith("DICT_")}
    assert opencv == ARUCO_DICTIONARIES
