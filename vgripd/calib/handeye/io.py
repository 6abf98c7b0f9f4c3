"""Hand-eye files: the robot poses file (one pose per line in a vendor's convention) and the
samples file (JSON) that lets a calibration be solved again without robot and images."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.handeye.samples import FloatArray, Sample, check_mode
from vgripd.errors import CalibrationError, ConversionError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import check_transform
from vgripd.geometry.vendors import convention, transform_from_vendor

SAMPLES_FORMAT = "vgripd-handeye-samples/1"


def read_poses(path: str | Path, pose_format: str) -> list[FloatArray]:
    """Robot flange poses ``T_base_flange`` (mm) from a text file, one pose per line.

    Each line holds the numbers of one pose in ``pose_format``'s field order and units as
    ``vgripd.geometry.vendors`` defines them (e.g. kuka: X Y Z mm, A B C deg; ur: x y z m,
    rx ry rz rad; matrix: 16 numbers row-major, mm), separated by spaces and/or commas. ``#``
    starts a comment; blank lines are skipped. CalibrationError names ``file:line`` for a bad
    line.
    """
    p = Path(path)
    try:
        convention(pose_format)
    except ConversionError as err:
        raise CalibrationError(f"--pose-format: {err}") from None
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise CalibrationError(f"{p}: cannot read robot poses: {err}") from None
    poses = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        values = line.split("#", 1)[0].replace(",", " ").split()
        if not values:
            continue
        try:
            poses.append(transform_from_vendor(pose_format, values))
        except ConversionError as err:
            raise CalibrationError(f"{p}:{line_number}: {err}") from None
    if not poses:
        raise CalibrationError(f"{p}: no robot poses (one pose per line, '#' for comments)")
    return poses


def save_samples(path: str | Path, samples: Sequence[Sample], mode: str, board: str | None,
                 camera: CameraModel | None) -> Path:
    """Write the samples as JSON so that a calibration can be solved again without the robot
    and the images: robot poses as 4x4 (mm), the detected corners (board points ``obj_mm`` and
    their pixels ``px``) or, for pose-only samples, ``T_cam_board``; plus mode, board spec (for
    information) and intrinsics."""
    entries: list[dict[str, Any]] = []
    for s in samples:
        entry: dict[str, Any] = {"image": s.image, "T_base_flange": s.T_base_flange.tolist()}
        if s.obj is not None and s.px is not None:
            entry["obj_mm"] = s.obj.tolist()
            entry["px"] = s.px.tolist()
        else:
            if s.T_cam_board is None:
                raise CalibrationError(f"{s.image}: sample has neither corners nor a board pose")
            entry["T_cam_board"] = s.T_cam_board.tolist()
        entries.append(entry)
    data = {"format": SAMPLES_FORMAT, "mode": mode, "board": board,
            "camera": None if camera is None else dataclasses.asdict(camera),
            "units": "mm, px (OpenCV convention)", "samples": entries}
    p = Path(path)
    try:
        p.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    except (OSError, ValueError) as err:
        raise CalibrationError(f"{p}: cannot write samples: {err}") from None
    return p


def load_samples(path: str | Path,
                 ) -> tuple[str, str | None, CameraModel | None, list[Sample]]:
    """Read :func:`save_samples`' file: (mode, board spec, camera, samples)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CalibrationError(f"{p}: cannot read samples: {err}") from None
    if not isinstance(data, dict) or data.get("format") != SAMPLES_FORMAT:
        raise CalibrationError(f"{p}: not a hand-eye samples file (format must be "
                               f"{SAMPLES_FORMAT!r})")
    mode, board = data.get("mode"), data.get("board")
    check_mode(str(mode))
    try:
        camera = None if data.get("camera") is None else CameraModel(**data["camera"])
    except (TypeError, DegenerateInputError) as err:
        raise CalibrationError(f"{p}: camera: {err}") from None
    samples = []
    for i, e in enumerate(data.get("samples", [])):
        where = f"{p}: samples[{i}]"
        try:
            T = check_transform(e["T_base_flange"], "T_base_flange")
            if "px" in e:
                obj = np.asarray(e["obj_mm"], dtype=np.float64).reshape(-1, 3)
                px = np.asarray(e["px"], dtype=np.float64).reshape(-1, 2)
                if len(obj) != len(px) or len(px) < 4:
                    raise CalibrationError(f"{where}: need at least 4 corners with as many "
                                           f"obj_mm as px, got {len(obj)} and {len(px)}")
                samples.append(Sample(T, None, str(e.get("image", "")), obj, px))
            else:
                B = check_transform(e["T_cam_board"], "T_cam_board")
                samples.append(Sample(T, B, str(e.get("image", ""))))
        except (KeyError, TypeError, ValueError, DegenerateInputError) as err:
            raise CalibrationError(f"{where}: {type(err).__name__}: {err}") from None
    return str(mode), board, camera, samples
