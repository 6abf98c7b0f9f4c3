"""The S7 link's data block without the PLC (``vgripd.peer.s7_block``): the plan of writes that
takes the PLC's copy of the block to the register bank's state, replayed on a list of words.
The link sending these plans to a PLC: tests/drivers/links/test_s7.py, test_s7_conveyor.py."""

from __future__ import annotations

from vgripd.peer.registers import (
    LATCH_AREA,
    MAP_SIZE_V4,
    BlockWrite,
    Reg,
    RegisterBank,
    ValueCodec,
)
from vgripd.peer.s7_block import plan_db_writes
from vgripd.types import BeltPose, JobResult, RobotTarget, Status


def kuka_result(job_id: int) -> JobResult:
    target = RobotTarget("kuka", ("x", "y", "z", "a", "b", "c"),
                         (412.5, -133.25, 287.0625, 12.34, -29.0, 179.5))
    return JobResult(job_id=job_id, status=Status.OK, target=target,
                     residuals={"fit_rms_mm": 0.042})


def belt_result(seq: int, count: int) -> JobResult:
    """An answer in belt terms at ``count``, the latch its request carried."""
    target = RobotTarget("kuka", tuple("XYZABC"), (400.0 + seq, 12.5, 10.0, 30.0, 0.0, 180.0))
    belt = BeltPose(count=count, source=1, error_mm=0.05, along_mm=400.0 + seq,
                    across_mm=-7.25, theta_deg=30.0, queued=3)
    return JobResult(job_id=100 + seq, status=Status.OK, target=target, belt=belt)


def test_plan_sends_data_in_one_write_then_ack_alone() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    sent = list(bank.image.words)
    journal.clear()
    bank.write(0, [1, 9, 0])
    bank.captured(9, 3)
    bank.publish(9, kuka_result(3), 0)
    plan = plan_db_writes(sent, journal)
    assert all(w.address >= 3 for w in plan)
    acks = [w for w in plan if w.address <= Reg.ACK_SEQ < w.address + len(w.words)
            and len(w.words) == 1]
    assert acks == [BlockWrite(Reg.ACK_SEQ, (9,))]  # 0 -> 0 at the start is no change
    assert plan[-1] == BlockWrite(Reg.ACK_SEQ, (9,))
    assert len(plan) == 2  # the job's data (state, captured, result) in one write
    # replaying the plan on the PLC's copy gives the bank's image outside the command area
    image = list(sent)
    for w in plan:
        image[w.address:w.address + len(w.words)] = w.words
    assert image[3:] == bank.image.words[3:]
    # The next job retracts the acknowledge before its data is cleared.
    sent2, journal[:] = image, []
    bank.write(0, [1, 10, 0])
    plan2 = plan_db_writes(sent2, journal)
    assert plan2[0] == BlockWrite(Reg.ACK_SEQ, (0,))
    assert all(len(w.words) > 1 or w.address != Reg.ACK_SEQ for w in plan2[1:])


def test_the_plan_never_writes_the_latch() -> None:
    """A publish changes words on both sides of the latch (the pick list below, the belt
    result above): one write on each side, never a span over the PLC's LATCH_COUNT."""
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal, version=4)
    bank.handshake.queue = True
    sent = list(bank.image.words)
    journal.clear()
    bank.write(Reg.LATCH_COUNT, [0x1234, 0x5678])
    bank.write(0, [1, 9, 0])
    bank.captured(9, 3)
    bank.publish(9, belt_result(9, 0x12345678), 0)
    own = [range(3, LATCH_AREA.start), range(LATCH_AREA.stop, MAP_SIZE_V4)]
    plan = plan_db_writes(sent, journal, own)
    assert all(not (w.address < LATCH_AREA.stop and w.address + len(w.words) > LATCH_AREA.start)
               for w in plan), plan
    assert plan[-1] == BlockWrite(Reg.ACK_SEQ, (9,))
    assert [w.address for w in plan[:-1]] == [Reg.STATE, Reg.RESULT_COUNT]
