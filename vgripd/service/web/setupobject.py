"""The setup's object step (docs/setup.md, step 4), beside ``SetupRoutes`` (``setup.py``)::

    POST /api/setup/object/find          the marks both cameras see, in the base frame (the
                                         templates taught here found again)
    POST /api/setup/object/template      {"box": [x, y, w, h], "label"}: a region of the last
                                         find's left image taught as a template, found in
                                         both images, offered as a mark
    POST /api/setup/object/save          {"name", "marks": [ids]}: the object from them, judged

The image work (marks, a template's search) runs in the web view's image helper process; the
object is one config transaction (``vgripd.service.host.configtxn``), a template's patch file
written before it under a new name.
"""

from __future__ import annotations

import asyncio
import hashlib
from pathlib import Path
from typing import Any

from aiohttp import web

from vgripd.errors import VgripError
from vgripd.service.web import setupimages
from vgripd.service.web.bodies import json_body, outcome_response
from vgripd.service.web.setupstate import SetupState
from vgripd.service.web.setupsteps import mark_name, object_edit, template_box
from vgripd.vision.survey import judge_layout


class SetupObject:
    """The routes above, beside ``SetupRoutes`` (the setup's shared state: its lock, last
    grab and folder)."""

    def __init__(self, state: SetupState) -> None:
        self.state = state
        self.ctx = state.ctx
        self._marks: list[dict[str, Any]] = []
        self._views: list[Any] = []  # the last find's images (a template is cut from them)
        self._templates: dict[str, Any] = {}  # label -> patch, taught on this page
        self._template_png: dict[str, bytes] = {}

    def add(self, router: web.UrlDispatcher) -> None:
        router.add_post("/api/setup/object/find", self.find_object)
        router.add_post("/api/setup/object/template", self.teach_template)
        router.add_post("/api/setup/object/save", self.save_object)

    async def find_object(self, request: web.Request) -> web.Response:
        self.ctx.config_writer(request)
        if self.ctx.daemon.config.calibration is None:
            raise web.HTTPConflict(text="the marks are measured with the calibration and the "
                                        "hand-eye: those steps first")
        async with self.state.lock:
            pair = await self.ctx.camera.grab_between_jobs()
            if pair is None:
                raise web.HTTPConflict(text="a job runs (or the camera cannot grab): try again")
            views = list(pair.views)
            try:
                jpegs, marks, missed = await self.ctx.images.call(
                    setupimages.find_marks, views, self.ctx.daemon.config, dict(self._templates))
            except (ValueError, VgripError) as err:
                raise web.HTTPConflict(text=str(err)) from None
            self.state.show(jpegs)
            self._marks, self._views = marks, views
        return web.json_response(self._marks_view(missed))

    def _marks_view(self, missed: list[str]) -> dict[str, Any]:
        return {"marks": self._marks, "missed": missed, "grab": self.state.grab_n,
                "sizes": [[int(v.shape[1]), int(v.shape[0])] for v in self._views],
                "images": self.state.live_urls()}

    async def teach_template(self, request: web.Request) -> web.Response:
        """A region of the last find's left image taught as a template (docs/setup.md, step
        4): found once in each image, triangulated, added to the marks offered; found again
        by every later find. Nothing is written until the object is saved."""
        self.ctx.config_writer(request)
        body = await json_body(request)
        try:
            box, label = template_box(body)
        except ValueError as err:
            raise web.HTTPBadRequest(text=str(err)) from None
        async with self.state.lock:
            if not self._views:
                raise web.HTTPConflict(text="find the marks first: the template is cut from "
                                            "that left image")
            self._marks = [m for m in self._marks if m.get("label") != label]
            mark_id = max((int(m["id"]) for m in self._marks), default=0) + 1
            try:
                jpegs, mark, patch, png = await self.ctx.images.call(
                    setupimages.teach_template, self._views, self.ctx.daemon.config, box, label,
                    mark_id)
            except (ValueError, VgripError) as err:  # TemplateRefused is a ValueError
                raise web.HTTPUnprocessableEntity(text=str(err)) from None
            self._templates[label] = patch
            self._template_png[label] = png
            self._marks.append(mark)
            self.state.show(jpegs)
        return web.json_response({**self._marks_view([]), "taught": mark})

    async def save_object(self, request: web.Request) -> web.Response:
        reloader = self.ctx.config_writer(request)
        body = await json_body(request)
        if not isinstance(body, dict) or not isinstance(body.get("marks"), list):
            raise web.HTTPBadRequest(text='{"name": "...", "marks": [ids]}')
        name = str(body.get("name") or "object").strip()[:64] or "object"
        by_id = {m["id"]: m for m in self._marks}
        unknown = [i for i in body["marks"] if i not in by_id]
        if unknown:
            raise web.HTTPBadRequest(text=f"marks {unknown}: not among the marks found last "
                                          f"({', '.join(map(str, by_id)) or 'none'})")
        chosen = [{**by_id[i], "name": mark_name(by_id[i])} for i in body["marks"]]
        for mark in chosen:
            if mark.get("kind") == "template":
                mark["template"] = str(await self._template_file(mark["label"]))
        findings = judge_layout([m["name"] for m in chosen],
                                [m["xyz_mm"] for m in chosen],  # type: ignore[arg-type]
                                # a template's centre is a point, not a blob that merges
                                [0.0 if m.get("kind") == "template" else m["diameter_mm"]
                                 for m in chosen],
                                identified=[m.get("kind") != "circle" for m in chosen])
        judged = [f.as_dict() for f in findings]
        if any(f.level == "ERROR" for f in findings):
            return web.json_response({"applied": False, "layout": judged, "message": (
                "refused, nothing written: " + "; ".join(
                    f.message for f in findings if f.level == "ERROR"))}, status=422)
        outcome = await reloader.write(object_edit(name, chosen), f"web {request.remote}",
                                       "setup: object")
        if outcome.applied:
            await self.state.mark("object")
        return outcome_response(outcome, layout=judged)

    async def _template_file(self, label: str) -> Path:
        """The taught template's patch saved as ``<state>/setup/templates/LABEL-HASH.png``
        (atomically, in turn with the config writes): a new name for new pixels, so the running
        config's file is never changed under it; the object's feature names it once the object
        is judged and saved."""
        png = self._template_png[label]
        folder = await self.state.folder() / "templates"
        await asyncio.to_thread(folder.mkdir, exist_ok=True)
        path = folder / f"{label}-{hashlib.sha256(png).hexdigest()[:12]}.png"
        if not await asyncio.to_thread(path.exists):
            await self.ctx.reloader().write_file(path, png)
        return path
