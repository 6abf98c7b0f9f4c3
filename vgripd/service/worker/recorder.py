"""Job recording: every job's images and data in a size-capped folder, for offline replay.

One folder per job, named so that names sort by time (job ids restart with the daemon)::

    <folder>/20261122-044158.123-job000042/
        left.png  right.png   the images as grabbed (right.png only for stereo; a cell with
                              more than two cameras: view0.png, view1.png, ... in camera order)
        pair.json             ImagePair source, capture time, meta, T_base_flange, truth
        config.toml           the configuration the job ran with, secrets redacted
                              (``vgripd.redaction``; loadable as is)
        result.json           the JobResult

Files are written mode 0640 and folders 0750 (whatever the umask): a recording shows the cell
and is for the service and its group only. ``pair.json`` and ``result.json`` pass through the
same redaction as the config (a camera source may be a URL with a password).

A job folder is written under a ``.partial-`` name and renamed when complete, so a reader
never sees half a job. ``vgripd replay -c JOB/config.toml JOB`` reproduces the job offline
(relative paths in the config, e.g. template images, resolve against the current directory).

Writing runs on the recorder's own single thread, never on the event loop, and never fails a
job: a full or broken disk is logged once (and once more when it works again).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2

from vgripd.redaction import redact
from vgripd.serialize import jsonable, toml_from_dict
from vgripd.types import ImagePair, JobResult, PickInstance

log = logging.getLogger(__name__)

PARTIAL_PREFIX = ".partial-"
# Jobs waiting for the disk beyond this are not recorded (a stalled disk must not eat memory).
MAX_PENDING = 4
FILE_MODE = 0o640
FOLDER_MODE = 0o750


def dict_from_result(result: JobResult) -> dict[str, Any]:
    """A JobResult as JSON data (status by name and code, target with its field names)."""
    target = result.target
    return {
        "job_id": result.job_id,
        "recipe": result.recipe,
        "status": result.status.name,
        "status_code": int(result.status),
        "message": result.message,
        "target": None if target is None else {
            "vendor": target.vendor,
            "fields": list(target.fields),
            "values": list(target.values),
        },
        "T_base_obj": jsonable(result.T_base_obj),
        "offset": jsonable(result.offset),
        "residuals": jsonable(result.residuals),
        "timings_ms": jsonable(result.timings_ms),
        "features_used": list(result.features_used),
        "features_missing": list(result.features_missing),
        "t_capture_mono_ns": result.t_capture_mono_ns,
        "t_done_mono_ns": result.t_done_mono_ns,
        # A failed job's diagnosis (vgripd.vision.diagnosis): stage counts, likely causes.
        "diagnosis": None if result.diagnosis is None else result.diagnosis.as_dict(),
        # The pick list (picking.max_objects > 1, docs/picklists.md); [] for one object.
        "instances": [dict_from_instance(i) for i in result.instances],
    }


def dict_from_instance(instance: PickInstance) -> dict[str, Any]:
    """One instance of a pick list as JSON data (the JobResult fields of the same names)."""
    target = instance.target
    return {
        "status": instance.status.name,
        "status_code": int(instance.status),
        "message": instance.message,
        "pick_id": instance.pick_id,
        "score": instance.score,
        "target": None if target is None else {
            "vendor": target.vendor, "fields": list(target.fields),
            "values": list(target.values)},
        "T_base_obj": jsonable(instance.T_base_obj),
        "offset": jsonable(instance.offset),
        "residuals": jsonable(instance.residuals),
        "features_used": list(instance.features_used),
    }


def _write_text(path: Path, text: str) -> None:
    """``text`` to a new file created mode ``FILE_MODE`` (never wider, whatever the umask)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE)
    os.fchmod(fd, FILE_MODE)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def _dir_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


class Recorder:
    """Writes jobs to ``folder`` and keeps it under ``max_bytes`` by deleting the oldest jobs.

    ``config_snapshot`` is the configuration as JSON data without None values
    (``Config.model_dump(mode="json", exclude_none=True)``), written beside every job as TOML
    so that a recorded job can be reproduced even after the live config changed; its secrets
    are redacted (a recording is for replay and support, not for the token).
    """

    def __init__(self, folder: Path, max_bytes: int, config_snapshot: Mapping[str, Any]) -> None:
        self.folder = folder
        self.max_bytes = max_bytes
        self._config_toml = toml_from_dict(redact(jsonable(config_snapshot)))
        self._jobs: OrderedDict[str, int] = OrderedDict()  # name -> bytes, oldest first
        # Kept as a plain int (not summed on demand) so the event loop can read it while the
        # writer thread changes ``_jobs``.
        self.total_bytes = 0
        self._executor: ThreadPoolExecutor | None = None
        self._pending = 0
        self._lock = threading.Lock()
        self._failing = False

    def scan(self) -> None:
        """Take stock of jobs already in the folder; drop leftovers of interrupted writes."""
        if not self.folder.is_dir():
            self.folder.mkdir(mode=FOLDER_MODE, parents=True, exist_ok=True)
            os.chmod(self.folder, FOLDER_MODE)
        self._jobs.clear()
        for entry in sorted(self.folder.iterdir()):
            if not entry.is_dir():
                continue
            if entry.name.startswith(PARTIAL_PREFIX):
                shutil.rmtree(entry, ignore_errors=True)
            else:
                self._jobs[entry.name] = _dir_bytes(entry)
        self.total_bytes = sum(self._jobs.values())

    def write(self, pair: ImagePair, result: JobResult) -> Path:
        """Write one job (blocking) and prune; raises OSError if the disk refuses."""
        t = time.time()
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(t)) + f".{int(t % 1 * 1000):03d}"
        name = f"{stamp}-job{result.job_id:06d}"
        tmp = self.folder / (PARTIAL_PREFIX + name)
        tmp.mkdir(mode=FOLDER_MODE, parents=True)
        try:
            os.chmod(tmp, FOLDER_MODE)  # before anything is in it (mkdir's mode meets the umask)
            if len(pair.views) > 2:  # a multi-camera cell: camera order of the config
                images = {f"view{j}": image for j, image in enumerate(pair.views)}
            else:
                images = dict(zip(("left", "right"), pair.views, strict=False))
            for side, image in images.items():
                if not cv2.imwrite(str(tmp / f"{side}.png"), image):
                    raise OSError(f"{tmp / side}.png: cv2.imwrite failed")
                os.chmod(tmp / f"{side}.png", FILE_MODE)
            meta = {
                "source": redact(pair.source),
                "t_mono_ns": pair.t_mono_ns,
                "meta": jsonable(pair.meta),
                "T_base_flange": jsonable(pair.T_base_flange),
                "truth": jsonable(pair.truth),
            }
            meta["meta"] = redact(meta["meta"])
            _write_text(tmp / "pair.json", json.dumps(meta, indent=2))
            _write_text(tmp / "config.toml", self._config_toml)
            _write_text(tmp / "result.json",
                        json.dumps(redact(dict_from_result(result)), indent=2))
            final = self.folder / name
            tmp.rename(final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self._jobs[name] = _dir_bytes(final)
        self.total_bytes += self._jobs[name]
        self._prune(keep=name)
        return final

    def _prune(self, keep: str) -> None:
        while self.total_bytes > self.max_bytes and len(self._jobs) > 1:
            oldest = next(iter(self._jobs))
            if oldest == keep:
                break
            shutil.rmtree(self.folder / oldest, ignore_errors=True)
            self.total_bytes -= self._jobs.pop(oldest)

    # --- non-blocking use from the daemon ------------------------------------------------

    def start(self) -> None:
        """Start the writer thread and scan the folder on it (the caller never waits)."""
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="vgripd-record")
        self._executor.submit(self.scan).add_done_callback(self._report)

    def submit(self, pair: ImagePair, result: JobResult) -> bool:
        """Queue a job for writing; False if it was dropped because the disk is behind."""
        if self._executor is None:
            raise RuntimeError("Recorder.submit before start")
        with self._lock:
            if self._pending >= MAX_PENDING:
                log.warning("record: job %d not recorded, %d jobs still waiting for the disk",
                            result.job_id, self._pending)
                return False
            self._pending += 1
        self._executor.submit(self.write, pair, result).add_done_callback(self._written)
        return True

    def _written(self, fut: Future[Any]) -> None:
        with self._lock:
            self._pending -= 1
        self._report(fut)

    def _report(self, fut: Future[Any]) -> None:
        err = fut.exception()
        if err is not None and not self._failing:
            self._failing = True
            log.error("record: cannot write to %s: %s (jobs keep running; logged once)",
                      self.folder, err)
        elif err is None and self._failing:
            self._failing = False
            log.info("record: writing to %s works again", self.folder)

    def close(self) -> None:
        """Finish queued writes and stop the writer thread."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None


def recorded_job(folder: Path, job_id: int, since_wall: float) -> str | None:
    """The folder ``Recorder.write`` made for ``job_id`` in ``folder`` during the run started
    at ``since_wall`` (time.time()): names sort by time and job ids restart with the daemon,
    so only folders stamped after the start count (None: none, or the folder cannot be
    read). Blocking."""
    start = time.strftime("%Y%m%d-%H%M%S", time.localtime(since_wall - 1))
    suffix = f"-job{job_id:06d}"
    try:
        names = sorted(e.name for e in os.scandir(folder)
                       if e.name.endswith(suffix) and not e.name.startswith(PARTIAL_PREFIX)
                       and e.name >= start)
    except OSError:
        return None
    return str(folder / names[-1]) if names else None
