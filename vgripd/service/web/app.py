"""The operator web view, its JSON API and ``/metrics``: an aiohttp application served on the
daemon's own event loop (``WebServer``).

Why aiohttp: it is asyncio from the ground up, so it runs inside the daemon's loop beside the
links (``AppRunner`` + ``TCPSite``, no second loop, no thread, no ASGI server to embed), has
server-sent events as a plain streamed response, and a test client. What it serves is answered
from memory (the daemon's snapshot, the job history kept here, cached JPEGs); what costs CPU
(drawing and encoding images) runs in a helper process (``images.ImageRenderer``) and what
touches the disk (support bundle, recorded images) runs off the loop, so a browser never makes
the PLC wait.

Routes (docs/web.md)::

    GET  /                           the page (static/index.html, vanilla JS, no build step)
    GET  /api/status  (/status)      the daemon's status JSON (``vgripd status`` reads it)
    GET  /api/jobs                   the last ``status.history`` jobs, newest first
    GET  /api/jobs/{id}              one job
    GET  /api/jobs/{id}/image/{left|right}.jpg   annotated, downscaled JPEG
    GET  /api/jobs/{id}/image/view{j}.jpg        camera j of a multi-camera cell (from 0)
    GET  /api/events                 server-sent events: ``status``, ``job``, ``links``, ``walk``
    GET  /api/config                 the loaded config, secrets redacted
    GET  /api/registers              each register link's map as its peer reads it, decoded
    GET  /metrics                    Prometheus text format
    POST /api/trigger[?recipe=N]     test trigger      (status.allow_trigger + token)
    GET  /api/support-bundle         zip download      (status.allow_support_bundle + token)
    GET  /login, POST /login         the token form; sets the session cookie (guarded reads)
    GET  /api/audit, GET|POST /api/tuning, POST /api/reload   commissioning (``commission``)
    GET  /api/teach, POST /api/teach/{shot,clear,save}        teaching (``teaching``)
    GET  /api/cameras, GET /api/cameras/{j}/preview.jpg       live cameras (``preview``)
    GET  /api/cameras/settings, POST /api/cameras/{j}/settings exposure, gain (``camsettings``)
    GET  /handeye/{plan,walk}, /api/handeye, POST /api/handeye/...  walked hand-eye (``walking``)
    GET  /setup, /api/setup..., POST /api/setup/...            the guided setup (``setup``)

Security model (``access.Access``, docs/web.md): read-only by default and bound to 127.0.0.1;
the config refuses a non-loopback bind without ``status.token``, and such a bind needs the
token on every route unless ``status.public_read``. A foreign ``Host:`` gets 421; every answer
carries the security headers. An action answers 404 while disabled (naming its ``status``
switch) and 403 without the token
(``Authorization: Bearer <token>`` only, compared in constant time: the cookie is not enough).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.errors import VgripError
from vgripd.redaction import REDACTED, redact
from vgripd.serialize import jsonable, toml_from_dict
from vgripd.service.jobs.jobrecord import JobRecord
from vgripd.service.links.webtrigger import WEB_LINK, WebTriggerLink
from vgripd.service.web.access import Access, ServerLogLimit
from vgripd.service.web.bundle import write_bundle
from vgripd.service.web.camsettings import CameraSettingsRoutes
from vgripd.service.web.commission import CommissionRoutes
from vgripd.service.web.context import CameraTurns, JobHistory, WebContext
from vgripd.service.web.daemonview import DaemonView
from vgripd.service.web.events import (
    KEEPALIVE_S,
    RETRY_MS,
    EventHub,
    StatusFeed,
    frame,
    stream_caps,
)
from vgripd.service.web.guard import GuardedSite, make_guard
from vgripd.service.web.images import ImageRenderer
from vgripd.service.web.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE
from vgripd.service.web.metrics import Metrics
from vgripd.service.web.preview import PreviewRoutes
from vgripd.service.web.registers import register_views
from vgripd.service.web.setup import SetupRoutes
from vgripd.service.web.teaching import TeachRoutes
from vgripd.service.web.walking import WalkRoutes
from vgripd.service.worker.recorder import dict_from_result, recorded_job
from vgripd.types import ImagePair

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
LOG_LINES = 2000
SHUTDOWN_TIMEOUT_S = 1.0
LOG_FLUSH_S = 10.0
# Job ids and camera numbers in a path: more digits than this is no job (and int() of
# thousands of digits raises).
MAX_ID_DIGITS = 18
# The loggers whose lines about bad requests are rate-limited while the view runs.
SERVER_LOGGERS = ("aiohttp.server", "aiohttp.web")


class StatusEndpointError(VgripError):
    """The web view cannot listen (port in use, address not on this host): the daemon does not
    start (exit 1, like a link that cannot listen)."""


def _id(text: str) -> int:
    """A job id or camera number from the path (the route admits digits only): 404 when it
    cannot be one."""
    if not text.isascii() or not text.isdigit() or len(text) > MAX_ID_DIGITS:
        raise web.HTTPNotFound(text="no such job in the history")
    return int(text)


class LogRing(logging.Handler):
    """The last ``LOG_LINES`` log lines, for the support bundle (journald keeps the rest)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: deque[str] = deque(maxlen=LOG_LINES)
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.lines.append(self.format(record))


def job_summary(record: JobRecord, t_wall: float, images: bool) -> dict[str, Any]:
    """A finished job as the view shows it (JSON data; a message that quotes a camera URL
    does not show its credentials)."""
    r = redact(dict_from_result(record.result))
    return {
        "id": record.job_id, "link": record.link, "seq": record.seq, "recipe": record.recipe,
        "status": r["status"], "status_code": r["status_code"], "message": r["message"],
        "published": None if record.published is None else record.published.name,
        "cycle_ms": record.cycle_ms, "t_wall": t_wall,
        "target": r["target"], "residuals": r["residuals"], "timings_ms": r["timings_ms"],
        "features_used": r.get("features_used", list(record.result.features_used)),
        "features_missing": r.get("features_missing", list(record.result.features_missing)),
        "images": images, "stereo": None, "views": [],
    }


def view_names(config: Any, pair: ImagePair) -> list[list[str]]:
    """``[url side, caption]`` of each image of a job: left (and right), or every camera of a
    multi-camera cell as ``view<j>`` with its name from ``calibration.cameras`` (a cell of
    ``vision.views``: its views ``view1`` .. ``viewN``, as ``scene.views_config`` names them)."""
    cameras = config.calibration.cameras if config.calibration is not None else None
    if cameras is None and config.vision.views == 1:
        return [[side, side] for side in ("left", "right")[:len(pair.views)]]
    names = ([c.name for c in cameras] if cameras is not None
             else [f"view{k + 1}" for k in range(config.vision.views)])
    return [[f"view{j}", names[j] if j < len(names) else f"image {j}"]
            for j in range(len(pair.views))]


class WebServer:
    """The web view of one daemon, on its loop. ``start`` listens (``StatusEndpointError`` in
    one line), ``close`` stops; ``port`` is the bound port."""

    def __init__(self, daemon: DaemonView) -> None:
        self.daemon = daemon
        st = daemon.config.status
        self.host = st.host
        self._requested_port = st.port
        if st.token == REDACTED:
            raise StatusEndpointError(
                f"status.token is {REDACTED!r} (a recorded or bundled config): set the real "
                f"token, or [status] enabled = false")
        self.access = Access(st)
        self._log_limit = ServerLogLimit(self.access.ratelog)
        self._allow_trigger = st.allow_trigger
        self._allow_bundle = st.allow_support_bundle
        self.jobs = JobHistory(st.history)
        self.events = EventHub()
        self.feed = StatusFeed(daemon, self.events, self.status_document)
        self.metrics = Metrics(daemon, self.access)
        self.images = ImageRenderer(daemon.config)
        self.camera = CameraTurns(daemon)
        self.context = WebContext(daemon, self.access, self.images, self.jobs, self.camera,
                                  self.events.publish)
        self.logs = LogRing()
        self._runner: web.AppRunner | None = None
        self._port = 0
        self._io: ThreadPoolExecutor | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._t_start_wall = time.time()
        self.app = self._make_app()

    # --- lifecycle ----------------------------------------------------------------------

    @property
    def port(self) -> int:
        """The bound port (the real one when configured as 0)."""
        if not self._port:
            raise RuntimeError("web view not started")
        return self._port

    async def start(self) -> None:
        # connections: the daemon's gate at accept, HTTP read timeouts (guard.py)
        self.guard = make_guard(self.daemon)
        self.events.anonymous, self.events.holders = stream_caps(self.guard.gate.cap)
        self.app.middlewares.append(self.guard.middleware)
        runner = web.AppRunner(self.app, access_log=None, handle_signals=False,
                               shutdown_timeout=SHUTDOWN_TIMEOUT_S)
        await runner.setup()
        site = GuardedSite(runner, self.host, self._requested_port, self.guard)
        try:
            await site.start()
        except OSError as err:
            await runner.cleanup()
            reason = os.strerror(err.errno) if err.errno else str(err)
            raise StatusEndpointError(
                f"status endpoint cannot listen on {self.host}:{self._requested_port}: {reason} "
                f"(set [status] port = another port or 0 for any free one, [status] host, or "
                f"[status] enabled = false)") from None
        self._runner = runner
        self._port = site.port
        self.guard.start()
        self._io = ThreadPoolExecutor(1, thread_name_prefix="vgripd-web-io")
        self.daemon.rooms.jobs.listeners.append(self._on_job)
        logging.getLogger().addHandler(self.logs)
        for name in SERVER_LOGGERS:
            logging.getLogger(name).addFilter(self._log_limit)
        self._spawn(self.feed.run())
        self._spawn(self._flush_logs())
        log.info("web view: http://%s:%d/ (status JSON at /api/status, metrics at /metrics)",
                 self.host, self.port)

    async def close(self) -> None:
        with contextlib.suppress(ValueError):
            self.daemon.rooms.jobs.listeners.remove(self._on_job)
        logging.getLogger().removeHandler(self.logs)
        for name in SERVER_LOGGERS:
            logging.getLogger(name).removeFilter(self._log_limit)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.setup.close()
        self.events.close()
        if self._runner is not None:
            await self.guard.stop()
            await self._runner.cleanup()
            self._runner = None
        self.images.close()
        if self._io is not None:
            self._io.shutdown(wait=True, cancel_futures=True)
            self._io = None

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # --- what the daemon tells us ---------------------------------------------------------

    def _on_job(self, pair: ImagePair | None, record: JobRecord) -> None:
        """Job listener (on the loop, after the result was published): history, metrics,
        the event to every page, and the images handed to the helper process."""
        summary = job_summary(record, time.time(), images=pair is not None)
        summary["stereo"] = None if pair is None else pair.is_stereo
        summary["views"] = [] if pair is None else view_names(self.daemon.config, pair)
        self.jobs.add(record, summary, pair)
        self.metrics.observe(record)
        # Drawn at once while a page watches; otherwise on request (the last pair is kept for
        # that, older jobs come from the recorder), so an unwatched cell spends no CPU on
        # pictures.
        if pair is not None and self.events.clients:
            self.images.submit(record.job_id, pair, record.result, eager=True)
        self.events.publish("job", summary)

    async def _flush_logs(self) -> None:
        """Report held rate-limited log lines whose minute is over (a burst that stopped)."""
        while True:
            await asyncio.sleep(LOG_FLUSH_S)
            self.access.ratelog.flush()

    # --- the application ------------------------------------------------------------------

    def _make_app(self) -> web.Application:
        app = web.Application(client_max_size=64 * 1024, middlewares=[self.access.middleware])
        app.on_response_prepare.append(self.access.add_headers)
        r = app.router
        r.add_get("/", self._index)
        r.add_get("/login", self.access.login_form)
        r.add_post("/login", self.access.login)
        r.add_route("*", "/status", self._status)
        r.add_get("/api/status", self._status)
        r.add_get("/api/jobs", self._jobs)
        r.add_get("/api/jobs/{id:\\d+}", self._job)
        r.add_get("/api/jobs/{id:\\d+}/image/{side:left|right|view\\d+}.jpg", self._image)
        r.add_get("/api/events", self._events)
        r.add_get("/api/config", self._config)
        r.add_get("/api/registers", self._registers)
        r.add_get("/metrics", self._metrics)
        r.add_route("*", "/api/trigger", self._trigger)
        r.add_get("/api/support-bundle", self._bundle)
        ctx = self.context
        CommissionRoutes(ctx).add(r)
        TeachRoutes(ctx).add(r)
        self.previews = PreviewRoutes(ctx)
        self.previews.add(r)
        self.camera_settings = CameraSettingsRoutes(ctx)
        self.camera_settings.add(r)
        WalkRoutes(ctx).add(r)
        self.setup = SetupRoutes(ctx)
        self.setup.add(r)
        r.add_static("/static/", STATIC)
        return app

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html",
                                headers={"Cache-Control": "no-cache"})

    def status_document(self) -> dict[str, Any]:
        """The status JSON of ``/api/status`` and the pushed ``status`` event (redacted)."""
        status = self.daemon.snapshot()
        status["web"] = {"trigger": self._allow_trigger, "support_bundle": self._allow_bundle,
                         "config_edit": self.daemon.config.status.allow_config_edit,
                         "history": self.jobs.maxlen}
        result: dict[str, Any] = redact(jsonable(status))
        return result

    async def _status(self, request: web.Request) -> web.Response:
        if request.method != "GET":
            return web.json_response({"error": "only GET /api/status"}, status=404)
        return web.Response(text=json.dumps(self.status_document(), indent=1),
                            content_type="application/json")

    async def _jobs(self, request: web.Request) -> web.Response:
        return web.json_response(self.jobs.summaries())

    async def _job(self, request: web.Request) -> web.Response:
        found = self.jobs.find(_id(request.match_info["id"]))
        if found is None:
            raise web.HTTPNotFound(text="no such job in the history")
        return web.json_response(found[1])

    async def _image(self, request: web.Request) -> web.Response:
        job_id = _id(request.match_info["id"])
        name = request.match_info["side"]
        side = {"left": 0, "right": 1}.get(name) if not name.startswith("view") else _id(
            name[4:])
        assert side is not None  # the route admits nothing else
        fut = self.images.cached(job_id)
        if fut is None:
            found = self.jobs.find(job_id)
            if found is None or not found[1]["images"]:
                raise web.HTTPNotFound(text="no images for this job")
            source: ImagePair | str | None = self.jobs.pair_of(job_id)
            rec = self.daemon.rooms.jobs.recorder
            if source is None and rec is not None:
                loop = asyncio.get_running_loop()
                source = await loop.run_in_executor(self._io, recorded_job, Path(rec.folder),
                                                    job_id, self._t_start_wall)
            if source is None:
                raise web.HTTPNotFound(text="the job's images are no longer kept (enable "
                                            "[record] to open older jobs)")
            fut = self.images.submit(job_id, source, found[0].result)
            assert fut is not None
        try:
            jpegs = await asyncio.shield(fut)
        except Exception as err:
            raise web.HTTPNotFound(text=f"images cannot be drawn: {err}") from None
        if side >= len(jpegs):
            raise web.HTTPNotFound(text="no right image (mono camera)" if name == "right"
                                   else f"no image {name}: the job has {len(jpegs)}")
        return web.Response(body=jpegs[side], content_type="image/jpeg",
                            headers={"Cache-Control": "private, max-age=3600"})

    async def _events(self, request: web.Request) -> web.StreamResponse:
        address = request.remote or "?"
        client = self.events.admit(address, self.access.holds_token(request))
        if client is None:
            self.access.ratelog.info(address, "streams", "web view: event stream refused to "
                                     "%s: too many open without the token", address)
            raise web.HTTPServiceUnavailable(text="too many pages open (log in with the token "
                                                  "at /login to be served always)")
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache"})
        try:
            await resp.prepare(request)
            # the state now, then every change (``StatusFeed``)
            await resp.write(f"retry: {RETRY_MS}\n\n".encode()
                             + frame("status", self.status_document()))
            while True:
                try:
                    async with asyncio.timeout(KEEPALIVE_S):
                        event = await client.queue.get()
                except TimeoutError:
                    event = b": keepalive\n\n"
                if event is None:
                    break
                await resp.write(event)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.events.leave(client)
        return resp

    async def _config(self, request: web.Request) -> web.Response:
        data = self.daemon.config.model_dump(mode="json", exclude_none=True)
        return web.json_response(redact(data))

    async def _registers(self, request: web.Request) -> web.Response:
        return web.json_response(jsonable(register_views(self.daemon.rooms.links.links)))

    async def _metrics(self, request: web.Request) -> web.Response:
        return web.Response(body=self.metrics.render(),
                            headers={"Content-Type": METRICS_CONTENT_TYPE})

    # --- guarded actions ------------------------------------------------------------------

    async def _trigger(self, request: web.Request) -> web.Response:
        self.access.require_action(request, self._allow_trigger, "allow_trigger")
        if request.method != "POST":
            raise web.HTTPMethodNotAllowed(request.method, ["POST"])
        link = self.daemon.rooms.links.links.get(WEB_LINK)
        if not isinstance(link, WebTriggerLink):
            raise web.HTTPNotFound(text="no web trigger link")
        text = request.query.get("recipe", "0")
        if not text.isascii() or not text.isdigit() or len(text) > 5 or int(text) > 65535:
            raise web.HTTPBadRequest(text=f"recipe={text!r}: a recipe number is 0 .. 65535")
        log.info("web view: test trigger (recipe %s) from %s", text, request.remote)
        timeout_s = self.daemon.config.daemon.job_timeout_s + 5.0
        try:
            result = await link.trigger(timeout_s, int(text))
        except (TimeoutError, RuntimeError) as err:
            raise web.HTTPServiceUnavailable(text=f"no answer: {err!r}") from None
        return web.json_response(jsonable(dict_from_result(result)))

    async def _bundle(self, request: web.Request) -> web.StreamResponse:
        self.access.require_action(request, self._allow_bundle, "allow_support_bundle")
        log.info("web view: support bundle for %s", request.remote)
        loop = asyncio.get_running_loop()
        status = self.daemon.snapshot()
        parts = {
            "status.json": json.dumps(redact(jsonable(status)), indent=1),
            "jobs.json": json.dumps(self.jobs.summaries(), indent=1),
            "config.toml": toml_from_dict(redact(jsonable(
                self.daemon.config.model_dump(mode="json", exclude_none=True)))),
            "metrics.txt": self.metrics.render().decode(),
            "log.txt": "\n".join(redact(list(self.logs.lines))) + "\n",
        }
        rec = self.daemon.rooms.jobs.recorder
        folder = None if rec is None else Path(rec.folder)
        n_jobs = self.daemon.config.status.bundle_jobs
        file = await loop.run_in_executor(self._io, write_bundle, parts, folder, n_jobs)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        resp = web.StreamResponse(headers={
            "Content-Type": "application/zip",
            "Content-Disposition": f'attachment; filename="vgripd-support-{stamp}.zip"'})
        try:
            await resp.prepare(request)
            while chunk := await loop.run_in_executor(self._io, file.read, 1 << 20):
                await resp.write(chunk)
            await resp.write_eof()
        finally:
            file.close()
        return resp
