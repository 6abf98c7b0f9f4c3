"""Protocol defects a security review found, each through the real daemon (worker process,
synthetic camera, one object per image) and the real peer of its link:

- S7 (snap7's server as the PLC, its own log of writes): CLEAR wrote STATUS 0 and JOB_ID 0 while
  ACK_SEQ still named the previous request, then changed ACK_SEQ straight to CLEAR's. Replaying
  the server's log, no write may change the result data while ACK_SEQ names a request.
- NEXT after a single-object job (S7, and OPC UA through asyncua's client): a list of one, so
  COUNT 1 and INDEX 2 = COUNT + 1 with NOT_FOUND; it answered COUNT 0 with INDEX 2.
- Robot socket (raw TCP frames): a NEXT whose list another link's job took is answered RESULT
  BAD_REQUEST with job 0 (docs/robot_socket.md); it was REFUSED.
"""

from __future__ import annotations

import asyncio
import struct

import pytest

from tests.integration.test_daemon import Plc, running
from vgripd.config import Config, config_from_dict
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import MAP_SIZE, PICK_AREA, Reg
from vgripd.peer.socket_frames import ANSWER_SIZE, AnswerKind, Request, SocketCommand, decode_answer
from vgripd.service.links.protocol import LinkState
from vgripd.sim.opcua_client import OpcUaClientProcess
from vgripd.sim.s7_plc import DbWrite, MockS7Plc, S7PlcServer, words_of
from vgripd.types import Status

pytestmark = pytest.mark.timeout(180)

WAIT_S = 30.0
DB = 10
#: Result data: STATUS .. FIT_RMS and COUNT .. SCORE, except what is live (RESULT_AGE_MS runs
#: with the heartbeat, WARNINGS is the daemon's state).
DATA = (set(range(Reg.STATUS, Reg.WARNINGS)) - {Reg.RESULT_AGE_MS, Reg.RESULT_AGE_MS + 1}
        | set(PICK_AREA))


def ordering_faults(writes: list[DbWrite]) -> list[str]:
    """Replay the PLC's log of writes: every write that changes result data while ACK_SEQ
    names a request (non-zero), and every change of ACK_SEQ in a write that changes more."""
    block = [0] * MAP_SIZE
    faults = []
    for n, w in enumerate(writes):
        if w.db != DB or w.start % 2 or len(w.data) % 2:
            continue
        first = w.start // 2
        words = struct.unpack(f">{len(w.data) // 2}H", w.data)
        touched = range(first, first + len(words))
        changed = {a for a, v in zip(touched, words, strict=True) if block[a] != v}
        if changed & DATA and block[Reg.ACK_SEQ] != 0:
            faults.append(f"write {n} (byte {w.start}) changes {sorted(changed & DATA)} while "
                          f"ACK_SEQ = {block[Reg.ACK_SEQ]}")
        if Reg.ACK_SEQ in changed and len(changed) > 1:
            faults.append(f"write {n}: ACK_SEQ changed together with other words")
        block[first:first + len(words)] = words
    return faults


def s7_config(server: S7PlcServer) -> Config:
    return config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "s7", "host": server.host, "port": server.port, "db": DB}],
        "status": {"port": 0}})


async def test_s7_clear_retracts_ack_first_and_writes_it_last() -> None:
    async with S7PlcServer(DB) as server, MockS7Plc(server.host, server.port, DB) as plc, \
            running(s7_config(server)) as run:
            link = run.daemon.rooms.links.links["s7"]
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            job = words_of((await plc.run_job(1, WAIT_S)).raw)
            clear = words_of((await plc.run_job(2, WAIT_S, Command.CLEAR)).raw)
            await server.wait_write(lambda w: w.start == 2 * Reg.ACK_SEQ
                                    and w.data == b"\x00\x02", WAIT_S)
    assert (job[Reg.ACK_SEQ], job[Reg.STATUS]) == (1, Status.OK)
    assert (clear[Reg.ACK_SEQ], clear[Reg.STATUS], clear[Reg.COUNT]) == (2, Status.IDLE, 0)
    assert clear[Reg.JOB_ID:Reg.JOB_ID + 2] == (0, 0)
    assert ordering_faults(server.writes) == []
    # CLEAR's own writes: ACK_SEQ 0 alone, then its data, then ACK_SEQ 2 alone (the live
    # HEARTBEAT word is written on its own clock, between them or after)
    start = max(i for i, w in enumerate(server.writes)
                if w.start == 2 * Reg.ACK_SEQ and w.data == b"\x00\x01")
    ours = [w for w in server.writes[start + 1:]
            if w.start >= 6 and w.start != 2 * Reg.HEARTBEAT]
    assert [w.data for w in ours if w.start == 2 * Reg.ACK_SEQ] == [b"\x00\x00", b"\x00\x02"]
    assert ours[0] == DbWrite(DB, 2 * Reg.ACK_SEQ, b"\x00\x00")
    assert ours[-1] == DbWrite(DB, 2 * Reg.ACK_SEQ, b"\x00\x02")


async def test_s7_next_after_one_object_is_a_list_of_one() -> None:
    async with S7PlcServer(DB) as server, MockS7Plc(server.host, server.port, DB) as plc, \
            running(s7_config(server)) as run:
            link = run.daemon.rooms.links.links["s7"]
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            job = words_of((await plc.run_job(1, WAIT_S)).raw)
            nxt = words_of((await plc.run_job(2, WAIT_S, Command.NEXT)).raw)
            again = words_of((await plc.run_job(3, WAIT_S, Command.NEXT)).raw)
    assert (job[Reg.STATUS], job[Reg.COUNT], job[Reg.INDEX]) == (Status.OK, 1, 1)
    for answer in (nxt, again):  # past the end of a list of one, and it stays so
        assert (answer[Reg.STATUS], answer[Reg.COUNT], answer[Reg.INDEX],
                answer[Reg.N_VALUES]) == (Status.NOT_FOUND, 1, 2, 0)
        assert answer[Reg.JOB_ID:Reg.JOB_ID + 2] == job[Reg.JOB_ID:Reg.JOB_ID + 2]
    assert ordering_faults(server.writes) == []


async def test_opcua_next_after_one_object_is_a_list_of_one() -> None:
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
                   "allow_anonymous": True, "models": ["vgripd"]}],  # its older namespace
        "status": {"port": 0}})
    async with running(config) as run:
        await run.daemon.wait_for(lambda: all(link.health().state is LinkState.UP
                                              for link in run.daemon.rooms.links.links.values()), WAIT_S)
        async with OpcUaClientProcess(f"opc.tcp://127.0.0.1:{run.port(0)}/vgripd") as client:
            assert client.connected["event"] == "connected", client.connected
            job = await client.send("job")
            nxt = await client.send("next")
            again = await client.send("next")
    assert (job["Status"], job["Count"], job["Index"]) == (Status.OK, 1, 1)
    for answer in (nxt, again):
        assert (answer["Status"], answer["Count"], answer["Index"], answer["Values"]) == (
            Status.NOT_FOUND, 1, 2, [])
        assert answer["JobId"] == job["JobId"]


async def _answer(reader: asyncio.StreamReader) -> tuple[int, int, int, int]:
    async with asyncio.timeout(WAIT_S):
        a = decode_answer(await reader.readexactly(ANSWER_SIZE))
    return a.kind, a.request_id, a.status, a.job_id


async def test_robot_socket_next_after_another_links_job_is_result_bad_request() -> None:
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "robot_socket", "host": "127.0.0.1", "port": 0},
                  {"type": "modbus_server", "host": "127.0.0.1", "port": 0}],
        "status": {"port": 0}})
    async with running(config) as run:
        reader, writer = await asyncio.open_connection("127.0.0.1", run.port(0))
        try:
            writer.write(Request(SocketCommand.LOCATE, 7).encode())
            await writer.drain()
            captured = await _answer(reader)
            located = await _answer(reader)
            async with Plc(run.port(1)) as plc:  # another link's job takes the list
                await plc.trigger(1)
                assert (await plc.result(1))[Reg.STATUS] == Status.OK
            writer.write(Request(SocketCommand.NEXT, 8).encode())
            await writer.drain()
            nxt = await _answer(reader)
        finally:
            writer.close()
    assert captured[:2] == (AnswerKind.CAPTURED, 7)
    assert located[:3] == (AnswerKind.RESULT, 7, Status.OK)
    assert nxt == (AnswerKind.RESULT, 8, Status.BAD_REQUEST, 0)
