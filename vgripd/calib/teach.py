"""Teaching the reference: measure the object several times where the robot learnt to grip it,
average, and turn the result into the ``[reference]`` section a config includes.

The chapter's relative orientation: the reference measurement is the object (its pose for a
CAD model, or its measured feature points for ``object.definition = "reference"``) in the robot
base frame at teach time; every later job is computed against it. docs/teach.md has the story.

The pose in the base frame, ``T_base_obj = T_base_camera @ T_cam_obj``, depends only on the
calibration and the images, never on the reference already in the config: the reference enters
only the offset and its limits. So shots are measured with :func:`measuring_config`, which
lifts the offset limits (a re-taught object may sit far from the old reference) and keeps every
other check (residuals, workspace box).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vgripd.calib.files import pose_table
from vgripd.config import Config, PoseConfig, ReferenceConfig
from vgripd.errors import CalibrationError
from vgripd.geometry.transforms import (
    make_transform,
    matrix_from_quat,
    pose_error,
    quat_from_matrix,
)
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.types import FloatArray, ImagePair, JobResult, Status

DEFAULT_SHOTS = 5
#: Default repeatability limits: about 5x the demo cell's 1-sigma pose noise (docs/teach.md).
DEFAULT_MAX_SPREAD_MM = 0.2
DEFAULT_MAX_SPREAD_DEG = 0.1


def measuring_config(config: Config) -> Config:
    """``config`` as the shots are measured: offset limits lifted, output the plain offset.

    A CAD object without a taught reference gets a placeholder (identity) so that the pipeline
    can be built; the offset it produces is never used.
    """
    limits = config.limits.model_copy(
        update={"max_translation_mm": math.inf, "max_rotation_deg": 360.0})
    reference = config.reference
    if config.object.definition == "cad" and reference.T_base_obj is None:
        reference = ReferenceConfig(T_base_obj=PoseConfig(translation_mm=(0.0, 0.0, 0.0)))
    output = config.output.model_copy(update={"mode": "offset"})
    return config.model_copy(update={"limits": limits, "reference": reference, "output": output})


async def acquire(config: Config, shots: int) -> list[ImagePair]:
    """``shots`` images (pairs) from the configured camera, each within
    ``daemon.job_timeout_s``; raises ``CameraError`` / ``ConfigError``."""
    cls = load_class(CAMERAS, "camera", config.camera.type)
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    await camera.open()
    try:
        return [await camera.grab(config.daemon.job_timeout_s) for _ in range(shots)]
    finally:
        await camera.close()


@dataclass(frozen=True)
class Shot:
    """One accepted measurement: pose (4, 4) mm and feature points (3,) mm, base frame."""

    index: int  # 1-based, as reported to the operator
    T_base_obj: FloatArray
    points_base: Mapping[str, FloatArray]
    residuals: Mapping[str, float]


def shot_from_result(index: int, result: JobResult, points_base: Mapping[str, FloatArray],
                     names: Sequence[str]) -> Shot:
    """The shot of one pipeline result; ``CalibrationError`` saying why it cannot be used.

    A reference must be clean: anything but status OK (OK_RECALIBRATE included: the rig needs
    a calibration first) and any feature not found refuse the shot.
    """
    if result.status is not Status.OK:
        why = f": {result.message}" if result.message else ""
        raise CalibrationError(f"shot {index}: status {result.status.name}{why}")
    missing = [n for n in names if n not in points_base]
    if missing or result.T_base_obj is None:
        raise CalibrationError(
            f"shot {index}: feature(s) {' '.join(missing)} not found (teaching needs every "
            "feature)")
    return Shot(index, np.asarray(result.T_base_obj, dtype=np.float64),
                {n: np.asarray(points_base[n], dtype=np.float64) for n in names},
                dict(result.residuals))


def mean_transform(Ts: Sequence[FloatArray]) -> FloatArray:
    """Mean of rigid transforms (k, 4, 4): mean translation, and the rotation whose unit
    quaternion maximises the summed squared dot products with the shots' quaternions (the
    principal eigenvector of ``sum q q^T``; sign-free, so q and -q count alike)."""
    if not Ts:
        raise CalibrationError("no shots to average")
    q = np.array([quat_from_matrix(np.asarray(T)[:3, :3]) for T in Ts])
    _, vectors = np.linalg.eigh(q.T @ q)
    t = np.mean([np.asarray(T)[:3, 3] for T in Ts], axis=0)
    return make_transform(matrix_from_quat(vectors[:, -1]), t)


@dataclass(frozen=True)
class Taught:
    """The averaged reference and its repeatability over the shots.

    ``deviations``: per shot (mm, deg) from the mean pose; ``point_deviations_mm``: per shot the
    largest distance of a feature point from its mean. ``spread_*``: the maxima.
    """

    T_base_obj: FloatArray
    points_base: Mapping[str, FloatArray]
    shots: tuple[Shot, ...]
    deviations: tuple[tuple[float, float], ...]
    point_deviations_mm: tuple[float, ...]

    @property
    def spread_mm(self) -> float:
        return max(d[0] for d in self.deviations)

    @property
    def spread_deg(self) -> float:
        return max(d[1] for d in self.deviations)

    @property
    def points_spread_mm(self) -> float:
        return max(self.point_deviations_mm)

    def problems(self, max_spread_mm: float, max_spread_deg: float,
                 check_points: bool = False) -> list[str]:
        """Why the reference must not be written (empty: it may). ``check_points``: the
        feature points are the reference too (``reference`` definition), so their spread
        counts against ``max_spread_mm``."""
        out = []
        if self.spread_mm > max_spread_mm:
            out.append(f"pose spread {self.spread_mm:.3f} mm > --max-spread-mm {max_spread_mm}")
        if self.spread_deg > max_spread_deg:
            out.append(f"pose spread {self.spread_deg:.4f} deg > --max-spread-deg "
                       f"{max_spread_deg}")
        if check_points and self.points_spread_mm > max_spread_mm:
            out.append(f"feature point spread {self.points_spread_mm:.3f} mm > "
                       f"--max-spread-mm {max_spread_mm}")
        return out


def average(shots: Sequence[Shot]) -> Taught:
    """Mean pose and mean feature points of accepted shots, with each shot's deviation."""
    T_mean = mean_transform([s.T_base_obj for s in shots])
    names = list(shots[0].points_base)
    stack = np.array([[s.points_base[n] for n in names] for s in shots])  # (k, n, 3)
    mean_points = stack.mean(axis=0)
    point_dev = np.linalg.norm(stack - mean_points, axis=2).max(axis=1)
    return Taught(
        T_base_obj=T_mean,
        points_base=dict(zip(names, mean_points, strict=True)),
        shots=tuple(shots),
        deviations=tuple(pose_error(s.T_base_obj, T_mean) for s in shots),
        point_deviations_mm=tuple(float(d) for d in point_dev),
    )


def measure(config: Config, pairs: Sequence[ImagePair]) -> Taught:
    """Run the pipeline on every pair and average; ``CalibrationError`` naming every refused
    shot and why."""
    from vgripd.vision.pipeline import Pipeline  # OpenCV; kept out of the import of this module

    pipeline = Pipeline(measuring_config(config))
    shots: list[Shot] = []
    refused: list[str] = []
    for index, pair in enumerate(pairs, start=1):
        result, points = pipeline.process_with_points(pair, index)
        try:
            shots.append(shot_from_result(index, result, points, pipeline.names))
        except CalibrationError as err:
            refused.append(str(err))
    if refused:
        raise CalibrationError(
            f"{len(refused)} of {len(pairs)} shot(s) refused, nothing taught:\n  "
            + "\n  ".join(refused))
    return average(shots)


def reference_sections(config: Config, taught: Taught,
                       T_base_grip: FloatArray | None = None) -> dict[str, Any]:
    """The ``[reference]`` section for the config's object definition (see ReferenceConfig)."""
    reference: dict[str, Any]
    if config.object.definition == "cad":
        reference = {"T_base_obj": pose_table(taught.T_base_obj)}
    else:
        reference = {"points_mm": {n: [float(v) for v in p]
                                   for n, p in taught.points_base.items()}}
    if T_base_grip is not None:
        reference["grip"] = pose_table(T_base_grip)
    return {"reference": reference}
