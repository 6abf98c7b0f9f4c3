"""The walked hand-eye calibration from the web view (docs/web.md, "Walked hand-eye
calibration"): plan, dry run, walk, watch, solve, accept.

::

    GET  /handeye/plan, /handeye/walk   the two pages (static, vanilla JS)
    GET  /api/handeye                   the walk (as /api/status "walk") and the last plan
    GET  /api/handeye/plan.png          the last plan's drawing (board outlines in the image)
    POST /api/handeye/plan              compute a plan: dry run, or saved with "save" (token)
    POST /api/handeye/walk/start        walk a plan over a link, {"plan", "link"} (token)
    POST /api/handeye/walk/stop         stop it; the record stays, start again resumes (token;
                                        ?by=command: the command's Ctrl-C, as the message says)
    POST /api/handeye/solve             solve the record in a child process (token)
    POST /api/handeye/accept            write the solved hand-eye into the config, reload (token)

Every action needs the token and ``status.allow_config_edit`` (as teaching and tuning), and a
daemon started from a config file (``vgripd run``). The plan is computed by ``vgripd calibrate
handeye plan`` in a child process (the loop keeps serving the PLC); its refusals come back with
the command's reason. A plan file is a ``.toml`` inside the config's folder.

Accepting writes ``[calibration.hand_eye]`` (and the solved file's ``[about]``: residuals,
leave-one-out spread, plan condition, camera-model fingerprint) into the one included file that
holds the hand-eye now: one transaction of the config writer (``vgripd.service.host.configtxn``, as
the tuning save), judged as ``vgripd check`` judges it; refused, no include is touched. A saved
plan is written by the same writer (``write_file``), in turn with the config writes. A taught
reference not measured with the new hand-eye would be wrong with it: the accept is refused,
naming its file, unless told to set such references aside (``{"set_aside_references":
true}``, ``vgripd.service.web.stale``); then jobs end NOT_CALIBRATED until the reference is
taught again.
"""

from __future__ import annotations

import asyncio
import json
import logging
import tempfile
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.calib.boards import Board
from vgripd.calib.handeye.plan import board_size_problem, plan_inside
from vgripd.config import read_config_data
from vgripd.configsnapshot import Snapshot
from vgripd.errors import VgripError
from vgripd.serialize import jsonable, toml_from_dict
from vgripd.service.host.commands import run_vgripd
from vgripd.service.host.configtxn import Edit, EditRefused
from vgripd.service.web.bodies import json_body
from vgripd.service.web.commission import TuningError, holding_include
from vgripd.service.web.context import WebContext
from vgripd.service.web.stale import set_aside, stale_references

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
#: The planner in its child process gets this long.
PLAN_TIMEOUT_S = 120.0
#: Who stopped a walk (``POST /api/handeye/walk/stop?by=...``), as the walk's message says it.
STOPPED_BY = {"web": "stopped from the web view",
              "command": "stopped by Ctrl-C of vgripd calibrate handeye walk --running"}
#: Form fields of a plan request and the command's flags.
PLAN_FIELDS = {"mode": "--mode", "board": "--board", "around": "--around", "box": "--box",
               "distance": "--distance", "count": "--count", "board_offset": "--board-offset",
               "pose_format": "--pose-format"}
MAX_FIELD = 200


def hand_eye_target(config_path: Path, files: Mapping[str, bytes] | None = None) -> Path:
    """The included file that sets ``calibration.hand_eye`` now (``TuningError`` unless one)."""
    return holding_include(config_path, "calibration.hand_eye.",
                           "vgripd calibrate handeye -o writes such a file; include it", files)


def with_hand_eye(text: str, solved: str) -> str:
    """``text`` (the include holding the hand-eye) with the solved ``[calibration.hand_eye]``;
    a file of the hand-eye alone takes the solved file's ``[about]`` too (its fingerprint)."""
    data, new = tomllib.loads(text), tomllib.loads(solved)
    calibration = data.setdefault("calibration", {})
    calibration["hand_eye"] = new["calibration"]["hand_eye"]
    if set(calibration) == {"hand_eye"} and set(data) <= {"calibration", "about"}:
        return solved
    return toml_from_dict(data)


def accepted_calibration(config_path: Path, include_text: str,
                         files: Mapping[str, bytes] | None = None) -> dict[str, Any]:
    """The config's ``[calibration]`` with the solved hand-eye (as the include will hold it)."""
    data = read_config_data(config_path, files=files)
    calibration: dict[str, Any] = dict(data.get("calibration", {}))
    calibration["hand_eye"] = tomllib.loads(include_text)["calibration"]["hand_eye"]
    return calibration


def accept_edit(solved_file: str, aside: bool, found: dict[str, Any]) -> Edit:
    """The solved hand-eye written into its include, and the taught references it makes wrong
    set aside when told (``aside``), as an edit of the config writer; ``found`` gets the
    ``target``, the ``stale`` reference files and a ``refusal`` (the edit is refused then)."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        main = snapshot.main
        solved = Path(solved_file).read_text(encoding="utf-8")
        target = hand_eye_target(main, snapshot.files)
        after = with_hand_eye(snapshot.text(target), solved)
        stale, in_main = stale_references(
            main, accepted_calibration(main, after, snapshot.files), snapshot.files)
        found.update(target=target, stale=stale)
        refusal = stale_refusal(main, stale, in_main, aside)
        if refusal is not None:
            found["refusal"] = refusal
            raise EditRefused(refusal)
        texts = {target: after}
        for path in stale:  # set aside, as told (in the hand-eye's own text if it is one)
            texts[path] = set_aside(texts.get(path, snapshot.text(path)))
        return {path: snapshot.encoded(path, text) for path, text in texts.items()}
    return edit


def stale_refusal(config_path: Path, stale: list[Path], in_main: bool,
                  aside: bool) -> str | None:
    """Why the accept must not go on with these taught references; None when it may."""
    if in_main:
        return (f"{config_path} holds a taught reference itself: the new hand-eye makes it "
                "wrong, and the page never writes the main config file; move it into an "
                "include (vgripd teach -o writes one) or remove it, then accept; nothing "
                "written")
    if stale and not aside:
        names = ", ".join(p.name for p in stale)
        return (f"the taught reference in {names} was not measured with the new hand-eye: "
                "accepting it makes that reference wrong (the order is: cameras/rig -> "
                "hand-eye -> teach). Accept with 'set the taught references aside' (their "
                "files are backed up, jobs end NOT_CALIBRATED (31) until you teach again), or "
                "keep the hand-eye you have; nothing written")
    return None


def plan_command(form: dict[str, Any], config_path: Path, drawing: Path,
                 output: Path | None) -> list[str]:
    """The ``vgripd calibrate handeye plan`` arguments of a form (``TuningError`` for a
    field that is no short text or number); each value joined to its flag (``--box=250 30``),
    so that a value like ``--draw=/x`` stays a value."""
    words = ["calibrate", "handeye", "plan", "-c", str(config_path), "--json", "--draw",
             str(drawing)]
    for field, flag in PLAN_FIELDS.items():
        value = form.get(field)
        if value is None or value == "":
            continue
        if isinstance(value, list):
            value = " ".join(str(v) for v in value)
        if not isinstance(value, str | int | float) or isinstance(value, bool) or len(
                str(value)) > MAX_FIELD:
            raise TuningError(f"plan: {field} = {str(value)[:40]!r}: a number or short text "
                              f"(at most {MAX_FIELD} characters)")
        if any(ord(c) < 32 or ord(c) == 127 for c in str(value)):
            raise TuningError(f"plan: {field} = {value!r}: a control character (such as NUL)")
        words.append(f"{flag}={value}")  # one word: a value is never read as an option
    words += ["-o", str(output)] if output is not None else ["--dry-run"]
    return words


def planned_board_problem(form: dict[str, Any], config: Any) -> str | None:
    """Why the form's board cannot be planned at its distance with the running camera model
    (``board_size_problem``), judged before the planner is spawned; None when it may be, or
    when the form cannot say (the planner then names what is wrong)."""
    if config.calibration is None or not isinstance(form.get("board"), str):
        return None
    try:
        board = Board.parse(form["board"])
        distance = float(form.get("distance"))  # type: ignore[arg-type]
    except (VgripError, TypeError, ValueError):
        return None
    left = config.calibration.left
    return board_size_problem(board.cols, board.rows, board.pitch_mm, distance, left.width,
                              left.height, left.fx, left.fy)


def _reason(stderr: str, rc: int) -> str:
    lines = [ln.removeprefix("error: ") for ln in stderr.strip().splitlines() if ln.strip()]
    return "\n".join(lines[-20:]) or f"the command exited with {rc}"


class WalkRoutes:
    """The routes above for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self.last_plan: dict[str, Any] | None = None
        self.drawing: bytes | None = None
        self._lock = asyncio.Lock()
        ctx.daemon.rooms.walks.listeners.append(lambda data: ctx.publish("walk", data))

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/handeye/plan", self._page("handeye-plan.html"))
        router.add_get("/handeye/walk", self._page("handeye-walk.html"))
        router.add_get("/api/handeye", self.show)
        router.add_get("/api/handeye/plan.png", self.plan_png)
        router.add_post("/api/handeye/plan", self.plan)
        router.add_post("/api/handeye/walk/start", self.start)
        router.add_post("/api/handeye/walk/stop", self.stop)
        router.add_post("/api/handeye/solve", self.solve)
        router.add_post("/api/handeye/accept", self.accept)

    @staticmethod
    def _page(name: str) -> Any:
        async def page(request: web.Request) -> web.StreamResponse:
            return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-cache"})
        return page

    async def _body(self, request: web.Request) -> dict[str, Any]:
        body = await json_body(request)
        if not isinstance(body, dict):
            raise web.HTTPBadRequest(text="a JSON object")
        return body

    async def show(self, request: web.Request) -> web.Response:
        config = self.ctx.daemon.config
        links = [{"index": i, "type": s.type} for i, s in enumerate(config.links)]
        return web.json_response(jsonable({"walk": self.ctx.daemon.rooms.walks.snapshot(),
                                           "plan": self.last_plan, "links": links,
                                           "vendor": config.output.vendor}))

    async def plan_png(self, request: web.Request) -> web.Response:
        if self.drawing is None:
            raise web.HTTPNotFound(text="no plan drawn yet")
        return web.Response(body=self.drawing, content_type="image/png",
                            headers={"Cache-Control": "no-cache"})

    async def plan(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        config_path = reloader.path
        form = await self._body(request)
        save = form.get("save") or None
        async with self._lock:
            try:
                output = None if save is None else plan_inside(config_path, str(save))
                if output is not None and output.exists() and b"[plan]" not in \
                        output.read_bytes()[:4096]:
                    raise TuningError(f"{output}: exists and is no plan: choose another name")
                board_problem = planned_board_problem(form, self.ctx.daemon.config)
                if board_problem:
                    raise TuningError(f"plan: {board_problem}; the planner was not started")
                with tempfile.TemporaryDirectory(prefix="vgripd-plan-") as tmp:
                    drawing = Path(tmp) / "plan.png"
                    planned = None if output is None else Path(tmp) / "plan.toml"
                    words = plan_command(form, config_path, drawing, planned)
                    rc, out, err = await run_vgripd(words, PLAN_TIMEOUT_S)
                    self.drawing = drawing.read_bytes() if drawing.exists() else None
                    if rc == 0 and output is not None and planned is not None:
                        # in turn with the config writes, atomically, never through a link
                        await reloader.write_file(output, planned.read_bytes())
            except (VgripError, OSError) as err_:
                return web.json_response({"refused": str(err_)}, status=422)
        try:
            summary = json.loads(out) if out.strip() else {}
        except ValueError:
            summary = {}
        summary["drawing"] = self.drawing is not None
        if rc != 0:
            summary["refused"] = _reason(err, rc)
            log.info("web view: hand-eye plan refused (%s): %s", request.remote,
                     summary["refused"])
            return web.json_response(summary, status=422)
        summary["saved"] = None if output is None else output.name
        self.last_plan = summary
        log.info("web view: hand-eye plan (%s) from %s%s", summary.get("mode"), request.remote,
                 f", saved to {output}" if output else ", dry run")
        return web.json_response(summary)

    async def start(self, request: web.Request) -> web.Response:
        config_path = self.ctx.config_writer(request).path
        body = await self._body(request)
        plan, link = body.get("plan"), body.get("link", 0)
        if not isinstance(plan, str) or not isinstance(link, int) or isinstance(link, bool):
            raise web.HTTPBadRequest(text='{"plan": "name.toml", "link": 0}')
        try:
            data = self.ctx.daemon.rooms.walks.start(config_path, plan, link)
        except VgripError as err:
            return web.json_response({"refused": str(err)}, status=409)
        log.info("web view: walk of %s started on link %d from %s", plan, link, request.remote)
        return web.json_response(jsonable(data))

    async def stop(self, request: web.Request) -> web.Response:
        self.ctx.check_edit(request)
        by = request.query.get("by", "web")
        if by not in STOPPED_BY:
            raise web.HTTPBadRequest(text=f"by={by[:40]!r}: one of {', '.join(STOPPED_BY)}")
        why = f"{STOPPED_BY[by]} ({request.remote})"
        log.info("web view: walk %s", why)
        return web.json_response(jsonable(await self.ctx.daemon.rooms.walks.stop(why)))

    async def solve(self, request: web.Request) -> web.Response:
        config_path = self.ctx.config_writer(request).path
        try:
            data = await self.ctx.daemon.rooms.walks.solve(config_path)
        except VgripError as err:
            return web.json_response({"refused": str(err)}, status=409)
        ok = bool(data["solution"] and data["solution"]["ok"])
        return web.json_response(jsonable(data), status=200 if ok else 422)

    async def accept(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        solution = self.ctx.daemon.rooms.walks.solution
        if not solution or not solution.get("ok"):
            raise web.HTTPConflict(text="nothing solved to accept: solve the walk first")
        body = await self._body(request) if request.body_exists else {}
        aside = body.get("set_aside_references") is True
        source = f"web {request.remote}"
        found: dict[str, Any] = {}
        async with self._lock:
            outcome = await reloader.write(
                accept_edit(solution["file"], aside, found), source,
                f"hand-eye from the walk {Path(solution['walk']).name}"
                + (" (taught references set aside)" if aside else ""),
                untaught_ok=aside)
        stale: list[Path] = found.get("stale", [])
        if "refusal" in found:
            return web.json_response({"refused": found["refusal"], "stale_references":
                                      [p.name for p in stale]}, status=409)
        target = found.get("target")
        return web.json_response({**outcome.as_dict(), "file": target and target.name,
                                  "set_aside": [p.name for p in stale]},
                                 status=200 if outcome.applied else 422)
