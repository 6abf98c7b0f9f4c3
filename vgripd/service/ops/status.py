"""The daemon's status, read from its rooms: one line for ``systemctl status`` (sd_notify
STATUS=) and the JSON snapshot the web view serves (``GET /api/status``).

Counters count what the peers were told: the job runner's answers and refusals, plus the
refusals each register link made on its own handshake (``RobotLink.refusals``).
"""

from __future__ import annotations

import os
import time
from collections import Counter
from typing import Any

import numpy as np

from vgripd.config import Config
from vgripd.peer.beltqueue import BeltLine, belt_pose
from vgripd.service.jobs.runner import JobRunner, recipe_label
from vgripd.service.links.supervision import LinkSupervisor
from vgripd.service.worker.cameras import CameraSupervisor
from vgripd.service.worker.process import WorkerClient


def queued_parts(line: BeltLine) -> list[dict[str, Any]]:
    """The queued parts in belt terms at the newest count (downstream first): the web view's
    belt strip draws them there, with the window."""
    at = line.last_count
    if at is None:
        return []
    out = []
    for p in line.queue.parts:
        b = belt_pose(line.belt, p.at(line.belt, at), at, p.source, p.error_mm, 0)
        out.append({"uid": p.uid, "job_id": p.job_id, "along_mm": round(b.along_mm, 2),
                    "across_mm": round(b.across_mm, 2), "theta_deg": round(b.theta_deg, 2),
                    "sightings": p.sightings})
    return out


class StatusBoard:
    """Reads the job runner, the links, the camera and the worker; changes nothing."""

    def __init__(self, config: Config, runner: JobRunner, links: LinkSupervisor,
                 cameras: CameraSupervisor, worker: WorkerClient | None) -> None:
        self.config = config
        self.runner = runner
        self.links = links
        self.cameras = cameras
        self.worker = worker

    def cycle_percentiles_ms(self) -> dict[str, float]:
        cycle_ms = self.runner.cycle_ms
        if not cycle_ms:
            return {}
        p50, p95, p99 = np.percentile(np.fromiter(cycle_ms, float), (50, 95, 99))
        return {"p50": float(p50), "p95": float(p95), "p99": float(p99),
                "max": max(cycle_ms)}

    def answered(self) -> tuple[Counter[str], Counter[str]]:
        """All answers the peers were told and the refusals among them, by status name: the
        daemon's (``counters``, ``refusals``) plus the links' own refusals."""
        by_links: Counter[str] = Counter()
        for counts in self.links.refusals().values():
            by_links.update(counts)
        return self.runner.counters + by_links, self.runner.refusals + by_links

    def line(self) -> str:
        """One line for ``systemctl status`` (sd_notify STATUS=)."""
        r = self.runner
        told, _ = self.answered()
        triggers = sum(told.values()) + sum(r.undelivered.values())
        counts = ", ".join(f"{k} {v}" for k, v in sorted(told.items()))
        if r.undelivered:
            counts += (", " if counts else "") + f"{sum(r.undelivered.values())} not delivered"
        line = f"{r.state.value}; {triggers} triggers" + (f" ({counts})" if counts else "")
        if r.last_job is not None:
            lj = r.last_job
            line += f"; last job {lj.job_id} {lj.result.status.name} {lj.cycle_ms:.0f} ms"
        if self.config.recipes and r.active_recipe is not None:
            line += f"; recipe {recipe_label(self.config, r.active_recipe)}"
        if r.pick_list is not None and r.pick_list.result.instances:  # several objects
            pl = r.pick_list
            line += f"; pick list {min(pl.index, pl.count)}/{pl.count}"
        if r.views is not None:
            line += f"; views {r.views.next_view - 1}/{r.views.count}"
        if r.epipolar.warning:
            line += "; RECALIBRATE"
        if self.cameras.fault:
            line += "; CAMERA FAULT"
        elif self.cameras.down:
            line += "; CAMERA DOWN"
        return line

    def recipe_snapshot(self) -> dict[str, Any]:
        """The active recipe (the running or last job's; None before the first job) and every
        configured one with whether it can run."""
        active = self.runner.active_recipe
        return {
            "active": active,
            "active_name": None if active is None else self.config.recipe_name(active),
            "recipes": [{"number": n, "name": self.config.recipe_name(n),
                         "object": self.config.for_recipe(n).object.name,
                         "problem": self.runner.recipe_problems.get(n)}
                        for n in self.config.recipe_numbers()],
        }

    def conveyor_snapshot(self) -> dict[str, Any]:
        """Each conveyor recipe's part queue (docs/conveyor.md), by recipe number."""
        r = self.runner
        out: dict[str, Any] = {}
        for number, line in r.core.lines.items():
            q, lat = line.queue, sorted(line.latency_ms)
            travel = line.travel.stats if line.travel is not None else None
            out[str(number)] = {
                "trigger": "request" if travel is None else "travel",
                "travel_images": travel.images if travel else 0,
                "skipped": travel.skipped if travel else 0,
                "rebased": travel.rebased if travel else 0,
                "queued": len(q), "seen": q.stats.seen, "duplicates": q.stats.duplicates,
                "dropped": q.stats.dropped, "served": q.stats.served,
                "last_count": line.last_count, "latch": line.latch_kind.name.lower(),
                "queue_latency_ms_p50": lat[len(lat) // 2] if lat else None,
                "window_mm": list(q.window_mm), "parts": queued_parts(line)}
        return out

    def snapshot(self, run_state: str, t_start_ns: int, health_problem: str) -> dict[str, Any]:
        """The status as JSON data (served by ``GET /status``)."""
        r, cam = self.runner, self.cameras
        now = time.monotonic_ns()
        job = None
        if r.job is not None:
            job_id, trig, _ = r.job
            job = {"id": job_id, "link": trig.link, "seq": trig.seq, "recipe": trig.recipe,
                   "age_s": (now - r.job_started_ns) / 1e9}
        last = None
        if r.last_job is not None:
            lj = r.last_job
            last = {"id": lj.job_id, "link": lj.link, "seq": lj.seq, "recipe": lj.recipe,
                    "status": lj.result.status.name, "status_code": int(lj.result.status),
                    "published": None if lj.published is None else lj.published.name,
                    "message": lj.result.message, "cycle_ms": lj.cycle_ms,
                    "diagnosis": None if lj.result.diagnosis is None
                    else lj.result.diagnosis.as_dict(),
                    "age_s": (now - lj.t_done_mono_ns) / 1e9}
        links = []
        link_refusals = self.links.refusals()
        for name, link in self.links.links.items():
            h = link.health()
            links.append({"name": name, "state": h.state.value, "peer": h.peer,
                          "peers": h.peers, "last_error": h.last_error,
                          "reconnects": h.reconnects, "refusals": dict(link_refusals[name])})
        told, refused = self.answered()
        return {
            "pid": os.getpid(),
            "run_state": run_state,
            "state": r.state.value,
            "uptime_s": (now - t_start_ns) / 1e9 if t_start_ns else 0.0,
            "camera": {"type": self.config.camera.type, "open": cam.is_open,
                       "error": cam.error or None, "fault": cam.fault or None,
                       "down": cam.down or None, "down_s": round(cam.down_for_s(), 1)},
            "healthy": not health_problem,
            "health_problem": health_problem or None,
            "worker": None if self.worker is None else self.worker.snapshot(),
            "calibrated": not r.recipe_problems.get(0, ""),
            "recipe": self.recipe_snapshot(),
            "job": job,
            "last_job": last,
            "pick_list": None if r.pick_list is None else {
                "job_id": r.pick_list.result.job_id, "link": r.pick_list.link,
                "count": r.pick_list.count, "index": r.pick_list.index,
                "instances": len(r.pick_list.result.instances)},
            "next_answers": dict(r.next_answers),
            "conveyor": self.conveyor_snapshot(),
            "views": None if r.views is None else {
                "job_id": r.views.job_id, "link": r.views.link,
                "taken": r.views.next_view - 1, "count": r.views.count},
            "links": links,
            "counters": dict(told),
            "refusals": dict(refused),
            "undelivered": dict(r.undelivered),
            "cycle_ms": {"window": len(r.cycle_ms), **self.cycle_percentiles_ms()},
            "recalibrate": r.epipolar.snapshot(now),
            "record": None if r.recorder is None else {
                "folder": str(r.recorder.folder), "bytes": r.recorder.total_bytes},
        }
