"""The TOML configuration, validated by pydantic: the one place that judges a config.

Every model forbids unknown keys, so a typo is an error naming its field path
(``calibration.left.fx: Input should be greater than 0``). Driver sections carry a ``type``
plus options that the chosen driver validates against its own model (``vgripd.registry``).

One module per section, the whole file and its rules across sections in ``top``, reading the
files in ``loader``:

- ``common``: the base ``Model``, ``PoseConfig``, the ``allow`` list of a server surface;
- ``calibration``: ``[calibration]`` (cameras, stereo rig, hand-eye, multi-camera cells) and
  ``[calibration_walk]``;
- ``objects``: ``[object]`` and ``[reference]``;
- ``vision``: ``[vision]`` and ``[picking]`` (pick lists, docs/picklists.md);
- ``output``: ``[output]`` and ``[limits]``;
- ``conveyor``: ``[conveyor]`` (a moving belt, docs/conveyor.md);
- ``service``: ``[daemon]``, ``[record]`` and ``[status]``;
- ``recipes``: ``[recipes.N]`` (docs/recipes.md);
- ``top``: ``Config`` and the combinations refused across sections;
- ``loader``: the TOML files with their includes, ``load_config``.

This module is the package's public surface: import from ``vgripd.config``.
"""

from vgripd.config.calibration import (
    DEMO_CALIBRATION,
    MAX_CAMERAS,
    NAME_PATTERN,
    CalibrationConfig,
    CalibrationWalkConfig,
    CameraEntryConfig,
    HandEyeConfig,
    IntrinsicsConfig,
    RigConfig,
    StereoConfig,
)
from vgripd.config.common import AllowList, Model, PoseConfig, Vec3
from vgripd.config.conveyor import BELT_PLANE_DEG, COUNTS_PER_MM_RANGE, ConveyorConfig
from vgripd.config.loader import (
    MEASURED_REFERENCE_KEYS,
    REDO_STEPS,
    check_calibration_files,
    load_config,
    measured_references,
    read_config_data,
)
from vgripd.config.objects import (
    DEMO_OBJECT,
    DEMO_REFERENCE,
    MIN_PNP_FEATURES,
    ArucoFeature,
    CircleFeature,
    FeatureConfig,
    ObjectConfig,
    ReferenceConfig,
    TemplateFeature,
)
from vgripd.config.output import LimitsConfig, OutputConfig
from vgripd.config.recipes import (
    MAX_RECIPE_NAME,
    RECIPE_SECTIONS,
    RECIPE_WHOLE_SECTIONS,
    RecipeConfig,
    unknown_recipe,
)
from vgripd.config.service import DaemonConfig, RecordConfig, StatusConfig
from vgripd.config.top import Config, config_from_dict, single_camera_problem
from vgripd.config.vision import PickingConfig, PickPointConfig, VisionConfig
from vgripd.configbase import DriverSection, format_validation_error

__all__ = [
    "BELT_PLANE_DEG", "COUNTS_PER_MM_RANGE", "DEMO_CALIBRATION", "DEMO_OBJECT",
    "DEMO_REFERENCE", "MAX_CAMERAS", "MAX_RECIPE_NAME", "MEASURED_REFERENCE_KEYS",
    "MIN_PNP_FEATURES", "NAME_PATTERN", "RECIPE_SECTIONS", "RECIPE_WHOLE_SECTIONS",
    "REDO_STEPS", "AllowList", "ArucoFeature", "CalibrationConfig", "CalibrationWalkConfig",
    "CameraEntryConfig", "CircleFeature", "Config", "ConveyorConfig", "DaemonConfig",
    "DriverSection", "FeatureConfig", "HandEyeConfig", "IntrinsicsConfig", "LimitsConfig",
    "Model", "ObjectConfig", "OutputConfig", "PickPointConfig", "PickingConfig", "PoseConfig",
    "RecipeConfig", "RecordConfig", "ReferenceConfig", "RigConfig", "StatusConfig",
    "StereoConfig", "TemplateFeature", "Vec3", "check_calibration_files", "config_from_dict",
    "format_validation_error", "load_config", "measured_references", "read_config_data",
    "single_camera_problem",
    "VisionConfig", "unknown_recipe",
]
