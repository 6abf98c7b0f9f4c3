"""Triggering by belt travel in the daemon (docs/conveyor.md, "Triggering by travel"): the thin
shell around ``belttravel.TravelRule``.

The count's source is the first link in ``links`` that publishes one (``publishes_count``: the
Modbus server and RTU links take each write of LATCH_COUNT, the Modbus client and S7 links
read it with every poll); it hands every count to ``BeltTravel.on_count``. Each count is kept
by every conveyor recipe that triggers by travel (its images are latched from them), and fed
to the rule of the active recipe (the running or last job's; 0 before the first job) when that
recipe triggers by travel. The rule's ``Travel.IMAGE`` starts a job through the daemon's own
trigger path (walk, admission, camera, processing, queue, counters, recorder, listeners), as a
request of the ``BeltLink`` (named ``BELT_LINK``): its answer goes nowhere, its parts only to
the part queue, where NEXT serves them. A job that runs, a several-view job waiting or a walk
makes the rule skip; a jump in the count is logged (rate-limited) and the rule starts again.
"""

from __future__ import annotations

import logging
from typing import ClassVar

from pydantic import BaseModel

from vgripd.peer.belttravel import Travel, TravelRule
from vgripd.peer.jobcore import Command
from vgripd.registry import LinkCapabilities
from vgripd.service.jobs.runner import JobRunner
from vgripd.service.jobs.walkmode import WalkMode
from vgripd.service.links.protocol import LinkHealth, LinkState, RobotLink, Trigger, TriggerHandler
from vgripd.service.links.ratelog import RateLimitedLog
from vgripd.service.links.supervision import LinkSupervisor
from vgripd.types import JobResult, Status

log = logging.getLogger("vgripd.conveyor")

BELT_LINK = "belt"


class _NoOptions(BaseModel):
    pass


class BeltLink(RobotLink):
    """The requester of the jobs the belt's travel starts: no peer, its answers stay here."""

    Options: ClassVar[type[BaseModel]] = _NoOptions
    capabilities: ClassVar[LinkCapabilities] = LinkCapabilities(max_values=1 << 16)

    def __init__(self, source: str) -> None:
        super().__init__(BELT_LINK, _NoOptions())
        self.source = source
        self._state = LinkState.UP  # nothing to open

    async def open(self, on_trigger: TriggerHandler) -> None:
        self._state = LinkState.UP
        self.health_changed()

    async def close(self) -> None:
        self._state = LinkState.STOPPED
        self.health_changed()

    def health(self) -> LinkHealth:
        return LinkHealth(state=self._state, peer=f"belt travel (count from {self.source})")

    async def image_captured(self, seq: int, job_id: int) -> None:
        pass

    async def publish(self, seq: int, result: JobResult) -> Status:
        return result.status


class BeltTravel:
    """Counts in, jobs out (the module docstring has the rules). Jobs start through
    ``walks.on_trigger`` (the daemon's trigger handler: a walk's link goes to the walk, the
    rest to ``runner``)."""

    def __init__(self, runner: JobRunner, links: LinkSupervisor, walks: WalkMode) -> None:
        self.runner = runner
        self.links = links
        self._walks = walks
        self.source = next((name for name, link in links.links.items()
                            if link.publishes_count), None)
        self._seq = 0
        self._rule: TravelRule | None = None  # the rule fed last (a new one starts afresh)
        self._jumps = RateLimitedLog(log, interval_s=60.0)
        if self.source is not None:
            links.links[self.source].watch_count(self.on_count)

    def on_count(self, count: int, t_ns: int) -> None:
        """A count the source link read at ``t_ns``; never raises into the link."""
        try:
            self._count(count, t_ns)
        except Exception:
            log.exception("conveyor: count %d from %s", count, self.source)

    def _count(self, count: int, t_ns: int) -> None:
        runner = self.runner
        for each in runner.core.lines.values():
            if each.travel is not None:
                each.count_read(count, t_ns)
        recipe = runner.active_recipe or 0
        line = runner.core.lines.get(recipe)
        if line is None or line.travel is None or not runner.accepting:
            return
        rule = line.travel
        if rule is not self._rule:  # another recipe, or a reload's new belt: start afresh
            rule.restart()
            self._rule = rule
        busy = runner.job is not None or runner.views is not None or self._walks.walking
        step = rule.feed(count, t_ns, busy)
        where = f"conveyor of recipe {recipe}"
        if step.jump:
            self._jumps.warning(str(recipe), "jump", "%s: %s: re-based, the next image at count "
                                "%d (a PLC restart or a counter preset?)", where, step.jump, count)
        elif step.first:
            log.info("%s: triggering by travel from count %d (%s), an image every %g mm",
                     where, count, self.source, rule.distance_mm)
        if step.burst_start and step.action is Travel.SKIP:
            job = runner.job[0] if runner.job is not None else "(views or walk)"
            log.warning("%s: trigger point passed at count %d while job %s runs: image skipped "
                        "(the belt outruns the jobs; the skipped images of this burst are "
                        "counted in vgripd_conveyor_skipped_total, not logged)", where, count,
                        job)
        elif step.burst_start:
            log.warning("%s: %d trigger points passed between two counts read (now %d): "
                        "images skipped (the count is published too seldom for the belt)",
                        where, step.skipped, count)
        if step.action is Travel.IMAGE:
            self._start(recipe, count, t_ns)

    def _start(self, recipe: int, count: int, t_ns: int) -> None:
        if BELT_LINK not in self.links.links:  # added with the first job the belt starts
            belt = BeltLink(self.source or "?")
            self.links.links[BELT_LINK] = belt
            self.links.watch(belt)
            belt.health_changed()  # a new link in the status
        self._seq = self._seq % 0xFFFF + 1
        self._walks.on_trigger(Trigger(link=BELT_LINK, seq=self._seq, command=Command.TRIGGER,
                              t_mono_ns=t_ns, recipe=recipe, latch_count=count))
