"""Live camera pictures in the web view (docs/web.md, "Live cameras").

::

    GET /api/cameras                 the cameras and the last preview's figures
    GET /api/cameras/{j}/preview.jpg camera j's live picture (over-exposure red, the marks the
                                     finder sees circled)

A preview grabs through the same camera as the jobs (in the worker process), so it is taken
only while the daemon is idle (no job, no several-view job between views, no hand-eye walk), at
most ``MAX_PREVIEW_FPS`` grabs a second whatever the number of pages watching (they share the last
picture), one at a time, and drawn in the image helper process. During a job a page gets the
last picture again (its ``X-Vgripd-Preview-Age-S`` header says how old). A trigger that arrives
while a preview grab runs waits for that grab (one grab, a few tens of ms with a real camera):
the preview never starts while a job runs, but the camera is one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from typing import Any

from aiohttp import web

from vgripd.errors import VgripError

log = logging.getLogger(__name__)

#: Preview grabs a second, all pages together.
MAX_PREVIEW_FPS = 2.0
#: A preview grab that takes longer is given up (the camera is then the job's problem).
PREVIEW_GRAB_TIMEOUT_S = 2.0


class PreviewRoutes:
    """The routes above for one ``WebServer``."""

    def __init__(self, server: Any) -> None:
        self.server = server
        self._lock = asyncio.Lock()
        self._last: tuple[float, list[bytes], list[dict[str, Any]]] = (0.0, [], [])
        self.grabs = 0

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/cameras", self.cameras)
        router.add_get("/api/cameras/{j:\\d+}/preview.jpg", self.preview)

    def _idle(self) -> bool:
        d = self.server.daemon
        state = getattr(d, "state", None)
        return (getattr(state, "value", "") == "idle" and getattr(d, "views", None) is None
                and not getattr(getattr(d, "walks", None), "walking", False)  # its camera
                and getattr(d, "run_state", None) is not None
                and d.run_state.value == "running")

    async def cameras(self, request: web.Request) -> web.Response:
        t, jpegs, figures = self._last
        return web.json_response({"count": len(jpegs), "figures": figures,
                                  "age_s": None if not t else time.monotonic() - t,
                                  "max_fps": MAX_PREVIEW_FPS, "grabs": self.grabs})

    @contextlib.asynccontextmanager
    async def between_jobs(self) -> AsyncIterator[bool]:
        """Hold the camera for the page (no preview grab meanwhile); yields whether the
        daemon is idle (no job, no several-view job between views)."""
        async with self._lock:
            yield self._idle()

    async def grab_between_jobs(self) -> Any:
        """A pair grabbed now if the daemon is idle (the tuning trial's fresh grab); None when
        a job runs or the camera cannot grab."""
        async with self._lock:
            if not self._idle():
                return None
            try:
                pair = await self.server.daemon.camera.grab(PREVIEW_GRAB_TIMEOUT_S)
            except (VgripError, TimeoutError) as err:
                log.info("web view: grab for a trial failed: %s", err)
                return None
            self.grabs += 1
            return pair

    async def _refresh(self) -> None:
        """A new picture when the last is older than a frame period and nothing runs."""
        async with self._lock:
            if time.monotonic() - self._last[0] < 1.0 / MAX_PREVIEW_FPS or not self._idle():
                return
            from vgripd.service.web.images import render_preview

            camera = self.server.daemon.camera
            try:
                pair = await camera.grab(PREVIEW_GRAB_TIMEOUT_S)
            except (VgripError, TimeoutError) as err:
                log.info("web view: preview grab failed: %s", err)
                self._last = (time.monotonic(), self._last[1], self._last[2])
                return
            self.grabs += 1
            jpegs, figures = await self.server.images.call(render_preview, list(pair.views))
            self._last = (time.monotonic(), jpegs, figures)

    async def preview(self, request: web.Request) -> web.Response:
        text = request.match_info["j"]
        if len(text) > 2:
            raise web.HTTPNotFound(text="no such camera")
        await self._refresh()
        t, jpegs, figures = self._last
        j = int(text)
        if j >= len(jpegs):
            raise web.HTTPServiceUnavailable(text="no preview yet (a job runs, or the camera "
                                                  "cannot grab)")
        return web.Response(body=jpegs[j], content_type="image/jpeg", headers={
            "Cache-Control": "no-store", "X-Vgripd-Preview-Age-S": f"{time.monotonic() - t:.2f}",
            "X-Vgripd-Focus": f"{figures[j]['focus']:.1f}",
            "X-Vgripd-Saturated-Share": f"{figures[j]['saturated_share']:.4f}"})
