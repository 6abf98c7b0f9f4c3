"""Robot socket link: trigger to result vs a bare asyncio socket peer, same run.

The robot side is one asyncio client (a kept connection, like the KUKA, ABB and Staubli
programs) that writes a 16-byte LOCATE and waits for the 64-byte RESULT; the time is from the
write to the RESULT being read, over TCP on 127.0.0.1. The daemon stand-in answers at once,
so what is timed is the link: framing, request
judging, the trigger hand-off to the daemon's handler, CAPTURED and RESULT encoding.

The named peer is a bare ``asyncio.start_server`` handler that reads 16 bytes and writes a
prepared CAPTURED and RESULT with the request id patched in: the least any server speaking this
format can do. Both run in blocks of 100 jobs, alternating, so load changes hit both.
"""

from __future__ import annotations

import asyncio
import struct
import time

from bench.links import LinkRun, Series, answer_at_once
from drivers.links.robot_socket import RobotSocketLink, RobotSocketOptions
from vgripd.peer.socket_frames import (
    ANSWER_SIZE,
    Answer,
    AnswerKind,
    Request,
    SocketCommand,
    ValueEncoding,
    decode_answer,
)
from vgripd.types import RobotTarget, Status

DEFAULT_JOBS = 2000
POSE = (412.5, -133.25, 287.0625, 0.1234, -2.9, 179.5)
BLOCK = 100


class Robot:
    """The robot program's side: one connection, one request at a time."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.seq = 0

    async def job(self) -> float:
        self.seq += 1
        t0 = time.perf_counter()
        self.writer.write(Request(SocketCommand.LOCATE, self.seq).encode())
        while True:
            answer = decode_answer(await self.reader.readexactly(ANSWER_SIZE))
            if answer.kind is not AnswerKind.CAPTURED:
                break
        dt_ms = (time.perf_counter() - t0) * 1e3
        assert (answer.request_id, answer.status) == (self.seq, Status.OK), answer
        return dt_ms


async def link_peer() -> RobotSocketLink:
    link = RobotSocketLink("bench", RobotSocketOptions(host="127.0.0.1", port=0))
    await link.open(answer_at_once(link, RobotTarget("kuka", ("X", "Y", "Z", "A", "B", "C"),
                                                     POSE)))
    return link


async def bare_peer(finished: asyncio.Event) -> asyncio.Server:
    encoding = ValueEncoding()
    captured = bytearray(Answer(AnswerKind.CAPTURED, 0, 0, 1).encode(encoding))
    result = bytearray(Answer(AnswerKind.RESULT, 0, int(Status.OK), 1, 0, POSE).encode(encoding))

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                request = await reader.readexactly(16)
                captured[4:8] = result[4:8] = request[4:8]  # echo the request id
                writer.write(bytes(captured))
                writer.write(bytes(result))
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()
        finally:
            finished.set()

    return await asyncio.start_server(serve, "127.0.0.1", 0)


async def measure(jobs: int) -> LinkRun:
    link = await link_peer()
    bare_done = asyncio.Event()
    bare = await bare_peer(bare_done)
    robots = {}
    for name, port in (("link", link.port), ("bare", bare.sockets[0].getsockname()[1])):
        robots[name] = Robot(*await asyncio.open_connection("127.0.0.1", port))
    times: dict[str, list[float]] = {"link": [], "bare": []}
    for name in ("link", "bare"):  # warm-up, not counted
        for _ in range(20):
            await robots[name].job()
    done = 0
    while done < jobs:
        n = min(BLOCK, jobs - done)
        for name in ("link", "bare"):
            for _ in range(n):
                times[name].append(await robots[name].job())
        done += n
    for robot in robots.values():
        robot.writer.close()
        await robot.writer.wait_closed()
    await bare_done.wait()
    await link.close()
    bare.close()
    await bare.wait_closed()
    frame = struct.calcsize(">4I"), ANSWER_SIZE
    peer = "bare asyncio socket peer: read 16 bytes, write two prepared answers"
    return LinkRun(
        heading="Robot socket link",
        setup=(f"{jobs} jobs per row, a kept connection on 127.0.0.1, blocks of {BLOCK} "
               "alternating link and peer after 20 warm-up jobs each. Timed: a robot-side "
               "asyncio client (as the KUKA, ABB and Staubli programs keep theirs), from "
               "writing a 16-byte LOCATE to having read the RESULT; the daemon side answers at "
               "once."),
        series=[Series("vgripd RobotSocketLink", times["link"], against=peer),
                Series(peer, times["bare"])],
        notes=[f"Bytes per job: {frame[0]} request + 2 x {frame[1]} answers (CAPTURED, "
               "RESULT)."])
