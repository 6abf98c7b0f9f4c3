"""Pick lists in the register map (version 3): COUNT, INDEX, PICK_ID, SCORE and Command.NEXT
(vgripd.peer.registers), without I/O.

The answers a NEXT gets are built with ``next_answer`` (what the daemon does) and published
through the same ``RegisterBank`` a Modbus server, RTU or mirror client link uses.
"""

from __future__ import annotations

import dataclasses
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from vgripd.errors import LinkError
from vgripd.peer.jobcore import (
    UNKNOWN_SCORE,
    Action,
    Command,
    Handshake,
    HandshakeState,
    NextAnswer,
    PickPosition,
    next_answer,
    pick_position,
    pickable_count,
)
from vgripd.peer.registers import MAP_SIZE, BlockWrite, Reg, RegisterBank, ValueCodec
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

FIELDS = tuple(f"v{i}" for i in range(6))


def pallet_job(n_ok: int, rejected: int = 0, job_id: int = 7) -> JobResult:
    """A job of ``n_ok`` pickable instances (x = 100, 200, ...; pick ids 11, 12, ...; scores
    0.9, 0.8, ...) then ``rejected`` OUT_OF_LIMITS ones; the top level shows instance 1 (or the
    first rejected one when none is pickable), as the vision's contract says."""
    ok = tuple(PickInstance(Status.OK, target=RobotTarget("kuka", FIELDS,
                                                          (100.0 * (i + 1), 0, 0, 0, 0, 0)),
                            pick_id=11 + i, score=0.9 - 0.1 * i,
                            residuals={"fit_rms_mm": 0.1 * (i + 1)})
               for i in range(n_ok))
    bad = tuple(PickInstance(Status.OUT_OF_LIMITS, "offset beyond the limit", score=0.5,
                             pick_id=1) for _ in range(rejected))
    instances = ok + bad
    first = instances[0]
    return JobResult(job_id=job_id, status=first.status, message=first.message,
                     target=first.target, residuals=first.residuals,
                     t_capture_mono_ns=500_000_000, t_done_mono_ns=1_000_000_000,
                     instances=instances)


def x_of(codec: ValueCodec, w: list[int]) -> float:
    return codec.decode_value(w[Reg.VALUES:Reg.VALUES + 2])


def score_of(codec: ValueCodec, w: list[int]) -> float:
    return codec.decode_value(w[Reg.SCORE:Reg.SCORE + 2])


def run_job(bank: RegisterBank, seq: int, result: JobResult) -> list[int]:
    assert bank.write(Reg.CMD, [Command.TRIGGER, seq, 0]).action is Action.START
    bank.captured(seq, result.job_id)
    bank.publish(seq, result, now_ns=0)
    return bank.read(0, MAP_SIZE, result.t_done_mono_ns)


def run_next(bank: RegisterBank, seq: int, job: JobResult, index: int) -> list[int]:
    decision = bank.write(Reg.CMD, [Command.NEXT, seq, 0])
    assert (decision.action, decision.command) == (Action.START, Command.NEXT)
    bank.publish(seq, next_answer(job, index), now_ns=0)
    return bank.read(0, MAP_SIZE, job.t_done_mono_ns + 2_500_000_000)


# --- positions and answers ---------------------------------------------------------------


def test_positions_of_single_object_and_pick_list_results() -> None:
    single = JobResult(job_id=1, status=Status.OK, target=RobotTarget("kuka", FIELDS, (0,) * 6))
    assert pick_position(single) == PickPosition(1, 1, 0, UNKNOWN_SCORE)
    failed = JobResult(job_id=1, status=Status.NOT_FOUND)
    assert pick_position(failed) == PickPosition(0, 0)
    assert not pick_position(failed).listed
    job = pallet_job(3, rejected=2)
    assert pickable_count(job) == 3
    assert pick_position(job) == PickPosition(3, 1, 11, pytest.approx(0.9))
    none_pickable = pallet_job(0, rejected=2)
    assert none_pickable.status is Status.OUT_OF_LIMITS
    assert pick_position(none_pickable) == PickPosition(0, 0)


def test_next_answers_walk_the_pickable_instances_then_run_past_the_end() -> None:
    job = pallet_job(3, rejected=2)
    answers = [next_answer(job, i) for i in (2, 3, 4, 9)]
    assert [a.target.values[0] if a.target else None for a in answers] == [200, 300, None, None]
    assert [(a.status, a.index) for a in answers] == [
        (Status.OK, 2), (Status.OK, 3), (Status.NOT_FOUND, 4), (Status.NOT_FOUND, 4)]
    assert [pick_position(a) for a in answers[:2]] == [
        PickPosition(3, 2, 12, pytest.approx(0.8)), PickPosition(3, 3, 13, pytest.approx(0.7))]
    assert pick_position(answers[2]) == PickPosition(3, 4)
    assert "all 3 pickable instances were handed out" in answers[2].message
    for a in answers:  # the job's identity and age, never a new job
        assert (a.job_id, a.t_capture_mono_ns, a.t_done_mono_ns) == (7, 500_000_000,
                                                                     1_000_000_000)
    assert answers[0].residuals["fit_rms_mm"] == pytest.approx(0.2)
    # A rejected instance is never handed out by NEXT: the list ends at the pickable ones.
    assert all(a.status.pose_valid or a.target is None for a in answers)


def test_next_answer_refuses_a_job_without_a_list() -> None:
    with pytest.raises(ValueError, match="no pick list instance 2"):
        next_answer(JobResult(job_id=3, status=Status.NOT_FOUND), 2)
    with pytest.raises(ValueError, match="no pick list instance 0"):
        next_answer(pallet_job(2), 0)


def test_a_single_object_job_is_a_list_of_one() -> None:
    single = JobResult(job_id=5, status=Status.OK, t_done_mono_ns=9,
                       target=RobotTarget("kuka", FIELDS, (1, 2, 3, 4, 5, 6)))
    again = next_answer(single, 1)
    assert (again.target, again.index, again.job_id) == (single.target, 1, 5)
    assert (next_answer(single, 2).status, next_answer(single, 2).index) == (Status.NOT_FOUND, 2)


# --- handshake ---------------------------------------------------------------------------


def test_handshake_next_needs_a_list_and_an_idle_link() -> None:
    hs = Handshake()
    refused = hs.on_request(Command.NEXT, 1)  # after start: no list
    assert (refused.action, refused.code) == (Action.REJECT, Status.BAD_REQUEST)
    assert hs.on_request(Command.TRIGGER, 2).action is Action.START
    assert hs.on_request(Command.NEXT, 3).code is Status.BUSY  # while the job runs
    hs.on_published(2, listed=True)
    nxt = hs.on_request(Command.NEXT, 4)
    assert (nxt.action, nxt.command) == (Action.START, Command.NEXT)
    assert hs.on_request(Command.NEXT, 5).code is Status.BUSY  # while the NEXT is answered
    hs.on_published(4, listed=True)
    assert hs.on_request(Command.NEXT, 6).action is Action.START
    hs.on_published(6, listed=True)
    assert hs.on_request(Command.CLEAR, 7).action is Action.CLEAR
    assert hs.on_request(Command.NEXT, 8).code is Status.BAD_REQUEST  # CLEAR ends the list
    assert hs.on_request(Command.TRIGGER, 9).action is Action.START
    hs.on_published(9, listed=False)  # a job that found nothing
    assert hs.on_request(Command.NEXT, 10).code is Status.BAD_REQUEST


def test_a_new_trigger_ends_the_list_before_its_job_is_published() -> None:
    hs = Handshake()
    hs.on_request(Command.TRIGGER, 1)
    hs.on_published(1, listed=True)
    hs.on_request(Command.TRIGGER, 2)
    hs.on_published(2, listed=False)  # e.g. the daemon's BUSY or a failed job
    assert hs.on_request(Command.NEXT, 3).code is Status.BAD_REQUEST


# --- register bank -----------------------------------------------------------------------


@pytest.mark.parametrize("codec", [ValueCodec(), ValueCodec("CDAB", "int32", 10000)])
def test_pallet_walked_with_next_over_the_bank(codec: ValueCodec) -> None:
    bank = RegisterBank(codec)
    job = pallet_job(3, rejected=1)
    w = run_job(bank, 1, job)
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.COUNT], w[Reg.INDEX], w[Reg.PICK_ID]) == (
        1, Status.OK, 3, 1, 11)
    assert (x_of(codec, w), score_of(codec, w)) == pytest.approx((100.0, 0.9), abs=1e-4)
    for seq, index in ((2, 2), (3, 3)):
        w = run_next(bank, seq, job, index)
        assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.COUNT], w[Reg.INDEX]) == (
            seq, Status.OK, 3, index)
        assert w[Reg.PICK_ID] == 10 + index
        assert x_of(codec, w) == pytest.approx(100.0 * index)
        assert codec.decode_u32(w[Reg.JOB_ID:Reg.JOB_ID + 2]) == 7  # the same job
        # RESULT_AGE_MS counts from the job's result (the images are that old): 2.5 s
        assert codec.decode_u32(w[Reg.RESULT_AGE_MS:Reg.RESULT_AGE_MS + 2]) == 2500
        assert w[Reg.CAPTURED_SEQ] == 1  # no image was taken for a NEXT
    w = run_next(bank, 4, job, 4)
    assert (w[Reg.STATUS], w[Reg.N_VALUES], w[Reg.COUNT], w[Reg.INDEX], w[Reg.PICK_ID]) == (
        Status.NOT_FOUND, 0, 3, 4, 0)
    assert w[Reg.VALUES:Reg.FIT_RMS] == [0] * 14
    assert score_of(codec, w) == -1
    # past the end the list is still there: NEXT keeps answering NOT_FOUND at COUNT + 1
    assert run_next(bank, 5, job, 5)[Reg.INDEX] == 4


def test_next_retracts_ack_first_and_publishes_the_pick_area_before_ack() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    job = pallet_job(2)
    run_job(bank, 1, job)
    journal.clear()
    bank.write(Reg.CMD, [Command.NEXT, 2, 0])
    assert journal[1] == BlockWrite(Reg.ACK_SEQ, (0,))  # [0] is the peer's own write
    cleared = {w.address: w.words for w in journal[2:]}
    assert cleared[Reg.COUNT] == (0,) * 5
    assert cleared[Reg.STATUS][0] == Status.IDLE
    journal.clear()
    bank.publish(2, next_answer(job, 2), now_ns=0)
    assert journal[-1] == BlockWrite(Reg.ACK_SEQ, (2,))
    touched = {a for w in journal[:-1] for a in range(w.address, w.address + len(w.words))}
    assert set(range(Reg.STATUS, Reg.WARNINGS)) | set(range(Reg.COUNT, MAP_SIZE)) <= touched
    assert Reg.WARNINGS not in touched


def test_next_refusals_change_nothing_but_the_reject_registers() -> None:
    bank = RegisterBank(ValueCodec())
    job = pallet_job(2)
    run_job(bank, 1, job)
    bank.write(Reg.CMD, [Command.CLEAR, 2, 0])
    before = bank.read(0, MAP_SIZE, 0)
    refused = bank.write(Reg.CMD, [Command.NEXT, 3, 0])
    assert (refused.action, refused.code) == (Action.REJECT, Status.BAD_REQUEST)
    after = bank.read(0, MAP_SIZE, 0)
    assert [i for i in range(MAP_SIZE) if before[i] != after[i]] == [
        Reg.CMD, Reg.REQ_SEQ, Reg.REJECT_SEQ, Reg.REJECT_CODE]
    assert bank.refusals == {"BAD_REQUEST": 1}


def test_no_stale_pose_of_a_previous_job_after_a_new_trigger() -> None:
    # Job A lists 3; job B finds nothing: a NEXT must not hand out A's second instance.
    bank = RegisterBank(ValueCodec())
    run_job(bank, 1, pallet_job(3, job_id=1))
    w = run_job(bank, 2, JobResult(job_id=2, status=Status.NOT_FOUND, t_done_mono_ns=5))
    assert (w[Reg.COUNT], w[Reg.INDEX]) == (0, 0)
    assert bank.write(Reg.CMD, [Command.NEXT, 3, 0]).code is Status.BAD_REQUEST
    assert bank.read(Reg.ACK_SEQ, 2, 0) == [2, Status.NOT_FOUND]


def test_daemon_refusal_of_next_ends_the_list_in_the_link() -> None:
    # The daemon answers BAD_REQUEST (its list belongs to another link's later job).
    bank = RegisterBank(ValueCodec())
    run_job(bank, 1, pallet_job(2))
    assert bank.write(Reg.CMD, [Command.NEXT, 2, 0]).action is Action.START
    bank.publish(2, JobResult(job_id=0, status=Status.BAD_REQUEST), now_ns=0)
    w = bank.read(0, MAP_SIZE, 0)
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.COUNT], w[Reg.N_VALUES]) == (
        2, Status.BAD_REQUEST, 0, 0)
    assert bank.write(Reg.CMD, [Command.NEXT, 3, 0]).code is Status.BAD_REQUEST


def test_instance_that_overflows_int32_is_skipped_not_the_list() -> None:
    codec = ValueCodec("ABCD", "int32", 10000)
    bank = RegisterBank(codec)
    job = pallet_job(2)
    far = dataclasses.replace(job.instances[1], target=RobotTarget("kuka", FIELDS,
                                                                    (1e6, 0, 0, 0, 0, 0)))
    job = dataclasses.replace(job, instances=(job.instances[0], far))
    run_job(bank, 1, job)
    w = run_next(bank, 2, job, 2)
    assert (w[Reg.STATUS], w[Reg.N_VALUES], w[Reg.COUNT], w[Reg.INDEX]) == (
        Status.OUT_OF_LIMITS, 0, 2, 2)
    assert bank.handshake.listed  # the PLC can still step past it
    assert run_next(bank, 3, job, 3)[Reg.INDEX] == 3


def test_bank_state_after_next_is_done_and_counts_as_a_request() -> None:
    bank = RegisterBank(ValueCodec())
    job = pallet_job(2)
    run_job(bank, 1, job)
    bank.write(Reg.CMD, [Command.NEXT, 2, 0])
    assert bank.read(Reg.STATE, 1, 0) == [HandshakeState.TRIGGERED]
    assert bank.read(Reg.ACK_SEQ, 1, 0) == [0]
    bank.publish(2, next_answer(job, 2), now_ns=0)
    assert bank.read(Reg.STATE, 1, 0) == [HandshakeState.DONE]
    assert isinstance(next_answer(job, 2), NextAnswer)


# --- UR pick register --------------------------------------------------------------------


def test_ur_pick_word() -> None:
    regs = URRegisterMap()
    assert (regs.pick, URRegisterMap(upper=True).pick) == (22, 46)
    assert regs.pick_word(PickPosition(5, 2)) == 5002.0
    assert regs.pick_word(PickPosition(0, 0)) == 0.0
    assert {1, 3} == regs.COMMANDS
    with pytest.raises(LinkError, match="count 1000"):
        regs.pick_word(PickPosition(1000, 1))
    # the robot program's decoding (robots/urscript): floor(p / 1000), p - 1000 * count
    p = regs.pick_word(PickPosition(17, 18))
    assert (int(p // 1000), int(p - 1000 * (p // 1000))) == (17, 18)
    assert struct.unpack(">d", struct.pack(">d", p))[0] == p  # exact as a double


# --- properties ----------------------------------------------------------------------------


@given(st.integers(0, 6), st.integers(0, 3))
def test_walking_a_list_hands_out_each_pickable_instance_once_in_order(n_ok: int,
                                                                       rejected: int) -> None:
    if n_ok + rejected == 0:
        return
    job = pallet_job(n_ok, rejected)
    if n_ok == 0:
        assert not pick_position(job).listed
        return
    walk = [job] + [next_answer(job, i) for i in range(2, n_ok + 3)]
    shown = [a.target for a in walk if a.target is not None]
    assert shown == [i.target for i in job.instances[:n_ok]]
    assert [pick_position(a).index for a in walk] == [*range(1, n_ok + 2), n_ok + 1]
    assert all(pick_position(a).count == n_ok for a in walk)
    assert [a.status for a in walk[n_ok:]] == [Status.NOT_FOUND, Status.NOT_FOUND]


OPS = st.lists(st.sampled_from(["trigger_list", "trigger_none", "next", "clear"]),
               max_size=30)


@given(OPS)
def test_a_pose_shown_always_belongs_to_the_latest_job(ops: list[str]) -> None:
    """Any sequence of PLC requests against the bank and a daemon stand-in that answers NEXT
    from the last job's list (as the daemon does): whenever ACK_SEQ shows a pose, it is an
    instance of the job triggered last, never of an earlier one, and never a second time."""
    bank = RegisterBank(ValueCodec())
    job_id = 0
    cursor: tuple[JobResult, int] | None = None
    handed: set[tuple[int, float]] = set()
    for seq, op in enumerate(ops, start=1):
        command = {"next": Command.NEXT, "clear": Command.CLEAR}.get(op, Command.TRIGGER)
        decision = bank.write(Reg.CMD, [command, seq, 0])
        if decision.action is Action.START and command == Command.TRIGGER:
            job_id += 1
            job = (pallet_job(3, job_id=job_id) if op == "trigger_list"
                   else JobResult(job_id=job_id, status=Status.NOT_FOUND))
            bank.captured(seq, job_id)
            bank.publish(seq, job, now_ns=0)
            cursor = (job, 1) if pick_position(job).listed else None
        elif decision.action is Action.START:  # NEXT, accepted by the handshake
            assert cursor is not None
            assert cursor[0].job_id == job_id
            index = min(cursor[1] + 1, pickable_count(cursor[0]) + 1)
            cursor = (cursor[0], index)
            bank.publish(seq, next_answer(cursor[0], index), now_ns=0)
        elif decision.action is Action.CLEAR:
            cursor = None
        w = bank.read(0, MAP_SIZE, 0)
        if w[Reg.ACK_SEQ] == seq and w[Reg.N_VALUES]:
            shown_job = ValueCodec().decode_u32(w[Reg.JOB_ID:Reg.JOB_ID + 2])
            assert shown_job == job_id
            key = (shown_job, x_of(ValueCodec(), w))
            assert key not in handed, f"instance {key} handed out twice"
            handed.add(key)


def test_next_answers_keep_the_jobs_recipe() -> None:
    job = dataclasses.replace(pallet_job(2), recipe=4)
    assert [next_answer(job, i).recipe for i in (2, 3)] == [4, 4]
