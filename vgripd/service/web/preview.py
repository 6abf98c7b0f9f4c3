"""Live camera pictures in the web view (docs/web.md, "Live cameras").

::

    GET /api/cameras                 the cameras and the last preview's figures
    GET /api/cameras/{j}/preview.jpg camera j's live picture (over-exposure red, the marks the
                                     finder sees circled)

A preview grabs through the same camera as the jobs (in the worker process), through the
camera supervisor (``CameraSupervisor.grab_for_page``), so it is taken only while the daemon is
idle (no job, no several-view job between views, no hand-eye walk), at most ``MAX_PREVIEW_FPS``
grabs a second whatever the number of pages watching (they share the last picture), one at a
time, and drawn in the image helper process. During a job a page gets the last picture again
(its ``X-Vgripd-Preview-Age-S`` header says how old). A page waits for its grab
``context.PREVIEW_GRAB_TIMEOUT_S`` at most, then answers as for a failed grab (the last picture,
or 503 "camera busy"); the grab goes on, is judged hung only as a job's is (by
``daemon.job_timeout_s``) and is taken by the next preview. A trigger that arrives while a
preview grab runs waits for that grab (one grab, a few tens of ms with a real camera): the
preview never starts while a job runs, but the camera is one. The camera's turns between jobs
(shared with the trials, the setup and the camera settings) are ``context.CameraTurns``.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from aiohttp import web

from vgripd.errors import VgripError
from vgripd.service.web.context import WebContext

log = logging.getLogger(__name__)

#: Preview grabs a second, all pages together.
MAX_PREVIEW_FPS = 2.0


class PreviewRoutes:
    """The routes above for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self._last: tuple[float, list[bytes], list[dict[str, Any]]] = (0.0, [], [])
        self._failed = ""  # why the last preview grab gave no picture ("" when it gave one)

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/cameras", self.cameras)
        router.add_get("/api/cameras/{j:\\d+}/preview.jpg", self.preview)

    async def cameras(self, request: web.Request) -> web.Response:
        t, jpegs, figures = self._last
        return web.json_response({"count": len(jpegs), "figures": figures,
                                  "age_s": None if not t else time.monotonic() - t,
                                  "max_fps": MAX_PREVIEW_FPS, "grabs": self.ctx.camera.grabs})

    async def _refresh(self) -> None:
        """A new picture when the last is older than a frame period and nothing runs."""
        async with self.ctx.camera.between_jobs() as idle:
            if time.monotonic() - self._last[0] < 1.0 / MAX_PREVIEW_FPS or not idle:
                return
            from vgripd.service.web.images import render_preview

            try:
                pair = await self.ctx.camera.grab()
            except (VgripError, TimeoutError) as err:
                log.info("web view: preview grab failed: %s", err)
                self._last = (time.monotonic(), self._last[1], self._last[2])
                self._failed = str(err)
                return
            self._failed = ""
            jpegs, figures = await self.ctx.images.call(render_preview, list(pair.views))
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
                                                  "cannot grab)" + (f": {self._failed}"
                                                                    if self._failed else ""))
        return web.Response(body=jpegs[j], content_type="image/jpeg", headers={
            "Cache-Control": "no-store", "X-Vgripd-Preview-Age-S": f"{time.monotonic() - t:.2f}",
            "X-Vgripd-Focus": f"{figures[j]['focus']:.1f}",
            "X-Vgripd-Saturated-Share": f"{figures[j]['saturated_share']:.4f}"})
