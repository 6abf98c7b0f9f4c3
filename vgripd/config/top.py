"""The whole file: ``Config``, its sections (each judged by its own module of this package)
and the rules across sections, judged when the config is loaded.

Combinations that cannot work are refused here: every link must be able to carry
``output.vendor`` (each link type's ``LinkCapabilities``, looked up through ``vgripd.registry``,
so this package never imports ``drivers/``), a conveyor needs links that latch the encoder count,
several views need one robot-mounted camera.

Recipes (docs/recipes.md): each recipe's effective config (``Config.for_recipe``) is built and
validated when the config is, so a bad recipe is refused at load with its own field path
(``recipes.2.object.features.3.diameter_mm: ...``).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field, PrivateAttr, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from vgripd import registry
from vgripd.config.calibration import DEMO_CALIBRATION, CalibrationConfig, CalibrationWalkConfig
from vgripd.config.common import Model
from vgripd.config.conveyor import ConveyorConfig
from vgripd.config.objects import (
    DEMO_OBJECT,
    DEMO_REFERENCE,
    MIN_PNP_FEATURES,
    ObjectConfig,
    ReferenceConfig,
    marker_problems,
)
from vgripd.config.output import LimitsConfig, OutputConfig
from vgripd.config.recipes import RECIPE_WHOLE_SECTIONS, RecipeConfig, RecipeNumber, unknown_recipe
from vgripd.config.service import DaemonConfig, RecordConfig, StatusConfig
from vgripd.config.vision import PickingConfig, VisionConfig
from vgripd.configbase import (
    COMBINATION,
    PLACED,
    RECIPE_PROBLEMS,
    DriverSection,
    format_validation_error,
)
from vgripd.errors import ConfigError


class Config(Model):
    """The whole file. Each section is its own model (one module of this package per section)."""

    camera: DriverSection = DriverSection(type="synthetic")
    output: OutputConfig = OutputConfig()
    limits: LimitsConfig = LimitsConfig()
    vision: VisionConfig = VisionConfig()
    picking: PickingConfig = PickingConfig()
    daemon: DaemonConfig = DaemonConfig()
    record: RecordConfig = RecordConfig()
    status: StatusConfig = StatusConfig()
    calibration_walk: CalibrationWalkConfig = CalibrationWalkConfig()
    # A moving belt (docs/conveyor.md); None: parts stand still until picked.
    conveyor: ConveyorConfig | None = None
    links: tuple[DriverSection, ...] = ()
    # Free-form notes on where a file came from (result files of `vgripd calibrate` carry one).
    about: dict[str, Any] = Field(default_factory=dict)
    # The demo cell applies only where a file does not say otherwise: a real camera without a
    # [calibration] is uncalibrated, a custom [object] without a [reference] is untaught.
    calibration: CalibrationConfig | None = DEMO_CALIBRATION
    object: ObjectConfig = DEMO_OBJECT
    reference: ReferenceConfig = DEMO_REFERENCE
    # Recipes selected by number with the trigger (docs/recipes.md); 0 is this config itself.
    recipes: dict[RecipeNumber, RecipeConfig] = Field(default_factory=dict)
    # Effective config of each recipe, built and validated with this one.
    _recipe_configs: dict[int, Config] = PrivateAttr(default_factory=dict)
    # What load_config found questionable in the files but accepted (check_calibration_files).
    _load_warnings: list[str] = PrivateAttr(default_factory=list)

    @property
    def load_warnings(self) -> list[str]:
        """Warnings about the files this config was loaded from (an included hand-eye or
        taught reference without a camera-model fingerprint)."""
        return list(self._load_warnings)

    @model_validator(mode="before")
    @classmethod
    def _demo_defaults_only_for_demo(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        data = dict(data)
        camera = data.get("camera")
        camera_type = camera.get("type") if isinstance(camera, dict) else None
        if "calibration" not in data and camera_type not in (None, "synthetic"):
            data["calibration"] = None
        if "object" in data and "reference" not in data:
            data["reference"] = {}
        return data

    @model_validator(mode="after")
    def _reference_matches_definition(self) -> Config:
        if self.object.definition == "reference" and self.reference.T_base_obj is not None:
            raise ValueError(
                'reference.T_base_obj must be unset when object.definition = "reference" '
                "(the object frame is the base frame at teach time)"
            )
        points = self.reference.points_mm
        if points is not None:
            if self.object.definition != "reference":
                raise ValueError(
                    'reference.points_mm is only for object.definition = "reference" '
                    "(a CAD object takes reference.T_base_obj)"
                )
            names = [f.name for f in self.object.features]
            missing = [n for n in names if n not in points]
            unknown = sorted(set(points) - set(names))
            if missing or unknown:
                raise ValueError(
                    f"reference.points_mm must name every feature of object {self.object.name!r}"
                    f" exactly once: missing {missing}, unknown {unknown}"
                )
        return self

    @model_validator(mode="after")
    def _features_findable(self) -> Config:
        """What finding the object needs of its features: pick lists group one kind of mark
        per camera setup, and ArUco ids are unique in known dictionaries. Judged once the cell
        is calibrated (without a calibration the jobs answer NOT_CALIBRATED anyway).

        Enough identified features for one camera (PnP) is judged before a job runs, not at
        load (``single_camera_problem``): a cell calibrating its cameras before its object
        loads a single-camera config with circle marks on purpose."""
        cal = self.calibration
        if cal is None:
            return self
        problems = []
        kinds = [f.kind for f in self.object.features]
        stereo = cal.right is not None
        if self.picking.max_objects > 1 and not (
                (stereo and all(k == "circle" for k in kinds))
                or (not stereo and all(k == "aruco" for k in kinds))):
            problems.append(
                "picking.max_objects > 1 needs a stereo rig and an object of circle marks only, "
                "or a single camera and an object of ArUco markers only (docs/picklists.md)")
        problems += marker_problems(self.object.features)
        if problems:
            raise PydanticCustomError(PLACED, "{problems}", {"problems": "\n".join(problems)})
        return self

    @model_validator(mode="after")
    def _views_need_one_robot_camera(self) -> Config:
        """``vision.views`` > 1 is one robot-mounted camera moved through the views."""
        if self.vision.views == 1:
            return self
        cal = self.calibration
        why = ("no [calibration]" if cal is None else
               "calibration.cameras is set (a multi-camera cell takes its views at once)"
               if cal.cameras is not None else
               "calibration.right is set (one camera only)" if cal.right is not None else
               'calibration.hand_eye.mounting is "fixed" (the camera must ride on the robot)'
               if cal.hand_eye.mounting != "robot" else
               "picking.max_objects > 1 (pick lists take one view)"
               if self.picking.max_objects > 1 else "")
        if why:
            raise ValueError(f"vision.views = {self.vision.views} needs one robot-mounted "
                             f"camera: {why}")
        problems = registry.views_problems(self.links, self.vision.views)
        if problems:
            raise PydanticCustomError(COMBINATION, "{problems}",
                                      {"problems": "\n".join(problems)})
        return self

    @model_validator(mode="after")
    def _window_in_workspace(self) -> Config:
        """The conveyor's pick window lies in ``limits.workspace_*`` (when a box is set)."""
        belt, lo, hi = self.conveyor, self.limits.workspace_min_mm, self.limits.workspace_max_mm
        if belt is None or lo is None or hi is None:
            return self
        for which, point in zip(("upstream", "downstream"), belt.window_points(), strict=True):
            if not all(a <= p <= b for a, p, b in zip(lo, point, hi, strict=True)):
                raise ValueError(
                    f"conveyor.window_mm: the {which} end {[round(p, 1) for p in point]} mm "
                    f"lies outside the workspace limits.workspace_min_mm {list(lo)} .. "
                    f"workspace_max_mm {list(hi)}: no part there could be picked")
        return self

    @model_validator(mode="after")
    def _links_carry_the_latch(self) -> Config:
        """A conveyor's jobs need the encoder count with each request: every register link
        serves map version 4 (the latch area)."""
        if self.conveyor is None:
            return self
        problems = registry.travel_problems(self.links, self.vision.views) \
            if self.conveyor.trigger == "travel" else []
        if not self.links and not problems:
            return self
        problems += registry.latch_problems(self.links)
        if problems:
            raise PydanticCustomError(COMBINATION, "{problems}",
                                      {"problems": "\n".join(problems)})
        return self

    @model_validator(mode="after")
    def _links_carry_output(self) -> Config:
        """Every link must be able to carry ``output.vendor`` (its class's capabilities)."""
        if not self.links:
            return self
        default = "vendor" not in self.output.model_fields_set
        problems = registry.link_problems(self.links, self.output.vendor, default)
        if problems:
            raise PydanticCustomError(COMBINATION, "{problems}",
                                      {"problems": "\n".join(problems)})
        return self


    @model_validator(mode="after")
    def _recipes_valid(self) -> Config:
        """Build and validate every recipe's effective config; all problems at once, each with
        its ``recipes.N.`` path."""
        lines: list[str] = []
        for number in sorted(self.recipes):
            try:
                self._recipe_configs[number] = Config.model_validate(self._recipe_data(number))
            except ValidationError as err:
                lines += [f"recipes.{number}.{line}" if not line.startswith("<root>") else
                          f"recipes.{number}{line.removeprefix('<root>')}"
                          for line in _problem_lines(err)]
        if lines:
            raise PydanticCustomError(RECIPE_PROBLEMS, "{lines}", {"lines": "\n".join(lines)})
        return self

    def _recipe_data(self, number: int) -> dict[str, Any]:
        """The effective config data of recipe ``number`` (the overlay rule: RecipeConfig)."""
        data = self.model_dump(exclude_unset=True, exclude={"recipes"})
        overlays = self.recipes[number].sections()
        for section, overlay in overlays.items():
            top = getattr(self, section).model_dump(exclude_unset=True)
            if section in RECIPE_WHOLE_SECTIONS or (section == "reference"
                                                    and "object" in overlays):
                top = {}  # another object; a reference taught on the top-level object
            if section == "picking" and "object" in overlays:
                top.pop("pick_points", None)  # grip points of the top-level object
            data[section] = {**top, **overlay}
        if "object" in overlays and "reference" not in overlays:
            data["reference"] = {}
        if "object" in overlays and "picking" not in overlays and "picking" in data:
            data["picking"] = {k: v for k, v in data["picking"].items() if k != "pick_points"}
        return data

    def recipe_numbers(self) -> tuple[int, ...]:
        """Every recipe a trigger may select: 0 (this config) and the configured ones."""
        return (0, *sorted(self.recipes))

    def recipe_name(self, number: int) -> str:
        """The recipe's ``name``; recipe 0 is ``"default"``."""
        return "default" if number == 0 else self.recipes[number].name

    def for_recipe(self, number: int) -> Config:
        """The full effective config of recipe ``number`` (0: this one). ``ConfigError`` for a
        number that is not configured, naming the configured ones.

        Built when this config was validated: a ``model_copy(update=...)`` of it keeps the
        recipes of the original (validate a new config to change the top level under them)."""
        if number == 0:
            return self
        if number not in self.recipes:
            raise ConfigError(unknown_recipe(number, self.recipe_numbers()))
        if number not in self._recipe_configs:  # a copy made without validation
            self._recipe_configs[number] = Config.model_validate(self._recipe_data(number))
        return self._recipe_configs[number]


def single_camera_problem(config: Config) -> str:
    """Why one camera cannot locate the object ("" when it can, or the cell has more cameras
    or views): a single-camera (PnP) pose needs ``MIN_PNP_FEATURES`` identified features, since
    circle marks cannot be told apart in one image. Not a load rule (``_features_findable``);
    ``vgripd.vision.readiness`` raises it as a ``ConfigError`` naming ``object.features``."""
    cal = config.calibration
    if cal is None or cal.cameras is not None or cal.right is not None or config.vision.views > 1:
        return ""
    identified = sum(f.kind != "circle" for f in config.object.features)
    if identified >= MIN_PNP_FEATURES:
        return ""
    return ("object.features: single-camera (PnP) mode needs at least "
            f"{MIN_PNP_FEATURES} aruco/template features, the object has {identified} "
            "(circle marks cannot be told apart in one image)")


def _problem_lines(err: ValidationError) -> list[str]:
    """``path: message`` per problem (``<root>: message`` for whole-config ones)."""
    lines = []
    for e in err.errors():
        if e["type"] in (COMBINATION, RECIPE_PROBLEMS):
            lines += [f"<root>: {line}" for line in e["msg"].splitlines()]
        elif e["type"] == PLACED:  # each line starts with its field path
            lines += e["msg"].splitlines()
        else:
            lines.append(f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}")
    return lines


def config_from_dict(
    data: dict[str, Any], source: str = "<config>", owner: dict[str, str] | None = None
) -> Config:
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, source, owner)) from None
