"""What every route module of the web view is handed: ``WebContext``.

A route parses the request and answers; what it reads or changes lives in a room of its own,
reached through the context by public names only: the daemon (``DaemonView``), the access
check (``Access.require_action``), the config writer (``config_writer``: the daemon's one
judged transaction, ``vgripd.service.host.configtxn``, the only way a route writes a file the daemon
runs on), the jobs this view has seen (``JobHistory``), the camera between jobs
(``CameraTurns``), the image helper process and the event stream.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from aiohttp import web

from vgripd.errors import VgripError
from vgripd.service.jobs.jobrecord import JobRecord
from vgripd.service.ops.reload import Reloader
from vgripd.service.web.access import Access
from vgripd.service.web.daemonview import DaemonView
from vgripd.service.web.images import ImageRenderer
from vgripd.types import ImagePair

log = logging.getLogger(__name__)

#: A page (preview, trial, setup) waits this long for its grab, then answers as for a failed
#: one; the grab itself goes on and is judged by the camera supervisor, as a job's is.
PREVIEW_GRAB_TIMEOUT_S = 2.0
NO_CONFIG_FILE = "this daemon was not started from a config file"


class JobHistory:
    """The last ``maxlen`` jobs of this run as the view shows them (oldest first), and the
    images of the last job that had any (kept for drawing on request, teaching, trials)."""

    def __init__(self, maxlen: int) -> None:
        self._entries: deque[tuple[JobRecord, dict[str, Any]]] = deque(maxlen=maxlen)
        self._last_pair: tuple[int, ImagePair] | None = None

    @property
    def maxlen(self) -> int | None:
        return self._entries.maxlen

    def add(self, record: JobRecord, summary: dict[str, Any], pair: ImagePair | None) -> None:
        self._entries.append((record, summary))
        if pair is not None:
            self._last_pair = (record.job_id, pair)

    def newest_first(self) -> Iterator[tuple[JobRecord, dict[str, Any]]]:
        return reversed(self._entries)

    def summaries(self) -> list[dict[str, Any]]:
        """Every job's summary, newest first."""
        return [s for _, s in self.newest_first()]

    def find(self, job_id: int) -> tuple[JobRecord, dict[str, Any]] | None:
        for record, summary in self.newest_first():
            if record.job_id == job_id:
                return record, summary
        return None

    @property
    def last_pair(self) -> tuple[int, ImagePair] | None:
        """``(job id, images)`` of the last job that had images."""
        return self._last_pair

    def pair_of(self, job_id: int) -> ImagePair | None:
        """The images of ``job_id`` while they are still the last kept."""
        if self._last_pair is not None and self._last_pair[0] == job_id:
            return self._last_pair[1]
        return None

    def last_recipe(self) -> int:
        """The recipe of the last job with images (0 when there is none, or it left the
        history)."""
        if self._last_pair is None:
            return 0
        found = self.find(self._last_pair[0])
        return 0 if found is None else int(found[0].recipe)

    def last_pose(self) -> np.ndarray | None:
        """``T_base_obj`` of the newest job that measured one."""
        for record, _ in self.newest_first():
            if record.result.T_base_obj is not None:
                return record.result.T_base_obj
        return None


class CameraTurns:
    """The camera as the pages take it: only while the daemon is idle (no job, no several-view
    job between views, no hand-eye walk, running), one page at a time."""

    def __init__(self, daemon: DaemonView) -> None:
        self._daemon = daemon
        self._lock = asyncio.Lock()
        self.grabs = 0  # pictures the pages took

    def idle(self) -> bool:
        d = self._daemon
        jobs = d.rooms.jobs
        return (jobs.state.value == "idle" and jobs.views is None and not d.rooms.walks.walking
                and d.run_state.value == "running")

    @contextlib.asynccontextmanager
    async def between_jobs(self) -> AsyncIterator[bool]:
        """Hold the camera for the page (no other page grabs meanwhile); yields whether the
        daemon is idle."""
        async with self._lock:
            yield self.idle()

    async def grab(self, *, fresh: bool = False) -> ImagePair:
        """A pair grabbed now through the camera supervisor (``grab_for_page``: a grab that
        hangs is recovered from as a job's is), waited for ``PREVIEW_GRAB_TIMEOUT_S`` at most
        (``CameraError`` "busy" after that); only inside ``between_jobs`` that found the
        daemon idle. The preview may take a grab another page started; ``fresh`` (trials,
        setup) never does: its frame is exposed after the call."""
        pair = await self._daemon.rooms.cameras.grab_for_page(PREVIEW_GRAB_TIMEOUT_S,
                                                              fresh=fresh)
        self.grabs += 1
        return pair

    async def grab_between_jobs(self) -> ImagePair | None:
        """A pair grabbed now if the daemon is idle; None when a job runs or the camera cannot
        grab."""
        async with self.between_jobs() as idle:
            if not idle:
                return None
            try:
                return await self.grab(fresh=True)
            except (VgripError, TimeoutError) as err:
                log.info("web view: grab for a trial failed: %s", err)
                return None


@dataclass(frozen=True)
class WebContext:
    """What a route module is handed (see the module's docstring)."""

    daemon: DaemonView
    access: Access
    images: ImageRenderer
    jobs: JobHistory
    camera: CameraTurns
    publish: Callable[[str, Any], None]

    @property
    def edit_allowed(self) -> bool:
        return bool(self.daemon.config.status.allow_config_edit)

    def check_action(self, request: web.Request, enabled: bool, key: str) -> None:
        """404 while the action is disabled (naming ``status.<key>``), 403 without the
        token."""
        self.access.require_action(request, enabled, key)

    def check_edit(self, request: web.Request) -> None:
        """The check of an action behind ``status.allow_config_edit``."""
        self.access.require_action(request, self.edit_allowed, "allow_config_edit")

    def reloader(self) -> Reloader:
        """The daemon's config writer; 404 when the daemon runs on no config file."""
        reloader = self.daemon.reloader
        if reloader is None:
            raise web.HTTPNotFound(text=NO_CONFIG_FILE)
        return reloader

    def config_writer(self, request: web.Request) -> Reloader:
        """The config writer for an edit from ``request``: the edit check first (404
        disabled, 403 without the token), then the writer (404 without a config file)."""
        self.check_edit(request)
        return self.reloader()
