"""Exposure and gain from the web view's live camera page (docs/web.md, "Live cameras").

::

    GET  /api/cameras/settings       exposure_us and gain_db as they run
    POST /api/cameras/{j}/settings   {"exposure_us": 8000, "gain_db": 3}   (status.allow_config_edit
                                     + token): applied live, then written to the config

The values are the ``[camera]`` section's ``exposure_us`` and ``gain_db`` (shared by every camera
of the acquisition; ``j`` names the camera the page shows and must exist). They go to the camera
driver's ``set_settings`` (in the worker process when the driver runs there), which checks them
as at open against what the device reports and reads them back. Only between jobs: during a job
(or a several-view job between views) the answer is 409; a value out of the device's range is
400 naming the camera, the feature and the range, and changes nothing.

Applied, the values are written to the include file that holds ``[object]`` (the tuning save's
file), as ``[camera]`` keys beside the main file's ``[camera]`` table, so the next start keeps
them: one transaction of the config writer (``vgripd.service.host.configtxn``: judged, numbered
backup, one audit entry with the diff), in turn with every other save and reload. A reload
does not apply a ``camera`` key (it needs a restart), so this route applies them live itself
and tells the reloader (``Reloader.live``): the running config takes the values the file now
holds, and no reload names them as needing a restart.
"""

from __future__ import annotations

import dataclasses
import logging
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.config import read_config_data
from vgripd.configsnapshot import Snapshot
from vgripd.errors import CameraError, CameraSettingError, ConfigError
from vgripd.serialize import toml_from_dict
from vgripd.service.host.configtxn import Edit, Outcome
from vgripd.service.ops.reload import Reloader
from vgripd.service.web.bodies import json_body
from vgripd.service.web.commission import tuning_target
from vgripd.service.web.context import WebContext

log = logging.getLogger(__name__)

KEYS = ("exposure_us", "gain_db")


def parse_settings(body: Any) -> dict[str, float]:
    """``{"exposure_us": number, "gain_db": number}`` (one or both), checked for shape only:
    the device judges the values."""
    if not isinstance(body, dict) or not body or set(body) - set(KEYS):
        raise web.HTTPBadRequest(text='a JSON object {"exposure_us": ..., "gain_db": ...} '
                                      "(one or both)")
    out = {}
    for key, value in body.items():
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float) or value != value:
            raise web.HTTPBadRequest(text=f"camera.{key}: {value!r} is not a number")
        out[key] = float(value)
    if not out:
        raise web.HTTPBadRequest(text="give exposure_us or gain_db")
    return out


def settings_target(config_path: Path, files: Mapping[str, bytes] | None = None) -> Path:
    """The include a camera setting is written to: the include that sets the settings or the
    camera (``camera.toml`` of ``vgripd init``'s layout), else the tuning save's file, when no
    other file already sets the key (``TuningError``/``ConfigError`` naming it otherwise)."""
    owner: dict[str, str] = {}
    read_config_data(config_path, owner, files=files)
    holders = {Path(owner[f"camera.{k}"]) for k in KEYS if f"camera.{k}" in owner}
    camera_file = Path(owner.get("camera.type", str(config_path)))
    if not holders and camera_file != Path(config_path):
        return camera_file
    if len(holders) == 1 and next(iter(holders)) != Path(config_path):
        return next(iter(holders))
    target = tuning_target(config_path, files)
    for key in KEYS:
        where = owner.get(f"camera.{key}")
        if where is not None and Path(where) != target:
            raise ConfigError(f"camera.{key} is set in {where}: the page writes it only to "
                              f"{target.name}; move it there")
    return target


def settings_edit(values: dict[str, float]) -> Edit:
    """``values`` as ``[camera]`` keys of the include, an edit of the config writer."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        target = settings_target(snapshot.main, snapshot.files)
        data = tomllib.loads(snapshot.text(target))
        data.setdefault("camera", {}).update(values)
        return {target: snapshot.encoded(target, toml_from_dict(data))}
    return edit


async def save_settings(reloader: Reloader, values: dict[str, float], source: str) -> Outcome:
    """The values saved (judged, applied: the camera runs with them already), or why not."""
    outcome = await reloader.write(settings_edit(values), source, "camera settings")
    if outcome.written:
        return dataclasses.replace(outcome, message=f"applied live; saved to "
                                   f"{', '.join(outcome.written)} for the next start")
    if outcome.applied:
        return dataclasses.replace(outcome, message=f"applied live; {outcome.message}")
    return dataclasses.replace(outcome, message=f"applied live, not saved: {outcome.message}")


class CameraSettingsRoutes:
    """The routes above for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        #: What the cameras read back after the last change (None: as configured at start).
        self.live: dict[str, Any] | None = None
        self._values: dict[str, float] = {}

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/cameras/settings", self.current)
        router.add_post("/api/cameras/{j:\\d+}/settings", self.change)

    async def current(self, request: web.Request) -> web.Response:
        section = self.ctx.daemon.config.camera
        values = {k: self._values.get(k, getattr(section, k, None)) for k in KEYS}
        return web.json_response({**values, "read_back": self.live,
                                  "enabled": self.ctx.edit_allowed})

    async def change(self, request: web.Request) -> web.Response:
        daemon = self.ctx.daemon
        reloader = self.ctx.config_writer(request)
        body = await json_body(request)
        values = parse_settings(body)
        text = request.match_info["j"]
        cameras = (daemon.config.calibration.cameras if daemon.config.calibration is not None
                   else None)
        if len(text) > 2 or int(text) >= (2 if cameras is None else len(cameras)):
            raise web.HTTPNotFound(text="no such camera")
        camera = daemon.rooms.cameras.camera
        async with self.ctx.camera.between_jobs() as idle:
            if not idle:
                raise web.HTTPConflict(text="a job runs: exposure and gain are changed only "
                                            "between jobs; try again")
            try:
                read_back = await camera.set_settings(values.get("exposure_us"),
                                                      values.get("gain_db"))
            except CameraSettingError as err:
                raise web.HTTPBadRequest(text=str(err)) from None
            except CameraError as err:
                raise web.HTTPServiceUnavailable(text=f"the camera cannot take it now: {err}"
                                                 ) from None
        self.live, self._values = read_back, {**self._values, **values}
        reloader.live.update({f"camera.{key}": value for key, value in values.items()})
        log.info("web view: camera settings %s applied from %s, read back %s", values,
                 request.remote, read_back)
        outcome = await save_settings(reloader, values, f"web {request.remote}")
        return web.json_response({"applied": values, "read_back": read_back,
                                  "saved": outcome.as_dict()})
