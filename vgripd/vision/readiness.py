"""Whether a config can run jobs: the rules judged before the first job, once per recipe.

The config model (``vgripd.config``) judges what the file says; what it cannot judge without
the calibration's geometry or the files the config names is judged here, by ``ready``:

- calibration present and a valid camera model (stereo rig, multi-camera cell);
- the reference taught (``reference.T_base_obj``; ``reference.grip`` where ``limits.point``
  or ``output.mode`` is ``"grip"``);
- one camera: enough identified features for a PnP pose (``single_camera_problem``);
- every template file a readable image.

A lack of calibration or teaching is a ``NotCalibratedError`` (``NotTaughtError`` when only the
reference is missing): the service runs and that recipe's jobs answer NOT_CALIBRATED. A bad
section is a ``ConfigError`` naming it. The first problem in the order above is raised.

``Pipeline`` builds on what ``ready`` returns, and the daemon calls ``ready`` alone when its
worker process builds the pipelines, so the rules live here once and judging a config builds
no pipeline (no finders, no OpenCV). Only a template feature loads OpenCV, to read its file.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from vgripd.config import Config, single_camera_problem
from vgripd.errors import ConfigError, NotCalibratedError, NotTaughtError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.stereo import StereoRig
from vgripd.types import FloatArray
from vgripd.vision import scene
from vgripd.vision.pose_checks import limit_point

T = TypeVar("T")

#: A grey template image, (h, w) uint8.
Template = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class Ready:
    """What judging a config built, for the pipeline to build on (mm, object/base frames)."""

    config: Config  # several views expanded to the multi-camera cell they are
    left: CameraModel
    right: CameraModel | None
    rig: StereoRig | None
    model: FloatArray  # (n, 3) model points in feature order (``scene.model_points``)
    T_base_obj_ref: FloatArray  # (4, 4)
    limit_point: FloatArray | None  # (3,) object frame; None: the object origin
    limit_point_name: str
    T_base_grip_ref: FloatArray | None  # (4, 4) the taught grip of output.mode = "grip"
    templates: dict[int, Template] = field(default_factory=dict)  # by feature index


def ready(config: Config) -> Ready:
    """Judge ``config`` (one recipe's effective config) as the pipeline needs it.

    Raises
    ------
    NotCalibratedError
        Calibration missing or invalid, or the reference (``NotTaughtError``) or grip not
        taught.
    ConfigError
        A single camera with too few identified features, an unreadable template file.
    """
    config = scene.views_config(config)
    left, right = scene.camera_models(config)
    rig = scene.stereo_rig(config)
    model = scene.model_points(config)
    T_base_obj_ref = scene.T_base_obj_ref(config)
    picks = bool(config.picking.pick_points)
    if picks and config.limits.point == "grip" and config.limits.point_mm is None:
        point, point_name = None, "object origin"  # each pick point is "the grip"
    else:
        point, point_name = limit_point(config, model, T_base_obj_ref)
    T_base_grip_ref = None
    if config.output.mode == "grip" and not picks:
        if config.reference.grip is None:
            raise NotCalibratedError(
                'reference.grip: output.mode = "grip" needs the grip pose taught on the '
                "reference object (vgripd teach --grip)"
            )
        T_base_grip_ref = scene.matrix_from_pose(config.reference.grip)
    if scene.is_multi_camera(config):
        scene.multi_camera_models(config)
    problem = single_camera_problem(config)
    if problem:
        raise ConfigError(problem)
    templates = {i: load_template(f.template, f"object.features[{i}]")
                 for i, f in enumerate(config.object.features) if f.kind == "template"}
    return Ready(config, left, right, rig, model, T_base_obj_ref, point, point_name,
                 T_base_grip_ref, templates)


def recipe_readiness(config: Config, build: Callable[[Config], T]
                     ) -> tuple[dict[int, T], dict[int, str], set[int]]:
    """Every recipe judged by ``build`` (``ready``, or a pipeline class, which calls it):
    what it built for each recipe that can run, why each other one cannot (by number), and
    the numbers among those whose only lack is the taught reference. A bad section is a
    ``ConfigError`` naming its recipe (``recipes.2.object.features[0].template: ...``)."""
    built: dict[int, T] = {}
    problems: dict[int, str] = {}
    untaught: set[int] = set()
    for number in config.recipe_numbers():
        try:
            built[number] = build(config.for_recipe(number))
        except NotCalibratedError as err:
            problems[number] = str(err)
            if isinstance(err, NotTaughtError):
                untaught.add(number)
        except ConfigError as err:
            if not number:
                raise
            raise ConfigError(f"recipes.{number}.{err}") from None
    return built, problems, untaught


def load_template(path: str, where: str) -> Template:
    """The template image, grey; a relative path is taken from the working directory (as every
    path of the config is), so the message names the file actually tried."""
    import cv2  # only a config with templates pays for OpenCV here

    file = Path(path)
    image = cv2.imread(str(file), cv2.IMREAD_GRAYSCALE) if file.is_file() else None
    if image is None:
        why = "not an image" if file.is_file() else "no such file"
        tried = "" if file.is_absolute() else f", tried {file.absolute()}"
        raise ConfigError(f"{where}.template: cannot read image file {path!r} ({why}{tried})")
    return np.asarray(image, dtype=np.uint8)
