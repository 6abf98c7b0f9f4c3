"""Calibration health for the web view (``GET /api/calibration``, docs/web.md "Calibration
health"): which file each part of the calibration comes from, when and how it was made (the
result file's ``[about]``: command, date, RMS, standard deviations), and the cell's geometry for
the drawings from above and from the side (cameras with their viewing axis and field of view,
rigs, the taught reference, the last pose), so a camera mounted the wrong way shows at a glance.

Read-only and cheap (a few small TOML files, a few 4x4 products), answered on the loop.
"""

from __future__ import annotations

import math
import os
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.config import Config, read_config_data
from vgripd.errors import VgripError
from vgripd.redaction import redact
from vgripd.serialize import jsonable

#: Keys under ``calibration`` whose file is listed (a part each).
PARTS = ("left", "right", "stereo", "hand_eye", "cameras", "rigs")


def shown_path(source: str, folder: Path, full: bool) -> str:
    """``source`` as a reader may see it: in full for a token holder; else relative to the
    config's ``folder`` (inside it) or its name alone, never the machine's absolute path."""
    if full:
        return source
    path = Path(source)
    try:
        return str(path.relative_to(folder))
    except ValueError:
        return path.name


def calibration_files(config_path: Path | None, full_paths: bool = True) -> list[dict[str, Any]]:
    """Per file that sets part of ``calibration`` or ``reference``: its path (relative to the
    config's folder unless ``full_paths``), what it sets, its modification time and its
    ``[about]`` (how it was made; secrets redacted, as everything the view shows)."""
    if config_path is None:
        return []
    owner: dict[str, str] = {}
    try:
        read_config_data(config_path, owner)
    except VgripError:
        return []
    files: dict[str, set[str]] = {}
    for key, source in owner.items():
        head = key.split(".")
        if head[0] == "calibration" and len(head) > 1 and head[1] in PARTS:
            files.setdefault(source, set()).add(f"calibration.{head[1]}")
        elif head[0] == "reference":
            files.setdefault(source, set()).add("reference")
    out = []
    folder = config_path.absolute().parent
    for source, parts in sorted(files.items()):
        path = Path(source)
        shown = shown_path(source, folder, full_paths)
        entry: dict[str, Any] = {"file": shown, "sets": sorted(parts), "about": {}}
        try:
            entry["modified"] = time.strftime("%Y-%m-%dT%H:%M:%S%z",
                                              time.localtime(os.stat(path).st_mtime))
            entry["about"] = redact(jsonable(tomllib.loads(path.read_text(encoding="utf-8"))
                                             .get("about", {})))
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
            entry["error"] = redact(str(err).replace(source, shown))
        out.append(entry)
    return out


def _fov_deg(width: int, height: int, fx: float, fy: float) -> tuple[float, float]:
    return (math.degrees(2 * math.atan(width / (2 * fx))),
            math.degrees(2 * math.atan(height / (2 * fy))))


def cell_geometry(config: Config, T_base_obj_last: Any = None) -> dict[str, Any]:
    """Cameras (name, rig, position mm, viewing axis, right axis, field of view deg), the taught
    reference and the last pose, in the robot base frame, for the drawings."""
    from vgripd.vision import scene  # the daemon has it loaded (scene_pose)

    cal = config.calibration
    out: dict[str, Any] = {"cameras": [], "reference": None, "last": None, "note": ""}
    if cal is None:
        out["note"] = "not calibrated"
        return out

    def camera(name: str, rig: str, T: Any, width: int, height: int, fx: float,
               fy: float) -> dict[str, Any]:
        T = np.asarray(T, dtype=np.float64)
        return {"name": name, "rig": rig, "position_mm": T[:3, 3].tolist(),
                "axis": T[:3, 2].tolist(), "right": T[:3, 0].tolist(),
                "fov_deg": list(_fov_deg(width, height, fx, fy))}

    try:
        if cal.cameras is not None:
            rig_of = {c: r.name for r in cal.rigs for c in r.cameras}
            poses = scene.T_base_cameras(config)
            for cam, T in zip(cal.cameras, poses, strict=True):
                i = cam.intrinsics
                out["cameras"].append(camera(cam.name, rig_of.get(cam.name, cam.name), T,
                                             i.width, i.height, i.fx, i.fy))
        else:
            T_left = scene.T_base_camera(config)
            left = cal.left
            out["cameras"].append(camera("left", "stereo" if cal.right else "camera", T_left,
                                         left.width, left.height, left.fx, left.fy))
            T_rl = scene.T_right_left(config)
            if cal.right is not None and T_rl is not None:
                out["cameras"].append(camera("right", "stereo", T_left @ np.linalg.inv(T_rl),
                                             cal.right.width, cal.right.height, cal.right.fx,
                                             cal.right.fy))
    except VgripError as err:  # robot-mounted: where the cameras are depends on the flange
        out["note"] = f"cameras not drawn: {err}"
    try:
        T_ref = scene.T_base_obj_ref(config)
        out["reference"] = {"position_mm": T_ref[:3, 3].tolist(),
                            "x": T_ref[:3, 0].tolist(), "z": T_ref[:3, 2].tolist()}
    except VgripError:
        pass
    if T_base_obj_last is not None:
        T = np.asarray(T_base_obj_last, dtype=np.float64)
        out["last"] = {"position_mm": T[:3, 3].tolist(), "x": T[:3, 0].tolist(),
                       "z": T[:3, 2].tolist()}
    return out
