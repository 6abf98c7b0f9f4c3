"""``[conveyor]``: a moving belt the parts are seen and picked on (docs/conveyor.md)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from vgripd.config.common import Model

#: coarser than a part's tolerance; above, no encoder input counts that fast at belt speed.
COUNTS_PER_MM_RANGE = (0.05, 5000.0)
#: Largest angle (deg) between ``conveyor.direction`` and the belt plane.
BELT_PLANE_DEG = 0.5


class ConveyorConfig(Model):
    """A moving belt the parts are seen and picked on (docs/conveyor.md). Absent: parts stand
    still between the trigger and the pick.

    ``latch``: where the belt position at the exposure comes from: ``"link"`` (the PLC or robot
    latches the encoder count with the trigger and writes it with the request), ``"frame_id"``
    (the camera is triggered by an encoder divider; the PLC writes the count it latched with
    the frame's id), ``"timestamp"`` (no latch: the count the link last reported, carried to
    the exposure's device timestamp at ``speed_mm_s``; each job states the error this leaves).
    ``direction``: the belt's travel in the base frame (unit, in the plane of ``normal``);
    ``origin_mm``: a point on the belt surface; ``window_mm``: the pick window as
    (upstream, downstream) distances along the belt from ``origin_mm``; ``trigger_distance_mm``:
    belt travel between two images; ``speed_mm_s``: the highest belt speed (for the blur check
    and the timestamp latch); ``max_blur_px``: the largest smear in the image during one
    exposure at that speed; ``sigma_mm``: one sigma of a part's position carried along the belt
    (from ``vgripd calibrate conveyor``), whose ``match_sigmas`` multiple matches the same part
    in two images. ``trigger``: ``"request"`` (each image is a job the PLC or robot asks for)
    or ``"travel"`` (the PLC only publishes the count; the daemon starts a job every
    ``trigger_distance_mm`` of travel, docs/conveyor.md "Triggering by travel").
    """

    latch: Literal["link", "frame_id", "timestamp"] = "link"
    trigger: Literal["request", "travel"] = "request"
    counts_per_mm: float = Field(gt=0)
    encoder_bits: Literal[16, 32] = 32
    direction: tuple[float, float, float]
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    window_mm: tuple[float, float]
    trigger_distance_mm: float = Field(gt=0)
    speed_mm_s: float = Field(gt=0, le=10_000.0)
    max_blur_px: float = Field(default=1.0, gt=0)
    sigma_mm: float = Field(default=0.5, gt=0)
    match_sigmas: float = Field(default=6.0, ge=1.0, le=100.0)
    match_deg: float = Field(default=5.0, gt=0, le=180.0)
    timestamp_error_ms: float = Field(default=2.0, ge=0)

    @model_validator(mode="after")
    def _belt(self) -> ConveyorConfig:
        for name in ("direction", "normal"):
            v = getattr(self, name)
            length = math.sqrt(sum(x * x for x in v))
            if abs(length - 1.0) > 1e-3:
                raise ValueError(f"conveyor.{name} {list(v)} is not a unit vector (length "
                                 f"{length:.6g}): give the belt's {name} normalised")
        dot = sum(a * b for a, b in zip(self.direction, self.normal, strict=True))
        tilt = math.degrees(math.asin(min(1.0, abs(dot))))
        if tilt > BELT_PLANE_DEG:
            raise ValueError(f"conveyor.direction {list(self.direction)} leaves the belt plane "
                             f"(normal {list(self.normal)}) by {tilt:.2f} deg (at most "
                             f"{BELT_PLANE_DEG} deg): the belt runs in its own plane")
        lo, hi = COUNTS_PER_MM_RANGE
        if not lo <= self.counts_per_mm <= hi:
            raise ValueError(f"conveyor.counts_per_mm {self.counts_per_mm:g} is implausible "
                             f"(expected {lo:g} .. {hi:g} counts per mm): mm per count given, "
                             "or counts per metre?")
        up, down = self.window_mm
        if not up < down:
            raise ValueError(f"conveyor.window_mm {list(self.window_mm)}: the upstream limit "
                             "must be below the downstream one (distances along direction)")
        if self.trigger_distance_mm >= down - up:
            raise ValueError(f"conveyor.trigger_distance_mm {self.trigger_distance_mm:g} is "
                             f"not shorter than the pick window ({down - up:g} mm): parts "
                             "would pass between two images")
        if self.trigger == "travel":
            self._travel_fits()
        return self

    def _travel_fits(self) -> None:
        """Triggering by travel: the count is read, not latched at the exposure, and the
        trigger distance is a small part of the counter's range (the wrap stays unambiguous)."""
        if self.latch != "timestamp":
            raise ValueError(f'conveyor.latch = "{self.latch}" with trigger = "travel": the '
                             "link publishes the count now, none is latched at the exposure "
                             'and LATCH_FRAME has no count of its own: set latch = "timestamp" '
                             "(the count carried to the image's time)")
        span = 1 << self.encoder_bits
        if self.trigger_distance_mm * self.counts_per_mm >= span / 4:
            raise ValueError(f"conveyor.trigger_distance_mm {self.trigger_distance_mm:g} is "
                             f"{self.trigger_distance_mm * self.counts_per_mm:.0f} counts, not "
                             f"below a quarter of the {self.encoder_bits}-bit counter "
                             f"({span // 4}): the travel between two counts read is ambiguous")

    def window_points(self) -> list[tuple[float, float, float]]:
        """The pick window's two ends on the belt line, in the base frame."""
        (ox, oy, oz), (dx, dy, dz) = self.origin_mm, self.direction
        return [(ox + s * dx, oy + s * dy, oz + s * dz) for s in self.window_mm]
