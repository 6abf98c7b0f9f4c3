"""Triggering by belt travel, without I/O (docs/conveyor.md, "Triggering by travel").

With ``conveyor.trigger = "travel"`` the PLC only publishes the belt's encoder count; the
daemon starts a job every ``trigger_distance_mm`` of travel. ``TravelRule`` is that decision
as a function of the counts read: each count goes in with the time it was read and whether a
job runs, a ``TravelStep`` comes out:

- the first count seen is an image (``Travel.IMAGE``); after it, an image each time the count
  has advanced ``trigger_distance_mm`` since the last image. A count that stands still, or
  moves less, is ``Travel.WAIT``;
- a trigger point that passes while a job runs is skipped (``Travel.SKIP``), counted, never
  taken late: the next trigger point is one distance further on. Trigger points the count
  stepped over between two readings are skipped too (the link reads too seldom for the belt);
- a count that moves farther than the belt can between two readings (``reach_mm``: the
  trigger distance plus twice ``speed_mm_s`` over the time between them), either way, is a
  jump (a PLC restart, a counter preset): the rule starts again from it as from a first
  count (one image, no burst), and says why.

Counts are ``bits`` wide and wrap; every difference is ``count_delta``'s shortest one, so the
rule sees the same belt on either side of the wrap. Positions are kept as the travel since the
last image in counts (a float: ``trigger_distance_mm * counts_per_mm`` need not be whole).
``TravelStats`` are the images started, the trigger points skipped and the jumps re-based.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from vgripd.geometry.belt import count_delta

#: Slack (counts) in comparing the travel with the trigger distance, against float rounding.
EPS_COUNTS = 1e-6


class Travel(enum.Enum):
    WAIT = "wait"  # no trigger point reached
    IMAGE = "image"  # start a job now, at this count
    SKIP = "skip"  # trigger points passed while a job ran: no image, counted


@dataclass(frozen=True)
class TravelStep:
    """The rule's answer to one count. ``skipped``: trigger points passed without their image
    at this reading; ``burst_start``: the first skipped since the last image (the one to log);
    ``first``: the count the rule started from (the first seen, or a jump's); ``jump``: why
    the count was re-based ("" when it was not)."""

    action: Travel
    count: int
    skipped: int = 0
    burst_start: bool = False
    first: bool = False
    jump: str = ""


@dataclass
class TravelStats:
    images: int = 0
    skipped: int = 0
    rebased: int = 0


@dataclass
class TravelRule:
    """When to take an image of the belt (the module docstring has the rules)."""

    counts_per_mm: float
    distance_mm: float
    speed_mm_s: float
    bits: int = 32
    stats: TravelStats = field(default_factory=TravelStats)
    _last: int | None = None
    _t_last_ns: int = 0
    #: Travel since the last image (or the last skipped trigger point), counts.
    _since: float = 0.0
    #: Trigger points skipped since the last image.
    _burst: int = 0

    @property
    def distance_counts(self) -> float:
        return self.distance_mm * self.counts_per_mm

    def restart(self) -> None:
        """Forget the counts seen: the next one is a first count (an image)."""
        self._last = None
        self._since = 0.0
        self._burst = 0

    def reach_mm(self, dt_ns: int) -> float:
        """The farthest the belt may move, either way, between two readings ``dt_ns`` apart
        before the second is a jump."""
        return self.distance_mm + 2.0 * self.speed_mm_s * max(dt_ns, 0) * 1e-9

    def feed(self, count: int, t_ns: int, busy: bool) -> TravelStep:
        """The count ``count`` read at ``t_ns`` (monotonic ns); ``busy``: a job runs."""
        count %= 1 << self.bits
        if self._last is None:
            return self._start(count, t_ns, busy, "")
        delta = count_delta(self._last, count, self.bits)
        dt_ns = t_ns - self._t_last_ns
        moved_mm = delta / self.counts_per_mm
        reach = self.reach_mm(dt_ns)
        if abs(moved_mm) > reach:
            self.stats.rebased += 1
            return self._start(count, t_ns, busy,
                               f"count {self._last} -> {count}: {moved_mm:+.1f} mm in "
                               f"{dt_ns / 1e9:.3f} s, farther than the belt moves "
                               f"({reach:.1f} mm)")
        self._last, self._t_last_ns = count, t_ns
        self._since += delta
        if self._since < self.distance_counts - EPS_COUNTS:
            return TravelStep(Travel.WAIT, count)
        passed = math.floor(self._since / self.distance_counts + EPS_COUNTS)
        if busy:
            self._since -= passed * self.distance_counts
            return self._skip(count, passed)
        stepped_over = passed - 1
        self._since = 0.0
        burst_start = stepped_over > 0 and self._burst == 0
        self._burst = 0
        self.stats.images += 1
        self.stats.skipped += stepped_over
        return TravelStep(Travel.IMAGE, count, stepped_over, burst_start)

    def _start(self, count: int, t_ns: int, busy: bool, jump: str) -> TravelStep:
        self._last, self._t_last_ns, self._since = count, t_ns, 0.0
        if busy:
            step = self._skip(count, 1)
            return TravelStep(step.action, count, 1, step.burst_start, True, jump)
        self._burst = 0
        self.stats.images += 1
        return TravelStep(Travel.IMAGE, count, first=True, jump=jump)

    def _skip(self, count: int, passed: int) -> TravelStep:
        burst_start = self._burst == 0
        self._burst += passed
        self.stats.skipped += passed
        return TravelStep(Travel.SKIP, count, passed, burst_start)
