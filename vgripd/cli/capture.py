"""vgripd capture: calibration image sets taken by the config's cameras, every camera at once.

``vgripd capture -c CONFIG --board SPEC -o DIR [--count 20]`` opens the config's ``[camera]``
with the daemon's own driver and grabs continuously (one grab = every camera at one trigger: a
synchronized set). In each set it finds the board in every image and keeps the set when

- the board is seen by every camera (``--min-cameras K``: by at least K of them; a multi-camera
  cell whose outer cameras never share a view chains sets seen by neighbours);
- the board is still: its points moved at most ``--still-px`` (1 px) since the previous grab
  in every camera that sees it, so a set is never blurred or torn between cameras by a moving
  hand (``--still-px 0``: keep moving boards, e.g. a replay of files);
- the set adds something: a new image region or tilt in some camera
  (``vgripd.calib.coverage``), or a board place at least ``--min-move-px`` (20 px, mean)
  away from every set kept so far.

Kept sets are written as ``DIR/<camera>_NNN.png`` (the names of ``calibration.cameras``, else
``left``/``right`` for a pair, ``camera`` for one), with ``DIR/capture.json`` (board, cameras,
per set: time, board points per camera, what it added) and, when the driver reports the robot
flange pose at capture, ``DIR/flange.txt`` (one ``x y z rx ry rz`` line per set, mm and rotation
vector in rad: the replay driver's ``flange_poses`` format). After each kept set one line shows
what it added and the coverage; at the end, what is still missing in each camera and the
``vgripd calibrate`` command for the images.

Stops after ``--count`` kept sets (exit 0), after ``--max-grabs`` grabs, when the camera fails
three times in a row or a replay runs out of files, or on Ctrl-C (exit 1 when fewer than
``--count`` sets were kept, saying why; what was kept stays written).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.boards import Board, Detection, detect
from vgripd.calib.coverage import Coverage, mean_moved_px, moved_px
from vgripd.config import Config, load_config
from vgripd.errors import CalibrationError, CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class, validate_options

#: Camera failures in a row after which the capture stops.
MAX_CAMERA_ERRORS = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", required=True, help="the cell's config ([camera])")
    parser.add_argument("--board", required=True, metavar="SPEC",
                        help="chessboard:COLSxROWS:SQUARE_MM (inner corners), circles:..., "
                             "acircles:..., charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]")
    parser.add_argument("-o", "--output", required=True, metavar="DIR",
                        help="folder for the images (created; existing sets are not touched)")
    parser.add_argument("--count", type=int, default=20, help="sets to keep (default 20)")
    parser.add_argument("--max-grabs", type=int, default=0,
                        help="stop after this many grabs (default: no limit)")
    parser.add_argument("--min-cameras", type=int, default=0,
                        help="keep a set seen by at least this many cameras (default: all)")
    parser.add_argument("--still-px", type=float, default=1.0,
                        help="the board counts as still when its points moved at most this "
                             "since the previous grab (px; 0: do not wait for stillness)")
    parser.add_argument("--min-move-px", type=float, default=20.0,
                        help="a set that adds no coverage is kept when the board moved at "
                             "least this (mean px) from every kept set")
    parser.add_argument("--every", type=float, default=0.0, metavar="S",
                        help="pause between grabs (s)")
    parser.add_argument("--timeout", type=float, default=None, metavar="S",
                        help="seconds per grab (default: daemon.job_timeout_s)")


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
        return f"set {index} kept ({why}); " + "; ".join(
            f"{n} {c.summary()}" for n, c in zip(self.names, self.coverage, strict=True))

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
                dets.append(None if image is None else _detect(self.board, image, name))
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
        if self.flange:
            (self.out / "flange.txt").write_text(
                "# x y z (mm) rx ry rz (rotation vector, rad): T_base_flange per set\n"
                + "\n".join(self.flange) + "\n")


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


def _detect(board: Board, image: Any, where: str) -> Detection | None:
    try:
        return detect(board, image, where)
    except CalibrationError:
        return None


async def capture(config: Config, args: argparse.Namespace, board: Board, out: Path,
                  say: Any = print) -> tuple[Capture, str]:
    """Grab and keep sets until done; the account and why it stopped."""
    cls = load_class(CAMERAS, "camera", config.camera.type)
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    timeout_s = args.timeout if args.timeout is not None else config.daemon.job_timeout_s
    state: Capture | None = None
    before = 0
    grabs = errors = 0
    why_stopped = ""
    last_note = ""
    await camera.open()
    try:
        while True:
            if state is not None and len(state.kept) - before >= args.count:
                why_stopped = f"{args.count} sets kept"
                break
            if args.max_grabs and grabs >= args.max_grabs:
                why_stopped = f"--max-grabs {args.max_grabs} reached"
                break
            try:
                pair = await camera.grab(timeout_s)
            except CameraError as err:
                errors += 1
                if "no more images" in str(err) or errors >= MAX_CAMERA_ERRORS:
                    why_stopped = f"the camera: {err}"
                    break
                say(f"camera: {err} (trying again)")
                continue
            errors = 0
            grabs += 1
            views = tuple(pair.views)
            if state is None:
                state = Capture(board, out, args.min_cameras, args.still_px,
                                args.min_move_px, camera_names(config, len(views)),
                                [Coverage((v.shape[1], v.shape[0])) for v in views])
                before = state.resume()
                if before:
                    say(f"{before} set(s) in {out} already: going on from there")
            dets = [_detect(board, v, f"{n} grab {grabs}")
                    for n, v in zip(state.names, views, strict=True)]
            ok, why = state.judge(dets)
            if ok:
                say(state.keep(views, dets, why, pair.t_mono_ns, pair.T_base_flange))
                state.write_manifest()
            elif why != last_note:
                say(f"grab {grabs}: {why}")
            last_note = "" if ok else why
            if args.every > 0:
                await asyncio.sleep(args.every)
    except asyncio.CancelledError:
        why_stopped = "stopped"
    finally:
        await camera.close()
    if state is None:
        raise CameraError(f"no image from the camera ({why_stopped or 'stopped'})")
    state.resumed = before
    return state, why_stopped


def run(args: argparse.Namespace) -> int:
    if args.count < 1 or args.max_grabs < 0 or args.min_cameras < 0 or args.still_px < 0:
        raise ConfigError("--count must be >= 1; --max-grabs, --min-cameras, --still-px >= 0")
    config = load_config(args.config)
    board = Board.parse(args.board)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        state, why = asyncio.run(capture(config, args, board, out))
    except KeyboardInterrupt:
        print("stopped (Ctrl-C); the sets kept so far are in", out)
        return 1
    new = len(state.kept) - state.resumed
    print(f"{new} set(s) kept in {out} in {time.monotonic() - t0:.0f} s ({why})"
          + (f", {len(state.kept)} with the earlier ones" if state.resumed else ""))
    for name, cov in zip(state.names, state.coverage, strict=True):
        missing = cov.missing()
        print(f"  {name}: {cov.summary()}"
              + (f"; still missing: {'; '.join(missing)}" if missing else "; complete"))
    if state.kept:
        print("next: " + next_command(state.names, out, board))
    if new < args.count:
        print(f"vgripd capture: only {new} of {args.count} sets kept ({why})")
        return 1
    return 0
