"""Several views per job in the register handshake (``Command.CAPTURE``, view in the CMD
word's high byte, STATE 4 VIEWS), without I/O: what a Modbus server, RTU or mirror client link
does with a CAPTURE request, through the ``RegisterBank`` they share.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from vgripd.errors import LinkError
from vgripd.peer.jobcore import (
    MAX_VIEWS,
    Action,
    Command,
    Handshake,
    HandshakeState,
    capture_word,
    split_command,
)
from vgripd.peer.registers import Reg, RegisterBank, ValueCodec
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.types import JobResult, Status


@given(st.integers(1, MAX_VIEWS))
def test_capture_word_round_trips(view: int) -> None:
    assert capture_word(view) == view * 256 + 4
    assert split_command(capture_word(view)) == (Command.CAPTURE, view)


@pytest.mark.parametrize("view", [0, MAX_VIEWS + 1, -1])
def test_capture_word_refuses_views_outside_1_to_8(view: int) -> None:
    with pytest.raises(ValueError, match="views are 1..8"):
        capture_word(view)


@given(st.integers(0, 0xFFFF))
def test_only_capture_words_carry_a_view(word: int) -> None:
    """Any other command keeps its whole word, so TRIGGER with a high byte stays unknown."""
    command, view = split_command(word)
    if word & 0xFF == Command.CAPTURE:
        assert (command, view) == (Command.CAPTURE, word >> 8)
    else:
        assert (command, view) == (word, 0)


@pytest.mark.parametrize("word", [Command.CAPTURE, capture_word(1) + 0x0800,
                                  Command.TRIGGER | 0x0100, 0xFF04])
def test_captures_without_a_valid_view_are_refused(word: int) -> None:
    hs = Handshake()
    decision = hs.on_request(word, 5)
    assert decision.action is Action.REJECT
    assert decision.code is Status.BAD_REQUEST
    assert hs.state is HandshakeState.IDLE


def test_a_view_taken_frees_the_handshake_for_the_next_view() -> None:
    bank = RegisterBank(ValueCodec())
    decision = bank.write(Reg.CMD, [capture_word(1), 1, 0])
    assert (decision.action, decision.command, decision.view) == (Action.START, Command.CAPTURE,
                                                                  1)
    # While the view is taken, another request is BUSY.
    assert bank.write(Reg.CMD, [capture_word(2), 2, 0]).code is Status.BUSY
    bank.view_captured(1, 77)
    words = bank.read(0, 46, now_ns=0)
    assert words[Reg.CAPTURED_SEQ] == 1
    assert words[Reg.STATE] == HandshakeState.VIEWS
    assert words[Reg.ACK_SEQ] == 0  # no result between the views
    assert words[Reg.N_VALUES] == 0
    assert words[Reg.JOB_ID:Reg.JOB_ID + 2] == [0, 77]
    decision = bank.write(Reg.CMD, [capture_word(2), 3, 0])
    assert (decision.action, decision.view) == (Action.START, 2)
    bank.captured(3, 77)
    bank.publish(3, JobResult(job_id=77, status=Status.NOT_FOUND), now_ns=0)
    words = bank.read(0, 46, now_ns=0)
    assert (words[Reg.ACK_SEQ], words[Reg.STATUS]) == (3, Status.NOT_FOUND)


def test_a_job_ended_between_views_is_answered_under_the_last_view() -> None:
    """The wait for the next view ran out: the daemon publishes under the last view's seq."""
    bank = RegisterBank(ValueCodec())
    bank.write(Reg.CMD, [capture_word(1), 9, 0])
    bank.view_captured(9, 5)
    bank.publish(9, JobResult(job_id=5, status=Status.CAMERA_ERROR), now_ns=0)
    words = bank.read(0, 46, now_ns=0)
    assert (words[Reg.ACK_SEQ], words[Reg.STATUS], words[Reg.STATE]) == (
        9, Status.CAMERA_ERROR, HandshakeState.DONE)


def test_view_captured_for_another_request_is_a_link_error() -> None:
    hs = Handshake()
    hs.on_request(capture_word(1), 4)
    with pytest.raises(LinkError, match="view_captured for request 3"):
        hs.on_view_captured(3)
    hs.on_view_captured(4)
    with pytest.raises(LinkError, match="publish for request 3"):
        hs.check_running(3, "publish")
    # A new request replaces the waiting one: its publish is no longer accepted.
    hs.on_request(capture_word(2), 5)
    with pytest.raises(LinkError, match="publish for request 4"):
        hs.check_running(4, "publish")


def test_ur_map_lets_captures_through() -> None:
    regs = URRegisterMap()
    assert regs.refusal(capture_word(3)) is None
    assert regs.refusal(Command.CAPTURE) is Status.BAD_REQUEST
    assert regs.refusal(capture_word(8) + 0x100) is Status.BAD_REQUEST
    assert regs.refusal(1) is None
