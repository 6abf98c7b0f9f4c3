"""Fingerprints of the camera model and of the hand-eye, so that calibration files that belong
together can be told apart from files made with another calibration.

A hand-eye is only right for the camera model it was computed with: a new intrinsic or stereo
calibration moves the (left) camera's frame (0.1 px of focal length or principal point is about
0.06 mm at 820 mm), and the old hand-eye with the new rig is off by 0.1-1.4 mm. The same holds for
a taught reference, which was measured through the camera model *and* the hand-eye. So each
result file records in its ``[about]``:

- ``camera_model``: the fingerprint of the camera model it was made with (a calibration of the
  cameras: of the model it defines), and ``camera_model_parts``: which sections it covers
  (``left``, ``right``, ``stereo``, ``cameras``);
- a taught reference also ``hand_eye``: the fingerprint of the hand-eye it was measured with.

The config loader (``vgripd.config.load_config``) compares them with the config's own sections
and refuses a mismatch naming both files (order of calibration: rig -> hand-eye -> teach).

A fingerprint is the first 12 hex digits of the SHA-256 of the values rounded to 1e-6 (px,
mm, dimensionless distortion and rotation-matrix entries), so rewriting a file with the same
numbers keeps it. Works on plain config tables (as read from TOML), no config model needed.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from vgripd.geometry.transforms import make_transform, matrix_from_rotvec

#: The sections of ``[calibration]`` that make up the camera model, in hashing order.
CAMERA_PARTS = ("left", "right", "stereo", "cameras")
DIGITS = 6
LENGTH = 12


def _r(x: Any) -> float:
    return round(float(x), DIGITS) + 0.0  # + 0.0: no "-0.0"


def _intrinsics(table: Mapping[str, Any]) -> list[float]:
    dist = list(table.get("dist", (0.0,) * 5))
    return [_r(table[k]) for k in ("fx", "fy", "cx", "cy")] + [_r(table.get("skew", 0.0))] + [
        _r(d) for d in dist] + [int(table.get("width", 0)), int(table.get("height", 0))]


def _pose(table: Mapping[str, Any] | None) -> list[float] | None:
    if table is None:
        return None
    if table.get("matrix") is not None:
        M = np.asarray(table["matrix"], dtype=float)
    else:
        M = make_transform(matrix_from_rotvec(table.get("rotvec_rad") or (0.0, 0.0, 0.0)),
                           table["translation_mm"])
    return [_r(x) for x in M[:3].ravel()]


def _digest(value: Any) -> str:
    text = json.dumps(value, separators=(",", ":"), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:LENGTH]


def camera_parts(calibration: Mapping[str, Any]) -> tuple[str, ...]:
    """The camera-model sections a ``[calibration]`` table holds (``left`` always counts once
    there is a camera at all; with ``cameras`` the derived ``left`` is not counted again)."""
    if calibration.get("cameras"):
        return ("cameras",)
    return tuple(p for p in ("left", "right", "stereo") if calibration.get(p) is not None)


def camera_fingerprint(calibration: Mapping[str, Any], parts: Iterable[str] | None = None) -> str:
    """The fingerprint of the camera model in ``calibration`` (a ``[calibration]`` table),
    over ``parts`` (default: every camera section it holds). A part it lacks hashes as null,
    so a file made with a stereo rig never matches a single camera."""
    chosen = camera_parts(calibration) if parts is None else tuple(parts)
    value: dict[str, Any] = {}
    for part in chosen:
        section = calibration.get(part)
        if section is None:
            value[part] = None
        elif part in ("left", "right"):
            value[part] = _intrinsics(section)
        elif part == "stereo":
            value[part] = _pose(section.get("T_right_left"))
        elif part == "cameras":
            value[part] = [[c["name"], _intrinsics(c["intrinsics"])] for c in section]
        else:
            raise ValueError(f"unknown camera model part {part!r} (one of {CAMERA_PARTS})")
    return _digest(value)


def camera_about(calibration: Mapping[str, Any],
                 parts: Iterable[str] | None = None) -> dict[str, Any]:
    """The ``[about]`` entries that record the camera model: ``camera_model`` and
    ``camera_model_parts``."""
    chosen = camera_parts(calibration) if parts is None else tuple(parts)
    return {"camera_model": camera_fingerprint(calibration, chosen),
            "camera_model_parts": list(chosen)}


def hand_eye_fingerprint(calibration: Mapping[str, Any]) -> str:
    """The fingerprint of where the camera(s) are: ``hand_eye`` (mounting and pose), or each
    entry of ``cameras`` (name, mounting, pose)."""
    if calibration.get("cameras"):
        value: Any = [[c["name"], c.get("mounting", "fixed"), _pose(c.get("T_base_camera")),
                       _pose(c.get("T_flange_camera"))] for c in calibration["cameras"]]
    else:
        he = calibration.get("hand_eye") or {}
        value = [he.get("mounting", "fixed"), _pose(he.get("T_base_camera")),
                 _pose(he.get("T_flange_camera"))]
    return _digest(value)


def intrinsics_table(camera: Any) -> dict[str, Any]:
    """A ``CameraModel``'s fields as a ``[calibration.left]`` table (for a fingerprint)."""
    return {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
            "skew": camera.skew, "dist": list(camera.dist), "width": camera.width,
            "height": camera.height}
