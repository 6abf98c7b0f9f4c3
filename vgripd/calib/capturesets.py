"""The account of a calibration capture: which synchronized sets of board images are worth
keeping (every camera sees the board, it is still, it adds coverage), the sets kept and their
files, and the coverage of each camera (``vgripd.calib.coverage``). ``vgripd capture`` and the
web view's setup page keep their sets with it, so both judge a grab alike.

Detection (``detect_or_none``) is CPU work: the daemon runs it in its image helper process.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.boards import Board, Detection, detect
from vgripd.calib.coverage import Coverage, mean_moved_px, moved_px
from vgripd.config import Config
from vgripd.errors import CalibrationError, CameraError, ConfigError


def camera_names(config: Config, n_views: int) -> list[str]:
    """File name stems of the views: the config's camera names, else left/right/camera."""
    cal = config.calibration
    if cal is not None and cal.cameras and len(cal.cameras) == n_views:
        return [c.name for c in cal.cameras]
    if n_views == 1:
        return ["camera"]
    if n_views == 2:
        return ["left", "right"]
    return [f"cam{i}" for i in range(n_views)]


@dataclass
class Capture:
    """The capture's account: kept sets, coverage per camera, the previous grab."""

    board: Board
    out: Path
    min_cameras: int
    still_px: float
    min_move_px: float
    names: list[str] = field(default_factory=list)
    coverage: list[Coverage] = field(default_factory=list)
    kept: list[list[Detection | None]] = field(default_factory=list)
    previous: list[Detection | None] = field(default_factory=list)
    manifest: list[dict[str, Any]] = field(default_factory=list)
    flange: list[str] = field(default_factory=list)
    first: int = 0
    resumed: int = 0

    def judge(self, dets: list[Detection | None]) -> tuple[bool, str]:
        """Whether this grab's detections make a set worth keeping, and why (not)."""
        seen = sum(d is not None for d in dets)
        need = self.min_cameras or len(dets)
        previous, self.previous = self.previous, dets
        if seen < need:
            missing = [n for n, d in zip(self.names, dets, strict=True) if d is None]
            return False, f"board seen by {seen} of {len(dets)} camera(s) (not in " \
                          f"{', '.join(missing)})"
        if self.still_px > 0:
            for name, d, p in zip(self.names, dets, previous or [None] * len(dets),
                                  strict=True):
                if d is None:
                    continue
                if p is None:
                    return False, "board just found: waiting for it to be still"
                if moved_px(d, p) > self.still_px:
                    return False, f"board moving in {name} ({moved_px(d, p):.1f} px)"
        news = [f"{name}: {', '.join(n)}" for name, cov, d in
                zip(self.names, self.coverage, dets, strict=True)
                if d is not None and (n := cov.news(self.board, d))]
        if news:
            return True, "; ".join(news)
        far = all(min((mean_moved_px(d, k) for d, k in zip(dets, kept, strict=True)
                       if d is not None and k is not None), default=float("inf"))
                  >= self.min_move_px for kept in self.kept)
        if far:
            return True, f"a new board place (>= {self.min_move_px:g} px from every kept set)"
        return False, "nothing new: move or tilt the board"

    def keep(self, images: tuple[Any, ...], dets: list[Detection | None], why: str,
             t_mono_ns: int, T_base_flange: Any) -> str:
        import cv2

        index = self.first + len(self.kept)  # first + sets kept (a resumed capture's too)
        files = []
        for name, image in zip(self.names, images, strict=True):
            path = self.out / f"{name}_{index:03d}.png"
            if not cv2.imwrite(str(path), np.asarray(image)):
                raise CameraError(f"cannot write {path}")
            files.append(path.name)
        for cov, d in zip(self.coverage, dets, strict=True):
            if d is not None:
                cov.add(self.board, d)
        self.kept.append(dets)
        entry: dict[str, Any] = {
            "set": index, "files": files, "t_mono_ns": t_mono_ns, "added": why,
            "points": {n: (0 if d is None else len(d.ids))
                       for n, d in zip(self.names, dets, strict=True)}}
        if T_base_flange is not None:
            T = np.asarray(T_base_flange, np.float64)
            rotvec = cv2.Rodrigues(T[:3, :3])[0].ravel()
            self.flange.append(" ".join(f"{v:.6f}" for v in (*T[:3, 3], *rotvec)))
            entry["flange"] = T.round(6).tolist()
        self.manifest.append(entry)
        mixed = 0 < len(self.flange) < len(self.manifest)
        return f"set {index} kept ({why}); " + "; ".join(
            f"{n} {c.summary()}" for n, c in zip(self.names, self.coverage, strict=True)) + (
            "; not every set has a flange pose: no flange.txt (capture.json has each set's)"
            if mixed else "")

    def resume(self) -> int:
        """Continue a capture in the same folder: its sets stay, their coverage counts, the
        numbering goes on; sets kept before (0 for a new folder)."""
        import cv2

        path = self.out / "capture.json"
        if not path.exists():
            return 0
        try:
            data = json.loads(path.read_text())
            sets = list(data["sets"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ConfigError(f"{path}: not a capture manifest ({err}): choose another "
                              "folder") from None
        if data.get("board") != self.board.spec or data.get("cameras") != self.names:
            raise ConfigError(f"{path}: a capture of board {data.get('board')} with cameras "
                              f"{data.get('cameras')}, not {self.board.spec} with "
                              f"{self.names}: choose another folder")
        for entry in sets:
            dets: list[Detection | None] = []
            for name, file in zip(self.names, entry["files"], strict=True):
                image = cv2.imread(str(self.out / file), cv2.IMREAD_GRAYSCALE)
                dets.append(None if image is None else detect_or_none(self.board, image, name))
            for cov, d in zip(self.coverage, dets, strict=True):
                if d is not None:
                    cov.add(self.board, d)
            self.kept.append(dets)
        self.manifest = sets
        flange = self.out / "flange.txt"
        if flange.exists():
            self.flange = [line for line in flange.read_text().splitlines()
                           if line.strip() and not line.startswith("#")]
        self.first = max((int(e["set"]) for e in sets), default=-1) + 1 - len(sets)
        return len(sets)

    def write_manifest(self) -> None:
        data = {"board": self.board.spec, "cameras": self.names, "sets": self.manifest}
        (self.out / "capture.json").write_text(json.dumps(data, indent=1) + "\n")
        # line k of flange.txt is set k (the replay driver's flange_poses): written only when
        # every set has its pose; a capture where some sets have none keeps each set's pose in
        # capture.json alone
        path = self.out / "flange.txt"
        if self.flange and len(self.flange) == len(self.manifest):
            path.write_text("# x y z (mm) rx ry rz (rotation vector, rad): T_base_flange per "
                            "set\n" + "\n".join(self.flange) + "\n")
        elif path.exists():
            path.unlink()


def next_command(names: list[str], out: Path, board: Board) -> str:
    """The calibrate command for the captured images."""
    if len(names) == 1:
        return (f"vgripd calibrate intrinsics --images '{out}/{names[0]}_*.png' "
                f"--board {board.spec} -o camera.toml")
    if names == ["left", "right"]:
        return (f"vgripd calibrate stereo --left '{out}/left_*.png' --right "
                f"'{out}/right_*.png' --board {board.spec} -o rig.toml")
    cams = " ".join(f"--camera {n}='{out}/{n}_*.png'" for n in names)
    return f"vgripd calibrate cameras {cams} --board {board.spec} -o cameras.toml"


def detect_or_none(board: Board, image: Any, where: str) -> Detection | None:
    try:
        return detect(board, image, where)
    except CalibrationError:
        return None


def put_aside(folder: Path, sets: set[int]) -> list[int]:
    """Sets ``sets`` of a capture folder moved to ``dropped/`` and out of its manifest
    (``capture.json``); the set numbers moved. Blocking."""
    manifest_path = folder / "capture.json"
    data = json.loads(manifest_path.read_text())
    aside = folder / "dropped"
    aside.mkdir(exist_ok=True)
    kept, moved = [], []
    for entry in data["sets"]:
        if entry["set"] in sets:
            for name in entry["files"]:
                (folder / name).replace(aside / name)
            moved.append(entry["set"])
        else:
            kept.append(entry)
    data["sets"] = kept
    manifest_path.write_text(json.dumps(data, indent=1) + "\n")
    return moved
