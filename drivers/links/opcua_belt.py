"""The conveyor on the OPC UA link (docs/conveyor.md; docs/opcua.md, "Conveyor").

Both address spaces carry what register map version 4 carries, with the same rules:

- two variables the client writes, ``LatchCount`` and ``LatchFrame`` (UInt32): the encoder count
  it latched with the trigger and, for ``latch = "frame_id"``, the camera frame that count
  belongs to. A request (StartSingleJob, StartContinuous's jobs, ``Plc.StartJob``, Next) takes
  the values in place when it starts, as a Modbus request takes LATCH_COUNT when REQ_SEQ
  changes. Variables rather than method arguments, so that the standard's methods keep their
  signatures and a PLC without structure support writes two plain UInt32 (one Write request)
  before its call;
- ``Predict(Count)``, a method with the count N as its one plain argument: where the part last
  served to this link will be at N (the register map's PREDICT with LATCH_COUNT = N);
- the belt result (``BELT_RESULT``): the count the pose belongs to, where that count came from,
  the error it leaves, the pose in belt terms and the queue's length, written with the other
  result data, before the request's id (all 0 for a part that stands still).

Nothing here keeps state: the link reads the latch variables at each request (``read_latch``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from asyncua import Server, ua

from vgripd.types import BeltPose

U32 = 0xFFFFFFFF

#: The belt result: name, type, value without a belt, description; written in this order with
#: the other result data (before RequestId / ResultId).
BELT_RESULT: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("ResultCount", ua.VariantType.UInt32, 0,
     "conveyor: the encoder count the pose shown belongs to (0: no conveyor)"),
    ("LatchSource", ua.VariantType.UInt16, 0,
     "where that count came from: 0 none (a part that stands still), 1 link, 2 frame id, "
     "3 timestamp"),
    ("LatchErrMm", ua.VariantType.Double, 0.0,
     "one-sigma position error along the belt the latch leaves, mm"),
    ("Along", ua.VariantType.Double, 0.0,
     "the pose at ResultCount along the belt, mm from the belt's origin in its direction"),
    ("Across", ua.VariantType.Double, 0.0,
     "the pose at ResultCount across the belt in its plane, mm (to the left of the travel)"),
    ("Theta", ua.VariantType.Double, 0.0, "its rotation about the belt's normal, deg"),
    ("Queued", ua.VariantType.UInt16, 0, "parts waiting in the recipe's queue after this answer"),
)
#: The variables the client writes (docs/opcua.md, "Conveyor").
LATCH_INPUTS: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("LatchCount", ua.VariantType.UInt32, 0,
     "written by the client: the encoder count latched with the next request (a job or Next)"),
    ("LatchFrame", ua.VariantType.UInt32, 0,
     "written by the client: the camera frame that count belongs to (latch = \"frame_id\")"),
)


def belt_values(belt: BeltPose | None) -> list[tuple[str, Any]]:
    """``BELT_RESULT``'s ``(name, value)`` pairs for a result's ``belt`` (None: the values of a
    part that stands still)."""
    if belt is None:
        return [(name, value) for name, _, value, _ in BELT_RESULT]
    return [("ResultCount", belt.count & U32), ("LatchSource", belt.source & 0xFFFF),
            ("LatchErrMm", float(belt.error_mm)), ("Along", float(belt.along_mm)),
            ("Across", float(belt.across_mm)), ("Theta", float(belt.theta_deg)),
            ("Queued", min(max(belt.queued, 0), 0xFFFF))]


def belt_finite(belt: BeltPose | None) -> bool:
    """The belt result's numbers are finite (a pose that is not is never shown)."""
    return belt is None or all(math.isfinite(v) for v in (
        belt.error_mm, belt.along_mm, belt.across_mm, belt.theta_deg))


def belt_variants(belt: BeltPose | None) -> list[tuple[str, ua.Variant]]:
    """The belt result as typed variants (OPC 40100's ResultContent pairs); none without a
    belt."""
    if belt is None:
        return []
    types = {name: vtype for name, vtype, _, _ in BELT_RESULT}
    return [(name, ua.Variant(value, types[name])) for name, value in belt_values(belt)]


def latch_word(value: ua.DataValue | None) -> int | None:
    """A latch variable's value as a request takes it: an unsigned 32-bit count; None when it
    holds none (a client wrote a bad status, which makes it null, or a value of another type
    onto the null)."""
    if value is None or value.Value is None or (
            value.StatusCode is not None and not value.StatusCode.is_good()):
        return None
    word = value.Value.Value
    if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= U32:
        return None
    return word


def read_latch(server: Server, count: ua.NodeId, frame: ua.NodeId) -> tuple[int | None,
                                                                            int | None]:
    """``(LatchCount, LatchFrame)`` as they are now (``latch_word`` each)."""
    return (latch_word(server.read_attribute_value(count)),
            latch_word(server.read_attribute_value(frame)))


def count_argument(method: str, args: Sequence[ua.Variant]) -> int | tuple[str, str]:
    """Predict's one argument, the count N (any integer type, 0 .. 2^32 - 1); else the
    refusal: ``(status code name, why)``."""
    if not args:
        return "BadArgumentsMissing", f"{method} needs Count (the encoder count N)"
    if len(args) > 1:
        return "BadTooManyArguments", f"{method} takes one argument (Count)"
    value = args[0].Value
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= U32:
        return "BadInvalidArgument", f"{method}: Count {value!r} is not an encoder count " \
                                     f"0..{U32}"
    return value
