"""The Modbus PDU answerer without a socket: every served function code, the exception codes
at each edge of the map and of the quantity limits, the decision a write hands the shell, and
that no PDU makes it raise.

Oracle: request and reply bytes packed here by hand with ``struct`` from the Modbus application
protocol, the bank's own words read back directly.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vgripd.peer.jobcore import Action, Command, Decision
from vgripd.peer.modbus_pdu import (
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    SERVED,
    Answered,
    Malformed,
    Refused,
    Written,
    answer,
)
from vgripd.peer.registers import MAP_SIZE, MAP_SIZE_V4, Reg, RegisterBank, ValueCodec

NOW_NS = 5_000_000_000


def bank(version: int = 3) -> RegisterBank:
    return RegisterBank(ValueCodec(), version=version)


def read(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def write_single(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, address, value)


def write_multiple(address: int, values: list[int], count: int | None = None,
                   byte_count: int | None = None) -> bytes:
    count = len(values) if count is None else count
    byte_count = 2 * len(values) if byte_count is None else byte_count
    return struct.pack(f">BHHB{len(values)}H", 16, address, count, byte_count, *values)


def mask_write(address: int, and_mask: int, or_mask: int) -> bytes:
    return struct.pack(">BHHH", 22, address, and_mask, or_mask)


def read_write(read_address: int, read_count: int, write_address: int,
               values: list[int], write_count: int | None = None) -> bytes:
    write_count = len(values) if write_count is None else write_count
    return struct.pack(f">BHHHHB{len(values)}H", 23, read_address, read_count, write_address,
                       write_count, 2 * len(values), *values)


def refused(pdu: bytes, b: RegisterBank, code: int) -> Refused:
    """Answer ``pdu``, which must be refused with ``code`` and leave the bank's words alone."""
    before = list(b.image.words)
    reply, decision = answer(pdu, b, NOW_NS)
    assert reply == bytes((pdu[0] | 0x80, code))
    assert isinstance(decision, Refused)
    assert (decision.function, decision.code) == (pdu[0], code)
    assert b.image.words == before
    return decision


# --- served ---------------------------------------------------------------------------------


@pytest.mark.parametrize("version", [3, 4])
def test_read_holding_serves_the_words(version: int) -> None:
    b = bank(version)
    size = b.image.size
    reply, decision = answer(read(0, size), b, NOW_NS)
    assert decision == Answered(3)
    assert reply == struct.pack(f">BB{size}H", 3, 2 * size, *b.image.words)
    assert struct.unpack_from(">H", reply, 2 + 2 * Reg.CHECK_U16) == (0x1234,)


def test_read_serves_the_result_age_as_of_the_time_passed_in() -> None:
    b = bank()
    b.image.set_result_time(NOW_NS - 250_000_000)
    reply, _ = answer(read(Reg.RESULT_AGE_MS, 2), b, NOW_NS)
    assert struct.unpack(">BBHH", reply) == (3, 4, 0, 250)
    reply, _ = answer(read(Reg.RESULT_AGE_MS, 2), b, NOW_NS + 1_000_000_000)
    assert struct.unpack(">BBHH", reply) == (3, 4, 0, 1250)


def test_write_single_echoes_and_writes() -> None:
    b = bank()
    pdu = write_single(Reg.RECIPE, 7)
    reply, decision = answer(pdu, b, NOW_NS)
    assert reply == pdu
    assert isinstance(decision, Written)
    assert (decision.function, decision.address, decision.values) == (6, Reg.RECIPE, (7,))
    assert decision.outcome.action is Action.IGNORE  # not the request register
    assert b.image.words[Reg.RECIPE] == 7


def test_write_to_the_request_register_decides_a_job() -> None:
    b = bank()
    reply, decision = answer(write_multiple(Reg.CMD, [Command.TRIGGER, 5, 2]), b, NOW_NS)
    assert reply == struct.pack(">BHH", 16, Reg.CMD, 3)
    assert isinstance(decision, Written)
    assert (decision.function, decision.address, decision.values) == (16, Reg.CMD,
                                                                      (Command.TRIGGER, 5, 2))
    outcome: Decision = decision.outcome
    assert (outcome.action, outcome.seq, outcome.command, outcome.recipe) == (
        Action.START, 5, Command.TRIGGER, 2)
    # the same seq again is no new request
    _, again = answer(write_single(Reg.REQ_SEQ, 5), b, NOW_NS)
    assert isinstance(again, Written)
    assert again.outcome.action is Action.IGNORE


def test_write_single_to_the_request_register_after_the_command() -> None:
    b = bank()
    answer(write_single(Reg.CMD, Command.TRIGGER), b, NOW_NS)
    _, decision = answer(write_single(Reg.REQ_SEQ, 9), b, NOW_NS)
    assert isinstance(decision, Written)
    assert (decision.outcome.action, decision.outcome.seq) == (Action.START, 9)


def test_a_refused_request_is_the_banks_decision_not_an_exception() -> None:
    b = bank()
    reply, decision = answer(write_multiple(Reg.CMD, [99, 3]), b, NOW_NS)
    assert reply == struct.pack(">BHH", 16, Reg.CMD, 2)
    assert isinstance(decision, Written)
    assert (decision.outcome.action, decision.outcome.seq) == (Action.REJECT, 3)


def test_mask_write() -> None:
    b = bank()
    answer(write_single(Reg.RECIPE, 0b1010_1010), b, NOW_NS)
    pdu = mask_write(Reg.RECIPE, 0b1111_0000, 0b0000_0101)
    reply, decision = answer(pdu, b, NOW_NS)
    assert reply == pdu
    assert isinstance(decision, Written)
    assert decision.values == (0b1010_0101,)
    assert b.image.words[Reg.RECIPE] == 0b1010_0101


def test_read_write_writes_then_reads() -> None:
    b = bank()
    reply, decision = answer(read_write(Reg.CMD, 3, Reg.CMD, [Command.TRIGGER, 4, 1]), b,
                             NOW_NS)
    assert reply == struct.pack(">BB3H", 23, 6, Command.TRIGGER, 4, 1)
    assert isinstance(decision, Written)
    assert decision.function == 23
    assert (decision.outcome.action, decision.outcome.seq) == (Action.START, 4)


def test_map_version_4_latch_is_writable() -> None:
    b = bank(4)
    _, decision = answer(write_multiple(Reg.LATCH_COUNT, [0, 42, 0, 7]), b, NOW_NS)
    assert isinstance(decision, Written)
    assert b.image.words[Reg.LATCH_COUNT:Reg.RESULT_COUNT] == [0, 42, 0, 7]


# --- refused --------------------------------------------------------------------------------


@pytest.mark.parametrize("function", [1, 2, 4, 5, 8, 15, 17, 20, 24, 43, 0x7F])
def test_function_not_served_is_exception_01(function: int) -> None:
    pdu = bytes((function, 0, 0, 0, 1))
    decision = refused(pdu, bank(), ILLEGAL_FUNCTION)
    assert (decision.address, decision.count) == (None, None)
    assert "not served" in decision.detail


@pytest.mark.parametrize("version", [3, 4])
def test_read_at_each_edge_of_the_map(version: int) -> None:
    b = bank(version)
    size = MAP_SIZE_V4 if version == 4 else MAP_SIZE
    for address, count in ((0, 1), (size - 1, 1), (0, size)):
        assert isinstance(answer(read(address, count), b, NOW_NS)[1], Answered)
    for address, count in ((size - 1, 2), (size, 1), (0, size + 1), (0xFFFF, 1),
                           (0xFFFF, 125)):
        decision = refused(read(address, count), b, ILLEGAL_ADDRESS)
        assert (decision.address, decision.count) == (address, count)
        assert f"map version {version}" in decision.detail


@pytest.mark.parametrize("count", [0, 126, 0xFFFF])
def test_read_count_out_of_range_is_exception_03(count: int) -> None:
    decision = refused(read(0, count), bank(), ILLEGAL_VALUE)
    assert decision.count == count


def test_read_of_the_most_registers_outside_the_map_is_an_address_fault() -> None:
    refused(read(0, 125), bank(), ILLEGAL_ADDRESS)  # the count is legal, the range is not


@pytest.mark.parametrize(("address", "register"), [
    (Reg.MAP_VERSION, "MAP_VERSION"), (Reg.STATE, "STATE"), (Reg.ACK_SEQ, "ACK_SEQ"),
    (Reg.SCORE + 1, "SCORE"),
])
def test_write_to_a_read_only_register_is_exception_02(address: int, register: str) -> None:
    for pdu in (write_single(address, 1), write_multiple(address, [1]),
                mask_write(address, 0, 1)):
        decision = refused(pdu, bank(), ILLEGAL_ADDRESS)
        assert (decision.address, decision.count) == (address, 1)
        assert f"{register}) is read-only" in decision.detail


def test_write_at_each_edge_of_the_command_area() -> None:
    b = bank()
    assert isinstance(answer(write_single(Reg.RECIPE, 1), b, NOW_NS)[1], Written)
    refused(write_multiple(Reg.RECIPE, [1, 1]), b, ILLEGAL_ADDRESS)  # into MAP_VERSION
    refused(write_single(MAP_SIZE, 1), b, ILLEGAL_ADDRESS)  # beyond map version 3
    refused(mask_write(MAP_SIZE, 0, 1), b, ILLEGAL_ADDRESS)
    refused(write_single(0xFFFF, 1), b, ILLEGAL_ADDRESS)
    refused(write_single(Reg.LATCH_COUNT, 1), b, ILLEGAL_ADDRESS)  # the latch is version 4


@pytest.mark.parametrize(("count", "n_values"), [(0, 0), (124, 124), (3, 2)])
def test_write_multiple_count_out_of_range_is_exception_03(count: int, n_values: int) -> None:
    decision = refused(write_multiple(Reg.CMD, [0] * n_values, count=count), bank(),
                       ILLEGAL_VALUE)
    assert decision.count == count


def test_write_multiple_of_123_is_a_legal_count() -> None:
    refused(write_multiple(Reg.CMD, [0] * 123), bank(), ILLEGAL_ADDRESS)  # count ok, range not


@pytest.mark.parametrize(("read_count", "write_count"), [(0, 1), (126, 1), (1, 0), (1, 122)])
def test_read_write_counts_out_of_range_are_exception_03(read_count: int,
                                                         write_count: int) -> None:
    refused(read_write(0, read_count, Reg.CMD, [0] * write_count), bank(), ILLEGAL_VALUE)


def test_read_write_with_an_illegal_read_range_writes_nothing() -> None:
    b = bank()
    decision = refused(read_write(MAP_SIZE, 1, Reg.CMD, [Command.TRIGGER, 1]), b,
                       ILLEGAL_ADDRESS)
    assert (decision.address, decision.count) == (MAP_SIZE, 1)
    assert b.handshake.running_seq == 0  # no job started either


def test_read_write_with_an_illegal_write_range() -> None:
    decision = refused(read_write(0, 1, Reg.STATE, [1]), bank(), ILLEGAL_ADDRESS)
    assert (decision.address, decision.count) == (Reg.STATE, 1)


# --- malformed ------------------------------------------------------------------------------


@pytest.mark.parametrize("pdu", [
    b"",
    bytes((0, 0, 0, 0, 1)),  # function code 0
    bytes((0x83, 0, 0, 0, 1)),  # an exception response, not a request
    bytes((3, 0, 0, 0)),  # truncated
    bytes((3, 0, 0, 0, 1, 0)),  # trailing byte
    bytes((6, 0, 0, 0)),
    bytes((16, 0, 0, 0)),  # truncated before the byte count
    bytes((16, 0, 0, 0, 1, 2, 0)),  # byte count 2, one data byte
    bytes((16, 0, 0, 0, 1, 2, 0, 1, 9)),  # byte count 2, three data bytes
    bytes((22, 0, 0, 0, 0, 0)),
    bytes((23, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0)),
])
def test_malformed_requests(pdu: bytes) -> None:
    b = bank()
    before = list(b.image.words)
    reply, decision = answer(pdu, b, NOW_NS)
    assert isinstance(decision, Malformed)
    assert decision.function == (pdu[0] if pdu else None)
    assert reply == bytes(((pdu[0] if pdu else 0) | 0x80, ILLEGAL_VALUE))
    assert decision.detail
    assert b.image.words == before


# --- any PDU --------------------------------------------------------------------------------

served_pdus = st.builds(
    lambda f, body: bytes((f,)) + body, st.sampled_from(SERVED),
    st.binary(max_size=252))
near_map = st.builds(
    lambda f, a, n, extra: struct.pack(">BHH", f, a, n) + extra,
    st.sampled_from(SERVED), st.integers(0, 70), st.integers(0, 130), st.binary(max_size=20))


@settings(max_examples=400, deadline=None)
@given(st.one_of(st.binary(max_size=253), served_pdus, near_map), st.sampled_from([3, 4]))
def test_any_pdu_gets_a_reply_or_a_clean_exception(pdu: bytes, version: int) -> None:
    b = bank(version)
    reply, decision = answer(pdu, b, NOW_NS)
    assert isinstance(decision, Answered | Written | Refused | Malformed)
    assert 2 <= len(reply) <= 253
    if isinstance(decision, Answered | Written):
        assert reply[0] == pdu[0]
    else:
        assert len(reply) == 2
        assert reply[0] == ((pdu[0] if pdu else 0) | 0x80)
        assert reply[1] in (ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE)
    if isinstance(decision, Written):
        writable = [*range(Reg.CMD, Reg.RECIPE + 1)]
        if version == 4:
            writable += range(Reg.LATCH_COUNT, Reg.RESULT_COUNT)
        assert all(a in writable
                   for a in range(decision.address, decision.address + len(decision.values)))
