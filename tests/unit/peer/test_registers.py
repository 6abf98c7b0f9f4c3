"""Register map, codec, handshake and publish ordering (vgripd.peer.registers), without I/O.

Oracle for the encodings: ``struct`` packing written out here by hand (big-endian bytes, words
swapped for CDAB), not the codec under test.
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from vgripd.errors import LinkError
from vgripd.geometry.vendors import CONVENTIONS
from vgripd.peer.jobcore import Action, Command, Handshake, HandshakeState
from vgripd.peer.registers import (
    CHECK_F32,
    MAP_SIZE,
    MAP_VERSION,
    NO_AGE,
    BlockWrite,
    Reg,
    RegisterAccessError,
    RegisterBank,
    RegisterOverflowError,
    ValueCodec,
    Warnings,
)
from vgripd.registry import REGISTER_CAPABILITIES, LinkCapabilities
from vgripd.types import JobResult, PickInstance, RobotTarget, Status


def words_from_bytes(raw: bytes, order: str) -> list[int]:
    hi, lo = int.from_bytes(raw[:2], "big"), int.from_bytes(raw[2:], "big")
    return [hi, lo] if order == "ABCD" else [lo, hi]


def ok_result(values: tuple[float, ...], job_id: int = 7, rms: float = 0.25) -> JobResult:
    fields = tuple(f"v{i}" for i in range(len(values)))
    return JobResult(job_id=job_id, status=Status.OK, target=RobotTarget("kuka", fields, values),
                     residuals={"fit_rms_mm": rms}, t_done_mono_ns=1_000_000_000)


def pallet(*values: tuple[float, ...], rejected: int = 0) -> tuple[PickInstance, ...]:
    """Pickable instances with these values (pick ids 11, 12, ..., scores 0.9, 0.8, ...), then
    ``rejected`` OUT_OF_LIMITS ones."""
    fields = tuple(f"v{i}" for i in range(6))
    ok = tuple(PickInstance(Status.OK, target=RobotTarget("kuka", fields, v), pick_id=11 + i,
                            score=0.9 - 0.1 * i, residuals={"fit_rms_mm": 0.1 * (i + 1)})
               for i, v in enumerate(values))
    return ok + tuple(PickInstance(Status.OUT_OF_LIMITS, "offset beyond the limit", score=0.5)
                      for _ in range(rejected))


# --- codec ------------------------------------------------------------------------------------

@pytest.mark.parametrize("order", ["ABCD", "CDAB"])
def test_check_words_match_struct(order: str) -> None:
    bank = RegisterBank(ValueCodec(order))  # type: ignore[arg-type]
    w = bank.read(0, MAP_SIZE, 0)
    assert w[Reg.CHECK_U16] == 0x1234
    assert w[Reg.CHECK_U32:Reg.CHECK_U32 + 2] == words_from_bytes(bytes.fromhex("12345678"), order)
    assert w[Reg.CHECK_F32:Reg.CHECK_F32 + 2] == words_from_bytes(struct.pack(">f", CHECK_F32), order)
    # 123.456 as float32 is 0x42F6E979: the integrator's reference figure in docs/registers.md
    assert struct.pack(">f", CHECK_F32).hex() == "42f6e979"
    assert w[Reg.RESULT_AGE_MS:Reg.RESULT_AGE_MS + 2] == [0xFFFF, 0xFFFF]


@pytest.mark.parametrize("order", ["ABCD", "CDAB"])
@given(value=st.floats(-1e6, 1e6, allow_nan=False))
def test_float32_words(order: str, value: float) -> None:
    codec = ValueCodec(order, "float32")  # type: ignore[arg-type]
    words = codec.value(value)
    assert list(words) == words_from_bytes(struct.pack(">f", value), order)
    assert codec.decode_value(words) == np.float32(value)


@pytest.mark.parametrize("order", ["ABCD", "CDAB"])
@given(value=st.floats(-200_000, 200_000, allow_nan=False))
def test_int32_scaled_words(order: str, value: float) -> None:
    codec = ValueCodec(order, "int32", 10000)  # type: ignore[arg-type]
    words = codec.value(value)
    raw = round(value * 10000)
    assert list(words) == words_from_bytes(struct.pack(">i", raw), order)
    assert abs(codec.decode_value(words) - value) <= 0.5e-4 + 1e-9


@pytest.mark.parametrize(
    ("fmt", "value", "match"),
    [
        ("int32", 214748.3648, "does not fit an int32"),  # 2**31 / 10000
        ("int32", -214748.3649, "does not fit an int32"),
        ("int32", float("nan"), "not a finite number"),
        ("float32", 1e39, "float32 range"),
        ("float32", float("inf"), "not a finite number"),
    ],
)
def test_out_of_range_values_raise(fmt: str, value: float, match: str) -> None:
    codec = ValueCodec("ABCD", fmt, 10000)  # type: ignore[arg-type]
    with pytest.raises(RegisterOverflowError, match=match):
        codec.value(value, "VALUES[0]")


def test_int32_range_edges_are_exact() -> None:
    codec = ValueCodec("ABCD", "int32", 10000)
    assert list(codec.value(214748.3647)) == words_from_bytes(struct.pack(">i", 2**31 - 1), "ABCD")
    assert list(codec.value(-214748.3648)) == words_from_bytes(struct.pack(">i", -(2**31)), "ABCD")


# --- handshake --------------------------------------------------------------------------------

def test_handshake_edges_on_sequence() -> None:
    hs = Handshake()
    assert hs.on_request(Command.TRIGGER, 0).action is Action.IGNORE  # 0 is never a request
    start = hs.on_request(Command.TRIGGER, 5, recipe=3)
    assert (start.action, start.seq, start.recipe) == (Action.START, 5, 3)
    assert hs.state is HandshakeState.TRIGGERED
    assert hs.on_request(Command.TRIGGER, 5).action is Action.IGNORE  # level, not edge
    busy = hs.on_request(Command.TRIGGER, 6)
    assert (busy.action, busy.code) == (Action.REJECT, Status.BUSY)
    assert hs.running_seq == 5
    hs.on_captured(5)
    assert hs.state is HandshakeState.BUSY
    assert hs.on_request(Command.CLEAR, 7).code is Status.BUSY
    hs.on_published(5)
    assert hs.state is HandshakeState.DONE
    assert hs.on_request(Command.TRIGGER, 7).action is Action.IGNORE  # 7 was already refused
    assert hs.on_request(Command.TRIGGER, 8).action is Action.START
    assert hs.on_request(99, 9).code is Status.BAD_REQUEST


def test_handshake_restarted_plc_rearms_with_zero() -> None:
    hs = Handshake()
    assert hs.on_request(Command.CLEAR, 1).action is Action.CLEAR
    assert hs.on_request(Command.CLEAR, 1).action is Action.IGNORE
    assert hs.on_request(Command.CLEAR, 0).action is Action.IGNORE
    assert hs.on_request(Command.TRIGGER, 1).action is Action.START


def test_handshake_refuses_answers_for_other_requests() -> None:
    hs = Handshake()
    with pytest.raises(LinkError, match="publish for request 3, but the running request is none"):
        hs.on_published(3)
    hs.on_request(Command.TRIGGER, 4)
    with pytest.raises(LinkError, match="image_captured for request 3, but the running request is 4"):
        hs.on_captured(3)


# --- register bank: ordering and content ------------------------------------------------------

def test_publish_writes_data_first_and_ack_last() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    bank.write(Reg.CMD, [Command.TRIGGER, 11, 0])
    bank.captured(11, 42)
    journal.clear()
    bank.publish(11, ok_result((1.0, 2.0, 3.0, 4.0, 5.0, 6.0)), now_ns=0)
    assert journal[-1] == BlockWrite(Reg.ACK_SEQ, (11,))
    touched = {a for w in journal[:-1] for a in range(w.address, w.address + len(w.words))}
    assert set(range(Reg.STATUS, Reg.WARNINGS)) <= touched
    assert Reg.WARNINGS not in touched  # not part of a result


def test_new_job_retracts_ack_before_clearing_data() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    bank.write(Reg.CMD, [Command.TRIGGER, 1, 0])
    bank.captured(1, 1)
    bank.publish(1, ok_result((1.0, 2.0, 3.0, 4.0, 5.0, 6.0)), now_ns=0)
    journal.clear()
    bank.write(Reg.REQ_SEQ, [2])
    first_data = next(i for i, w in enumerate(journal) if w.address == Reg.STATUS)
    ack = next(i for i, w in enumerate(journal) if w.address == Reg.ACK_SEQ)
    assert journal[ack].words == (0,)
    assert ack < first_data
    w = bank.read(0, MAP_SIZE, 0)
    assert w[Reg.N_VALUES] == 0
    assert w[Reg.VALUES:Reg.WARNINGS] == [0] * (Reg.WARNINGS - Reg.VALUES)
    assert w[Reg.STATE] == HandshakeState.TRIGGERED


def test_busy_reject_leaves_running_job_untouched() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    bank.write(Reg.CMD, [Command.TRIGGER, 20, 0])
    bank.captured(20, 5)
    before = bank.read(0, MAP_SIZE, 0)
    journal.clear()
    decision = bank.write(Reg.REQ_SEQ, [21])
    assert decision.code is Status.BUSY
    assert journal[1:] == [BlockWrite(Reg.REJECT_CODE, (40,)), BlockWrite(Reg.REJECT_SEQ, (21,))]
    after = bank.read(0, MAP_SIZE, 0)
    changed = [i for i in range(MAP_SIZE) if before[i] != after[i]]
    assert changed == [Reg.REQ_SEQ, Reg.REJECT_SEQ, Reg.REJECT_CODE]
    bank.publish(20, ok_result((1.0, 2.0, 3.0, 4.0, 5.0, 6.0), job_id=5), now_ns=0)
    assert bank.read(Reg.ACK_SEQ, 2, 0) == [20, Status.OK]


def test_publish_content_quaternion_and_age() -> None:
    codec = ValueCodec("CDAB", "int32", 1000)
    bank = RegisterBank(codec)
    bank.write(Reg.CMD, [Command.TRIGGER, 3, 0])
    bank.captured(3, 0x01020304)
    values = (600.5, -100.25, 10.0, 0.5, 0.5, -0.5, 0.5)
    published = bank.publish(3, ok_result(values, job_id=0x01020304, rms=0.125), now_ns=0)
    assert published.status is Status.OK
    w = bank.read(0, MAP_SIZE, 1_000_000_000 + 1_234_000_000)
    assert w[Reg.N_VALUES] == 7
    got = [codec.decode_value(w[Reg.VALUES + 2 * i:Reg.VALUES + 2 * i + 2]) for i in range(7)]
    assert got == pytest.approx(values, abs=1e-9)
    assert codec.decode_u32(w[Reg.JOB_ID:Reg.JOB_ID + 2]) == 0x01020304
    assert codec.decode_u32(w[Reg.RESULT_AGE_MS:Reg.RESULT_AGE_MS + 2]) == 1234
    assert codec.decode_value(w[Reg.FIT_RMS:Reg.FIT_RMS + 2]) == 0.125
    assert (w[Reg.CAPTURED_SEQ], w[Reg.STATE], w[Reg.ACK_SEQ]) == (3, HandshakeState.DONE, 3)


def test_unrepresentable_value_publishes_out_of_limits_without_pose() -> None:
    bank = RegisterBank(ValueCodec("ABCD", "int32", 10000))
    bank.write(Reg.CMD, [Command.TRIGGER, 9, 0])
    published = bank.publish(9, ok_result((1e6, 0.0, 0.0, 0.0, 0.0, 0.0)), now_ns=0)
    assert published.status is Status.OUT_OF_LIMITS
    assert "does not fit an int32" in published.message
    w = bank.read(0, MAP_SIZE, 0)
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.N_VALUES]) == (9, Status.OUT_OF_LIMITS, 0)
    assert w[Reg.VALUES:Reg.FIT_RMS] == [0] * 14


def test_more_values_than_registers_is_internal_not_a_job_outcome() -> None:
    # Defensive only: REGISTER_CAPABILITIES makes the config check refuse such a vendor.
    bank = RegisterBank(ValueCodec())
    bank.write(Reg.CMD, [Command.TRIGGER, 4, 0])
    published = bank.publish(4, ok_result(tuple(float(i) for i in range(16))), now_ns=0)
    assert published.status is Status.INTERNAL
    assert "16 pose values (kuka) do not fit the 7 VALUES registers" in published.message
    w = bank.read(0, MAP_SIZE, 0)
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.N_VALUES]) == (4, Status.INTERNAL, 0)


def test_register_capabilities_carry_every_six_or_seven_value_convention() -> None:
    carried = {n for n, c in CONVENTIONS.items() if REGISTER_CAPABILITIES.refusal(c) is None}
    assert carried == {n for n, c in CONVENTIONS.items() if len(c.fields) in (6, 7)}
    assert carried >= {"kuka", "abb", "ur", "fanuc"}
    why = REGISTER_CAPABILITIES.refusal(CONVENTIONS["matrix"])
    assert why is not None
    assert "at most 7 pose values" in why
    assert '"matrix" has 16' in why


def test_capabilities_limited_to_named_conventions() -> None:
    caps = LinkCapabilities(6, frozenset({"ur"}), "m and rad")
    assert caps.refusal(CONVENTIONS["ur"]) is None
    assert caps.refusal(CONVENTIONS["kuka"]) == 'it carries only the "ur" convention (m and rad)'


def test_handshake_refusals_are_counted_by_code() -> None:
    bank = RegisterBank(ValueCodec())
    bank.write(Reg.CMD, [Command.TRIGGER, 1, 0])
    assert bank.write(Reg.CMD, [Command.TRIGGER, 2, 0]).code is Status.BUSY
    assert bank.write(Reg.CMD, [Command.TRIGGER, 3, 0]).code is Status.BUSY
    assert bank.write(Reg.CMD, [9, 4, 0]).code is Status.BAD_REQUEST
    assert bank.write(Reg.CMD, [9, 4, 0]).action is Action.IGNORE  # same sequence: no request
    assert bank.refusals == {"BUSY": 2, "BAD_REQUEST": 1}
    bank.publish(1, ok_result((1.0,) * 6), now_ns=0)
    assert bank.refusals == {"BUSY": 2, "BAD_REQUEST": 1}


def test_clear_resets_result_and_acknowledges() -> None:
    bank = RegisterBank(ValueCodec())
    bank.write(Reg.CMD, [Command.TRIGGER, 1, 0])
    bank.publish(1, ok_result((1.0,) * 6), now_ns=0)
    bank.write(Reg.CMD, [Command.CLEAR, 2, 0])
    w = bank.read(0, MAP_SIZE, 10**12)
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.N_VALUES], w[Reg.STATE]) == (2, 0, 0, 0)
    assert ValueCodec().decode_u32(w[Reg.RESULT_AGE_MS:Reg.RESULT_AGE_MS + 2]) == NO_AGE


@pytest.mark.parametrize(
    ("address", "values", "match"),
    [
        (3, [1], "only 0..2 \\(command area\\) are writable"),
        (2, [1, 1], "write of 2 registers at 2"),
        (Reg.ACK_SEQ, [5], "at 17"),
        (0, [70000], "0..65535"),
    ],
)
def test_writes_outside_the_command_area_are_refused(address: int, values: list[int], match: str) -> None:
    bank = RegisterBank(ValueCodec())
    before = bank.read(0, MAP_SIZE, 0)
    with pytest.raises(RegisterAccessError, match=match):
        bank.write(address, values)
    assert bank.read(0, MAP_SIZE, 0) == before


@pytest.mark.parametrize(("address", "count"), [(45, 2), (-1, 1), (46, 1), (0, 47), (0, 0)])
def test_reads_outside_the_map_are_refused(address: int, count: int) -> None:
    with pytest.raises(RegisterAccessError, match="outside 0..45"):
        RegisterBank(ValueCodec()).read(address, count, 0)


# The version 2 map, written out here (docs/registers.md, map version 2): a version 3 server
# must keep each of these at the same address, so a v2 client reading 0-40 keeps working.
V2_MAP = {"CMD": 0, "REQ_SEQ": 1, "RECIPE": 2, "MAP_VERSION": 3, "CHECK_U16": 4, "CHECK_U32": 5,
          "CHECK_F32": 7, "VALUE_FORMAT": 9, "VALUE_SCALE": 10, "HEARTBEAT": 12, "STATE": 13,
          "CAPTURED_SEQ": 14, "REJECT_SEQ": 15, "REJECT_CODE": 16, "ACK_SEQ": 17, "STATUS": 18,
          "JOB_ID": 19, "RESULT_AGE_MS": 21, "N_VALUES": 23, "VALUES": 24, "FIT_RMS": 38,
          "WARNINGS": 40}


def test_map_version_3_appends_the_pick_list_to_version_2() -> None:
    assert (MAP_VERSION, MAP_SIZE) == (4, 46)  # MAP_SIZE: the version 3 map, the default
    assert {r.name: int(r) for r in Reg if r < 41} == V2_MAP
    assert [(r.name, int(r)) for r in Reg if 41 <= r < MAP_SIZE] == [
        ("COUNT", 41), ("INDEX", 42), ("PICK_ID", 43), ("SCORE", 44)]  # SCORE: 44-45
    assert (int(Command.TRIGGER), int(Command.CLEAR), int(Command.NEXT)) == (1, 2, 3)
    bank = RegisterBank(ValueCodec())
    assert bank.read(Reg.MAP_VERSION, 1, 0) == [3]
    assert bank.read(Reg.WARNINGS, 6, 0) == [0] * 6


def test_v2_client_reading_0_to_40_sees_the_first_pickable_instance() -> None:
    # A pick-list job and the same object as a single-object job give the same words 0-40 to
    # a client that reads only those (apart from MAP_VERSION): version 2 clients keep working.
    values = (10.0, 20.0, 30.0, 1.0, 2.0, 3.0)
    single = ok_result(values, job_id=4, rms=0.5)
    listed = dataclasses.replace(single, instances=pallet(values, (5.0,) * 6))
    seen = []
    for result in (single, listed):
        bank = RegisterBank(ValueCodec())
        bank.write(Reg.CMD, [Command.TRIGGER, 1, 0])
        bank.captured(1, 4)
        bank.publish(1, result, now_ns=0)
        seen.append(bank.read(0, 41, 1_000_000_000))
    assert seen[0] == seen[1]


def test_warnings_are_live_and_survive_jobs_and_clear() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    journal.clear()
    bank.set_warnings(Warnings.RECALIBRATE)
    assert journal == [BlockWrite(Reg.WARNINGS, (1,))]
    bank.write(Reg.CMD, [Command.TRIGGER, 1, 0])  # a new job clears the result area only
    bank.captured(1, 1)
    bank.publish(1, ok_result((1.0,) * 6), now_ns=0)
    bank.write(Reg.CMD, [Command.CLEAR, 2, 0])
    assert bank.read(0, MAP_SIZE, 0)[Reg.WARNINGS] == 1
    bank.set_warnings(0)
    assert bank.read(Reg.WARNINGS, 1, 0) == [0]


@pytest.mark.parametrize("bits", [2, 0x8000, 0x10000, -1])
def test_reserved_warning_bits_are_refused(bits: int) -> None:
    bank = RegisterBank(ValueCodec())
    with pytest.raises(LinkError, match=f"warnings {bits:#x}: only bits 0x1"):
        bank.set_warnings(bits)
    assert bank.read(Reg.WARNINGS, 1, 0) == [0]


def test_heartbeat_wraps() -> None:
    bank = RegisterBank(ValueCodec())
    bank._heartbeat = 0xFFFE
    assert [bank.beat(), bank.beat()] == [0xFFFF, 0]
    assert bank.read(Reg.HEARTBEAT, 1, 0) == [0]
