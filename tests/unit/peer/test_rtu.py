"""The RTU framer without a serial line: silence by the spec, stray bytes, CRC errors, frames
in pieces, other slaves' responses. The link on a pty pair is tested in
tests/drivers/links/test_modbus_rtu.py."""

from __future__ import annotations

import pytest

from vgripd.peer.rtu import RtuFramer, char_time_s, crc_ok, silence_s, with_crc

BAUD = 115200
READ_7 = with_crc(bytes.fromhex("07 03 0000 0029"))  # unit 7: read the whole map
CHAR_S = char_time_s(BAUD, "N", 1)
SILENCE_S = silence_s(BAUD, "N", 1)


def framer() -> RtuFramer:
    return RtuFramer(CHAR_S, SILENCE_S)


def test_silence_values_follow_the_spec() -> None:
    assert silence_s(19200, "E", 1) == pytest.approx(3.5 * 11 / 19200)  # 2.0 ms
    assert silence_s(9600, "N", 2) == pytest.approx(3.5 * 11 / 9600)
    assert silence_s(115200, "N", 1) == 0.00175  # fixed above 19200 baud
    assert crc_ok(READ_7)
    assert not crc_ok(READ_7[:-1] + bytes([READ_7[-1] ^ 1]))


@pytest.mark.parametrize("stray", [0x01, 0x07, 0x10, 0x17, 0xFF])
def test_stray_byte_then_silence_costs_nothing(stray: int) -> None:
    f = framer()
    assert f.feed(bytes([stray]), 10.0) == []
    assert f.feed(READ_7, 10.0 + 5.0) == [READ_7]  # 5 s of silence in between
    assert f.garbage == 1


@pytest.mark.parametrize("stray", [0x01, 0x07, 0x10, 0x17, 0xFF])
def test_stray_byte_glued_to_a_request_is_skipped(stray: int) -> None:
    f = framer()
    assert f.feed(bytes([stray]) + READ_7, 1.0) == [READ_7]
    assert f.garbage == 1


def test_frame_delivered_in_pieces_is_kept() -> None:
    """A USB adapter hands what it received over every 16 ms (its latency timer), so a long
    frame at 9600 baud arrives in pieces with gaps far longer than 3.5 characters."""
    write = with_crc(bytes([7, 16, 0, 0, 0, 20, 40, *range(40)]))  # 49 bytes, 51 ms on the wire
    f = RtuFramer(char_time_s(9600, "N", 1), silence_s(9600, "N", 1))
    char_s = char_time_s(9600, "N", 1)
    pieces, t, sent = [], 0.0, 0
    while sent < len(write):
        t += 0.016
        arrived = min(len(write), int(t / char_s))
        pieces.append((write[sent:arrived], t))
        sent = arrived
    assert len(pieces) == 4
    got = [frame for piece, at in pieces for frame in f.feed(piece, at)]
    assert got == [write]
    assert f.garbage == 0


def test_partial_frame_before_silence_is_dropped() -> None:
    f = framer()
    assert f.feed(READ_7[:5], 1.0) == []
    assert f.feed(READ_7, 1.5) == [READ_7]
    assert f.garbage == 5


def test_crc_error_costs_only_its_frame() -> None:
    bad = READ_7[:-1] + bytes([READ_7[-1] ^ 0x55])
    f = framer()
    assert f.feed(bad + READ_7, 1.0) == [READ_7]
    assert f.garbage == len(bad)


def test_other_slaves_responses_and_our_echo_are_not_requests() -> None:
    response = with_crc(bytes([8, 3, 4, 0, 1, 0, 2]))  # unit 8 answers a read of 2 registers
    exception = with_crc(bytes([8, 0x83, 2]))
    f = framer()
    assert f.feed(READ_7 + response + exception + READ_7, 1.0) == [READ_7, READ_7]
    assert (f.responses, f.garbage) == (2, 0)
