"""A seeded fuzzer over Modbus/TCP frames against the real server link on loopback.

Today 3,827 fuzzed frames leave 536 tracebacks in the log and a 12-byte frame can produce up to
1,130 bytes of it. Here 4,000 frames (valid requests with random fields, mutated ones, unknown
function codes, garbage), in batches of 1-8 per connection from 4 clients at once, while a
stand-in daemon answers every trigger they cause. Asserted: the link keeps serving, nothing is
logged with a traceback and no error reaches the event loop, every answer is a well-formed
frame with a legal exception code, the registers only vgripd writes are intact, and the log
stays under a byte per frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import socket
import struct

import pytest

from tests.faults.modbus_raw import Served, mbap
from vgripd.peer.jobcore import HandshakeState
from vgripd.peer.registers import CHECK_U16, MAP_SIZE, MAP_VERSIONS, Reg
from vgripd.service.links.protocol import LinkState
from vgripd.sim.plc import MockPlc
from vgripd.types import JobResult, RobotTarget, Status

SEED = 20240611
FRAMES = 4000
WORKERS = 4
POSE = (612.5, -98.125, 10.75, 2.5, -0.75, 179.5)
SERVED = {3, 6, 16, 22, 23}


def _address(rng: random.Random) -> int:
    return rng.choice([0, 1, 2, Reg.ACK_SEQ, MAP_SIZE - 1, MAP_SIZE, rng.randrange(64),
                       rng.randrange(65536)])


def _count(rng: random.Random, top: int) -> int:
    return rng.choice([0, 1, 2, 3, rng.randrange(1, 42), top, top + 1, rng.randrange(65536)])


def request_pdu(rng: random.Random) -> bytes:
    """A request of a served function code with random (often illegal) fields."""
    function = rng.choice(sorted(SERVED))
    address = _address(rng)
    if function == 3:
        return struct.pack(">BHH", 3, address, _count(rng, 125))
    if function == 6:
        return struct.pack(">BHH", 6, address, rng.randrange(65536))
    if function == 22:
        return struct.pack(">BHHH", 22, address, rng.randrange(65536), rng.randrange(65536))
    if function == 16:
        n = rng.choice([0, 1, 2, 3, rng.randrange(1, 124)])
        data = rng.randbytes(min(2 * n + rng.choice([0, 0, 0, -1, 1]), 246) if n else 0)
        return struct.pack(">BHHB", 16, address, n, len(data)) + data
    n = rng.choice([0, 1, 3, rng.randrange(1, 122)])
    data = rng.randbytes(min(2 * n, 242))
    return struct.pack(">BHHHHB", 23, _address(rng), _count(rng, 125), address, n,
                       len(data)) + data


def fuzz_frame(rng: random.Random, tid: int) -> bytes:
    unit = rng.choice([1, 1, 1, 0, 255, rng.randrange(256)])
    roll = rng.random()
    if roll < 0.35:
        return mbap(tid, request_pdu(rng), unit)
    if roll < 0.5:  # an unknown (or response) function code with any payload
        return mbap(tid, bytes([rng.randrange(256)]) + rng.randbytes(rng.randrange(12)), unit)
    if roll < 0.9:  # a valid frame, mutated
        frame = bytearray(mbap(tid, request_pdu(rng), unit))
        mutation = rng.randrange(5)
        if mutation == 0:
            for _ in range(rng.randint(1, 3)):
                frame[rng.randrange(len(frame))] = rng.randrange(256)
        elif mutation == 1:
            del frame[rng.randrange(1, len(frame)):]
        elif mutation == 2:
            frame += rng.randbytes(rng.randint(1, 10))
        elif mutation == 3:
            frame[4:6] = struct.pack(">H", rng.choice([0, 1, 2, 255, rng.randrange(65536)]))
        else:
            frame[2:4] = struct.pack(">H", rng.randrange(1, 65536))
        return bytes(frame)
    return rng.randbytes(rng.randint(1, 300))  # garbage


def check_answers(data: bytes) -> int:
    """Every answer a well-formed frame: protocol 0, length matching, a served function code
    or its exception with code 01, 02 or 03. Returns the number of answers."""
    pos = n = 0
    while pos < len(data):
        assert len(data) - pos >= 9, data[pos:].hex()
        _, protocol, length = struct.unpack_from(">HHH", data, pos)
        assert protocol == 0, data[pos:pos + 8].hex()
        assert 3 <= length <= 254, data[pos:pos + 8].hex()
        pdu = data[pos + 7:pos + 6 + length]
        assert len(pdu) == length - 1, data[pos:].hex()
        function = pdu[0]
        if function & 0x80:
            assert function != 0x80, pdu.hex()  # today's answer to a read of 0 registers
            assert len(pdu) == 2, pdu.hex()
            assert pdu[1] in (1, 2, 3), pdu.hex()
            assert pdu[1] == 1 or function & 0x7F in SERVED, pdu.hex()
        else:
            assert function in SERVED, pdu.hex()
        pos += 6 + length
        n += 1
    return n


async def send_batch(port: int, batch: bytes, abort: bool) -> bytes:
    """One connection: the batch, then half-close and read the answers to EOF (or, with
    ``abort``, a reset right after writing)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    received = b""
    try:
        writer.write(batch)
        if abort:
            sock = writer.get_extra_info("socket")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            return received
        writer.write_eof()
        async with asyncio.timeout(10):
            while chunk := await reader.read(65536):
                received += chunk
    except ConnectionError:
        pass  # the server closed on a malformed frame while we were still writing
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()
    return received


async def test_fuzzed_frames_leave_no_traceback_intact_registers_and_a_small_log(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    loop = asyncio.get_running_loop()
    loop_errors: list[dict[str, object]] = []
    loop.set_exception_handler(lambda _, context: loop_errors.append(context))
    served = await Served.open()
    link = served.link
    before = link.bank.read(0, MAP_SIZE, 0)
    jobs = 0

    async def stand_in_daemon() -> None:
        nonlocal jobs
        while True:
            t = await served.triggers.get()
            jobs += 1
            await link.image_captured(t.seq, jobs)
            await link.publish(t.seq, JobResult(job_id=jobs, status=Status.OK,
                                                target=RobotTarget("kuka", tuple("XYZABC"), POSE)))

    async def worker(index: int, frames: int) -> tuple[int, int]:
        rng = random.Random(SEED + index)
        sent = answers = 0
        while sent < frames:
            n = min(rng.randint(1, 8), frames - sent)
            batch = b"".join(fuzz_frame(rng, rng.randrange(65536)) for _ in range(n))
            sent += n
            answers += check_answers(await send_batch(link.port, batch, rng.random() < 0.1))
        return sent, answers

    daemon = asyncio.create_task(stand_in_daemon())
    try:
        results = await asyncio.wait_for(
            asyncio.gather(*(worker(i, FRAMES // WORKERS) for i in range(WORKERS))), 60)
        frames = sum(sent for sent, _ in results)
        answered = sum(a for _, a in results)
        assert frames == FRAMES
        assert answered > FRAMES // 10  # a fair share were requests that got an answer
        assert link.faults["malformed"] > FRAMES // 10

        # still serving, and the registers only vgripd writes are intact
        assert link.health().state is LinkState.UP
        async with MockPlc("127.0.0.1", link.port, poll_s=0.002) as plc:
            await plc.check_byte_order()
            words = await plc.read()
            assert words[Reg.MAP_VERSION:Reg.HEARTBEAT] == before[Reg.MAP_VERSION:Reg.HEARTBEAT]
            assert (words[Reg.MAP_VERSION], words[Reg.CHECK_U16]) == (MAP_VERSIONS[0], CHECK_U16)
            assert words[Reg.WARNINGS] == 0
            assert words[Reg.STATE] in {int(state) for state in HandshakeState}
            if words[Reg.ACK_SEQ] and words[Reg.STATUS] == Status.OK:
                assert words[Reg.N_VALUES] == 6
            result = await plc.cycle()  # a whole job still goes through
            assert (result.status, result.values) == (Status.OK, POSE)
    finally:
        daemon.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await daemon
        await link.close()
        loop.set_exception_handler(None)

    assert not loop_errors, loop_errors
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    # the server side's log (the test's own pymodbus client logs its requests at DEBUG)
    lines = [r.getMessage() for r in caplog.records if not r.name.startswith("pymodbus")]
    log_bytes = sum(len(line) + 40 for line in lines)  # + level, time, logger name
    print(f"fuzz: {frames} frames, {answered} answers, {jobs} jobs, faults "
          f"{dict(link.faults)}, {len(lines)} log lines, {log_bytes} log bytes")
    assert log_bytes < frames, lines
    # one client address: per kind of fault, the first line and the count reported at close
    kinds = set(link.faults) | {"connected", "handshake"}
    assert link.ratelog.lines <= 2 * len(kinds), [r.getMessage() for r in caplog.records]
