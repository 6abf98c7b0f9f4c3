"""The setup's hand-eye from the captured sets (docs/setup.md, step 3), beside ``SetupRoutes``
(``setup.py``)::

    POST /api/setup/handeye/solve        {"mode": "eye-in-hand" | "eye-to-hand"}: ``vgripd
                                         calibrate handeye`` on the calibration step's kept
                                         sets and their flange poses, in a child process
    GET  /api/setup/handeye/solve[?wait=1]   running (seconds), or its result
    POST /api/setup/handeye/use          the solved hand-eye saved with the accepted
                                         calibration (one judged transaction)

The flange pose of every kept set (``capture.json``'s ``flange``, 4x4 mm, recorded with the set)
goes to a poses file in the matrix convention; the images are the first camera's of each set (the
hand-eye is the first camera's: ``left`` of a pair), the intrinsics the accepted calibration's,
else the running config's. A capture where a set has no flange pose is refused naming the sets.
"""

from __future__ import annotations

import asyncio
import time
import tomllib
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.errors import VgripError
from vgripd.serialize import jsonable
from vgripd.service.host.commands import run_vgripd
from vgripd.service.web.bodies import json_body
from vgripd.service.web.setupstate import SetupState

SOLVE_TIMEOUT_S = 600.0
POLL_S = 5.0
MODES = ("eye-in-hand", "eye-to-hand")
#: A hand-eye needs this many sets with a flange pose at least (the command's own minimum).
MIN_POSES = 3
#: The hand-eye step's save of a hand-eye (``SetupRoutes.save_hand_eye``).
SaveHandEye = Callable[[web.Request, dict[str, Any] | None], Awaitable[web.Response]]


def poses_file(manifest: list[dict[str, Any]]) -> str:
    """The kept sets' flange poses as a ``--pose-format matrix`` file (16 numbers, mm, a line
    per set in set order); ``ValueError`` naming the sets without one."""
    missing = [e["set"] for e in manifest if e.get("flange") is None]
    if missing:
        raise ValueError(f"sets {', '.join(map(str, missing))} have no flange pose (the robot's "
                         "pose is read from the camera or a link that reports it, e.g. UR "
                         "RTDE): put them aside, or capture with the robot link up")
    if len(manifest) < MIN_POSES:
        raise ValueError(f"{len(manifest)} set(s) with a flange pose: at least {MIN_POSES}")
    import numpy as np

    from vgripd.geometry.transforms import project_rotation

    lines = ["# T_base_flange per kept set (4x4 row by row, mm), from capture.json"]
    for entry in manifest:
        T = np.asarray(entry["flange"], np.float64)
        # capture.json keeps 6 decimals: the nearest rotation again, to the reader's 1e-6
        T[:3, :3] = project_rotation(T[:3, :3])
        lines.append(" ".join(f"{v:.12g}" for v in T.ravel()) + f"  # set {entry['set']}")
    return "\n".join(lines) + "\n"


def solve_command(mode: str, poses: Path, images: str, board: str, intrinsics: Path,
                  out: Path) -> list[str]:
    return ["calibrate", "handeye", "--mode", mode, "--poses", str(poses), "--pose-format",
            "matrix", "--images", images, "--board", board, "--intrinsics", str(intrinsics),
            "-o", str(out)]


def read_solution(text: str) -> dict[str, Any]:
    """What the page shows of a ``calibrate handeye`` result: the hand-eye table, the RMS, the
    fit check, the warnings and each sample's RMS."""
    data = tomllib.loads(text)
    about = data.get("about", {})
    return {"hand_eye": data.get("calibration", {}).get("hand_eye"), "mode": about.get("mode"),
            "solver": about.get("solver"), "rms_px": about.get("rms_px"),
            "fit_check": about.get("fit_check"), "warnings": about.get("warnings", []),
            "per_sample": about.get("per_sample", []), "samples": about.get("samples")}


class SetupHandEye:
    """The routes above, beside ``SetupRoutes`` (the setup's shared state: its capture,
    folder, progress; ``save``: the hand-eye step's save of a hand-eye)."""

    def __init__(self, setup: SetupState, save: SaveHandEye) -> None:
        self.setup = setup
        self.save = save
        self._solve: dict[str, Any] = {"running": False}
        self._tasks: set[asyncio.Task[Any]] = set()

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_post("/api/setup/handeye/solve", self.start)
        router.add_get("/api/setup/handeye/solve", self.state)
        router.add_post("/api/setup/handeye/use", self.use)

    async def state(self, request: web.Request) -> web.Response:
        if request.query.get("wait") and self._solve.get("running") and self._tasks:
            await asyncio.wait(set(self._tasks), timeout=POLL_S)
        solve = dict(self._solve)
        if solve.get("running"):
            solve["elapsed_s"] = round(time.monotonic() - solve["t0"], 1)
        solve.pop("t0", None)
        return web.json_response(jsonable(solve))

    async def start(self, request: web.Request) -> web.Response:
        self.setup.ctx.config_writer(request)
        body = await json_body(request)
        mode = body.get("mode") if isinstance(body, dict) else None
        if mode not in MODES:
            raise web.HTTPBadRequest(text=f"mode: one of {', '.join(MODES)} (camera on the "
                                          f"flange, or fixed with the board on the flange), "
                                          f"got {mode!r}")
        if self._solve.get("running"):
            raise web.HTTPConflict(text="a hand-eye solve runs")
        state = self.setup.capture
        if state is None or not state.manifest:
            raise web.HTTPConflict(text="no captured sets: capture them on the calibration "
                                        "step (each keeps the robot's flange pose)")
        try:
            text = poses_file(state.manifest)
        except ValueError as err:
            raise web.HTTPConflict(text=f"{state.out}: {err}") from None
        folder = await self.setup.folder()
        progress = await self.setup.progress()
        intrinsics = Path(progress.get("pending_calibration")
                          or self.setup.ctx.reloader().path)
        poses, out = folder / "handeye-poses.txt", folder / "handeye-result.toml"
        await asyncio.to_thread(poses.write_text, text, encoding="utf-8")
        args = solve_command(str(mode), poses, str(state.out / f"{state.names[0]}_*.png"),
                             state.board.spec, intrinsics, out)
        self._solve = {"running": True, "t0": time.monotonic(), "mode": mode,
                       "sets": len(state.manifest), "command": "vgripd " + " ".join(args)}
        task = asyncio.ensure_future(self._run(args, out))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return web.json_response({"running": True, "command": self._solve["command"]})

    async def _run(self, args: list[str], out: Path) -> None:
        t0, command = self._solve["t0"], self._solve.get("command")
        try:
            await asyncio.to_thread(out.unlink, True)
            rc, stdout, stderr = await run_vgripd(args, SOLVE_TIMEOUT_S)
            result = None
            if rc == 0:
                result = read_solution(await asyncio.to_thread(out.read_text,
                                                               encoding="utf-8"))
            self._solve = {"running": False, "ok": rc == 0, "command": command,
                           "seconds": round(time.monotonic() - t0, 1),
                           "output": (stdout + stderr)[-4000:], "result": result}
        except VgripError as err:
            self._solve = {"running": False, "ok": False, "command": command,
                           "output": str(err), "result": None}

    async def use(self, request: web.Request) -> web.Response:
        """The solved hand-eye saved as the hand-eye step's Save saves a typed one."""
        self.setup.ctx.config_writer(request)
        result = self._solve.get("result") or {}
        if not self._solve.get("ok") or not result.get("hand_eye"):
            raise web.HTTPConflict(text="no solved hand-eye: solve it from the captured sets "
                                        "first")
        return await self.save(request, dict(result["hand_eye"]))

    async def close(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
