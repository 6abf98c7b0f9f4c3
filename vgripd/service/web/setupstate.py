"""What the guided setup's steps share (``setup.py`` and the step modules beside it): the
web view's context, the calibration capture, one lock over grabs and capture changes, the last
grab's pictures, and the setup's own folder with its progress file (written through the
config writer, in turn with every config write).
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.calib.capturesets import Capture
from vgripd.service.web.context import WebContext
from vgripd.service.web.setupsteps import dump_progress, load_progress, state_dir


class SetupState:
    """The setup's shared state for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self.capture: Capture | None = None
        self.lock = asyncio.Lock()  # one grab or capture change at a time
        self.grab_n = 0
        self.live: list[bytes] = []

    def show(self, jpegs: list[bytes]) -> int:
        """``jpegs`` become the last grab's pictures (``/api/setup/live/{n}/{k}.jpg``); their
        grab number ``n``."""
        self.grab_n += 1
        self.live = jpegs
        return self.grab_n

    def live_urls(self) -> list[str]:
        return [f"/api/setup/live/{self.grab_n}/{k}.jpg" for k in range(len(self.live))]

    async def folder(self) -> Path:
        """The setup's own folder beside the writable includes (``<state>/setup``)."""
        reloader = self.ctx.reloader()
        state = await asyncio.to_thread(state_dir, reloader.path)
        if state is None:
            raise web.HTTPConflict(text=f"{reloader.path} includes no writable files: the setup "
                                        "writes into the includes vgripd init lays out")
        folder = state / "setup"
        await asyncio.to_thread(folder.mkdir, parents=True, exist_ok=True)
        return folder

    async def progress(self) -> dict[str, Any]:
        return await asyncio.to_thread(load_progress, await self.folder() / "progress.json")

    async def save_progress(self, data: dict[str, Any]) -> None:
        path = await self.folder() / "progress.json"
        await self.ctx.reloader().write_file(path, dump_progress(data))

    async def mark(self, *steps: str, done: bool = True) -> None:
        """``steps`` marked done (now), or open again."""
        data = await self.progress()
        for step in steps:
            if done:
                data["done"][step] = time.time()
            else:
                data["done"].pop(step, None)
        await self.save_progress(data)
