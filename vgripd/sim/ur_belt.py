"""The conveyor part of the mock UR controller's simulated robot program: the twin of the
conveyor functions of ``robots/urscript/vgripd.script`` (docs/ur_rtde.md, "Conveyor").

The controller's encoder is a number the test sets (``set_encoder``: the raw tick count,
``encoder_get_tick_count(VGRIPD_ENCODER, opt="raw")``, 32 bits that wrap). Every request of a
conveyor program writes the count into the latch register in the same data package as its
sequence: the encoder now, or for PREDICT (command 5) the count N it asks for. Each answer's belt
block is read once its own sequence is in it.

``belt_track`` is ``vgripd_belt_track``: NEXT, the part's grip at RESULT_COUNT carried along the
belt to the count at which tracking starts (``travel``), where ``track_conveyor_linear`` takes
over; ``tracked`` is the controller's side of that: the TCP target at any later count, moved
with the belt. ``belt_intercept`` is ``vgripd_belt_intercept``: NEXT, then PREDICT for the
count ``lead`` ticks ahead, the grip where the part will be then (a fixed station's intercept).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from vgripd.peer.jobcore import Command
from vgripd.peer.ur_registers import URRegisterMap, int32_bits

if TYPE_CHECKING:
    from vgripd.peer.ur_registers import URRegisterMap as _Regs


def travel_m(count_from: int, count_to: int, ticks_per_m: float, bits: int = 32) -> float:
    """``vgripd_belt_travel``: metres the belt moved from ``count_from`` to ``count_to`` (raw
    counts), across the counter's wrap (the shorter way round)."""
    span = float(1 << bits)
    d = float(count_to) - float(count_from)
    d = d % span
    if d >= span / 2:
        d -= span
    return d / ticks_per_m


def pose_add(pose: Sequence[float], shift: Sequence[float]) -> tuple[float, ...]:
    """URScript ``pose_add`` with a pure translation (rotation vector 0): the position moved."""
    return (*(p + s for p, s in zip(pose[:3], shift, strict=True)), *pose[3:])


def tracked(grip: Sequence[float], start_count: int, count: int, direction: Sequence[float],
            ticks_per_m: float, bits: int = 32) -> tuple[float, ...]:
    """The controller while ``track_conveyor_linear(direction, ticks_per_m)`` runs: a target
    given at ``start_count`` (tracking started) is at this pose at ``count``."""
    s = travel_m(start_count, count, ticks_per_m, bits)
    return pose_add(grip, [d * s for d in direction[:3]])


class BeltProgram:
    """Mixin of the mock controller's server process (``ur_controller._Server``)."""

    #: The raw encoder count (int32 bits), as ``encoder_get_tick_count(.., opt="raw")``.
    encoder: int = 0
    #: The count N a PREDICT asks for (the script's ``vgripd_predict_count``).
    predict_count: int = 0

    if TYPE_CHECKING:
        inputs: dict[str, Any]
        outputs: dict[str, Any]
        default_attempts: int
        default_busy_wait_s: float

        def trigger(self, command: int, regs: _Regs, recipe: int = 0) -> int: ...

        async def wait_input(self, name: str, value: int, deadline: float) -> bool: ...

        async def program(self, command: int, seq: int, regs: _Regs, timeout_s: float,
                          taught_pose: Sequence[float] | None, t_start: float, attempts: int,
                          busy_wait_s: float, recipe: int = 0) -> dict[str, Any]: ...

    def write_latch(self, command: int, regs: URRegisterMap) -> None:
        """The latch of a request, set with its sequence (``vgripd_request``)."""
        if regs.conveyor:
            count = self.predict_count if command == Command.PREDICT else self.encoder
            self.outputs[f"output_int_register_{regs.latch}"] = int32_bits(count)

    async def read_belt(self, seq: int, regs: URRegisterMap, deadline: float,
                        result: dict[str, Any]) -> bool:
        """The belt block of the answer to ``seq`` into ``result["belt"]``; False when its
        sequence did not come before ``deadline``."""
        names = regs.belt_names
        if not await self.wait_input(names[0], seq, deadline):
            result["error"] = f"timeout waiting for {names[0]} == {seq}"
            return False
        seq_, count, source, queued, err, along, across, theta = (
            self.inputs.get(n, 0) for n in names)
        result["belt"] = {"count": int(count) & 0xFFFFFFFF, "raw_count": int(count),
                          "source": int(source), "queued": int(queued), "error_mm": float(err),
                          "along_mm": float(along), "across_mm": float(across),
                          "theta_deg": float(theta)}
        return True

    async def ask(self, command: int, regs: URRegisterMap, timeout_s: float,
                  taught: Sequence[float] | None, recipe: int) -> dict[str, Any]:
        """``vgripd_locate(command, timeout_s)`` of a conveyor program."""
        seq = self.trigger(command, regs, recipe)
        return await self.program(command, seq, regs, timeout_s, taught, time.monotonic(),
                                  self.default_attempts, self.default_busy_wait_s, recipe)

    async def cmd_set_encoder(self, count: int) -> None:
        self.encoder = int32_bits(count)

    async def cmd_set_predict_count(self, count: int) -> None:
        self.predict_count = int32_bits(count)

    async def cmd_belt_track(self, taught: Sequence[float], direction: Sequence[float],
                             ticks_per_m: float, bits: int, timeout_s: float, upper: bool,
                             recipe: int) -> dict[str, Any]:
        """``vgripd_belt_track``: NEXT; for status 1/2 ``grip`` (at RESULT_COUNT) carried to
        ``start_count`` (the encoder now, when tracking starts) is ``start_grip``."""
        regs = URRegisterMap(upper, conveyor=True)
        result = await self.ask(int(Command.NEXT), regs, timeout_s, taught, recipe)
        if result.get("target") is None or "belt" not in result:
            return result
        start = self.encoder
        result["start_count"] = start
        s = travel_m(result["belt"]["raw_count"], start, ticks_per_m, bits)
        result["start_grip"] = pose_add(result["target"], [d * s for d in direction[:3]])
        return result

    async def cmd_belt_intercept(self, taught: Sequence[float], lead: int, timeout_s: float,
                                 upper: bool, recipe: int) -> dict[str, Any]:
        """``vgripd_belt_intercept``: NEXT, then PREDICT for the encoder now + ``lead`` ticks;
        ``next`` is the NEXT's answer, the rest the PREDICT's (``target``: the grip there)."""
        regs = URRegisterMap(upper, conveyor=True)
        served = await self.ask(int(Command.NEXT), regs, timeout_s, taught, recipe)
        if served.get("status") not in (1, 2):
            return {**served, "next": served}
        self.predict_count = int32_bits(self.encoder + lead)
        result = await self.ask(int(Command.PREDICT), regs, timeout_s, taught, recipe)
        return {**result, "next": served, "predict_count": self.predict_count & 0xFFFFFFFF}
