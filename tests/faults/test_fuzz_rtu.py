"""A seeded fuzzer over the bytes on an RTU line (a socat pty pair): noise, frames with a bad
CRC, truncated frames, frames for other units, unknown function codes, refused reads and writes.
After each burst and a silence, a valid request must be answered with the register map intact;
the link never goes down, nothing is logged with a traceback, no job is triggered.

``VGRIPD_FUZZ_SEED`` replays another sequence; the failing case is in the assertion message.
"""

from __future__ import annotations

import asyncio
import logging
import os
import random
import struct
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.links.modbus_rtu import ModbusRtuLink
from tests.faults.rtu_line import BAUD, PtyLine, RawMaster, read_request, read_words
from vgripd.peer.registers import MAP_SIZE, Reg
from vgripd.peer.rtu import crc_ok, with_crc
from vgripd.service.links.protocol import LinkState, Trigger

pytestmark = pytest.mark.timeout(120)
SEED = int(os.environ.get("VGRIPD_FUZZ_SEED", "5150"))
CASES = 150
UNIT = 7
WRITES = {5, 6, 15, 16, 22, 23}  # function codes that could change the command area


def request_for(rng: random.Random, unit: int, function: int) -> bytes:
    """A well-formed request of ``function`` (random fields), CRC included."""
    if function in (1, 2, 3, 4):
        body = struct.pack(">BBHH", unit, function, rng.randrange(65536), rng.randint(0, 300))
    elif function in (5, 6):
        body = struct.pack(">BBHH", unit, function, rng.randint(3, 65535), rng.randrange(65536))
    elif function in (15, 16):
        count = rng.randint(1, 20)
        body = struct.pack(">BBHHB", unit, function, rng.randint(3, 65535), count, 2 * count)
        body += rng.randbytes(2 * count)
    else:
        body = bytes((unit, function)) + rng.randbytes(rng.randint(0, 12))
    return with_crc(body)


def fuzz_case(rng: random.Random) -> tuple[str, bytes]:
    kind = rng.choice(["noise", "bad_crc", "truncated", "other_unit", "unknown_function",
                       "refused_read", "refused_write", "noise_then_frame"])
    if kind == "noise":
        return kind, rng.randbytes(rng.randint(1, 60))
    if kind == "bad_crc":
        frame = bytearray(request_for(rng, UNIT, 3))
        frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        return kind, bytes(frame)
    if kind == "truncated":
        frame = request_for(rng, UNIT, rng.choice([3, 6, 16, 23]))
        return kind, frame[:rng.randint(1, len(frame) - 1)]
    if kind == "other_unit":
        unit = rng.choice([u for u in range(0, 248) if u != UNIT])
        return kind, request_for(rng, unit, rng.choice([3, 6, 16, 23, 43]))
    if kind == "unknown_function":
        function = rng.choice([f for f in range(1, 128) if f not in WRITES])
        return kind, request_for(rng, UNIT, function)
    if kind == "refused_read":
        address = rng.choice([MAP_SIZE, rng.randint(0, 65535)])
        count = rng.choice([0, 126, rng.randint(MAP_SIZE - address + 1, 200)
                            if address < MAP_SIZE else 1])
        return kind, with_crc(struct.pack(">BBHH", UNIT, 3, address, count))
    if kind == "refused_write":
        return kind, request_for(rng, UNIT, rng.choice([6, 16]))  # address >= 3: read-only
    frame = request_for(rng, rng.randint(1, 247), 3)
    return kind, rng.randbytes(rng.randint(1, 8)) + frame


@pytest.fixture
def line(tmp_path: Path) -> Iterator[PtyLine]:
    pty = PtyLine(tmp_path)
    pty.plug()
    try:
        yield pty
    finally:
        pty.unplug()


def read_after(master: RawMaster, count: int) -> bytes | None:
    """Read the map after a fuzzed frame. The test gives a fuzzed frame 10 ms for its answer
    (a real master would wait its whole response timeout); on a busy machine an exception
    answer to it may come later, after the read is sent: a whole frame that is not the read's
    answer is that late answer and is passed over (at most three)."""
    answer = master.request(read_request(UNIT, 0, count))
    for _ in range(3):
        if answer is None or not crc_ok(answer) or answer[1:3] == bytes((3, 2 * count)):
            break
        answer = master.answer()
    return answer


async def test_fuzzed_line_never_costs_the_map(line: PtyLine,
                                                caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    triggers: list[Trigger] = []
    link = ModbusRtuLink("rtu", ModbusRtuLink.Options(
        port=str(line.server), baudrate=BAUD, parity="N", unit_id=UNIT, heartbeat_ms=1000))
    await link.open(triggers.append)
    master = RawMaster(line.client)
    rng = random.Random(SEED)
    try:
        reference = read_words(await asyncio.to_thread(
            master.request, read_request(UNIT, 0, MAP_SIZE)), MAP_SIZE)
        for i in range(CASES):
            kind, data = fuzz_case(rng)
            where = f"seed {SEED} case {i} ({kind}: {data.hex()})"
            await asyncio.to_thread(master.send, data)
            await asyncio.to_thread(master.answer, 0.01)  # an exception answer, if any
            await asyncio.sleep(0.005)  # silence: more than 3.5 characters (1.75 ms)
            answer = await asyncio.to_thread(read_after, master, MAP_SIZE)
            words = read_words(answer, MAP_SIZE)
            words[Reg.HEARTBEAT] = reference[Reg.HEARTBEAT]
            assert words == reference, where
            assert link.health().state is LinkState.UP, where
    finally:
        master.close()
        await link.close()
    assert triggers == []
    assert all(r.exc_info is None and "Traceback" not in r.getMessage()
               for r in caplog.records)
    assert link.frames_answered >= CASES + 1
