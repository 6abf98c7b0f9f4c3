"""The guided setup in the browser (docs/setup.md): cameras, calibration, hand-eye, object,
link, test pick, one page (``/setup``) over these routes::

    GET  /setup                          the page (static/setup.html, vanilla JS)
    GET  /api/setup                      the steps, what is done (kept in the state folder:
                                         resumable), the cell as it runs, the capture so far
    GET  /api/setup/check                vgripd check of the running files, each finding under
                                         its step (token: it runs a child process)
    POST /api/setup/done                 {"step", "done"}: mark a step done or open again
    POST /api/setup/calib/grab           {"board", "keep", "auto"}: grab (between jobs), the
                                         board's corners in every camera, the set judged as
                                         vgripd capture judges it, kept when worth it
    GET  /api/setup/live/{n}/{k}.jpg     camera k of the last grab n, corners or marks drawn
    POST /api/setup/calib/run            vgripd calibrate intrinsics/stereo/cameras on the kept
                                         sets (one, two, more cameras), in a child
    GET  /api/setup/calib[?wait=1]       the calibration: running (seconds), or its result
    POST /api/setup/calib/drop           {"sets": [n, ...]}: sets put aside (outliers)
    POST /api/setup/calib/accept         the result kept to go live with the hand-eye
    POST /api/setup/handeye              {"translation_mm", "rotvec_rad"}: a fixed camera's pose
                                         (of a cameras result: the reference camera's)
    /api/setup/handeye/solve, .../use    the hand-eye from the captured sets' flange poses
                                         (``setuphandeye.py``)
    POST /api/setup/object/find          the marks both cameras see, in the base frame (the
                                         templates taught here found again)
    POST /api/setup/object/template      {"box": [x, y, w, h], "label"}: a region of the last
                                         find's left image taught as a template, found in
                                         both images, offered as a mark
    POST /api/setup/object/save          {"name", "marks": [ids]}: the object from them, judged
    GET  /api/setup/robot-program.zip    ?brand=B: vgripd robot-program for the link (child)
    /api/setup/cameras/..., /api/setup/link/...   choosing the cameras and the link, the
                                         link's contract (``setupchoose.py``)

Every POST (and the check) needs ``status.allow_config_edit`` and the token, as tuning,
teaching and the walk pages do; every config write is one transaction of the daemon's config
writer (``vgripd.service.host.configtxn``): judged as ``vgripd check`` judges it, then applied and
saved, or refused with the includes untouched. Image work (corners, marks, a capture folder read
back) runs in the image helper process, the calibration and the check in child processes
(``vgripd.service.host.commands``): the loop keeps answering the PLC.
"""

from __future__ import annotations

import asyncio
import io
import logging
import secrets
import shutil
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.calib.capturesets import Capture, camera_names, put_aside
from vgripd.config import DEMO_CALIBRATION
from vgripd.errors import VgripError
from vgripd.serialize import jsonable
from vgripd.service.host.commands import run_vgripd
from vgripd.service.links.protocol import robot_pose_now
from vgripd.service.web import setupimages
from vgripd.service.web.bodies import json_body, outcome_response
from vgripd.service.web.context import WebContext
from vgripd.service.web.registers import register_views
from vgripd.service.web.setupchoose import SetupChoices
from vgripd.service.web.setuphandeye import SetupHandEye
from vgripd.service.web.setupobject import SetupObject
from vgripd.service.web.setupstate import SetupState
from vgripd.service.web.setupsteps import (
    DEFAULT_BOARD,
    STEP_IDS,
    STEPS,
    calibration_command,
    calibration_edit,
    cameras_edit,
    flange_text,
    hand_eye_values,
    parse_check,
    pending_view,
    placed_cameras,
    read_result,
)

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
CHECK_TIMEOUT_S = 120.0
CALIBRATE_TIMEOUT_S = 900.0
PROGRAM_TIMEOUT_S = 60.0
CALIB_POLL_S = 5.0
#: Sets the calibration needs at least (the command refuses fewer than 3 pairs).
MIN_SETS = 3


class SetupRoutes:
    """The routes above for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self.state = SetupState(ctx)
        self._calib: dict[str, Any] = {"running": False}
        self._tasks: set[asyncio.Task[Any]] = set()
        self.instance = secrets.token_hex(6)
        self.solver = SetupHandEye(self.state, self.save_hand_eye)  # from the captured sets

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/setup", self.page)
        router.add_get("/api/setup", self.show)
        router.add_get("/api/setup/check", self.check)
        router.add_post("/api/setup/done", self.done)
        router.add_post("/api/setup/calib/grab", self.grab)
        router.add_get("/api/setup/live/{n:\\d+}/{k:\\d+}.jpg", self.live)
        router.add_post("/api/setup/calib/run", self.calibrate)
        router.add_get("/api/setup/calib", self.calibration)
        router.add_post("/api/setup/calib/drop", self.drop)
        router.add_post("/api/setup/calib/accept", self.accept)
        router.add_post("/api/setup/handeye", self.hand_eye)
        SetupObject(self.state).add(router)  # the object step (setupobject.py)
        self.solver.add(router)
        router.add_get("/api/setup/robot-program.zip", self.robot_program)
        SetupChoices(self.ctx).add(router)  # the cameras and the link chosen (setupchoose.py)

    # --- shared ---------------------------------------------------------------------------

    def _names(self, n_views: int) -> list[str]:
        return camera_names(self.ctx.daemon.config, n_views)

    # --- reads ----------------------------------------------------------------------------

    async def page(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "setup.html", headers={"Cache-Control": "no-cache"})

    async def show(self, request: web.Request) -> web.Response:
        config = self.ctx.daemon.config
        progress = await self.state.progress()
        cal = config.calibration
        cam = config.camera
        options = cam.model_dump(mode="json", exclude_none=True)
        capture = None
        if self.state.capture is not None:
            capture = self._capture_view(self.state.capture)
        return web.json_response(jsonable({
            "steps": [{"id": s, "title": t, "done": s in progress["done"]} for s, t in STEPS],
            "instance": self.instance,  # another after a restart
            "edit": bool(config.status.allow_config_edit),
            "trigger": bool(config.status.allow_trigger),
            "camera": {"type": cam.type,
                       "describe": self.ctx.daemon.rooms.cameras.camera.describe(),
                       "options": {k: v for k, v in options.items() if k != "type"}},
            "calibrated": cal is not None,
            "hand_eye": None if cal is None else cal.hand_eye.model_dump(mode="json",
                                                                         exclude_none=True),
            "learning_hand_eye": self._learning_hand_eye(),
            "pending_calibration": progress.get("pending_calibration") is not None,
            "pending": await asyncio.to_thread(_pending, progress.get("pending_calibration")),
            "board": progress.get("board") or options.get("board") or DEFAULT_BOARD,
            "object": {"name": config.object.name, "definition": config.object.definition,
                       "features": [f.name for f in config.object.features]},
            "vendor": config.output.vendor,
            "links": self.ctx.daemon.snapshot().get("links"),
            "registers": register_views(self.ctx.daemon.rooms.links.links),
            "capture": capture,
        }))

    def _learning_hand_eye(self) -> dict[str, Any] | None:
        """Where the learning cell's cameras are (the board camera renders through the demo
        cell's hand-eye): offered as the hand-eye step's values there, never elsewhere."""
        if self.ctx.daemon.config.camera.type != "board":
            return None
        return DEMO_CALIBRATION.hand_eye.model_dump(mode="json", exclude_none=True)

    async def check(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        path = str(self.ctx.reloader().path)
        rc, out, err = await run_vgripd(["check", "--running", "--untaught-ok", "-c", path],
                                        CHECK_TIMEOUT_S)
        ok, findings = parse_check(rc, out, err, path)
        step = request.query.get("step")
        chosen = [f for f in findings if step is None or f.step == step]
        return web.json_response({"ok": ok, "summary": next(
            (line for line in out.splitlines() if line.startswith("OK ")), ""),
            "findings": [f.as_dict() for f in chosen], "all": len(findings)})

    async def done(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        body = await json_body(request)
        step = body.get("step") if isinstance(body, dict) else None
        if step not in STEP_IDS:
            raise web.HTTPBadRequest(text=f"step: one of {', '.join(STEP_IDS)}")
        await self.state.mark(step, done=bool(body.get("done", True)))
        return web.json_response({"step": step, "done": bool(body.get("done", True))})

    async def live(self, request: web.Request) -> web.Response:
        n, k = request.match_info["n"], request.match_info["k"]
        live = self.state.live
        if len(n) > 9 or len(k) > 2 or int(n) != self.state.grab_n or int(k) >= len(live):
            raise web.HTTPNotFound(text="only the last grab's pictures are kept")
        return web.Response(body=live[int(k)], content_type="image/jpeg",
                            headers={"Cache-Control": "no-store"})

    # --- calibration capture ----------------------------------------------------------------

    def _capture_view(self, state: Capture) -> dict[str, Any]:
        return {"board": state.board.spec, "sets": len(state.kept), "folder": str(state.out),
                "cameras": [{"name": n, "summary": c.summary(), "missing": c.missing(),
                             "grid": c.grid, "cells": sorted(c.cells),
                             "tilts": sorted(c.tilts)}
                            for n, c in zip(state.names, state.coverage, strict=True)],
                "manifest": [{"set": e["set"], "added": e.get("added", ""),
                              "flange": flange_text(e.get("flange"))}
                             for e in state.manifest]}

    async def _account(self, spec: str, views: list[Any]) -> Capture:
        """The capture account of the setup folder for ``spec`` (read back once)."""
        names = self._names(len(views))
        if self.state.capture is not None and self.state.capture.board.spec == spec and (
                self.state.capture.names == names):
            return self.state.capture
        folder = await self.state.folder() / "calib"
        if self.state.capture is not None and self.state.capture.board.spec != spec:
            await asyncio.to_thread(shutil.rmtree, folder, True)  # a new board starts over
        sizes = [(int(v.shape[1]), int(v.shape[0])) for v in views]
        self.state.capture = await self.ctx.images.call(setupimages.resume_capture, spec,
                                                     str(folder), names, sizes)
        return self.state.capture

    async def grab(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        body = await json_body(request)
        if not isinstance(body, dict):
            raise web.HTTPBadRequest(text='a JSON object {"board": ..., "keep": ..., "auto": ...}')
        spec = str(body.get("board") or DEFAULT_BOARD)[:80]
        try:
            from vgripd.calib.boards import Board

            spec = Board.parse(spec).spec
        except VgripError as err:
            raise web.HTTPBadRequest(text=f"board: {err}") from None
        async with self.state.lock:
            pair = await self.ctx.camera.grab_between_jobs()
            if pair is None:
                raise web.HTTPConflict(text="a job runs (or the camera cannot grab): try again")
            views = list(pair.views)
            state = await self._account(spec, views)
            jpegs, dets = await self.ctx.images.call(setupimages.board_corners, views,
                                                        spec, state.names)
            ok, why = state.judge(dets)
            if body.get("keep") and not ok and all(d is not None for d in dets):
                ok, why = True, "taken on request"
            kept = None
            if ok and (body.get("keep") or body.get("auto")):
                flange = pair.T_base_flange  # the camera's (or its request's), else a link's
                links = self.ctx.daemon.rooms.links.links
                if flange is None and (now := await robot_pose_now(links)):
                    flange = now[1]
                kept = await asyncio.to_thread(state.keep, tuple(views), dets, why,
                                               pair.t_mono_ns, flange)
                await asyncio.to_thread(state.write_manifest)
            grab_n = self.state.show(jpegs)
            progress = await self.state.progress()
            if progress.get("board") != spec:
                progress["board"] = spec
                await self.state.save_progress(progress)
        return web.json_response({
            "grab": grab_n, "seen": [d is not None for d in dets], "worth": ok,
            "why": why, "kept": kept, "images": self.state.live_urls(),
            "capture": self._capture_view(state)})

    # --- calibration --------------------------------------------------------------------------

    async def calibration(self, request: web.Request) -> web.Response:
        """The calibration's state; ``?wait=1`` answers when it ends, or after
        ``CALIB_POLL_S`` (the page asks again at once: no timer of its own to slow down)."""
        if request.query.get("wait") and self._calib.get("running") and self._tasks:
            await asyncio.wait(set(self._tasks), timeout=CALIB_POLL_S)
        calib = dict(self._calib)
        if calib.get("running"):
            calib["elapsed_s"] = round(time.monotonic() - calib["t0"], 1)
        calib.pop("t0", None)
        return web.json_response(jsonable(calib))

    async def calibrate(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        if self._calib.get("running"):
            raise web.HTTPConflict(text="a calibration runs")
        state = self.state.capture
        if state is None or len(state.kept) < MIN_SETS:
            raise web.HTTPConflict(text=f"capture at least {MIN_SETS} sets first (kept: "
                                        f"{0 if state is None else len(state.kept)})")
        body = await json_body(request) if request.body_exists else {}
        kind = body.get("kind", "auto") if isinstance(body, dict) else body
        out = await self.state.folder() / "rig-result.toml"
        try:
            args = calibration_command(state.names, state.out, state.board.spec, out,
                                       str(kind))
        except ValueError as err:
            raise web.HTTPBadRequest(text=str(err)) from None
        self._calib = {"running": True, "t0": time.monotonic(), "sets": len(state.kept),
                       "command": "vgripd " + " ".join(args)}
        task = asyncio.ensure_future(self._run_calibration(args, out))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return web.json_response({"running": True, "command": self._calib["command"]})

    async def _run_calibration(self, args: list[str], out: Path) -> None:
        t0 = self._calib["t0"]
        try:
            await asyncio.to_thread(out.unlink, True)
            rc, stdout, stderr = await run_vgripd(args, CALIBRATE_TIMEOUT_S)
            result = None
            if rc == 0:
                text = await asyncio.to_thread(out.read_text, encoding="utf-8")
                result = read_result(text)
            self._calib = {"running": False, "ok": rc == 0, "seconds": round(
                time.monotonic() - t0, 1), "command": self._calib.get("command"),
                "output": (stdout + stderr)[-4000:], "result": result}
        except VgripError as err:
            self._calib = {"running": False, "ok": False, "output": str(err), "result": None}

    async def drop(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        body = await json_body(request)
        sets = body.get("sets") if isinstance(body, dict) else None
        if not (isinstance(sets, list) and all(isinstance(s, int) for s in sets)):
            raise web.HTTPBadRequest(text='{"sets": [set numbers]}')
        async with self.state.lock:
            state = self.state.capture
            if state is None:
                raise web.HTTPConflict(text="no capture")
            moved = await asyncio.to_thread(put_aside, state.out, set(sets))
            self.state.capture = None  # read back without them at the next grab
            self._calib = {"running": False}
        return web.json_response({"dropped": moved})

    async def accept(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        result = await self.state.folder() / "rig-result.toml"
        if not self._calib.get("ok") or not result.exists():
            raise web.HTTPConflict(text="no calibration result to accept: run it first")
        found = self._calib.get("result") or {}
        # The hand-eye belongs to one camera model (its [about] fingerprint): a new rig goes
        # live together with the cameras' pose, confirmed or measured again (next step).
        progress = await self.state.progress()
        progress["pending_calibration"] = str(result)
        progress["done"]["calibration"] = time.time()
        await self.state.save_progress(progress)
        if found.get("kind") == "cameras" and not found.get("usable"):
            reference = found.get("reference")
            message = (f"accepted: {len(found.get('cameras') or [])} cameras, their poses "
                       f"relative to {reference} (placed in no base frame yet). Next step, "
                       f"hand-eye: {reference}'s pose in the robot base frame places every "
                       f"camera (T_base_camera = T_base_{reference} @ T_{reference}_camera) "
                       "and writes them as [[calibration.cameras]], judged as one transaction")
        elif found.get("kind") == "cameras":
            message = ("accepted: the cameras are placed in the base frame by the calibration "
                       f"({found.get('base_frame')}); the next step (hand-eye) writes them as "
                       "[[calibration.cameras]], judged as one transaction")
        else:
            message = ("accepted: it goes live with the cameras' pose (next step, hand-eye), "
                       "which belongs to the camera model")
        return web.json_response({"applied": False, "pending": True, "message": message,
                                  "next": pending_view(await asyncio.to_thread(
                                      result.read_text, encoding="utf-8"))})

    async def hand_eye(self, request: web.Request) -> web.Response:
        """A fixed camera's ``T_base_camera`` typed on the page (for an accepted ``calibrate
        cameras`` result the reference camera's, none when the command placed them)."""
        self.ctx.config_writer(request)
        body = await json_body(request)
        waiting = await asyncio.to_thread(_pending, (await self.state.progress()).get(
            "pending_calibration"))
        if waiting is not None and waiting.get("placed"):
            return await self.save_hand_eye(request, None)
        try:
            hand_eye = hand_eye_values(body)
        except ValueError as err:
            raise web.HTTPBadRequest(text=str(err)) from None
        return await self.save_hand_eye(request, hand_eye)

    async def save_hand_eye(self, request: web.Request,
                            hand_eye: dict[str, Any] | None) -> web.Response:
        """The cameras' pose saved with the accepted calibration as one transaction; for an
        accepted ``calibrate cameras`` result ``hand_eye`` (fixed) is the reference camera's
        pose, which places every camera (None: the command placed them)."""
        reloader = self.ctx.config_writer(request)
        progress = await self.state.progress()
        pending = progress.get("pending_calibration")
        text = None
        if pending:
            text = await asyncio.to_thread(Path(pending).read_text, encoding="utf-8")
        elif self.ctx.daemon.config.calibration is None:
            raise web.HTTPConflict(text="calibrate the cameras first (step Calibration)")
        waiting = pending_view(text)
        if waiting is not None and waiting["kind"] == "cameras":
            assert text is not None
            if hand_eye is not None and hand_eye.get("mounting") != "fixed":
                raise web.HTTPUnprocessableEntity(text=(
                    "calibration.cameras: a robot-mounted hand-eye does not place a cameras "
                    "result here; run vgripd calibrate cameras --hand-eye NAME=FILE "
                    "(docs/calibration-multicamera.md)"))
            try:
                edit = cameras_edit(placed_cameras(
                    text, None if hand_eye is None else hand_eye["T_base_camera"]))
            except VgripError as err:
                raise web.HTTPUnprocessableEntity(text=str(err)) from None
        else:
            edit = calibration_edit(text, hand_eye)
        outcome = await reloader.write(edit, f"web {request.remote}", "setup: hand-eye",
                                       untaught_ok=True)
        if outcome.applied:
            progress = await self.state.progress()
            progress.pop("pending_calibration", None)
            progress["done"]["handeye"] = time.time()
            await self.state.save_progress(progress)
        return outcome_response(outcome)

    # --- the link -------------------------------------------------------------------------------

    async def robot_program(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        brand = request.query.get("brand", "")
        if not brand.isascii() or not brand.isalpha() or len(brand) > 20:
            raise web.HTTPBadRequest(text="brand: a robot brand (vgripd robot-program --help)")
        path = str(self.ctx.reloader().path)
        with tempfile.TemporaryDirectory(prefix="vgripd-program-") as tmp:
            rc, out, err = await run_vgripd(["robot-program", "--brand", brand, "-c", path,
                                             "-o", tmp], PROGRAM_TIMEOUT_S)
            if rc != 0:
                raise web.HTTPUnprocessableEntity(text=(err or out).strip()[-2000:])
            data = await asyncio.to_thread(_zip_folder, Path(tmp))
        return web.Response(body=data, content_type="application/zip", headers={
            "Content-Disposition": f'attachment; filename="vgripd-{brand}.zip"'})

    async def close(self) -> None:
        await self.solver.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)


def _pending(path: str | None) -> dict[str, Any] | None:
    """``pending_view`` of the accepted result file (None when there is none, or it is gone)."""
    if not path:
        return None
    try:
        return pending_view(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _zip_folder(folder: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                z.write(path, path.relative_to(folder))
    return buf.getvalue()
