"""The UR RTDE link's side of the handshake without I/O: ``jobcore.Handshake`` decides, this
module says what each decision writes into the UR registers (``URRegisterMap``).

The rules are the ones every link obeys (``vgripd.peer.jobcore``): a request is a change of
the robot's sequence (output_int_register ``seq``) to a new non-zero value, a request while this
link's own request runs is refused BUSY, an unknown command BAD_REQUEST, a NEXT without a pick
list (or a PREDICT without a conveyor) BAD_REQUEST, and the acknowledge is written last. What
the UR registers add is how the plan's steps look on them (``writes``):

- ``RETRACT``, ``CLEAR`` and ``STATE`` write nothing: the map has no state register, and the
  robot's own new sequence is the retraction (it reads nothing before ``ack`` names it, and it
  picks a sequence that neither an old request nor an old answer holds);
- ``JOB_ID`` and ``CAPTURED``: ``job_id``, then ``captured`` = seq;
- ``RESULT``: the translation page (a pose only), ``pick``, the belt block (map version 4),
  ``status``, ``job_id``; the rotation page waits for the robot's page request;
- ``ACK``: ``ack`` = seq, and the rotation page held for the robot's page request;
- ``REJECT``: the map has no refusal registers, so a refusal is an answer without a pose:
  ``pick`` 0, the belt block without a pose, ``status`` = code, ``job_id`` 0, then ``ack``.

A write is a tuple the link's child process carries out in order: ``("int", register,
value)`` (input_int_register), ``("double", register, value)`` (input_double_register),
``("belt", values)`` (the belt block, one data package), ``("page", seq, rotation | None)``
(the rotation page to hand out when the robot asks for ``seq``; None: none).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from vgripd.peer.jobcore import Command, Handshake, Part, Step
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.types import JobResult, Status

Write = tuple[Any, ...]


def handshake(regs: URRegisterMap) -> Handshake:
    """A UR link's handshake: register semantics (``edge``), the commands of the map (locate,
    next, capture; PREDICT with the conveyor's map). A conveyor's map lets NEXT and PREDICT
    through to the daemon until it says whether a recipe has a conveyor (``set_conveyor``)."""
    hs = Handshake(edge=True)
    hs.commands = frozenset({*regs.COMMANDS, int(Command.CAPTURE),
                             *([int(Command.PREDICT)] if regs.conveyor else [])})
    hs.queue = regs.conveyor
    return hs


def ur_answer(result: JobResult) -> tuple[JobResult, str]:
    """The answer the robot gets for ``result``, and why it differs ("" when it does not).

    A valid status needs a ``ur`` target of 6 finite values (the robot program's
    ``p[x, y, z, rx, ry, rz]``); otherwise the answer is INTERNAL without a pose, list or belt
    block (the config refuses any other ``output.vendor``, so only a bug gets here).
    """
    target = result.target
    if not result.status.pose_valid or (
            target is not None and target.vendor == "ur" and len(target.values) == 6
            and all(math.isfinite(v) for v in target.values)):
        return result, ""
    why = (f"job {result.job_id}: status {result.status.name} needs a 'ur' target of 6 finite "
           f"values, got {target}")
    return dataclasses.replace(result, status=Status.INTERNAL, target=None, instances=(),
                               belt=None, message=why), why


def writes(regs: URRegisterMap, plan: tuple[Step, ...]) -> tuple[Write, ...]:
    """The register writes of ``plan`` (a ``Handshake`` plan), in order."""
    out: list[Write] = []
    rotation: tuple[float, ...] | None = None
    for step in plan:
        if step.part is Part.JOB_ID:
            out.append(("int", regs.job_id, step.value))
        elif step.part is Part.CAPTURED:
            out.append(("int", regs.captured, step.seq))
        elif step.part is Part.RESULT:
            result, position = step.result, step.position
            assert result is not None
            assert position is not None
            rotation = None
            if result.status.pose_valid and result.target is not None:
                values = tuple(float(v) for v in result.target.values)
                out += [("double", reg, v) for reg, v in zip(regs.page, values[:3], strict=True)]
                rotation = values[3:]
            out.append(("double", regs.pick,
                        regs.pick_word(position) if position.listed else 0.0))
            if regs.conveyor:
                out.append(("belt", regs.belt_values(step.seq, result.belt)))
            out += [("int", regs.status, int(result.status)), ("int", regs.job_id, result.job_id)]
        elif step.part is Part.ACK:
            out += [("int", regs.ack, step.seq), ("page", step.seq, rotation)]
        elif step.part is Part.REJECT:
            out.append(("double", regs.pick, 0.0))
            if regs.conveyor:
                out.append(("belt", regs.belt_values(step.seq, None)))
            out += [("int", regs.status, step.value), ("int", regs.job_id, 0),
                    ("int", regs.ack, step.seq), ("page", step.seq, None)]
    return tuple(out)
