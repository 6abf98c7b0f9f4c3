"""Commissioning routes of the web view (docs/web.md, "Reload, tuning and audit").

::

    GET  /api/audit                  every reload and save, newest first (time, who, diff)
    GET  /api/tuning                 the vision parameters the page edits, as they run
    GET  /api/calibration            calibration health: files, [about], cell geometry (``health``)
    POST /api/reload                 reload the config file       (status.allow_config_edit + token)
    POST /api/tuning                 save parameters to the include, then reload (same)
    POST /api/tuning/try             run the edited pipeline on the last job's images, or a
                                     fresh grab between jobs ({"grab": true}) (same):
                                     status, likely causes, candidates by fate, picture URLs
    GET  /api/tuning/trial/{n}/{k}.jpg  trial n's picture of camera k (0 left, 1 right)

A save edits the include file that holds ``[object]`` (the config's own ``include = [...]``):
its ``[vision]`` keys and the circle marks' ``polarity``, as one transaction of the daemon's
config writer (``vgripd.service.host.configtxn``): judged as ``vgripd check`` judges it before the
include is replaced (the old file kept as a numbered backup, ``cell.toml.1``, ``.2`` ...); a
refused edit never reaches the include. Both routes answer the outcome
(``vgripd.service.host.configtxn.Outcome``); 422 when refused.
"""

from __future__ import annotations

import asyncio
import logging
import time
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.config import Config, config_from_dict, read_config_data
from vgripd.configsnapshot import Snapshot
from vgripd.errors import ConfigError
from vgripd.serialize import toml_from_dict
from vgripd.service.host.configtxn import Edit, Outcome
from vgripd.service.ops.reload import Reloader
from vgripd.service.web.bodies import json_body, outcome_response
from vgripd.service.web.context import WebContext
from vgripd.service.web.health import calibration_files, cell_geometry

log = logging.getLogger(__name__)

#: The ``[vision]`` keys the page edits, with their types.
TUNABLE: dict[str, type] = {
    "working_distance_mm": list, "min_contrast": float, "min_circularity": float,
    "template_min_score": float, "epipolar_tolerance_px": float, "model_tolerance_mm": float,
    "min_features": int, "max_fit_rms_mm": float, "max_reprojection_px": float,
    "downscale": int,
}
POLARITIES = ("dark", "bright")


class TuningError(ConfigError):
    """A save that cannot be written (no include holds ``[object]``, a key set elsewhere)."""


def holding_include(config_path: Path, prefix: str, hint: str,
                    files: Mapping[str, bytes] | None = None) -> Path:
    """The one included file that sets keys under ``prefix`` (``"reference."``), or, when no
    file sets one, holds its table empty (a reference set aside); ``TuningError`` naming where
    it is set otherwise, with ``hint`` (what writes such a file). ``files``: the snapshot."""
    owner: dict[str, str] = {}
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    read_config_data(config_path, owner, included, files)
    files_ = {src for key, src in owner.items() if key.startswith(prefix)}
    if not files_:
        files_ = {path for path, part, _ in included if _holds_table(part, prefix)}
    if len(files_) != 1 or Path(next(iter(files_))) == config_path:
        where = "the main config file" if files_ else "no file"
        raise TuningError(f"{config_path}: {prefix.rstrip('.')} is set in {where}: the page "
                          f"writes it only into the one included file that holds it ({hint})")
    return Path(next(iter(files_)))


def _holds_table(part: dict[str, Any], prefix: str) -> bool:
    table: Any = part
    for key in prefix.rstrip(".").split("."):
        table = table.get(key) if isinstance(table, dict) else None
    return isinstance(table, dict)


def tuning_target(config_path: Path, files: Mapping[str, bytes] | None = None) -> Path:
    """The include file a save writes: the one that sets ``object.features`` (``files``: the
    snapshot)."""
    owner: dict[str, str] = {}
    read_config_data(config_path, owner, files=files)
    where = owner.get("object.features")
    if where is None or Path(where) == config_path:
        raise TuningError(
            f"{config_path}: object.features is set in the main config file (or not at all): "
            f"the page saves only to an included file; move [vision] and [object] into a file "
            f"of their own and list it in include = [...]")
    return Path(where)


def edited(text: str, vision: dict[str, Any], polarity: str | None) -> str:
    """The include file's new text: ``vision`` keys set, every circle mark's polarity."""
    data = tomllib.loads(text)
    if vision:
        data.setdefault("vision", {}).update(vision)
    if polarity is not None:
        for feature in data.get("object", {}).get("features", []):
            if feature.get("kind") == "circle":
                feature["polarity"] = polarity
    return toml_from_dict(data)


def parse_edit(body: Any) -> tuple[dict[str, Any], str | None]:
    """The request's ``{"vision": {...}, "polarity": "dark"|"bright"}``, checked for shape (the
    values are judged by the reload, as any config)."""
    if not isinstance(body, dict) or set(body) - {"vision", "polarity", "grab"}:
        raise web.HTTPBadRequest(text='a JSON object {"vision": {...}, "polarity": ...}')
    vision = body.get("vision") or {}
    if not isinstance(vision, dict):
        raise web.HTTPBadRequest(text="vision: an object of [vision] keys")
    for key, value in vision.items():
        kind = TUNABLE.get(key)
        if kind is None:
            raise web.HTTPBadRequest(text=f"vision.{key}: not editable from the page "
                                          f"(editable: {', '.join(TUNABLE)})")
        ok = (isinstance(value, list) and len(value) == 2 and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            if kind is list else isinstance(value, int | float) and not isinstance(value, bool))
        if not ok:
            raise web.HTTPBadRequest(text=f"vision.{key}: {value!r} is not a "
                                          f"{'[near, far] pair' if kind is list else 'number'}")
    polarity = body.get("polarity")
    if polarity is not None and polarity not in POLARITIES:
        raise web.HTTPBadRequest(text=f"polarity: {polarity!r}, not one of {POLARITIES}")
    return vision, polarity


def tuning_edit(vision: dict[str, Any], polarity: str | None) -> Edit:
    """The tuning save as an edit of the config writer (``vgripd.service.host.configtxn``)."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        target = tuning_target(snapshot.main, snapshot.files)
        return {target: snapshot.encoded(target, edited(snapshot.text(target), vision,
                                                        polarity))}
    return edit


async def save_tuning(reloader: Reloader, vision: dict[str, Any], polarity: str | None,
                      source: str) -> Outcome:
    """The edit judged and applied, or refused with the include untouched."""
    return await reloader.write(tuning_edit(vision, polarity), source, "tuning save")


def edited_config(config: Config, vision: dict[str, Any], polarity: str | None) -> Config:
    """The running config with the page's edits, validated as any config (``ConfigError``
    naming the key)."""
    data = config.model_dump(mode="json", exclude_none=True)
    data["vision"].update(vision)
    if polarity is not None:
        for feature in data["object"]["features"]:
            if feature.get("kind") == "circle":
                feature["polarity"] = polarity
    return config_from_dict(data, "the page's edit")


def tuning_values(config: Any) -> dict[str, Any]:
    """What the page's form shows: the running vision keys and the marks' polarity."""
    v = config.vision
    polarities = sorted({f.polarity for f in config.object.features if f.kind == "circle"})
    return {"vision": {k: (list(getattr(v, k)) if TUNABLE[k] is list else getattr(v, k))
                       for k in TUNABLE},
            "polarity": polarities[0] if len(polarities) == 1 else None,
            "polarities": polarities}


class CommissionRoutes:
    """The routes above for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self._trying = asyncio.Lock()  # one trial at a time (the image helper is one process)
        self._trial: tuple[int, list[bytes]] = (0, [])

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/audit", self.audit)
        router.add_get("/api/tuning", self.tuning)
        router.add_get("/api/calibration", self.calibration)
        router.add_post("/api/reload", self.reload)
        router.add_post("/api/tuning", self.save)
        router.add_post("/api/tuning/try", self.trial)
        router.add_get("/api/tuning/trial/{n:\\d+}/{k:\\d+}.jpg", self.trial_image)

    async def audit(self, request: web.Request) -> web.Response:
        reloader = self.ctx.daemon.reloader
        entries = [] if reloader is None else [o.as_dict() for o in reloader.audit]
        return web.json_response({"enabled": self.ctx.edit_allowed, "reloading": bool(
            reloader is not None and reloader.running), "entries": entries})

    async def calibration(self, request: web.Request) -> web.Response:
        daemon = self.ctx.daemon
        reloader = daemon.reloader
        return web.json_response({
            "files": calibration_files(None if reloader is None else reloader.path,
                                       full_paths=self.ctx.access.holds_token(request)),
            "geometry": cell_geometry(daemon.config, self.ctx.jobs.last_pose()),
            "recalibrate": daemon.rooms.jobs.epipolar.snapshot(time.monotonic_ns()),
        })

    async def tuning(self, request: web.Request) -> web.Response:
        return web.json_response(tuning_values(self.ctx.daemon.config))

    async def reload(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        return outcome_response(await reloader.reload(f"web {request.remote}"))

    async def save(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        body = await json_body(request)
        vision, polarity = parse_edit(body)
        return outcome_response(await save_tuning(reloader, vision, polarity,
                                              f"web {request.remote}"))

    async def trial(self, request: web.Request) -> web.Response:
        """The edited pipeline on the last job's images (in the image helper process, never on
        the loop); nothing is saved or applied."""
        self.ctx.check_edit(request)
        body = await json_body(request)
        vision, polarity = parse_edit(body)
        job_id: int | None
        if body.get("grab"):  # a fresh picture, taken as a live preview is: between jobs only
            pair = await self.ctx.camera.grab_between_jobs()
            if pair is None:
                raise web.HTTPConflict(text="a job runs (or the camera cannot grab): a fresh "
                                            "grab is taken only between jobs; try again")
            job_id = None
        else:
            last = self.ctx.jobs.last_pair
            if last is None:
                raise web.HTTPConflict(text="no job's images yet: trigger a job first")
            job_id, pair = last
        try:
            config = edited_config(self.ctx.daemon.config, vision, polarity)
        except ConfigError as err:
            return web.json_response({"status": None, "message": f"refused: {err}"},
                                     status=422)
        async with self._trying:
            try:
                jpegs, outcome = await self.ctx.images.trial(pair, config)
            except Exception as err:
                raise web.HTTPInternalServerError(text=f"the trial failed: {err!r}") from None
            n = self._trial[0] + 1
            self._trial = (n, jpegs)
        log.info("web view: tuning trial %d on %s from %s: %s", n,
                 "a fresh grab" if job_id is None else f"job {job_id}", request.remote,
                 outcome["status"])
        return web.json_response({"trial": n, "job_id": job_id, **outcome, "images": [
            f"/api/tuning/trial/{n}/{k}.jpg" for k in range(len(jpegs))]})

    async def trial_image(self, request: web.Request) -> web.Response:
        texts = request.match_info["n"], request.match_info["k"]
        if any(len(t) > 9 for t in texts):
            raise web.HTTPNotFound(text="no such trial")
        n, k = int(texts[0]), int(texts[1])
        current, jpegs = self._trial
        if n != current or k >= len(jpegs):
            raise web.HTTPNotFound(text="only the last trial's pictures are kept")
        return web.Response(body=jpegs[k], content_type="image/jpeg",
                            headers={"Cache-Control": "no-store"})
