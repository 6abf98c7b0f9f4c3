"""The robot socket link against real TCP peers on 127.0.0.1 (plain asyncio streams that send
the documented bytes), and its codec.

Faults are checked as for the Modbus links: a malformed frame closes that connection only, a
peer silent in the middle of a frame is closed after ``frame_timeout_s``, a peer that does not
read is reset, connections are bounded; the client mode reconnects with back-off and logs one
line per outage; nothing logs a traceback. Every wait is on a state, a frame or EOF, with a
timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import socket
import struct
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.links.robot_socket import RobotSocketLink, RobotSocketOptions
from vgripd.errors import LinkError
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.peer.jobcore import next_answer
from vgripd.peer.socket_frames import (
    ANSWER_SIZE,
    CAPTURE_AT_SIZE,
    Answer,
    AnswerKind,
    BeltFrame,
    FrameError,
    Request,
    SocketCommand,
    ValueEncoding,
    decode_answer,
    decode_belt,
    decode_request,
    header_word,
    request_size,
    result_answer,
)
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.types import BeltPose, JobResult, PickInstance, RobotTarget, Status

WAIT_S = 30.0  # a bound for a busy machine, not a target
KUKA = ("X", "Y", "Z", "A", "B", "C")
POSE = (412.5, -133.25, 287.0625, 0.1234, -2.9, 179.5)


def ok(job_id: int, values: tuple[float, ...] = POSE, vendor: str = "kuka") -> JobResult:
    fields = KUKA if len(values) == 6 else ("x", "y", "z", "q1", "q2", "q3", "q4")
    return JobResult(job_id=job_id, status=Status.OK, target=RobotTarget(vendor, fields, values),
                     residuals={"fit_rms_mm": 0.0123})


# --- codec ------------------------------------------------------------------------------


def test_header_words_spell_vg_version_and_code() -> None:
    assert struct.pack(">I", header_word(SocketCommand.LOCATE)) == b"VG\x01\x01"
    assert struct.pack(">I", header_word(AnswerKind.RESULT)) == b"VG\x01\x82"
    assert header_word(SocketCommand.LOCATE) == 1447493889


def test_request_bytes_and_refusals() -> None:
    frame = Request(SocketCommand.LOCATE, 7, 3).encode()
    assert frame == b"VG\x01\x01" + bytes([0, 0, 0, 7, 0, 0, 0, 3, 0, 0, 0, 0])
    assert decode_request(frame) == Request(1, 7, 3, 0)
    assert Request(SocketCommand.LOCATE, 1).refusal() is None
    assert Request(SocketCommand.CLEAR, 1).refusal() is None
    assert Request(SocketCommand.NEXT, 1).refusal() is None  # the link judges its list
    assert Request(SocketCommand.CAPTURE_AT, 1).refusal() is None
    for bad in (Request(5, 1), Request(9, 1), Request(1, 0),
                Request(1, 2**31), Request(1, 1, 65536), Request(1, 1, 0, 5)):
        assert bad.refusal() is Status.BAD_REQUEST, bad
    for garbage in (b"XG\x01\x01" + bytes(12), b"VG\x02\x01" + bytes(12), bytes(15)):
        with pytest.raises(FrameError):
            decode_request(garbage)


@given(st.lists(st.floats(-2e5, 2e5, allow_nan=False), min_size=6, max_size=7),
       st.sampled_from([("int32", 10000), ("int32", 1000000), ("float32", 0)]))
def test_answer_values_round_trip(values: list[float], fmt: tuple[str, int]) -> None:
    encoding = ValueEncoding(fmt[0], fmt[1] or 10000)  # type: ignore[arg-type]
    if fmt[1] == 1000000:
        values = [v / 100 for v in values]  # m and rad stay within +-2147
    frame = Answer(AnswerKind.RESULT, 5, 1, 9, 1, tuple(values), 0.5).encode(encoding)
    assert len(frame) == ANSWER_SIZE
    answer = decode_answer(frame)
    assert (answer.kind, answer.request_id, answer.status, answer.job_id, answer.warnings) == (
        AnswerKind.RESULT, 5, 1, 9, 1)
    tol = 0.5 / fmt[1] if fmt[1] else 0.0
    for got, want in zip(answer.values, values, strict=True):
        assert got == pytest.approx(want, abs=tol + 1e-12, rel=1e-7 if not fmt[1] else 0)


def test_counted_requests_carry_the_count_and_a_belt_frame_goes_first() -> None:
    frame = Request(SocketCommand.NEXT, 7, 0, count=2**32 - 1, frame=9).encode()
    assert frame == (b"VG\x01\x43" + bytes([0, 0, 0, 7]) + bytes(8) + b"\xff" * 4
                     + bytes([0, 0, 0, 9]))
    assert request_size(frame) == 24
    assert decode_request(frame) == Request(SocketCommand.NEXT, 7, 0, 0, (), 2**32 - 1, 9)
    for bad in (Request(SocketCommand.CLEAR, 1, count=5), Request(SocketCommand.PREDICT, 1),
                Request(SocketCommand.CAPTURE_AT, 1, count=5)):
        assert decode_request(bad.encode()).refusal() is Status.BAD_REQUEST, bad
    belt = BeltPose(123, 1, 0.05, 700.25, -8.5, 12.0, 3)
    result = dataclasses.replace(ok(4, (1, 2, 3, 4, 5, 6)), belt=belt)
    frames, sent = result_answer(7, result, 0, ValueEncoding(), True, counted=True)
    assert sent is result
    assert len(frames) == 2 * ANSWER_SIZE
    assert decode_belt(frames[:ANSWER_SIZE]) == BeltFrame(7, 123, 1, 0.05, 700.25, -8.5, 12.0, 3)
    assert decode_answer(frames[ANSWER_SIZE:]).values == (1, 2, 3, 4, 5, 6)
    # a belt value beyond int32 x scale: no pose at all, the BELT frame all 0
    far = dataclasses.replace(result, belt=dataclasses.replace(belt, along_mm=3000.0))
    frames, sent = result_answer(8, far, 0, ValueEncoding("int32", 1000000), True, counted=True)
    assert sent.status is Status.OUT_OF_LIMITS
    assert "ALONG" in sent.message
    assert decode_belt(frames[:ANSWER_SIZE]) == BeltFrame(8)
    assert decode_answer(frames[ANSWER_SIZE:]).values == ()


def test_result_answer_refuses_what_does_not_fit() -> None:
    big = ok(4, (3e6, 0, 0, 0, 0, 0))
    frame, sent = result_answer(8, big, 0, ValueEncoding("int32", 10000), captured=True)
    assert sent.status is Status.OUT_OF_LIMITS
    answer = decode_answer(frame)
    assert (answer.kind, answer.status, answer.values) == (AnswerKind.RESULT, 20, ())
    refusal = JobResult(job_id=0, status=Status.BUSY)
    frame, sent = result_answer(9, refusal, 0, ValueEncoding(), captured=False)
    assert decode_answer(frame).kind is AnswerKind.REFUSED
    assert sent is refusal


def test_capture_at_bytes_carry_the_pose_in_the_links_encoding() -> None:
    pose = (412.5, -133.25, 287.0625, 0.1234, -2.9, 179.5)
    frame = Request(SocketCommand.CAPTURE_AT, 7, 0, 0, pose).encode(ValueEncoding("int32", 1000))
    assert len(frame) == CAPTURE_AT_SIZE == 44
    assert frame[:16] == b"VG\x01\x04" + bytes([0, 0, 0, 7]) + bytes(8)
    assert struct.unpack(">7i", frame[16:]) == (412500, -133250, 287062, 123, -2900, 179500, 0)
    decoded = decode_request(frame, ValueEncoding("int32", 1000))
    assert (decoded.command, decoded.request_id) == (4, 7)
    assert decoded.values == pytest.approx((*pose, 0.0), abs=0.0005)
    quat = (1.5, -2.25, 3.0, 0.70710678, 0.0, 0.70710678, 0.0)
    f32 = Request(SocketCommand.CAPTURE_AT, 2, 0, 0, quat).encode(ValueEncoding("float32"))
    assert decode_request(f32, ValueEncoding("float32")).values == pytest.approx(quat, rel=1e-7)
    for wrong in (frame[:16], frame + bytes(4), frame[:40]):  # its command says 44 bytes
        with pytest.raises(FrameError, match="command 4 is 44 bytes"):
            decode_request(wrong)


@given(st.lists(st.floats(-2e5, 2e5, allow_nan=False), min_size=7, max_size=7),
       st.integers(1, 2**31 - 1),
       st.sampled_from([("int32", 10000), ("int32", 1000), ("float32", 0)]))
def test_capture_at_round_trips(values: list[float], seq: int, fmt: tuple[str, int]) -> None:
    encoding = ValueEncoding(fmt[0], fmt[1] or 10000)  # type: ignore[arg-type]
    frame = Request(SocketCommand.CAPTURE_AT, seq, 0, 0, tuple(values)).encode(encoding)
    decoded = decode_request(frame, encoding)
    assert (decoded.command, decoded.request_id, decoded.refusal()) == (4, seq, None)
    tol = 0.5 / fmt[1] if fmt[1] else 0.0
    for got, want in zip(decoded.values, values, strict=True):
        assert got == pytest.approx(want, abs=tol + 1e-12, rel=1e-7 if not fmt[1] else 0)


def test_options_refuse_what_a_program_cannot_state() -> None:
    with pytest.raises(ValueError, match="power of ten"):
        RobotSocketOptions(scale=2500)
    with pytest.raises(ValueError, match="robot's host and port"):
        RobotSocketOptions(mode="client")
    assert RobotSocketOptions(value_format="float32", scale=2500).scale == 2500


# --- helpers ----------------------------------------------------------------------------


class Peer:
    """A robot program's side: an asyncio stream sending the documented frames."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def dial(cls, port: int) -> Peer:
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def request(self, seq: int, command: int = SocketCommand.LOCATE, recipe: int = 0) -> None:
        await self.send(Request(command, seq, recipe).encode())

    async def answer(self) -> Answer:
        async with asyncio.timeout(WAIT_S):
            return decode_answer(await self.reader.readexactly(ANSWER_SIZE))

    async def closed_by_link(self) -> None:
        async with asyncio.timeout(WAIT_S):
            assert await self.reader.read() == b""

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError):
            await self.writer.wait_closed()


@contextlib.asynccontextmanager
async def serving(**options: Any) -> AsyncIterator[tuple[RobotSocketLink, list[Trigger]]]:
    link = RobotSocketLink("robot_socket", RobotSocketOptions(
        **{"host": "127.0.0.1", "port": 0, **options}))
    triggers: list[Trigger] = []
    await link.open(triggers.append)
    try:
        yield link, triggers
    finally:
        await link.close()


async def until(predicate: Any) -> None:
    """Poll a count the link or the handler keeps (triggers, peers) until ``predicate`` holds,
    as a PLC polls; a timeout fails the test."""
    async with asyncio.timeout(WAIT_S):
        while True:
            if predicate():
                return
            await asyncio.sleep(0.005)


def no_tracebacks(caplog: pytest.LogCaptureFixture) -> None:
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"


def lines(caplog: pytest.LogCaptureFixture, text: str, level: int = logging.WARNING) -> int:
    return sum(1 for r in caplog.records if r.levelno >= level and text in r.getMessage())


# --- server mode ------------------------------------------------------------------------


async def test_a_job_is_triggered_captured_and_answered() -> None:
    async with serving() as (link, triggers):
        assert link.health().state is LinkState.UP
        peer = await Peer.dial(link.port)
        await peer.request(41, recipe=7)
        await until(lambda: triggers)
        trigger = triggers[0]
        assert (trigger.seq, trigger.command, trigger.recipe, trigger.link) == (41, 1, 7,
                                                                                "robot_socket")
        assert link.health().peers == 1
        await link.image_captured(41, 3)
        captured = await peer.answer()
        assert (captured.kind, captured.request_id, captured.job_id) == (AnswerKind.CAPTURED,
                                                                         41, 3)
        await link.set_warnings(1)
        assert await link.publish(41, ok(3)) is Status.OK
        result = await peer.answer()
        assert (result.kind, result.status, result.job_id, result.warnings) == (
            AnswerKind.RESULT, Status.OK, 3, 1)
        assert result.values == pytest.approx(POSE, abs=1e-4)
        assert result.fit_rms_mm == pytest.approx(0.0123, abs=1e-4)
        await peer.close()


async def test_busy_and_bad_requests_are_refused_by_the_link() -> None:
    async with serving() as (link, triggers):
        a, b = await Peer.dial(link.port), await Peer.dial(link.port)
        await a.request(1)
        await until(lambda: triggers)
        await b.request(1)  # same id from another robot: still a new request, refused BUSY
        busy = await b.answer()
        assert (busy.kind, busy.status, busy.job_id) == (AnswerKind.REFUSED, Status.BUSY, 0)
        for seq, command, recipe in ((2, 9, 0), (0, 1, 0), (3, 1, 70000)):
            await b.request(seq, command, recipe)
            bad = await b.answer()
            assert (bad.kind, bad.request_id, bad.status) == (AnswerKind.REFUSED, seq,
                                                              Status.BAD_REQUEST)
        assert await link.publish(1, ok(1)) is Status.OK  # the running job is untouched
        assert (await a.answer()).status == Status.OK
        await b.request(4, SocketCommand.CLEAR)
        cleared = await b.answer()
        assert (cleared.kind, cleared.status, cleared.values) == (AnswerKind.RESULT,
                                                                  Status.IDLE, ())
        assert len(triggers) == 1
        assert link.refusals() == {"BUSY": 1, "BAD_REQUEST": 3}
        await a.close()
        await b.close()


async def test_daemon_refusal_is_answered_refused_and_float32_values(
        caplog: pytest.LogCaptureFixture) -> None:
    async with serving(value_format="float32") as (link, triggers):
        peer = await Peer.dial(link.port)
        await peer.request(5)
        await until(lambda: triggers)
        busy = JobResult(job_id=0, status=Status.BUSY, message="refused: BUSY")
        assert await link.publish(5, busy) is Status.BUSY
        assert (await peer.answer()).kind is AnswerKind.REFUSED
        await peer.request(6)
        await until(lambda: len(triggers) == 2)
        await link.image_captured(6, 2)
        quat = (1.5, -2.25, 3.0, 0.70710678, 0.0, 0.70710678, 0.0)
        assert await link.publish(6, ok(2, quat, "abb")) is Status.OK
        assert (await peer.answer()).kind is AnswerKind.CAPTURED
        result = await peer.answer()
        assert result.values == pytest.approx(quat, rel=1e-7)
        await peer.close()


async def test_a_value_that_does_not_fit_is_answered_out_of_limits() -> None:
    async with serving(scale=1000000) as (link, triggers):
        peer = await Peer.dial(link.port)
        await peer.request(1)
        await until(lambda: triggers)
        assert await link.publish(1, ok(1, (4000.0, 0, 0, 0, 0, 0))) is Status.OUT_OF_LIMITS
        answer = await peer.answer()
        assert (answer.status, answer.values) == (Status.OUT_OF_LIMITS, ())
        with pytest.raises(LinkError, match="reserved|defined"):
            await link.set_warnings(0x8000)
        await peer.close()


async def test_malformed_frame_closes_only_that_connection(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    async with serving() as (link, triggers):
        good = await Peer.dial(link.port)
        for _ in range(3):  # a peer sending garbage again and again: one line
            bad = await Peer.dial(link.port)
            await bad.send(b"GET / HTTP/1.0\r\n\r\n")
            await bad.closed_by_link()
            await bad.close()
        await good.request(1)
        await until(lambda: triggers)
        assert link.faults["malformed"] == 3
        assert lines(caplog, "not a vgripd request") == 1
        assert link.health().state is LinkState.UP
        await good.close()
    no_tracebacks(caplog)


async def test_a_peer_silent_mid_frame_is_closed(caplog: pytest.LogCaptureFixture) -> None:
    async with serving(frame_timeout_s=0.2) as (link, _):
        peer = await Peer.dial(link.port)
        await peer.send(b"VG\x01\x01\x00")
        await peer.closed_by_link()
        assert link.faults["incomplete"] == 1
        assert lines(caplog, "request incomplete (5 of 16 bytes)") == 1
        await until(lambda: link.health().peers == 0)
        await peer.close()
    no_tracebacks(caplog)


async def test_connections_are_bounded_and_the_waiting_one_is_kept(
        caplog: pytest.LogCaptureFixture) -> None:
    async with serving(max_connections=2) as (link, triggers):
        waiting = await Peer.dial(link.port)
        await waiting.request(1)  # its job runs: never evicted
        await until(lambda: triggers)
        idle = await Peer.dial(link.port)
        await until(lambda: link.health().peers == 2)
        newest = await Peer.dial(link.port)
        await idle.closed_by_link()
        await until(lambda: link.health().peers == 2)
        assert link.faults["evicted"] == 1
        assert await link.publish(1, ok(1)) is Status.OK
        assert (await waiting.answer()).status == Status.OK
        for p in (waiting, idle, newest):
            await p.close()
    no_tracebacks(caplog)


async def test_a_flood_of_never_valid_newcomers_never_evicts_the_robot_that_talked(
        caplog: pytest.LogCaptureFixture) -> None:
    """The idle robot was evicted by newcomers that never sent a request (the
    longest idle went first). Now the flood evicts only itself; the robot's next LOCATE is
    answered on the same connection, and the eviction lines are rate limited."""
    async with serving(max_connections=4) as (link, triggers):
        robot = await Peer.dial(link.port)
        await robot.request(1, SocketCommand.CLEAR)
        assert (await robot.answer()).kind == AnswerKind.RESULT
        flood = [await Peer.dial(link.port) for _ in range(100)]
        await until(lambda: link.faults["evicted"] >= 97)
        assert link.health().peers <= 4
        await robot.request(2)
        await until(lambda: triggers)
        await link.image_captured(2, 5)
        assert (await robot.answer()).kind == AnswerKind.CAPTURED
        assert await link.publish(2, ok(5)) is Status.OK
        assert (await robot.answer()).status == Status.OK
        for p in [robot, *flood]:
            await p.close()
        assert lines(caplog, " evicted for ") <= 2
    no_tracebacks(caplog)


async def test_allow_list_closes_other_addresses_at_accept(
        caplog: pytest.LogCaptureFixture) -> None:
    """``allow = ["127.0.0.1"]``: a robot socket client from 127.0.0.2 is closed at accept,
    with one log line for many; 127.0.0.1 is served. Today the option is refused."""
    async with serving(allow=["127.0.0.1"]) as (link, triggers):
        loop = asyncio.get_running_loop()
        for _ in range(4):
            sock = socket.socket()
            sock.bind(("127.0.0.2", 0))
            sock.setblocking(False)
            await loop.sock_connect(sock, ("127.0.0.1", link.port))
            other = Peer(*await asyncio.open_connection(sock=sock))
            with contextlib.suppress(ConnectionError):
                await other.request(1)
            with contextlib.suppress(ConnectionError):
                await other.closed_by_link()
            await other.close()
        assert not triggers
        robot = await Peer.dial(link.port)
        await robot.request(3)
        await until(lambda: triggers)
        assert link.faults["not_allowed"] == 4
        assert lines(caplog, "not in allow") == 1
        await robot.close()
    with pytest.raises(ValueError, match="allow"):
        RobotSocketOptions(allow=["127.0.0.1", "localhost"])


async def test_an_answer_for_a_gone_robot_is_undelivered_and_the_link_serves_on(
        caplog: pytest.LogCaptureFixture) -> None:
    async with serving() as (link, triggers):
        peer = await Peer.dial(link.port)
        await peer.request(1)
        await until(lambda: triggers)
        await peer.close()
        await until(lambda: link.health().peers == 0)
        await link.image_captured(1, 1)  # nobody to tell: not an error
        with pytest.raises(LinkError, match="not delivered"):
            await link.publish(1, ok(1))
        assert lines(caplog, "gone while request 1 runs") == 1
        again = await Peer.dial(link.port)
        await again.request(2)  # the retry is a new request, not refused BUSY
        await until(lambda: len(triggers) == 2)
        assert await link.publish(2, ok(2)) is Status.OK
        assert (await again.answer()).request_id == 2
        await again.close()
    no_tracebacks(caplog)


async def test_a_peer_that_does_not_read_is_reset(caplog: pytest.LogCaptureFixture) -> None:
    async with serving(max_unsent_bytes=1024) as (link, _):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", link.port))
        reader, writer = await asyncio.open_connection(sock=sock)
        peer = Peer(reader, writer)
        burst = Request(SocketCommand.NEXT, 1).encode() * 4096  # each answered REFUSED
        with contextlib.suppress(ConnectionError):
            async with asyncio.timeout(WAIT_S):
                while not link.faults["not_reading"]:
                    await peer.send(burst)
        assert link.faults["not_reading"] == 1
        await until(lambda: link.health().peers == 0)
        assert lines(caplog, "answers unread") == 1
        await peer.close()
    no_tracebacks(caplog)


async def test_a_port_in_use_fails_naming_the_address() -> None:
    async with serving() as (link, _):
        other = RobotSocketLink("second", RobotSocketOptions(host="127.0.0.1", port=link.port))
        with pytest.raises(LinkError, match=rf"cannot listen on 127.0.0.1:{link.port}"):
            await other.open(lambda t: None)
        assert other.health().state is LinkState.FAILED


# --- client mode (the robot runs the server) --------------------------------------------


class RobotServer:
    """A robot-side server (the Yaskawa MotoPlus task's role) on a fixed port."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.peers: asyncio.Queue[Peer] = asyncio.Queue()
        self.server: asyncio.Server | None = None

    async def start(self) -> None:
        self.server = await asyncio.start_server(
            lambda r, w: self.peers.put_nowait(Peer(r, w)), "127.0.0.1", self.port)

    async def stop(self) -> None:
        if self.server is not None:
            self.server.close()
            await self.server.wait_closed()

    async def accepted(self) -> Peer:
        async with asyncio.timeout(WAIT_S):
            return await self.peers.get()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


async def test_client_mode_reconnects_with_back_off_and_one_line_per_outage(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    port = free_port()
    robot = RobotServer(port)
    async with serving(mode="client", port=port, backoff_initial_s=0.05,
                       backoff_max_s=0.2) as (link, triggers):
        assert link.health().state is LinkState.DOWN  # nobody listens yet
        await until(lambda: link.attempts >= 4)  # several refused attempts
        assert lines(caplog, "retrying with back-off") == 1
        assert "Connection refused" in link.health().last_error
        await robot.start()
        peer = await robot.accepted()
        health = await link.wait_state(LinkState.UP, WAIT_S)
        assert health.reconnects == 1
        await peer.request(1)
        await until(lambda: triggers)
        await link.image_captured(1, 1)
        assert await link.publish(1, ok(1)) is Status.OK
        assert (await peer.answer()).kind is AnswerKind.CAPTURED
        assert (await peer.answer()).values == pytest.approx(POSE, abs=1e-4)
        # garbage from the robot ends that connection; the link dials again
        await peer.send(b"\xff" * 16)
        await peer.closed_by_link()
        again = await robot.accepted()
        await link.wait_state(LinkState.UP, WAIT_S)
        assert link.health().reconnects == 2
        assert lines(caplog, "retrying with back-off") == 2
        await again.close()
        await peer.close()
    await robot.stop()
    no_tracebacks(caplog)


async def test_client_mode_peer_sending_garbage_at_once_is_one_outage_until_a_robot_answers(
        caplog: pytest.LogCaptureFixture) -> None:
    """A peer on the robot's port that sends garbage on every connection: one
    outage, logged once and retried with back-off; a real robot on that port then serves."""
    caplog.set_level(logging.INFO)
    port = free_port()
    garbage_peers: list[asyncio.StreamWriter] = []

    def garbage(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"\xff" * 16)  # one frame's worth, not a request
        garbage_peers.append(writer)

    fake = await asyncio.start_server(garbage, "127.0.0.1", port)
    async with serving(mode="client", port=port, backoff_initial_s=0.02,
                       backoff_max_s=0.1) as (link, triggers):
        await until(lambda: len(garbage_peers) >= 4)  # dialled again and again
        await link.wait_state(LinkState.DOWN, WAIT_S)
        assert "malformed frame" in link.health().last_error
        assert lines(caplog, "retrying with back-off") == 1
        assert lines(caplog, "connected to the robot", logging.INFO) <= 1
        fake.close()
        for w in garbage_peers:
            w.close()
        await fake.wait_closed()
        robot = RobotServer(port)
        await robot.start()
        peer = await robot.accepted()
        await link.wait_state(LinkState.UP, WAIT_S)
        await peer.request(1)
        await until(lambda: triggers)
        await link.image_captured(1, 1)
        assert await link.publish(1, ok(1)) is Status.OK
        assert (await peer.answer()).kind is AnswerKind.CAPTURED
        assert (await peer.answer()).values == pytest.approx(POSE, abs=1e-4)
        assert lines(caplog, "retrying with back-off") == 1
        await peer.close()
    await robot.stop()
    no_tracebacks(caplog)


async def test_client_mode_gives_up_on_a_connect_that_never_completes(
        caplog: pytest.LogCaptureFixture) -> None:
    """A robot that takes the TCP connection nowhere (its accept queue full, SYNs dropped)."""
    hog = socket.socket()
    hog.bind(("127.0.0.1", 0))
    hog.listen(0)
    port = hog.getsockname()[1]
    fillers = []
    for _ in range(4):
        s = socket.socket()
        s.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            s.connect(("127.0.0.1", port))
        fillers.append(s)
    try:
        async with serving(mode="client", port=port, connect_timeout_s=0.3,
                           backoff_initial_s=0.05) as (link, _):
            health = await link.wait_state(LinkState.DOWN, WAIT_S)
            assert "no connection to 127.0.0.1:" in health.last_error
            assert "within 0.3 s" in health.last_error
    finally:
        for s in fillers:
            s.close()
        hog.close()
    no_tracebacks(caplog)


# --- pick lists (NEXT) ------------------------------------------------------------------------


def pallet(job_id: int, n: int) -> JobResult:
    """``n`` pickable instances (X = 100, 200, ... mm, pick ids 1..n), the first on top."""
    instances = tuple(PickInstance(Status.OK, target=RobotTarget(
        "kuka", tuple("XYZABC"), (100.0 * (i + 1), *POSE[1:6])), pick_id=i + 1, score=0.9)
        for i in range(n))
    return JobResult(job_id=job_id, status=Status.OK, target=instances[0].target,
                     instances=instances)


async def test_next_walks_the_pick_list_and_ends_with_not_found() -> None:
    async with serving() as (link, triggers):
        peer = await Peer.dial(link.port)
        await peer.request(1, SocketCommand.NEXT)  # nothing located yet: no list
        refused = await peer.answer()
        assert (refused.kind, refused.status) == (AnswerKind.REFUSED, Status.BAD_REQUEST)
        job = pallet(8, 3)
        await peer.request(2)
        await until(lambda: triggers)
        await link.image_captured(2, 8)
        assert (await peer.answer()).kind is AnswerKind.CAPTURED
        await link.publish(2, job)
        first = await peer.answer()
        assert (first.status, first.values[0], first.remaining) == (Status.OK, 100.0, 2)
        walked = []
        for seq, index in ((3, 2), (4, 3), (5, 4)):
            await peer.request(seq, SocketCommand.NEXT)
            await until(lambda seq=seq: triggers[-1].seq == seq)
            assert triggers[-1].command == SocketCommand.NEXT
            await link.publish(seq, next_answer(job, index))
            walked.append(await peer.answer())  # no CAPTURED frame before it: no image
        assert [(a.kind, a.request_id, a.status, a.job_id, a.remaining) for a in walked] == [
            (AnswerKind.RESULT, 3, Status.OK, 8, 1), (AnswerKind.RESULT, 4, Status.OK, 8, 0),
            (AnswerKind.RESULT, 5, Status.NOT_FOUND, 8, 0)]
        assert [a.values[0] if a.values else None for a in walked] == [200.0, 300.0, None]
        await peer.request(6, SocketCommand.CLEAR)
        assert (await peer.answer()).status == Status.IDLE
        await peer.request(7, SocketCommand.NEXT)  # CLEAR ended the list
        assert (await peer.answer()).status == Status.BAD_REQUEST
        assert link.refusals() == {"BAD_REQUEST": 2}
        await peer.close()


async def test_a_new_locate_ends_the_old_list_even_before_its_result() -> None:
    async with serving() as (link, triggers):
        peer = await Peer.dial(link.port)
        await peer.request(1)
        await until(lambda: triggers)
        await link.publish(1, pallet(1, 2))
        await peer.answer()
        await peer.request(2)
        await until(lambda: len(triggers) == 2)
        await link.publish(2, JobResult(job_id=2, status=Status.NOT_FOUND))
        assert (await peer.answer()).status == Status.NOT_FOUND
        await peer.request(3, SocketCommand.NEXT)
        assert (await peer.answer()).status == Status.BAD_REQUEST  # never job 1's second
        await peer.close()


# --- CAPTURE_AT: a locate with the flange pose the robot reached ---------------------------


async def capture_at(peer: Peer, seq: int, values: tuple[float, ...],
                     encoding: ValueEncoding) -> None:
    await peer.send(Request(SocketCommand.CAPTURE_AT, seq, 0, 0, values).encode(encoding))


async def test_capture_at_is_a_trigger_with_the_flange_pose() -> None:
    async with serving(scale=1000) as (link, triggers):
        link.set_vendor("kuka")
        peer = await Peer.dial(link.port)
        await capture_at(peer, 12, POSE, link.encoding)
        await until(lambda: triggers)
        trigger = triggers[0]
        assert (trigger.seq, trigger.command) == (12, 1)  # a TRIGGER for the daemon and walks
        assert trigger.T_base_flange is not None
        want = transform_from_vendor("kuka", POSE)
        mm, deg = pose_error(trigger.T_base_flange, want)
        assert mm < 1e-3
        assert deg < 1e-3
        await link.image_captured(12, 4)
        assert (await peer.answer()).kind is AnswerKind.CAPTURED
        assert await link.publish(12, ok(4)) is Status.OK
        assert (await peer.answer()).status == Status.OK
        await peer.request(13)  # a plain 16-byte LOCATE right after: no flange pose
        await until(lambda: len(triggers) == 2)
        assert triggers[1].T_base_flange is None
        await peer.close()


@pytest.mark.parametrize(("vendor", "fmt", "values", "named"), [
    ("abb", "float32", (1.0, 2.0, 3.0, 0.9, 0.0, 0.0, 0.0), "not unit length"),
    ("abb", "float32", (float("nan"), 2.0, 3.0, 1.0, 0.0, 0.0, 0.0), "x"),
    ("abb", "float32", (1.0, 2.0, 3.0, float("inf"), 0.0, 0.0, 0.0), "q1"),
    ("kuka", "int32", (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 5.0), "word 10 (value 6)"),
])
async def test_capture_at_with_a_pose_that_is_not_a_transform_is_refused(
        vendor: str, fmt: str, values: tuple[float, ...], named: str,
        caplog: pytest.LogCaptureFixture) -> None:
    async with serving(value_format=fmt) as (link, triggers):
        link.set_vendor(vendor)
        peer = await Peer.dial(link.port)
        raw = b"".join(struct.pack(">f" if fmt == "float32" else ">i",
                                   v if fmt == "float32" else round(v * 10000))
                       for v in values)
        await peer.send(Request(SocketCommand.CAPTURE_AT, 3).encode()[:16] + raw)
        refused = await peer.answer()
        assert (refused.kind, refused.request_id, refused.status) == (
            AnswerKind.REFUSED, 3, Status.BAD_REQUEST)
        assert not triggers
        assert lines(caplog, "flange pose refused") == 1
        assert lines(caplog, named) == 1
        await peer.request(4)  # the connection serves on
        await until(lambda: triggers)
        await peer.close()
        no_tracebacks(caplog)


async def test_capture_at_of_the_wrong_length_ends_the_connection(
        caplog: pytest.LogCaptureFixture) -> None:
    async with serving(frame_timeout_s=0.2) as (link, triggers):
        link.set_vendor("kuka")
        full = Request(SocketCommand.CAPTURE_AT, 1, 0, 0, POSE).encode(link.encoding)
        long = await Peer.dial(link.port)
        # 4 bytes too many: the program's next request no longer starts a frame
        await long.send(full + bytes(4) + Request(SocketCommand.LOCATE, 2).encode())
        await long.closed_by_link()
        short = await Peer.dial(link.port)
        await short.send(full[:16])  # the 16-byte request alone: the pose never comes
        await short.closed_by_link()
        assert link.faults["malformed"] == 1
        assert link.faults["incomplete"] == 1
        assert lines(caplog, "(16 of 44 bytes)") == 1
        assert len(triggers) == 1  # the long one's request itself was whole
        no_tracebacks(caplog)


async def test_a_walk_lets_next_through_without_a_pick_list() -> None:
    async with serving() as (link, triggers):
        peer = await Peer.dial(link.port)
        await peer.request(1, SocketCommand.NEXT)
        assert (await peer.answer()).status == Status.BAD_REQUEST  # no list: the link refuses
        link.set_walking(True)
        await peer.request(2, SocketCommand.NEXT)  # the walk's first: give me a target
        await until(lambda: triggers)
        assert (triggers[0].seq, triggers[0].command) == (2, 3)
        await link.publish(2, JobResult(1, Status.NOT_FOUND, "walk complete"))
        assert (await peer.answer()).status == Status.NOT_FOUND
        link.set_walking(False)  # the walk is over: no pick list, the link refuses NEXT again
        await peer.request(3, SocketCommand.NEXT)
        assert (await peer.answer()).status == Status.BAD_REQUEST
        assert len(triggers) == 1
        await peer.close()


def test_check_warns_about_a_server_link_without_allow(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``vgripd check`` warns about a robot socket server open to any address (a hand-eye walk
    belongs to the first connection that asks NEXT); not with ``allow``, on a loopback
    address, or in client mode."""
    from vgripd.__main__ import main
    from vgripd.config import config_from_dict
    from vgripd.service.host.commissioning import check_link_exposure

    def found(**link: Any) -> list[str]:
        config = config_from_dict({
            "camera": {"type": "synthetic"}, "status": {"enabled": False},
            "links": [{"type": "robot_socket", "port": 50100, **link}]})
        return [f"{f.level} {f.key}: {f.message}" for f in check_link_exposure(config)]

    open_to_all = found(host="0.0.0.0")
    assert len(open_to_all) == 1
    assert open_to_all[0].startswith("WARNING links[0].allow: no allow list: any host that "
                                     "reaches 0.0.0.0:50100")
    assert "hand-eye walk" in open_to_all[0]
    assert found(host="0.0.0.0", allow=["10.0.0.21"]) == []
    assert found(host="127.0.0.1") == []
    assert found(mode="client", host="10.0.0.21") == []
    config = tmp_path / "cell.toml"
    config.write_text('[camera]\ntype = "synthetic"\n[status]\nenabled = false\n'
                      '[[links]]\ntype = "robot_socket"\nhost = "0.0.0.0"\nport = 50100\n')
    assert main(["check", "-c", str(config), "--running", "--no-camera"]) == 0
    out = capsys.readouterr().out
    assert "warning: " in out
    assert "links[0].allow: no allow list" in out
