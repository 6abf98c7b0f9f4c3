"""Recipes in the config (``[recipes.N]``, docs/recipes.md): the overlay rule, the effective
config of each recipe, error paths that name the recipe, unknown numbers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import REPO
from vgripd.config import (
    DEMO_OBJECT,
    DEMO_REFERENCE,
    RECIPE_SECTIONS,
    Config,
    VisionConfig,
    config_from_dict,
    load_config,
)
from vgripd.errors import ConfigError

SAMPLE = REPO / "config" / "samples" / "recipes.toml"


def features(diameter_mm: float = 8.0) -> list[dict[str, Any]]:
    return [{"name": f"p{i}", "kind": "circle", "diameter_mm": diameter_mm, "xyz_mm": xyz}
            for i, xyz in enumerate([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 35.0, 0.0],
                                     [42.0, 47.0, 0.0]])]


def refused(data: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "cell.toml")
    return str(info.value)


def test_recipe_zero_is_the_top_level_config() -> None:
    config = config_from_dict({"vision": {"min_contrast": 40.0}})
    assert config.recipe_numbers() == (0,)
    assert config.for_recipe(0) is config
    assert config.recipe_name(0) == "default"


def test_sections_merge_key_by_key_over_the_top_level() -> None:
    config = config_from_dict({
        "vision": {"min_contrast": 40.0, "downscale": 3},
        "limits": {"max_translation_mm": 20.0, "max_rotation_deg": 4.0},
        "output": {"vendor": "abb"},
        "recipes": {"7": {"name": "strict", "vision": {"min_contrast": 60.0},
                          "limits": {"max_rotation_deg": 2.0}}},
    })
    r7 = config.for_recipe(7)
    assert (r7.vision.min_contrast, r7.vision.downscale) == (60.0, 3)  # downscale inherited
    assert (r7.limits.max_translation_mm, r7.limits.max_rotation_deg) == (20.0, 2.0)
    assert r7.output.vendor == "abb"  # not overlaid: the top level's
    assert r7.object == DEMO_OBJECT
    assert r7.reference == DEMO_REFERENCE
    assert r7.recipes == {}
    assert config.vision.min_contrast == 40.0  # the top level is untouched
    assert config.recipe_numbers() == (0, 7)
    assert config.recipe_name(7) == "strict"


def test_own_object_replaces_it_whole_and_inherits_no_reference() -> None:
    config = config_from_dict({"recipes": {
        "1": {"name": "untaught", "object": {"features": features()}},
        "2": {"name": "taught", "object": {"name": "plate_b", "features": features(12.0)},
              "reference": {"T_base_obj": {"translation_mm": [590.0, 110.0, 12.0]}}},
        "3": {"name": "same plate, other grip",
              "reference": {"grip": {"translation_mm": [600.0, 100.0, 60.0]}}},
    }})
    r1, r2, r3 = (config.for_recipe(n) for n in (1, 2, 3))
    assert r1.object.name == "object"  # not the top level's "demo_plate": replaced whole
    assert r1.reference.T_base_obj is None  # taught on another object: not inherited
    assert r2.object.features[0].diameter_mm == 12.0
    assert r2.reference.T_base_obj is not None
    assert r2.reference.T_base_obj.translation_mm == (590.0, 110.0, 12.0)
    # Without its own object, a recipe's reference merges key by key: T_base_obj inherited.
    assert r3.reference.T_base_obj == DEMO_REFERENCE.T_base_obj
    assert r3.reference.grip is not None


@pytest.mark.parametrize(("data", "expected"), [
    ({"recipes": {"2": {"name": "b", "object": {"features": [
        *features()[:3], {**features()[3], "diameter_mm": -1.0}]}}}},
     "cell.toml: recipes.2.object.features.3.circle.diameter_mm: Input should be greater than 0"),
    ({"recipes": {"0": {"name": "zero"}}},
     "cell.toml: recipes.0: Input should be greater than or equal to 1 (a recipe number is "
     "1 .. 65535; 0 is the top level)"),
    ({"recipes": {"65536": {"name": "big"}}}, "cell.toml: recipes.65536: Input should be less"),
    ({"recipes": {"3": {"vision": {"downscale": 2}}}}, "cell.toml: recipes.3.name: Field required"),
    ({"recipes": {"3": {"name": "c", "camera": {"type": "replay"}}}},
     "cell.toml: recipes.3: Value error, 'camera' cannot be set per recipe"),
    ({"recipes": {"3": {"name": "c", "vision": {"min_contrst": 9.0}}}},
     "cell.toml: recipes.3.vision.min_contrst: Extra inputs are not permitted"),
    # Judged after the merge: the recipe's warn level against the top level's tolerance.
    ({"vision": {"epipolar_tolerance_px": 2.0},
      "recipes": {"4": {"name": "d", "vision": {"epipolar_warn_px": 2.5}}}},
     "cell.toml: recipes.4.vision: Value error, epipolar_warn_px must not exceed"),
    ({"recipes": {"5": {"name": "e", "object": {"definition": "reference",
                                                "features": features()},
                        "reference": {"T_base_obj": {"translation_mm": [0.0, 0.0, 0.0]}}}}},
     "cell.toml: recipes.5: Value error, reference.T_base_obj must be unset when"),
])
def test_errors_name_the_recipe_and_field(data: dict[str, Any], expected: str) -> None:
    assert refused(data).startswith(expected)


def test_every_recipe_output_is_checked_against_the_links() -> None:
    data = {"links": [{"type": "ur_rtde", "host": "192.0.2.1"}], "output": {"vendor": "ur"},
            "recipes": {"1": {"name": "ok"}, "2": {"name": "kuka", "output": {"vendor": "kuka"}}}}
    message = refused(data)
    assert message.startswith('cell.toml: recipes.2: links[0].type = "ur_rtde" cannot carry '
                              'output.vendor = "kuka"')
    assert "recipes.1" not in message
    data["recipes"]["2"]["output"]["vendor"] = "ur"
    config_from_dict(data)


def test_all_bad_recipes_are_reported_at_once() -> None:
    message = refused({"recipes": {"1": {"name": "a", "vision": {"downscale": 0}},
                                   "2": {"name": "b", "limits": {"max_rotation_deg": -1}}}})
    assert "recipes.1.vision.downscale" in message
    assert "recipes.2.limits.max_rotation_deg" in message


def test_unknown_recipe_names_the_configured_ones() -> None:
    config = config_from_dict({"recipes": {"4": {"name": "a"}, "2": {"name": "b"}}})
    with pytest.raises(ConfigError, match=r"recipe 3 is not configured \(configured: 0, 2, 4;"):
        config.for_recipe(3)


def test_recipe_sections_are_config_sections() -> None:
    """Each overlayable section is a top-level section (adding one is one edit)."""
    assert set(RECIPE_SECTIONS) <= set(Config.model_fields)


def test_included_fragment_sets_a_recipe_reference(tmp_path: Path) -> None:
    """``vgripd teach --recipe N`` writes ``[recipes.N.reference]`` for the config to include;
    a file that sets it too is refused naming both files."""
    (tmp_path / "ref.toml").write_text(
        "[recipes.2.reference.T_base_obj]\ntranslation_mm = [1.0, 2.0, 3.0]\n")
    cell = tmp_path / "cell.toml"
    body = ('[recipes.2]\nname = "b"\n[recipes.2.object]\nfeatures = [\n' + ",\n".join(
        f'{{ name = "{f["name"]}", kind = "circle", diameter_mm = 8.0, xyz_mm = {f["xyz_mm"]} }}'
        for f in features()) + "]\n")
    cell.write_text('include = ["ref.toml"]\n' + body)
    ref = load_config(cell).for_recipe(2).reference.T_base_obj
    assert ref is not None
    assert ref.translation_mm == (1.0, 2.0, 3.0)
    cell.write_text('include = ["ref.toml"]\n' + body
                    + "[recipes.2.reference.T_base_obj]\ntranslation_mm = [0.0, 0.0, 0.0]\n")
    with pytest.raises(ConfigError, match=r"recipes\.2\.reference\.T_base_obj\.translation_mm "
                                          r"is already set in .*cell\.toml"):
        load_config(cell)


def test_sample_has_two_plates() -> None:
    config = load_config(SAMPLE)
    assert config.recipe_numbers() == (0, 1, 2)
    a, b = config.for_recipe(1), config.for_recipe(2)
    assert {f.diameter_mm for f in a.object.features} != {f.diameter_mm for f in b.object.features}
    assert a.reference.T_base_obj is not None
    assert b.reference.T_base_obj is not None
    assert b.limits.max_translation_mm == 60.0
    assert a.limits.max_translation_mm == 50.0


# Vision keys with values that keep the section valid in any combination.
_VISION_VALUES = {"downscale": (1, 3), "min_contrast": (20.0, 45.0),
                  "min_circularity": (0.5, 0.8), "min_features": (3, 5),
                  "max_fit_rms_mm": (0.5, 2.0), "template_min_score": (0.6, 0.9)}


@given(top=st.dictionaries(st.sampled_from(sorted(_VISION_VALUES)), st.integers(0, 1)),
       recipe=st.dictionaries(st.sampled_from(sorted(_VISION_VALUES)), st.integers(0, 1)))
@settings(max_examples=60, deadline=None)
def test_overlay_takes_the_recipe_key_else_the_top_level_else_the_default(
        top: dict[str, int], recipe: dict[str, int]) -> None:
    top_vision = {k: _VISION_VALUES[k][i] for k, i in top.items()}
    recipe_vision = {k: _VISION_VALUES[k][1 - i] for k, i in recipe.items()}
    config = config_from_dict({"vision": top_vision,
                               "recipes": {"9": {"name": "r", "vision": recipe_vision}}})
    effective = config.for_recipe(9).vision
    default = VisionConfig()
    for key in _VISION_VALUES:
        expected = recipe_vision.get(key, top_vision.get(key, getattr(default, key)))
        assert getattr(effective, key) == expected, key
    assert config.vision == VisionConfig(**top_vision)


def test_picking_per_recipe_and_pick_points_stay_with_their_object() -> None:
    """A pallet recipe sets its own pick list; a recipe with another object inherits the pick
    list's size and order but not the grip points of the top-level object (docs/picklists.md)."""
    picks = [{"id": 3, "priority": 1, "pose": {"translation_mm": [0.0, 0.0, 5.0]}}]
    config = config_from_dict({
        "picking": {"max_objects": 4, "order": "score", "pick_points": picks},
        "recipes": {"1": {"name": "pallet", "picking": {"max_objects": 6}},
                    "2": {"name": "other", "object": {"features": features()}},
                    "3": {"name": "single", "picking": {"max_objects": 1,
                                                        "pick_points": []}}},
    })
    r1, r2, r3 = (config.for_recipe(n) for n in (1, 2, 3))
    assert (r1.picking.max_objects, r1.picking.order) == (6, "score")
    assert [p.id for p in r1.picking.pick_points] == [3]
    assert (r2.picking.max_objects, r2.picking.order) == (4, "score")
    assert r2.picking.pick_points == ()
    assert r3.picking.max_objects == 1
    # Single object, inherited grip points: refused, naming the recipe.
    message = refused({"picking": {"max_objects": 4, "pick_points": picks},
                       "recipes": {"5": {"name": "one", "picking": {"max_objects": 1}}}})
    assert "recipes.5" in message
    assert "pick_points need max_objects > 1" in message


@pytest.mark.parametrize(("name", "expected"), [
    ("a\nb", "recipes.1.name: Value error, 'a\\nb': a recipe name is one line without control "
             "characters"),
    ("tab\there", "recipes.1.name: Value error, 'tab\\there': a recipe name is one line"),
    ("x" * 65, "recipes.1.name: String should have at most 64 characters"),
])
def test_a_recipe_name_is_one_short_line(name: str, expected: str) -> None:
    assert expected in refused({"recipes": {"1": {"name": name}}})
    assert config_from_dict({"recipes": {"1": {"name": "x" * 64}}}).recipe_name(1) == "x" * 64


def test_recipe_numbers_at_the_edges() -> None:
    """1 and 65535 are the first and last recipe numbers (the RECIPE register is one word);
    0 is the top level and 65536 does not fit, both refused naming the range."""
    config = config_from_dict({"recipes": {"1": {"name": "first"}, "65535": {"name": "last"}}})
    assert config.recipe_numbers() == (0, 1, 65535)
    assert config.for_recipe(65535).object == config.object
    for number in ("0", "65536"):
        message = refused({"recipes": {number: {"name": "x"}}})
        assert f"recipes.{number}:" in message
        assert "a recipe number is 1 .. 65535; 0 is the top level" in message
    with pytest.raises(ConfigError, match="recipe 65536 is not configured"):
        config.for_recipe(65536)
