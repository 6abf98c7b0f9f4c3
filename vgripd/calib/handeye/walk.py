"""The walked hand-eye calibration's record: which plan targets the robot visited, the flange
pose it reached at each and the board corners seen there; resumable after an interruption.

The robot program does the walking (it reads the next target, moves with its own speed limit,
settles, asks for an image with the flange pose it reached, and says when it cannot reach a
target); vgripd never commands motion. This module is what vgripd keeps meanwhile: a
:class:`Walk` over one plan file, saved after every target (written beside its name and
renamed, so a robot stop or a lost link between two targets loses nothing). Opening the same
file again resumes at the first target without a record. A target the robot could not reach,
and one where the board was not found, are recorded with the reason and skipped.

The file is a samples file (``vgripd-handeye-samples/1``: ``vgripd calibrate handeye --samples
FILE`` solves it) with a ``walk`` table: the plan (path, digest of its poses, condition figure)
and one record per target visited. Every record and sample names its ``peer``: the robot
connection (or controller) whose request it records.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.boards import Board, Detection, detect
from vgripd.calib.handeye.io import SAMPLES_FORMAT
from vgripd.calib.handeye.plan import LoadedPlan
from vgripd.calib.handeye.samples import FloatArray, Sample
from vgripd.errors import CalibrationError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import check_transform

SEEN, NOT_SEEN, UNREACHABLE = "seen", "not_seen", "unreachable"


def plan_digest(poses: Sequence[FloatArray]) -> str:
    """Short digest of a plan's poses (rounded to 1e-6 mm): a walk resumes only its own plan."""
    flat = [round(float(x), 6) + 0.0 for T in poses for x in np.asarray(T)[:3].ravel()]
    return hashlib.sha256(json.dumps(flat).encode()).hexdigest()[:12]


@dataclass
class WalkRecord:
    index: int
    status: str
    T_base_flange: FloatArray | None = None
    image: str = ""
    px: FloatArray | None = None
    ids: np.ndarray | None = None
    reason: str = ""
    #: who asked: the robot connection (robot socket: address:port) or controller (RTDE)
    peer: str = ""


class Walk:
    """The record of walking ``plan`` (see the module docstring), kept in ``path``."""

    def __init__(self, path: str | Path, plan: LoadedPlan, board: Board,
                 camera: CameraModel | None) -> None:
        self.path = Path(path)
        self.plan = plan
        self.board = board
        self.camera = camera
        self.digest = plan_digest(plan.poses)
        self.records: dict[int, WalkRecord] = {}
        #: The board finder (``boards.detect``); the running daemon runs it in a helper process.
        self.detect: Callable[[Board, np.ndarray, str], Detection] = detect
        if self.path.exists():
            self._load()

    # ---- robot side asks
    def next_index(self) -> int | None:
        """The next target to visit (the first without a record), None when all are done."""
        for k in range(len(self.plan.poses)):
            if k not in self.records:
                return k
        return None

    def target(self, index: int) -> FloatArray:
        if not 0 <= index < len(self.plan.poses):
            raise CalibrationError(f"{self.plan.path}: no target {index} (the plan has "
                                   f"{len(self.plan.poses)})")
        return self.plan.poses[index]

    def capture(self, index: int, T_reached: Any, image: np.ndarray, name: str = "",
                peer: str = "") -> WalkRecord:
        """The image taken at target ``index`` with the flange pose the robot reached there:
        the board's corners recorded (or ``not_seen`` with the reason); ``peer``: who sent
        the pose."""
        self.target(index)
        try:
            T = check_transform(T_reached, f"target {index}: reached flange pose")
        except DegenerateInputError as err:
            raise CalibrationError(str(err)) from None
        name = name or f"walk-{index:02d}"
        try:
            d = self.detect(self.board, image, name)
        except CalibrationError as err:
            record = WalkRecord(index, NOT_SEEN, T, name, reason=str(err), peer=peer)
        else:
            record = WalkRecord(index, SEEN, T, name, d.px, d.ids, peer=peer)
        self.records[index] = record
        self.save()
        return record

    def unreachable(self, index: int, reason: str = "the robot cannot reach it",
                    peer: str = "") -> WalkRecord:
        self.target(index)
        record = WalkRecord(index, UNREACHABLE, reason=reason, peer=peer)
        self.records[index] = record
        self.save()
        return record

    # ---- results
    def samples(self) -> list[Sample]:
        points = self.board.object_points()
        return [Sample(r.T_base_flange, None, r.image, points[r.ids], r.px)
                for _, r in sorted(self.records.items())
                if r.status == SEEN and r.T_base_flange is not None and r.ids is not None
                and r.px is not None]

    def skipped(self) -> list[dict[str, Any]]:
        return [{"target": r.index, "status": r.status, "reason": r.reason}
                for _, r in sorted(self.records.items()) if r.status != SEEN]

    def save(self) -> None:
        entries = []
        points = self.board.object_points()
        for _, r in sorted(self.records.items()):
            if r.status == SEEN and r.ids is not None and r.px is not None:
                assert r.T_base_flange is not None
                entries.append({"image": r.image, "T_base_flange": r.T_base_flange.tolist(),
                                "obj_mm": points[r.ids].tolist(), "px": r.px.tolist(),
                                "target": r.index, "peer": r.peer})
        c = self.plan.condition
        data = {
            "format": SAMPLES_FORMAT, "mode": self.plan.mode, "board": self.board.spec,
            "camera": None if self.camera is None else {
                "fx": self.camera.fx, "fy": self.camera.fy, "cx": self.camera.cx,
                "cy": self.camera.cy, "skew": self.camera.skew, "dist": list(self.camera.dist),
                "width": self.camera.width, "height": self.camera.height},
            "units": "mm, px (OpenCV convention)", "samples": entries,
            "walk": {"plan": str(self.plan.path), "plan_digest": self.digest,
                     "targets": len(self.plan.poses),
                     "condition": {"condition": c.condition, "effective_deg": c.effective_deg},
                     "records": [{"target": r.index, "status": r.status, "reason": r.reason,
                                  "image": r.image, "peer": r.peer,
                                  "T_base_flange": None if r.T_base_flange is None
                                  else r.T_base_flange.tolist()}
                                 for _, r in sorted(self.records.items())]},
        }
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n", encoding="utf-8")
            os.replace(tmp, self.path)
        except (OSError, ValueError) as err:
            raise CalibrationError(f"{self.path}: cannot save the walk: {err}") from None

    def _load(self) -> None:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            walk = data["walk"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as err:
            raise CalibrationError(f"{self.path}: not a walk record to resume: {err}") from None
        if walk.get("plan_digest") != self.digest:
            raise CalibrationError(
                f"{self.path}: records a walk of another plan ({walk.get('plan')}, digest "
                f"{walk.get('plan_digest')}; this plan {self.plan.path} is {self.digest}): "
                "start a new walk file")
        by_target = {int(e["target"]): e for e in data.get("samples", []) if "target" in e}
        n = self.board.n_points
        points = self.board.object_points()
        for rec in walk.get("records", []):
            k = int(rec["target"])
            T = None if rec.get("T_base_flange") is None else np.asarray(rec["T_base_flange"])
            if rec["status"] == SEEN:
                e = by_target.get(k)
                if e is None:
                    continue  # its corners were not saved: visit it again
                obj = np.asarray(e["obj_mm"], dtype=float)
                ids = np.array([int(np.argmin(np.linalg.norm(points - p, axis=1))) for p in obj],
                               dtype=np.int64) if len(obj) != n else np.arange(n, dtype=np.int64)
                self.records[k] = WalkRecord(k, SEEN, T, str(rec.get("image", "")),
                                             np.asarray(e["px"], dtype=float), ids,
                                             peer=str(rec.get("peer", "")))
            else:
                self.records[k] = WalkRecord(k, str(rec["status"]), T,
                                             str(rec.get("image", "")),
                                             reason=str(rec.get("reason", "")),
                                             peer=str(rec.get("peer", "")))


def walk_info(path: str | Path) -> dict[str, Any] | None:
    """The ``walk`` table of a samples file written by a walk (None for other samples files)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    walk = data.get("walk") if isinstance(data, dict) else None
    return walk if isinstance(walk, dict) else None
