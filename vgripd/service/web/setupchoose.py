"""The setup's choices of hardware (docs/setup.md, steps 1 and 5): which cameras, which PLC or
robot link, and what the chosen link asks of the PLC or robot (its contract)::

    GET  /api/setup/cameras/discover     what pylon and Aravis find (``vgripd cameras --json``,
                                         a child process: the SDKs stay out of the daemon), and
                                         the camera types that need no device
    POST /api/setup/cameras/choose       {"type", "cameras": [{"name", "serial" | "ip" |
                                         "user_name"}], "options": {...}}: the ``[camera]``
    GET  /api/setup/link/options         every link type with its example's settings
    POST /api/setup/link/choose          {"links": [{"type", ...}]}: the ``[[links]]``
    GET  /api/setup/link/contract        ?type=T: the register map, the S7 UDT (``vgripd
                                         s7-udt``, a child), the OPC UA nodes a PLC uses, the
                                         robot program brands
    GET  /api/setup/focus                the lens focus where the camera has a focus control
                                         (a GenICam focus feature), else why not
    POST /api/setup/focus                {"value": number}: written between jobs, read back
    POST /api/setup/restart              the files as saved judged once more, then the daemon
                                         stopped between jobs to be started again (systemd;
                                         ``vgripd demo --setup`` itself)

A choice is written through the one config transaction (``vgripd.service.host.configtxn``) into the
include that holds the section (``camera.toml``, ``links.toml`` of ``vgripd init``'s layout),
judged first; a layout whose main file holds the section is refused naming the file. The camera
and the links are built once at start: the transaction saves the judged file and names the keys
that take effect at the next start (``Outcome.restart``); the page says so and offers the
restart: the camera driver (in the worker process, with the live preview's grabs) and the link
servers (their sockets, the PLC's connections) are built once, and swapping them under a
running job machinery is a start's work, not a reload's. The restart judges the files first
(a refused one keeps the daemon running, the reason shown), waits until no job runs, and stops
the daemon with exit status 75, which systemd's ``Restart=on-failure`` starts again.
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.configsnapshot import Snapshot
from vgripd.errors import CameraError, CameraSettingError, VgripError
from vgripd.peer.socket_frames import BRANDS
from vgripd.registry import CONTRACTS, LINKS, load_class
from vgripd.resources import EXAMPLES, shared
from vgripd.serialize import jsonable, toml_from_dict
from vgripd.service.host.commands import run_vgripd
from vgripd.service.host.configtxn import Edit, judge
from vgripd.service.web.bodies import json_body, outcome_response
from vgripd.service.web.context import WebContext
from vgripd.service.web.registers import register_views
from vgripd.service.web.setupsteps import include_for

DISCOVER_TIMEOUT_S = 60.0
#: The restart waits this long for the answer to go out, then at most this long for the
#: running job to end.
RESTART_DELAY_S = 0.3
RESTART_IDLE_S = 600.0
UDT_TIMEOUT_S = 60.0
#: Camera types the page offers: the two GenICam stacks (devices discovered) and the ones that
#: need no device (the learning cell's board camera, rendered images, recorded images).
DEVICE_TYPES = ("pylon", "aravis")
OTHER_TYPES = ("board", "synthetic", "replay")
CAMERA_TYPES = DEVICE_TYPES + OTHER_TYPES
#: What picks a device (``[[camera.cameras]]``: exactly one of them).
DEVICE_KEYS = ("serial", "ip", "user_name")
MAX_CAMERAS = 8
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")
#: Link types driving a robot program (the rest: a PLC reads the map or the nodes).
ROBOT_LINKS = ("robot_socket", "ur_rtde")
REGISTER_LINKS = ("modbus_server", "modbus_client", "modbus_rtu", "s7")


class ChoiceError(ValueError):
    """A choice the page sent that cannot be written; the text names the field."""


def camera_section(body: Any, current: dict[str, Any]) -> dict[str, Any]:
    """The ``[camera]`` table of the page's choice. The running camera's settings stay when
    the type stays (exposure, gain, ROI, trigger); another type starts from its defaults with
    a software trigger. ``ChoiceError`` naming the field."""
    if not isinstance(body, dict):
        raise ChoiceError('a JSON object {"type": ..., "cameras": [...]}')
    kind = body.get("type")
    if kind not in CAMERA_TYPES:
        raise ChoiceError(f"camera.type: one of {', '.join(CAMERA_TYPES)}, got {kind!r}")
    options = body.get("options", {})
    if not isinstance(options, dict) or {"type", "cameras"} & set(options):
        raise ChoiceError("camera options: a table of the type's settings (without type and "
                          "cameras)")
    table: dict[str, Any] = dict(current) if current.get("type") == kind else {"type": kind}
    table.update(options)
    table["type"] = kind
    if kind in DEVICE_TYPES:
        table.setdefault("trigger", "software")
        table["cameras"] = _device_entries(body.get("cameras"))
    elif body.get("cameras"):
        raise ChoiceError(f"camera.cameras: a {kind} camera has no devices to name")
    return table


def _device_entries(cameras: Any) -> list[dict[str, str]]:
    if not isinstance(cameras, list) or not 1 <= len(cameras) <= MAX_CAMERAS:
        raise ChoiceError(f"camera.cameras: 1 to {MAX_CAMERAS} cameras, each "
                          '{"name": ..., "serial" | "ip" | "user_name": ...}')
    entries, names = [], set()
    for k, cam in enumerate(cameras):
        where = f"camera.cameras[{k}]"
        if not isinstance(cam, dict):
            raise ChoiceError(f"{where}: a table with name and serial, ip or user_name")
        name = cam.get("name")
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise ChoiceError(f"{where}.name: a letter, then up to 31 letters, digits, _ or - "
                              f"(got {name!r})")
        if name in names:
            raise ChoiceError(f"{where}.name: {name!r} names two cameras")
        names.add(name)
        keys = [key for key in DEVICE_KEYS if cam.get(key)]
        if len(keys) != 1 or not isinstance(cam[keys[0]], str) or len(cam[keys[0]]) > 128:
            raise ChoiceError(f"{where}: exactly one of serial, ip, user_name (text)")
        entries.append({"name": name, keys[0]: cam[keys[0]]})
    return entries


def links_section(body: Any) -> list[dict[str, Any]]:
    """The ``[[links]]`` of the page's choice: each a table with a known ``type``; its
    settings are judged with the config (the driver's options)."""
    links = body.get("links") if isinstance(body, dict) else None
    if not isinstance(links, list) or not 1 <= len(links) <= 8:
        raise ChoiceError('{"links": [{"type": ..., settings ...}]}: 1 to 8 links')
    for k, link in enumerate(links):
        if not isinstance(link, dict) or link.get("type") not in LINKS:
            got = link.get("type") if isinstance(link, dict) else link
            raise ChoiceError(f"links[{k}].type: one of {', '.join(sorted(LINKS))}, got {got!r}")
    return [dict(link) for link in links]


def section_edit(prefix: str, key: str, value: Any) -> Edit:
    """``key`` set to ``value`` in the include that holds ``prefix`` (or the layout's)."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        target = include_for(snapshot, prefix)
        data = tomllib.loads(snapshot.text(target))
        data[key] = value
        return {target: snapshot.encoded(target, toml_from_dict(data))}
    return edit


def link_defaults() -> dict[str, dict[str, Any]]:
    """Each link type's settings in the first example config that uses it (the page's form
    starts from them: the settings a cell of that kind needs, commented in the example)."""
    out: dict[str, dict[str, Any]] = {}
    folder = shared(EXAMPLES)
    for path in sorted(folder.iterdir(), key=lambda p: p.name):
        if not path.name.endswith(".toml"):
            continue
        for link in tomllib.loads(path.read_text(encoding="utf-8")).get("links", []):
            if isinstance(link, dict) and link.get("type") in LINKS:
                out.setdefault(link["type"], {**link, "example": path.name})
    for kind in LINKS:
        out.setdefault(kind, {"type": kind})
    return out


def link_kind(kind: str) -> str:
    if kind in ROBOT_LINKS:
        return "robot"
    return "registers" if kind in REGISTER_LINKS else "nodes"


def opcua_nodes() -> dict[str, Any]:
    """The OPC UA nodes a PLC uses (the driver's list); ``{"unavailable": why}`` when the
    link's package is not installed."""
    try:
        nodes = load_class(CONTRACTS, "link contract", "opcua")()
    except VgripError as err:
        return {"unavailable": str(err)}
    return dict(nodes)


class SetupChoices:
    """The routes above, beside ``SetupRoutes``."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self._pending: set[Any] = set()

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/setup/cameras/discover", self.discover)
        router.add_post("/api/setup/cameras/choose", self.choose_camera)
        router.add_get("/api/setup/link/options", self.link_options)
        router.add_post("/api/setup/link/choose", self.choose_links)
        router.add_get("/api/setup/link/contract", self.contract)
        router.add_post("/api/setup/restart", self.restart)
        router.add_get("/api/setup/focus", self.focus)
        router.add_post("/api/setup/focus", self.focus)

    def _uncalibrated(self) -> bool:
        """A cell the daemon runs uncalibrated may stay so through a camera or link choice
        (its first steps come before the calibration); a calibrated one must stay calibrated."""
        d = self.ctx.daemon
        return any(number not in d.untaught for number in d.recipe_problems)

    async def discover(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        rc, out, err = await run_vgripd(["cameras", "--json"], DISCOVER_TIMEOUT_S)
        try:
            found = json.loads(out) if rc == 0 else None
        except ValueError:
            found = None
        if not isinstance(found, dict):
            raise web.HTTPBadGateway(text=f"vgripd cameras --json failed (exit {rc}): "
                                          f"{(err or out).strip()[-500:]}")
        current = self.ctx.daemon.config.camera.model_dump(mode="json", exclude_none=True)
        return web.json_response(jsonable({**found, "types": list(CAMERA_TYPES),
                                           "current": current}))

    async def choose_camera(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        body = await json_body(request)
        current = self.ctx.daemon.config.camera.model_dump(mode="json", exclude_none=True)
        try:
            table = camera_section(body, current)
        except ChoiceError as err:
            raise web.HTTPBadRequest(text=str(err)) from None
        outcome = await reloader.write(section_edit("camera.", "camera", table),
                                       f"web {request.remote}", "setup: cameras",
                                       untaught_ok=True, uncalibrated_ok=self._uncalibrated())
        return outcome_response(outcome, camera=table)

    async def link_options(self, request: web.Request) -> web.Response:
        import asyncio

        defaults = await asyncio.to_thread(link_defaults)
        running = [{"type": link.type, **link.options()} for link in self.ctx.daemon.config.links]
        return web.json_response(jsonable({
            "types": [{"type": t, "kind": link_kind(t), "defaults": defaults[t]}
                      for t in sorted(LINKS)],
            "running": running}))

    async def choose_links(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        body = await json_body(request)
        try:
            links = links_section(body)
        except ChoiceError as err:
            raise web.HTTPBadRequest(text=str(err)) from None
        outcome = await reloader.write(section_edit("links", "links", links),
                                       f"web {request.remote}", "setup: link",
                                       untaught_ok=True, uncalibrated_ok=self._uncalibrated())
        return outcome_response(outcome, links=links)

    async def contract(self, request: web.Request) -> web.Response:
        kind = request.query.get("type", "")
        if kind not in LINKS:
            raise web.HTTPBadRequest(text=f"type: one of {', '.join(sorted(LINKS))}")
        answer: dict[str, Any] = {"type": kind, "kind": link_kind(kind)}
        if kind in REGISTER_LINKS:
            answer["registers"] = register_views(self.ctx.daemon.rooms.links.links)
            answer["map_doc"] = "docs/registers.md"
        if kind == "s7":
            answer["s7_udt"] = await self._s7_udt()
        if kind == "opcua":
            import asyncio

            answer["opcua"] = await asyncio.to_thread(opcua_nodes)
        if kind in ROBOT_LINKS:
            # The robot socket's program per brand (vgripd robot-program); a UR on RTDE runs
            # the URScript of robots/urscript (docs/ur_rtde.md), no program to fill in.
            answer["brands"] = [] if kind == "ur_rtde" else sorted(BRANDS)
            answer["vendor"] = self.ctx.daemon.config.output.vendor
        return web.json_response(jsonable(answer))

    async def focus(self, request: web.Request) -> web.Response:
        """The camera's focus control (the driver's ``focus``): read (GET), or a value written
        between jobs and read back (POST, the token). Applied live, not saved: the page says
        how to keep it."""
        value = None
        if request.method == "POST":
            self.ctx.config_writer(request)
            body = await json_body(request)
            value = body.get("value") if isinstance(body, dict) else None
            if isinstance(value, bool) or not isinstance(value, int | float) or value != value:
                raise web.HTTPBadRequest(text=f'{{"value": number}}: the focus, got {value!r}')
        camera = self.ctx.daemon.rooms.cameras.camera
        async with self.ctx.camera.between_jobs() as idle:
            if not idle:
                raise web.HTTPConflict(text="a job runs: the focus is read and set only "
                                            "between jobs; try again")
            try:
                answer = await camera.focus(value)
            except CameraSettingError as err:
                raise web.HTTPBadRequest(text=str(err)) from None
            except CameraError as err:
                raise web.HTTPServiceUnavailable(text=f"the camera cannot take it now: {err}"
                                                 ) from None
        if value is not None and not answer.get("available"):
            raise web.HTTPConflict(text=f"no focus to set: {answer.get('reason')}")
        if value is not None:
            answer["note"] = ("applied live, not saved: to keep it at the next start, add it "
                              "to [camera] features (e.g. features = {"
                              f"{answer['cameras'][0]['feature']} = {value:g}}})")
        return web.json_response(jsonable(answer))

    async def restart(self, request: web.Request) -> web.Response:
        """The daemon started again on its files as saved, so a chosen camera or link runs:
        judged first as a write is (refused: 422, the daemon keeps running), then stopped
        between jobs once this answer is out."""
        import asyncio

        reloader = self.ctx.config_writer(request)
        snapshot = await asyncio.to_thread(Snapshot.read, reloader.path)
        problem = await judge(snapshot, untaught_ok=True, uncalibrated_ok=self._uncalibrated())
        if problem:
            return web.json_response({"restarting": False, "message": (
                f"refused, the daemon keeps running: {problem}")}, status=422)
        source = f"web {request.remote}"

        async def later() -> None:
            await asyncio.sleep(RESTART_DELAY_S)  # the answer goes out first
            await reloader.restart_between_jobs(source, RESTART_IDLE_S)

        task = asyncio.ensure_future(later())
        self._pending.add(task)
        task.add_done_callback(self._pending.discard)
        return web.json_response({"restarting": True, "message": (
            "judged: restarting between jobs with the files as saved (under systemd the "
            "service comes back by itself, Restart=on-failure; vgripd run by hand ends with "
            "exit status 75: start it again)")})

    async def _s7_udt(self) -> dict[str, Any]:
        """``vgripd s7-udt`` for the running config's s7 link, else with its defaults."""
        args = ["s7-udt"]
        reloader = self.ctx.daemon.reloader
        if reloader is not None and any(link.type == "s7" for link in self.ctx.daemon.config.links):
            args += ["-c", str(reloader.path)]
        rc, out, err = await run_vgripd(args, UDT_TIMEOUT_S)
        return {"command": "vgripd " + " ".join(args), "ok": rc == 0,
                "source": out if rc == 0 else (err or out).strip()[-2000:]}
