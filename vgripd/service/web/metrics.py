"""``GET /metrics``: the daemon in the Prometheus text format, through ``prometheus_client``.

Its own ``CollectorRegistry`` (not the library's global one): several daemons in one test
process, or a library user's own metrics, never mix. Per-job figures (status, cycle time, stage
durations, epipolar residual) are observed when a job finishes; what the daemon and its links
already count (link state, reconnects, refusals, undelivered answers, recorder) is read at
scrape time by a collector, so no figure is counted twice.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from vgripd.service.jobs.jobrecord import JobRecord
from vgripd.service.links.protocol import LinkState
from vgripd.service.web.daemonview import DaemonView
from vgripd.types import Status

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

# Seconds. A cell cycles in tens to hundreds of milliseconds; the tail shows a sick camera.
CYCLE_BUCKETS_S = (0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0, 5.0, 10.0)
STAGE_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0)
# Pixels: the recalibration trend (vision.epipolar_warn_px is typically 1-2 px).
EPIPOLAR_BUCKETS_PX = (0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)


class _DaemonCollector(Collector):
    """What the daemon already counts, read at scrape time."""

    def __init__(self, daemon: DaemonView) -> None:
        self._daemon = daemon

    def collect(self) -> Iterator[Any]:
        d = self._daemon
        up = GaugeMetricFamily("vgripd_link_up", "1 while the link is up (its peer connected "
                               "or the server listening with a peer)", labels=["link"])
        state = GaugeMetricFamily("vgripd_link_state", "The link's state (1 for the current "
                                  "one)", labels=["link", "state"])
        reconnects = CounterMetricFamily("vgripd_link_reconnects", "Reconnections of the "
                                         "link since the daemon started", labels=["link"])
        peers = GaugeMetricFamily("vgripd_link_peers", "Connected clients of a server link",
                                  labels=["link"])
        for name, link in d.rooms.links.links.items():
            h = link.health()
            up.add_metric([name], 1.0 if h.state is LinkState.UP else 0.0)
            for s in LinkState:
                state.add_metric([name, s.value], 1.0 if h.state is s else 0.0)
            reconnects.add_metric([name], h.reconnects)
            peers.add_metric([name], h.peers)
        yield from (up, state, reconnects, peers)

        _, refused = d.answered()
        refusals = CounterMetricFamily("vgripd_refusals", "Triggers refused without a job "
                                       "(daemon and link handshakes), by status",
                                       labels=["status"])
        for status in (Status.BUSY, Status.ABORTED, Status.BAD_REQUEST):
            refused.setdefault(status.name, 0)
        for name, n in sorted(refused.items()):
            refusals.add_metric([name], n)
        yield refusals
        undelivered = CounterMetricFamily("vgripd_undelivered", "Answers whose publish "
                                          "failed, by the job's status", labels=["status"])
        for name, n in sorted(d.rooms.jobs.undelivered.items()):
            undelivered.add_metric([name], n)
        yield undelivered

        recipe = GaugeMetricFamily("vgripd_recipe_active", "1 for the recipe of the running "
                                   "or last job (docs/recipes.md)", labels=["recipe", "name"])
        recipes = d.recipe_snapshot()
        for r in recipes["recipes"]:
            recipe.add_metric([str(r["number"]), r["name"]],
                              1.0 if r["number"] == recipes["active"] else 0.0)
        yield recipe
        rc = d.rooms.jobs.epipolar
        yield GaugeMetricFamily("vgripd_recalibrate_warning", "1 while the RECALIBRATE "
                                "warning is up", value=1.0 if rc.warning else 0.0)
        yield GaugeMetricFamily("vgripd_epipolar_share_above", "Share of the recent stereo jobs "
                                "whose epipolar residual exceeds vision.epipolar_warn_px",
                                value=rc.share())
        yield GaugeMetricFamily("vgripd_healthy", "0 when the service needs a restart "
                                "(camera fault, wedged job)", value=1.0 if d.healthy() else 0.0)
        snap = d.snapshot()
        belts: dict[str, GaugeMetricFamily | CounterMetricFamily] = {
            "queued": GaugeMetricFamily("vgripd_conveyor_queued", "Parts waiting in a conveyor "
                                        "recipe's queue (docs/conveyor.md)", labels=["recipe"]),
            "seen": CounterMetricFamily("vgripd_conveyor_seen", "Part sightings the conveyor's "
                                        "images gave", labels=["recipe"]),
            "duplicates": CounterMetricFamily("vgripd_conveyor_duplicates", "Sightings of a "
                                              "part already queued or served", labels=["recipe"]),
            "dropped": CounterMetricFamily("vgripd_conveyor_dropped", "Parts that left the pick "
                                           "window before they were served", labels=["recipe"]),
            "served": CounterMetricFamily("vgripd_conveyor_served", "Parts served by NEXT",
                                          labels=["recipe"]),
            "travel_images": CounterMetricFamily("vgripd_conveyor_travel_images", "Jobs the "
                                                 "belt's travel started (trigger = travel)",
                                                 labels=["recipe"]),
            "skipped": CounterMetricFamily("vgripd_conveyor_skipped", "Trigger points the belt "
                                           "passed without their image (a job still ran)",
                                           labels=["recipe"]),
            "rebased": CounterMetricFamily("vgripd_conveyor_rebased", "Jumps of the published "
                                           "count the travel trigger started again from",
                                           labels=["recipe"]),
        }
        for number, q in snap.get("conveyor", {}).items():
            for key, family in belts.items():
                family.add_metric([number], float(q[key]))
        yield from belts.values()
        camera_open = bool(snap["camera"]["open"])
        yield GaugeMetricFamily("vgripd_camera_open", "1 while the camera is open",
                                value=1.0 if camera_open else 0.0)
        rec = d.rooms.jobs.recorder
        if rec is not None:
            yield GaugeMetricFamily("vgripd_recorder_bytes", "Bytes in the recording folder",
                                    value=float(rec.total_bytes))
            yield CounterMetricFamily("vgripd_recorder_dropped", "Jobs not recorded because "
                                      "the disk was behind", value=d.rooms.jobs.record_dropped)


class _AccessCollector(Collector):
    """The web view's wrong tokens (``access.Access``), read at scrape time."""

    def __init__(self, access: Any) -> None:
        self._access = access

    def collect(self) -> Iterator[Any]:
        a = self._access
        yield CounterMetricFamily("vgripd_web_login_failures", "Wrong tokens presented to the "
                                  "web view (Bearer header or /login), all addresses",
                                  value=a.failures)
        yield CounterMetricFamily("vgripd_web_lockouts", "Client addresses locked out of the "
                                  "web view's token after status.login_failures wrong ones",
                                  value=a.lockouts)
        yield CounterMetricFamily("vgripd_web_login_refused_locked", "Tokens refused "
                                  "unchecked (429) while their address was locked out",
                                  value=a.refused_locked)


class Metrics:
    """The daemon's metrics registry; ``observe`` each finished job, ``render`` to scrape."""

    def __init__(self, daemon: DaemonView, access: Any = None) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.jobs = Counter("vgripd_jobs", "Finished jobs by status (what the job found; "
                            "refusals are vgripd_refusals_total)", ["status"], registry=r)
        for status in Status:  # every series from 0, so rate() sees the first job
            if status not in (Status.IDLE, Status.BUSY, Status.BAD_REQUEST):
                self.jobs.labels(status.name)
        self.cycle = Histogram("vgripd_cycle_seconds", "Trigger received to result published",
                               buckets=CYCLE_BUCKETS_S, registry=r)
        self.stage = Histogram("vgripd_stage_seconds", "Duration of each stage of a job "
                               "(acquire, process and the pipeline's own stages)", ["stage"],
                               buckets=STAGE_BUCKETS_S, registry=r)
        self.epipolar = Histogram("vgripd_epipolar_residual_px", "Median epipolar residual "
                                  "of each stereo job (pixels)", buckets=EPIPOLAR_BUCKETS_PX,
                                  registry=r)
        self.epipolar_last = Gauge("vgripd_epipolar_residual_last_px", "Median epipolar "
                                   "residual of the last stereo job (pixels)", registry=r)
        self.undelivered_jobs = Counter("vgripd_jobs_undelivered", "Finished jobs whose "
                                        "result could not be published", registry=r)
        r.register(_DaemonCollector(daemon))
        if access is not None:
            r.register(_AccessCollector(access))

    def observe(self, record: JobRecord) -> None:
        result = record.result
        self.jobs.labels(result.status.name).inc()
        if record.published is None:
            self.undelivered_jobs.inc()
        self.cycle.observe(record.cycle_ms / 1e3)
        for stage, ms in result.timings_ms.items():
            self.stage.labels(stage).observe(ms / 1e3)
        epipolar_px = result.residuals.get("epipolar_px")
        if epipolar_px is not None:
            self.epipolar.observe(epipolar_px)
            self.epipolar_last.set(epipolar_px)

    def render(self) -> bytes:
        return generate_latest(self.registry)
