"""The MBAP framer without a socket: frames in any pieces, the headers it refuses."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from vgripd.peer.mbap import MAX_LENGTH, MalformedFrame, MbapFrame, MbapFramer, encode

READ = bytes((3, 0, 0, 0, 46))  # read 46 holding registers from 0
WRITE = bytes((16, 0, 0, 0, 3, 6, 0, 1, 0, 7, 0, 0))


def frames_of(framer: MbapFramer) -> list[MbapFrame]:
    out = []
    while (frame := framer.next_frame()) is not None:
        out.append(frame)
    return out


def test_one_frame_whole() -> None:
    framer = MbapFramer()
    framer.feed(encode(0x1234, 1, READ))
    assert frames_of(framer) == [MbapFrame(0x1234, 1, READ)]
    assert framer.buffered == 0


def test_frame_split_at_every_byte() -> None:
    wire = encode(7, 1, WRITE)
    for cut in range(1, len(wire)):
        framer = MbapFramer()
        framer.feed(wire[:cut])
        assert framer.next_frame() is None, cut
        assert not framer.has_frame()
        framer.feed(wire[cut:])
        assert frames_of(framer) == [MbapFrame(7, 1, WRITE)], cut


def test_coalesced_frames_come_out_in_order_and_a_partial_one_waits() -> None:
    wire = encode(1, 1, READ) + encode(2, 255, WRITE) + encode(3, 0, READ)
    framer = MbapFramer()
    framer.feed(wire + encode(4, 1, READ)[:5])
    assert [f.tid for f in frames_of(framer)] == [1, 2, 3]
    assert framer.buffered == 5
    framer.feed(encode(4, 1, READ)[5:])
    assert frames_of(framer) == [MbapFrame(4, 1, READ)]


def test_wrong_protocol_id_is_malformed() -> None:
    framer = MbapFramer()
    framer.feed(b"\x00\x01\x00\x01\x00\x06\x01" + READ)
    with pytest.raises(MalformedFrame, match="protocol id 1"):
        framer.next_frame()


@pytest.mark.parametrize("length", [0, 1, MAX_LENGTH + 1, 0xFFFF])
def test_length_outside_the_limit_is_malformed_before_its_bytes_arrive(length: int) -> None:
    framer = MbapFramer()
    framer.feed(b"\x00\x01\x00\x00" + length.to_bytes(2, "big"))
    with pytest.raises(MalformedFrame, match=f"length {length} "):
        framer.has_frame()


def test_the_longest_frame_passes() -> None:
    pdu = bytes(MAX_LENGTH - 1)
    framer = MbapFramer()
    framer.feed(encode(9, 1, pdu))
    assert frames_of(framer) == [MbapFrame(9, 1, pdu)]


@given(st.lists(st.tuples(st.integers(0, 0xFFFF), st.integers(0, 255),
                          st.binary(min_size=1, max_size=MAX_LENGTH - 1)), max_size=8),
       st.data())
def test_any_split_of_any_frames_gives_them_back(
        sent: list[tuple[int, int, bytes]], data: st.DataObject) -> None:
    wire = b"".join(encode(*f) for f in sent)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(wire)), max_size=10)))
    framer = MbapFramer()
    got: list[MbapFrame] = []
    for a, b in zip([0, *cuts], [*cuts, len(wire)], strict=True):
        framer.feed(wire[a:b])
        got += frames_of(framer)
    assert got == [MbapFrame(*f) for f in sent]
    assert framer.buffered == 0
