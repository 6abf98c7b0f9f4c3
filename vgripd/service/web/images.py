"""Annotated, downscaled JPEGs of a job for the browser, made outside the daemon's interpreter.

The annotated full-resolution PNGs of ``vgripd replay --annotate`` are megabytes each; the
browser gets JPEGs at most ``MAX_WIDTH_PX`` wide. Drawing and encoding hold the GIL for tens of
milliseconds, so they run in one spawned helper process (``ImageRenderer``), never on the event
loop and never in a thread of the daemon's interpreter: a PLC poll is not delayed by a browser.

The helper builds its own ``Pipeline`` from the config (for the camera model and the object
model the drawing needs); without a calibration it writes only the status line on the image.
A job's images come either from the pair the daemon just handled (pickled to the helper once)
or, for an older job, from the recorder's folder (the helper reads the PNGs itself).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import threading
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.config import Config
from vgripd.service.host.children import ChildSetup, end_pool, start_child, start_server
from vgripd.service.host.children import context as children_context
from vgripd.types import ImagePair, JobResult, Status

log = logging.getLogger(__name__)

MAX_WIDTH_PX = 1024
JPEG_QUALITY = 80
# Jobs whose images are kept encoded in memory (about 2 x 100 kB each).
CACHE_JOBS = 32
# Renders waiting for the helper beyond this are not started eagerly (rendered on request).
MAX_PENDING = 2

_pipeline: Any = None  # in the helper process: the Pipeline, or None when not calibrated


#: The image helper's niceness: at least this many levels below the daemon and at least
#: WEB_IMAGES_NICE_FLOOR, below the worker (``vgripd.service.worker.process.WORKER_NICE``): nice 9
#: under the unit (daemon at -10), 10 by hand.
WEB_IMAGES_NICE = 10
WEB_IMAGES_NICE_FLOOR = 9
#: A helper let go (a reload, a restart, the daemon's stop) finishes what it holds within
#: this (a render: tens of milliseconds; a helper still starting: its start-up), then is ended.
STOP_S = 30.0


def _init_helper(config: Config, setup: ChildSetup) -> None:
    """Helper process start: end with the daemon, build the pipeline once.

    The helper holds nothing worth saving (a cache of pictures), so it ends as soon as the
    daemon does: SIGTERM (systemd signals the whole unit on stop) ends it at once (the default
    action), the daemon's death by any cause through the kernel. SIGINT (a terminal's Ctrl-C
    to the process group) is left to the daemon, which closes the helper. Pictures for a
    browser matter least: it runs below the worker, far below the daemon's loop.
    """
    global _pipeline
    start_child(setup)
    try:
        from vgripd.vision.pipeline import Pipeline

        _pipeline = Pipeline(config)
    except Exception as err:  # not calibrated, or a config the pipeline refuses
        log.info("web images: drawing the status line only (%s)", err)
        _pipeline = None


def _status_only(pair: ImagePair, result: JobResult) -> list[np.ndarray]:
    import cv2

    images = []
    for img in pair.views:
        arr = np.asarray(img)
        bgr = cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR) if arr.ndim == 2 else arr.copy()
        scale = max(1, bgr.shape[1] // 1200)
        cv2.putText(bgr, f"{result.status.name} {result.message}"[:120], (10, 30 * scale),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (0, 220, 255), 2 * scale)
        images.append(bgr)
    return images


def _load_recorded(folder: str) -> ImagePair:
    import cv2

    path = Path(folder)
    flange = None
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        meta = json.loads((path / "pair.json").read_text())
        if meta.get("T_base_flange") is not None:
            flange = np.asarray(meta["T_base_flange"], dtype=np.float64)
    if (path / "view0.png").exists():  # a multi-camera cell: view0.png ... in camera order
        views: list[np.ndarray] = []
        while (path / f"view{len(views)}.png").exists():
            image = cv2.imread(str(path / f"view{len(views)}.png"), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise FileNotFoundError(f"{path / f'view{len(views)}.png'}: cannot read")
            views.append(image)
        return ImagePair.of_views(views, 0, source=str(path), T_base_flange=flange)
    left = cv2.imread(str(path / "left.png"), cv2.IMREAD_UNCHANGED)
    if left is None:
        raise FileNotFoundError(f"{path / 'left.png'}: cannot read")
    right = cv2.imread(str(path / "right.png"), cv2.IMREAD_UNCHANGED)
    return ImagePair(left=left, right=right, t_mono_ns=0, source=str(path),
                     T_base_flange=flange)


def _portable(pair: ImagePair | str, result: JobResult) -> tuple[Any, JobResult]:
    """What the helper needs, picklable (the empty mappings of the value types are not)."""
    result = dataclasses.replace(result, residuals=dict(result.residuals),
                                 timings_ms=dict(result.timings_ms))
    if isinstance(pair, str):
        return pair, result
    return (pair.views, pair.T_base_flange), result


def _with_candidates(pair: ImagePair, result: JobResult) -> JobResult:
    """``result`` with every candidate's fate to draw: a failed job carries its diagnosis; for
    a good one the finders run again here (in the helper) to say what they dropped and why,
    as ``replay --annotate`` draws it. The job's own figures are kept."""
    if result.diagnosis is not None or _pipeline is None or not result.status.pose_valid:
        return result
    try:
        again = _pipeline.process_with_points(pair, result.job_id, diagnose=True)[0]
    except Exception as err:  # the picture still shows the job without its candidates
        log.info("web images: job %d: candidates not drawn: %r", result.job_id, err)
        return result
    return dataclasses.replace(result, diagnosis=again.diagnosis)


def render(pair: ImagePair | str | tuple[Any, Any], result: JobResult,
           max_width: int = MAX_WIDTH_PX, quality: int = JPEG_QUALITY) -> list[bytes]:
    """JPEGs of the job drawn as ``replay --annotate`` draws it: left (and right for stereo),
    or every camera's in camera order for a multi-camera cell.

    ``pair``: the images (an ``ImagePair`` or its ``views, T_base_flange``), or a recorded
    job's folder. Runs in the helper process (or anywhere in tests).
    """

    if isinstance(pair, str):
        pair = _load_recorded(pair)
    elif isinstance(pair, tuple):
        pair = ImagePair.of_views(pair[0], 0, T_base_flange=pair[1])
    if _pipeline is not None:
        from vgripd.vision.annotate import annotate

        try:
            images = annotate(_pipeline, pair, _with_candidates(pair, result))
        except Exception as err:  # a drawing problem must not hide the images
            log.warning("web images: job %d: annotation failed: %r", result.job_id, err)
            images = _status_only(pair, result)
    else:
        images = _status_only(pair, result)
    return _encode(images, max_width, quality)


def _encode(images: list[np.ndarray], max_width: int = MAX_WIDTH_PX,
            quality: int = JPEG_QUALITY) -> list[bytes]:
    """Each BGR image downscaled to ``max_width`` and JPEG-encoded."""
    import cv2

    out = []
    for img in images:
        h, w = img.shape[:2]
        if w > max_width:
            img = cv2.resize(img, (max_width, max(1, round(h * max_width / w))),
                             interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        out.append(buf.tobytes())
    return out


def render_trial(pair: tuple[Any, Any], config: Config) -> tuple[list[bytes], dict[str, Any]]:
    """A tuning trial (docs/web.md, "Tuning"): the pipeline of ``config`` (the running one with
    the page's edits) on a job's images, every candidate drawn with its fate; the JPEGs and
    the outcome (status, message, likely causes with their keys, candidates by fate)."""
    from collections import Counter

    from vgripd.vision.annotate import annotate
    from vgripd.vision.checked import CheckedPipeline

    images_pair = ImagePair.of_views(pair[0], 0, T_base_flange=pair[1])
    pipeline = CheckedPipeline(config)
    result = pipeline.process_with_points(images_pair, 0, diagnose=True)[0]
    d = result.diagnosis
    outcome = {
        "status": result.status.name, "message": result.message,
        "causes": [] if d is None else [{"key": c.key, "reason": c.reason} for c in d.causes],
        "candidates": [] if d is None else [
            {"image": st.side, **Counter(c.reason for c in st.candidates)} for st in d.images],
        "features_used": list(result.features_used),
    }
    return _encode(annotate(pipeline, images_pair, result)), outcome


#: A preview pixel at or above this grey level counts as over-exposed (drawn red).
SATURATED_LEVEL = 250


def render_preview(views: Any) -> tuple[list[bytes], list[dict[str, Any]]]:
    """Live camera pictures (docs/web.md, "Live cameras"): each image with its over-exposed
    pixels red, the marks the finder sees circled, and per image its figures: share of
    over-exposed pixels, focus (variance of the Laplacian on the full image: higher is
    sharper; compare it while turning the focus ring), marks found. Runs in the helper."""
    import cv2

    out_images, figures = [], []
    finders: list[Any] = []
    if _pipeline is not None:
        finders = list(_pipeline.finders) or [_pipeline.find_left, _pipeline.find_right]
    for j, image in enumerate(views):
        gray = np.asarray(image)
        if gray.ndim == 3:
            gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
        bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        over = gray >= SATURATED_LEVEL
        bgr[over] = (0, 0, 255)
        focus = float(cv2.Laplacian(gray, cv2.CV_64F).var())
        marks = 0
        if j < len(finders) and finders[j] is not None:
            try:
                found = finders[j](gray)
            except Exception:  # noqa: BLE001 - a preview never fails for its drawing
                found = None
            if found is not None:
                marks = len(found.circles) + len(found.identified)
                scale = max(1, bgr.shape[1] // 1200)
                for x, y in list(found.circles) + list(found.identified.values()):
                    cv2.circle(bgr, (int(round(x)), int(round(y))), 14 * scale, (0, 200, 0),
                               2 * scale)
        figures.append({"saturated_share": float(over.mean()), "focus": focus,
                        "marks": marks})
        out_images.append(bgr)
    return _encode(out_images), figures


class ImageRenderer:
    """Renders and caches each job's JPEGs in a helper process (one, spawned on first use)."""

    def __init__(self, config: Config) -> None:
        self._config = config
        self._pool: ProcessPoolExecutor | None = None
        # helpers let go by a reload or a crash, each ended by a thread of its own (a spawn
        # still starting takes seconds on a busy machine, a render tens of milliseconds);
        # close() joins them, so no helper or its manager thread outlives the daemon's stop
        self._retiring: list[threading.Thread] = []
        self._cache: OrderedDict[int, asyncio.Future[list[bytes]]] = OrderedDict()
        self._pending = 0

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                1, mp_context=children_context(),
                initializer=_init_helper, initargs=(self._config, ChildSetup.here(
                    nice_below=WEB_IMAGES_NICE, nice_floor=WEB_IMAGES_NICE_FLOOR)))
        return self._pool

    def cached(self, job_id: int) -> asyncio.Future[list[bytes]] | None:
        fut = self._cache.get(job_id)
        if fut is not None:
            self._cache.move_to_end(job_id)
        return fut

    def submit(self, job_id: int, pair: ImagePair | str, result: JobResult,
               eager: bool = False) -> asyncio.Future[list[bytes]] | None:
        """Start rendering a job (unless it is cached); None when ``eager`` and the helper is
        behind (the job is rendered on request later, from the recorder)."""
        fut = self.cached(job_id)
        if fut is not None:
            return fut
        if eager and self._pending >= MAX_PENDING:
            return None
        fut = asyncio.get_running_loop().create_task(self.call(render, *_portable(pair, result)))
        self._pending += 1
        fut.add_done_callback(self._done)
        self._cache[job_id] = fut
        while len(self._cache) > CACHE_JOBS:
            self._cache.popitem(last=False)
        return fut

    def _done(self, fut: asyncio.Future[list[bytes]]) -> None:
        self._pending -= 1
        if fut.cancelled():
            return
        err = fut.exception()
        if err is None:
            return
        for job_id, cached in list(self._cache.items()):
            if cached is fut:  # a failure is not cached: the next request tries again
                del self._cache[job_id]
        log.warning("web images: rendering failed: %r", err)

    async def call(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` in the helper process (a render, a trial, a teaching shot). A helper
        that died, before or while it ran the call, is replaced and the call given once to the
        new one: the pool learns of the death only when its manager thread wakes, so a call
        may go to a dead helper and fail ``BrokenProcessPool`` although nothing else is wrong."""
        loop = asyncio.get_running_loop()
        for attempt in (1, 2):
            if self._pool is None:  # the fork server ready off the event loop
                await asyncio.to_thread(start_server)
            pool = self._executor()
            try:
                return await asyncio.wrap_future(pool.submit(fn, *args), loop=loop)
            except BrokenProcessPool:
                if attempt == 2:
                    raise
                log.warning("web images: the helper process died; starting another")
                if self._pool is pool:  # not yet replaced by another call that saw it
                    self._restart()
        raise AssertionError("unreachable")

    async def trial(self, pair: ImagePair, config: Config
                    ) -> tuple[list[bytes], dict[str, Any]]:
        """``render_trial`` in the helper process (not cached)."""
        out: tuple[list[bytes], dict[str, Any]] = await self.call(
            render_trial, _portable(pair, JobResult(job_id=0, status=Status.OK))[0], config)
        return out

    def reconfigure(self, config: Config) -> None:
        """Draw later jobs with ``config`` (a reload): a new helper builds its pipeline from it;
        renders already queued finish on the old one."""
        self._config = config
        self._retire(cancel_futures=False)

    def _restart(self) -> None:
        self._retire(cancel_futures=True)

    def _retire(self, cancel_futures: bool) -> None:
        """Let the current helper go without waiting (it finishes what it holds)."""
        pool, self._pool = self._pool, None
        self._retiring = [t for t in self._retiring if t.is_alive()]
        if pool is not None:
            ender = threading.Thread(target=end_pool, name="web-images-retire",
                                     args=(pool, STOP_S, cancel_futures))
            ender.start()
            self._retiring.append(ender)

    def close(self) -> None:
        """Stop the helpers, the current one and any a reload let go (a render in progress is
        waited for: tens of milliseconds; a helper still starting: its start-up; each at most
        ``STOP_S``)."""
        self._retire(cancel_futures=True)
        for fut in self._cache.values():
            fut.cancel()
        self._cache.clear()
        retiring, self._retiring = self._retiring, []
        for ender in retiring:
            ender.join()
