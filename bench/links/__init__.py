"""The link-latency experiment, one module per link (``bench/bench_link.py --link NAME``).

Each module's ``measure(jobs)`` runs the link against its peer over loopback and a named peer
doing the least the same wire needs, in the same run, and returns a :class:`LinkRun`. On the
daemon side a stand-in answers every trigger at once (:func:`answer_at_once`: image captured,
then an OK pose), so what is timed is the link, not vision work.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from vgripd.service.links.protocol import Trigger
from vgripd.types import JobResult, RobotTarget, Status


@dataclass
class Series:
    """One measured row: trigger-to-result times in ms; ``against`` names the peer row it is
    compared with (None for a peer row)."""

    name: str
    ms: list[float]
    against: str | None = None


@dataclass
class LinkRun:
    heading: str  #: the section's heading in bench/RESULTS.md
    setup: str  #: what was timed, where, and what the peer does
    series: list[Series]
    notes: list[str] = field(default_factory=list)


def answer_at_once(link: Any, target: RobotTarget,
                   residuals: dict[str, float] | None = None) -> Callable[[Trigger], None]:
    """The daemon stand-in: for each trigger, ``image_captured`` then ``publish`` of an OK
    result with ``target``. Keeps its tasks referenced until they end."""
    tasks: set[asyncio.Task[None]] = set()

    async def answer(t: Trigger) -> None:
        await link.image_captured(t.seq, t.seq)
        await link.publish(t.seq, JobResult(job_id=t.seq, status=Status.OK, target=target,
                                            residuals=residuals or {}))

    def on_trigger(t: Trigger) -> None:
        task = asyncio.get_running_loop().create_task(answer(t))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    return on_trigger
