"""``[object]`` (the features and how their coordinates are defined) and ``[reference]``
(the taught reference); the embedded demo cell's object and reference."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator

from vgripd.config.common import Model, PoseConfig, Vec3

#: The fewest identified features (ArUco markers, templates) a single-camera (PnP) pose needs
#: (three points have up to four poses).
MIN_PNP_FEATURES = 4

#: OpenCV's predefined ArUco dictionaries (``cv2.aruco.DICT_*``), named here so that judging a
#: config needs no OpenCV; a test holds the set to OpenCV's own.
ARUCO_DICTIONARIES = frozenset(
    [f"DICT_{n}X{n}_{size}" for n in (4, 5, 6, 7) for size in (50, 100, 250, 1000)]
    + ["DICT_ARUCO_ORIGINAL", "DICT_ARUCO_MIP_36H12", "DICT_APRILTAG_16H5",
       "DICT_APRILTAG_25H9", "DICT_APRILTAG_36H10", "DICT_APRILTAG_36H11"])


def marker_problems(features: tuple[FeatureConfig, ...]) -> list[str]:
    """Why the object's ArUco markers cannot be told apart, one line per feature starting with
    its field (``object.features[i]``): an id used twice in one dictionary, an unknown
    dictionary."""
    problems = []
    seen: set[tuple[str, int]] = set()
    for i, f in enumerate(features):
        if f.kind != "aruco":
            continue
        if (f.dictionary, f.marker_id) in seen:
            problems.append(f"object.features[{i}]: marker id {f.marker_id} of {f.dictionary} "
                            "is used twice")
            continue
        seen.add((f.dictionary, f.marker_id))
        if f.dictionary.upper() not in ARUCO_DICTIONARIES:
            problems.append(f"object.features[{i}].dictionary: unknown ArUco dictionary "
                            f"{f.dictionary!r}")
    return problems


class _FeatureBase(Model):
    """``normal``: optional outward normal of the mark's face (object frame, any length > 0).

    A mark is seen only from the side its normal points to (a frame with marks on both sides:
    each camera sees its own side). Unset: the object's z axis, and the mark counts as seen
    from both sides (the single-rig cells that predate it look at the object from one side).
    """

    name: str = Field(min_length=1)
    xyz_mm: Vec3
    normal: Vec3 | None = None

    @field_validator("normal")
    @classmethod
    def _nonzero_normal(cls, normal: Vec3 | None) -> Vec3 | None:
        if normal is not None and not math.hypot(*normal) > 1e-9:
            raise ValueError(f"normal must be a non-zero vector, got {list(normal)}")
        return normal


class CircleFeature(_FeatureBase):
    """A circular mark; its centre is the feature point."""

    kind: Literal["circle"]
    diameter_mm: float = Field(gt=0)
    polarity: Literal["dark", "bright"] = "dark"


class ArucoFeature(_FeatureBase):
    """An ArUco marker; its centre is the feature point."""

    kind: Literal["aruco"]
    marker_id: int = Field(ge=0)
    dictionary: str = Field(default="DICT_4X4_50", pattern=r"^DICT_[A-Z0-9_]+$")
    size_mm: float = Field(gt=0)


class TemplateFeature(_FeatureBase):
    """A grey-level template (image file) whose centre is the feature point."""

    kind: Literal["template"]
    template: str = Field(min_length=1)
    size_px: int = Field(gt=0)


FeatureConfig = Annotated[
    CircleFeature | ArucoFeature | TemplateFeature, Field(discriminator="kind")
]


class ObjectConfig(Model):
    """The object's features and how their coordinates are defined.

    ``definition = "cad"``: ``xyz_mm`` are model points in the object frame (from CAD).
    ``definition = "reference"``: ``xyz_mm`` are the points as measured in the robot base frame
    with the object at its taught reference position (relative orientation, no CAD needed).
    """

    name: str = Field(default="object", min_length=1)
    definition: Literal["cad", "reference"] = "cad"
    features: tuple[FeatureConfig, ...]

    @field_validator("features")
    @classmethod
    def _enough_unique(cls, feats: tuple[Any, ...]) -> tuple[Any, ...]:
        if len(feats) < 3:
            raise ValueError(f"needs at least 3 features for a 6-DOF pose, got {len(feats)}")
        seen: set[str] = set()
        for i, f in enumerate(feats):
            if f.name in seen:
                raise ValueError(f"feature {i}: duplicate name {f.name!r}")
            seen.add(f.name)
        return feats


class ReferenceConfig(Model):
    """The taught reference: ``T_base_obj`` = object pose in the base frame at teach time.

    The gripping offset of a job is the base-frame correction
    ``T_offset = T_base_obj @ inv(T_base_obj_ref)``: a grip pose ``G`` taught on the reference
    object (in the base frame) becomes ``T_offset @ G`` for the object as found.
    Only for ``object.definition = "cad"``; with ``"reference"`` the object frame *is* the base
    frame at teach time (``T_base_obj_ref`` = identity) and this pose must not be set.
    Unset for a CAD object means "not taught yet": jobs end with NOT_CALIBRATED.

    ``points_mm`` (``"reference"`` only): the feature points measured in the base frame at the
    reference by ``vgripd teach``, one per feature name. When set, the pipeline fits these
    instead of the features' ``xyz_mm`` (which then only need to be a nominal layout).
    ``grip``: the robot's grip pose taught on the reference object (base frame); the absolute
    grip for a found object is ``T_offset @ grip`` (``output.mode = "grip"``).
    """

    T_base_obj: PoseConfig | None = None
    points_mm: dict[str, Vec3] | None = None
    grip: PoseConfig | None = None


DEMO_OBJECT = ObjectConfig(
    name="demo_plate",
    definition="cad",
    features=tuple(
        CircleFeature(name=f"m{i + 1}", xyz_mm=xyz, kind="circle", diameter_mm=10.0)
        for i, xyz in enumerate(
            [
                (-62.0, 29.0, 0.0),
                (-65.0, -44.0, 0.0),
                (-16.0, 46.0, 0.0),
                (-32.0, -15.0, 0.0),
                (48.0, -41.0, 20.0),
                (58.0, 16.0, 12.0),
            ]
        )
    ),
)
DEMO_REFERENCE = ReferenceConfig(
    T_base_obj=PoseConfig(translation_mm=(600.0, 100.0, 10.0), rotvec_rad=(0.0, 0.0, 0.05))
)
