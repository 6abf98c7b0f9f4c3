"""The UR link's handshake plans as register writes (``vgripd.peer.ur_wire``), no I/O:
the order the robot program relies on (docs/ur_rtde.md, "Handshake"), pinned write by write."""

from __future__ import annotations

from vgripd.peer import ur_wire
from vgripd.peer.jobcore import Action, Command
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.types import JobResult, RobotTarget, Status

UR = RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"), (0.1, 0.2, 0.3, 0.0, 0.1, 0.2))


def test_a_job_writes_data_then_ack_and_holds_the_rotation_page() -> None:
    regs = URRegisterMap()
    hs = ur_wire.handshake(regs)
    start = hs.on_request(Command.TRIGGER, 7)
    assert start.action is Action.START
    assert ur_wire.writes(regs, start.steps) == ()  # the robot's new seq retracts
    assert ur_wire.writes(regs, hs.on_captured(7, 3)) == (("int", 21, 3), ("int", 20, 7))
    plan = hs.publish(7, JobResult(3, Status.OK, target=UR))
    assert ur_wire.writes(regs, plan) == (
        ("double", 18, 0.1), ("double", 19, 0.2), ("double", 20, 0.3), ("double", 22, 1001.0),
        ("int", 19, 1), ("int", 21, 3), ("int", 18, 7), ("page", 7, (0.0, 0.1, 0.2)))


def test_refusals_are_answers_without_a_pose_and_clear_is_no_ur_command() -> None:
    regs = URRegisterMap(conveyor=True)
    hs = ur_wire.handshake(regs)
    clear = hs.on_request(Command.CLEAR, 1)
    assert (clear.action, clear.code) == (Action.REJECT, Status.BAD_REQUEST)
    assert ur_wire.writes(regs, clear.steps) == (
        ("double", 22, 0.0), ("belt", regs.belt_values(1, None)), ("int", 19, 32),
        ("int", 21, 0), ("int", 18, 1), ("page", 1, None))
    assert hs.on_request(Command.PREDICT, 2).action is Action.START  # map 4: the daemon judges
    busy = hs.on_request(Command.TRIGGER, 3)
    assert (busy.action, busy.code) == (Action.REJECT, Status.BUSY)
    assert hs.on_request(Command.TRIGGER, 3).action is Action.IGNORE  # the same seq again
    assert URRegisterMap().refusal(int(Command.CLEAR)) is Status.BAD_REQUEST


def test_a_pose_the_robot_cannot_take_is_answered_internal() -> None:
    kuka = RobotTarget("kuka", tuple("XYZABC"), (1.0, 2.0, 3.0, 0.0, 0.0, 0.0))
    answer, why = ur_wire.ur_answer(JobResult(8, Status.OK, target=kuka))
    assert (answer.status, answer.target, answer.job_id) == (Status.INTERNAL, None, 8)
    assert "needs a 'ur' target" in why
    ok = JobResult(9, Status.OK, target=UR)
    assert ur_wire.ur_answer(ok) == (ok, "")
