"""Teaching the reference from the web view (docs/web.md, "Teaching"), the page's ``vgripd
teach``:

::

    GET  /api/teach                  the shots so far, their mean against the taught reference
    POST /api/teach/shot             measure the last job's images as one shot (token)
    POST /api/teach/clear            drop the shots (token)
    POST /api/teach/save             write the mean as the reference, then reload (token)

Each shot is the last job's images measured as ``vgripd teach`` measures them
(``teach.measure``: offset limits lifted, every feature needed), in the image helper process,
never on the loop. Trigger a job (the PLC, or the page's test trigger) with the object where the
robot grips it, add the shot, repeat; the page shows the mean pose, the shots' spread, and how
far it lies from the reference taught now. Shots are kept per recipe (the job's); a shot of a
job already measured is refused.

Saving writes the ``[reference]`` section (for recipe N ``[recipes.N.reference]``) into the
include file that holds it now, keeping its ``grip``, with the fingerprints of the camera model
and hand-eye it was measured with in its ``[about]`` (as ``vgripd teach`` writes them): one
transaction of the config writer (``vgripd.service.host.configtxn``, as the tuning save), judged as
``vgripd check`` judges it; refused, the include is not touched.
"""

from __future__ import annotations

import asyncio
import logging
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web

from vgripd.calib import teach
from vgripd.config import Config
from vgripd.configsnapshot import Snapshot
from vgripd.errors import CalibrationError, VgripError
from vgripd.geometry.fingerprint import camera_about, hand_eye_fingerprint
from vgripd.geometry.transforms import pose_error
from vgripd.serialize import toml_from_dict
from vgripd.service.host.configtxn import Edit
from vgripd.service.web.commission import holding_include
from vgripd.service.web.context import WebContext
from vgripd.types import ImagePair

log = logging.getLogger(__name__)

#: Shots kept per recipe.
MAX_SHOTS = 50


def measure_shot(pair: tuple[Any, Any], config: Config) -> teach.Shot:
    """One shot of ``pair`` (runs in the image helper); ``CalibrationError`` why not."""
    images = ImagePair.of_views(pair[0], 0, T_base_flange=pair[1])
    return teach.measure(config, [images]).shots[0]


def reference_target(config_path: Path, recipe: int,
                     files: Mapping[str, bytes] | None = None) -> Path:
    """The include file that sets the reference of ``recipe`` now (or holds its table empty,
    set aside when a new hand-eye was accepted); ``files``: the snapshot."""
    prefix = "reference." if recipe == 0 else f"recipes.{recipe}.reference."
    return holding_include(config_path, prefix, "vgripd teach writes such a file", files)


def teach_edit(recipe: int, section: dict[str, Any],
               calibration: dict[str, Any] | None) -> Edit:
    """The taught reference as an edit of the config writer."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        target = reference_target(snapshot.main, recipe, snapshot.files)
        text = with_reference(snapshot.text(target), recipe, section, calibration)
        return {target: snapshot.encoded(target, text)}
    return edit


def with_reference(text: str, recipe: int, section: dict[str, Any],
                   calibration: dict[str, Any] | None = None) -> str:
    """``text`` with the reference of ``recipe`` taught anew; its ``[about]`` records the
    camera model and hand-eye of ``calibration`` (what it was measured with), as
    ``vgripd teach`` does, so the file loads with the calibration it belongs to."""
    data = tomllib.loads(text)
    if calibration is not None:
        about = data.setdefault("about", {})
        about.pop("set_aside", None)
        about.update(camera_about(calibration))
        about["hand_eye"] = hand_eye_fingerprint(calibration)
    holder = data if recipe == 0 else data.setdefault("recipes", {}).setdefault(str(recipe), {})
    old = holder.get("reference", {})
    kept = {k: v for k, v in old.items() if k not in ("T_base_obj", "points_mm")}
    holder["reference"] = {**kept, **section["reference"]}
    return toml_from_dict(data)


class TeachRoutes:
    """The routes above for one web view."""

    def __init__(self, ctx: WebContext) -> None:
        self.ctx = ctx
        self.shots: dict[int, list[tuple[int, teach.Shot]]] = {}
        self._lock = asyncio.Lock()

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/teach", self.show)
        router.add_post("/api/teach/shot", self.shot)
        router.add_post("/api/teach/clear", self.clear)
        router.add_post("/api/teach/save", self.save)

    def _summary(self, recipe: int) -> dict[str, Any]:
        shots = self.shots.get(recipe, [])
        out: dict[str, Any] = {"recipe": recipe, "shots": [j for j, _ in shots],
                               "mean": None, "spread_mm": None, "spread_deg": None,
                               "from_taught_mm": None, "from_taught_deg": None}
        if not shots:
            return out
        taught = teach.average([s for _, s in shots])
        T = taught.T_base_obj
        out.update(mean={"translation_mm": T[:3, 3].tolist()},
                   spread_mm=taught.spread_mm, spread_deg=taught.spread_deg)
        try:
            config = self.ctx.daemon.config.for_recipe(recipe)
            from vgripd.vision.scene import T_base_obj_ref

            mm, deg = pose_error(T_base_obj_ref(config), T)
            out.update(from_taught_mm=mm, from_taught_deg=deg,
                       taught={"translation_mm": T_base_obj_ref(config)[:3, 3].tolist()})
        except VgripError:
            out["taught"] = None  # nothing taught yet
        return out

    def _recipe(self, request: web.Request) -> int:
        text = request.query.get("recipe")
        if text is None:
            return self.ctx.jobs.last_recipe()
        if not text.isascii() or not text.isdigit() or len(text) > 5:
            raise web.HTTPBadRequest(text=f"recipe={text!r}: a recipe number")
        return int(text)

    async def show(self, request: web.Request) -> web.Response:
        return web.json_response(self._summary(self._recipe(request)))

    async def shot(self, request: web.Request) -> web.Response:
        self.ctx.check_edit(request)
        last = self.ctx.jobs.last_pair
        if last is None:
            raise web.HTTPConflict(text="no job's images yet: trigger a job first")
        job_id, pair = last
        recipe = self.ctx.jobs.last_recipe()
        async with self._lock:
            taken = self.shots.setdefault(recipe, [])
            if any(j == job_id for j, _ in taken):
                raise web.HTTPConflict(text=f"job {job_id} is already a shot: trigger a new job")
            config = self.ctx.daemon.config.for_recipe(recipe)
            try:
                shot = await self.ctx.images.call(
                    measure_shot, (pair.views, pair.T_base_flange), config)
            except CalibrationError as err:
                return web.json_response({**self._summary(recipe),
                                          "refused": f"job {job_id}: {err}"}, status=422)
            taken.append((job_id, shot))
            del taken[:-MAX_SHOTS]
        log.info("web view: teaching shot of job %d (recipe %d) from %s", job_id, recipe,
                 request.remote)
        return web.json_response(self._summary(recipe))

    async def clear(self, request: web.Request) -> web.Response:
        self.ctx.check_edit(request)
        recipe = self._recipe(request)
        self.shots.pop(recipe, None)
        return web.json_response(self._summary(recipe))

    async def save(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        recipe = self._recipe(request)
        shots = self.shots.get(recipe, [])
        if not shots:
            raise web.HTTPConflict(text=f"no shots for recipe {recipe}: add one first")
        source = f"web {request.remote}"
        async with self._lock:
            config = self.ctx.daemon.config.for_recipe(recipe)
            taught = teach.average([s for _, s in shots])
            section = teach.reference_sections(config, taught)
            calibration = (None if config.calibration is None
                           else config.calibration.model_dump(mode="json"))
            outcome = await reloader.write(teach_edit(recipe, section, calibration), source,
                                           f"teach recipe {recipe} from {len(shots)} shot(s)")
            if outcome.applied:
                self.shots.pop(recipe, None)
        return web.json_response({**outcome.as_dict(), "spread_mm": taught.spread_mm,
                                  "T_base_obj": np.asarray(taught.T_base_obj).tolist()},
                                 status=200 if outcome.applied else 422)
