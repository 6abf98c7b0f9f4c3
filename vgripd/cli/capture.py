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
import time
from pathlib import Path
from typing import Any

from vgripd.calib.boards import Board
from vgripd.calib.capturesets import Capture, camera_names, detect_or_none, next_command
from vgripd.calib.coverage import Coverage
from vgripd.config import Config, load_config
from vgripd.errors import CameraError, ConfigError
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
            dets = [detect_or_none(board, v, f"{n} grab {grabs}")
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
