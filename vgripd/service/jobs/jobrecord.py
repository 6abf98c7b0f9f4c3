"""What a finished job leaves behind, as the daemon hands it to its listeners (the web view,
metrics, the demo, tests): the ``JobRecord``, the listener signature, and the epipolar monitor
whose RECALIBRATE warning the status and metrics show. Kept below the daemon so its readers
(``vgripd.service.web``) need not import the daemon.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Callable
from typing import Any

from vgripd.types import ImagePair, JobResult, Status


@dataclasses.dataclass(frozen=True)
class JobRecord:
    """A finished job as the daemon remembers it (for status and listeners).

    ``published``: the status the triggering link gave its peer (``result.status`` unless the
    link had to answer something else); None when the publish failed.
    """

    job_id: int
    link: str
    seq: int
    result: JobResult
    cycle_ms: float  # trigger received -> result published
    t_done_mono_ns: int
    published: Status | None = None
    recipe: int = 0


JobListener = Callable[[ImagePair | None, JobRecord], None]


class EpipolarMonitor:
    """How often recent stereo jobs exceeded the epipolar warning level (the RECALIBRATE
    warning). Jobs without an ``epipolar_px`` residual (mono, no pose) are not counted.

    The warning is judged once ``min_jobs`` residuals are in the window of ``window``; it is up
    while the share above ``threshold_px`` exceeds ``share``.
    """

    def __init__(self, window: int, share: float, min_jobs: int, threshold_px: float) -> None:
        self.above: deque[bool] = deque(maxlen=window)
        self.share_limit = share
        self.min_jobs = min_jobs
        self.threshold_px = threshold_px
        self.warning = False
        self.since_mono_ns = 0

    def share(self) -> float:
        return sum(self.above) / len(self.above) if self.above else 0.0

    def add(self, epipolar_px: float, now_ns: int) -> bool:
        """Count one job's median epipolar residual (px); True when the warning changed."""
        self.above.append(epipolar_px > self.threshold_px)
        warning = len(self.above) >= self.min_jobs and self.share() > self.share_limit
        if warning == self.warning:
            return False
        self.warning, self.since_mono_ns = warning, now_ns
        return True

    def describe(self) -> str:
        return (f"{sum(self.above)} of the last {len(self.above)} stereo jobs had a median "
                f"epipolar residual above vision.epipolar_warn_px = {self.threshold_px} px "
                f"(share {self.share():.2f}, daemon.recalibrate_share = {self.share_limit})")

    def snapshot(self, now_ns: int) -> dict[str, Any]:
        return {"warning": self.warning, "jobs": len(self.above), "above": sum(self.above),
                "share": self.share(), "share_limit": self.share_limit,
                "threshold_px": self.threshold_px, "window": self.above.maxlen,
                "min_jobs": self.min_jobs,
                "since_s": (now_ns - self.since_mono_ns) / 1e9 if self.warning else None}
