"""The Modbus/TCP server link against a hostile or broken network, with raw sockets on loopback
(issue "A PLC interface nothing on the network can stall"): wrong quantities, unknown function
codes, malformed frames, pipelining, clients that do not read, connection floods, silent
clients, unit ids. The daemon-process rows (file limit, ports in use) are in
test_daemon_network_faults.py, the fuzzer in test_modbus_tcp_fuzz.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
from collections.abc import AsyncIterator

import pytest

from tests.faults.modbus_raw import (
    Served,
    close_quietly,
    closed_by_server,
    mbap,
    read_request,
    recv_frame,
    silent,
)
from vgripd.peer.registers import CHECK_U16, MAP_SIZE, MAP_VERSIONS, Reg
from vgripd.service.links.protocol import LinkState
from vgripd.sim.plc import MockPlc
from vgripd.types import JobResult, RobotTarget, Status

TCP_CLOSE, TCP_CLOSE_WAIT = 7, 8  # tcp_info.tcpi_state after a reset / a FIN from the server


@pytest.fixture
async def served() -> AsyncIterator[Served]:
    s = await Served.open()
    yield s
    await s.link.close()
    assert s.link.health().state is LinkState.STOPPED


def no_tracebacks(caplog: pytest.LogCaptureFixture) -> None:
    bad = [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    assert not bad, [r.getMessage() for r in bad]


# --- quantities and function codes -----------------------------------------------------

async def test_read_of_0_or_126_registers_is_exception_03(served: Served) -> None:
    """Today: pymodbus answers function code 0x80 (no such function) instead of 0x83."""
    reader, writer = await served.connect()
    try:
        cases = [
            (read_request(1, 0, 0), b"\x83\x03"),
            (read_request(2, 0, 126), b"\x83\x03"),
            (read_request(3, 0, 0xFFFF), b"\x83\x03"),
            (read_request(4, 0, 125), b"\x83\x02"),  # legal quantity, beyond the map
            (read_request(5, MAP_SIZE, 1), b"\x83\x02"),
            # FC16: 0 and 124 registers, byte count disagreeing with the quantity
            (mbap(6, struct.pack(">BHHB", 16, 0, 0, 0)), b"\x90\x03"),
            (mbap(7, struct.pack(">BHHB", 16, 0, 124, 246) + bytes(246)), b"\x90\x03"),
            (mbap(8, struct.pack(">BHHB", 16, 0, 2, 2) + bytes(2)), b"\x90\x03"),
            # FC23: read 0, write 122
            (mbap(9, struct.pack(">BHHHHB", 23, 0, 0, 0, 1, 2) + bytes(2)), b"\x97\x03"),
            (mbap(10, struct.pack(">BHHHHB", 23, 0, 1, 0, 122, 242) + bytes(242)), b"\x97\x03"),
        ]
        for frame, answer in cases:
            writer.write(frame)
            tid, unit, pdu = await recv_frame(reader)
            assert (tid, unit, pdu) == (struct.unpack(">H", frame[:2])[0], 1, answer), frame.hex()
        writer.write(read_request(11, Reg.MAP_VERSION, 2))  # the connection still serves
        assert await recv_frame(reader) == (11, 1, bytes([3, 4, 0, MAP_VERSIONS[0], 0x12, 0x34]))
    finally:
        await close_quietly(writer)


async def test_unknown_function_codes_get_exception_01_without_traceback(
        served: Served, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    reader, writer = await served.connect()
    try:
        functions = [1, 2, 4, 5, 7, 8, 11, 12, 15, 17, 20, 21, 24, 43, 0x5A, 0x63, 0x7F]
        for i, function in enumerate(functions * 5):
            writer.write(mbap(i, bytes([function]) + bytes(i % 7)))
            assert await recv_frame(reader) == (i, 1, bytes([function | 0x80, 1])), function
        assert served.link.faults["exception 01"] == 5 * len(functions)
    finally:
        await close_quietly(writer)
    no_tracebacks(caplog)
    lines = [r for r in caplog.records if "exception 01" in r.getMessage()]
    assert len(lines) == 1, [r.getMessage() for r in lines]  # rate limited: one per interval


# --- malformed frames -----------------------------------------------------------------

MALFORMED = {
    "protocol id 1": mbap(90, bytes.fromhex("0300000001"), protocol=1),
    "MBAP length 0": mbap(90, b"", length=0),
    "MBAP length 1": mbap(90, b"", length=1),
    "MBAP length 255": mbap(90, bytes(254), length=255),
    "MBAP length 0xffff": mbap(90, bytes.fromhex("0300000001"), length=0xFFFF),
    "FC3 truncated": mbap(90, bytes.fromhex("03000000")),
    "FC3 trailing byte": mbap(90, bytes.fromhex("030000000100")),
    "FC16 byte count lies": mbap(90, bytes.fromhex("10000000020600010002")),
    "FC23 truncated": mbap(90, bytes.fromhex("17000000010000")),
    "function 0": mbap(90, bytes.fromhex("00000000")),
    "exception code as request": mbap(90, bytes.fromhex("8302")),
}


@pytest.mark.parametrize("frame", MALFORMED.values(), ids=MALFORMED.keys())
async def test_malformed_frame_closes_its_connection(served: Served, frame: bytes) -> None:
    """Answers before the bad frame go out; nothing after it is answered; the connection is
    closed (today it stays open and answers nothing more); other connections are unaffected."""
    reader, writer = await served.connect()
    other_reader, other_writer = await served.connect()
    try:
        writer.write(read_request(1, Reg.CHECK_U16, 1) + frame + read_request(2, Reg.CHECK_U16, 1))
        assert await recv_frame(reader) == (1, 1, bytes([3, 2, 0x12, 0x34]))
        assert await closed_by_server(reader)
        assert served.link.faults["malformed"] == 1
        other_writer.write(read_request(3, Reg.CHECK_U16, 1))
        assert await recv_frame(other_reader) == (3, 1, bytes([3, 2, 0x12, 0x34]))
        assert served.link.peers() == 1
    finally:
        await close_quietly(writer)
        await close_quietly(other_writer)


async def test_malformed_frame_split_over_segments_is_still_found(served: Served) -> None:
    reader, writer = await served.connect()
    try:
        frame = MALFORMED["protocol id 1"]
        with contextlib.suppress(ConnectionError):
            for i in range(len(frame)):  # one byte at a time; closed after the 4th
                writer.write(frame[i:i + 1])
                await writer.drain()
                await asyncio.sleep(0.005)
        assert await closed_by_server(reader)
        assert served.link.faults["malformed"] == 1
    finally:
        await close_quietly(writer)


# --- pipelining ---------------------------------------------------------------------------

async def test_pipelined_requests_in_one_segment_are_all_answered_in_order(
        served: Served) -> None:
    """Today: of 5 requests in one segment, 1 is answered."""
    reader, writer = await served.connect()
    try:
        writer.write(b"".join([
            read_request(101, Reg.CHECK_U16, 1),
            mbap(102, struct.pack(">BHH", 6, Reg.RECIPE, 9)),  # write RECIPE
            read_request(103, Reg.RECIPE, 1),  # sees the write before it
            mbap(104, b"\x63"),  # unknown function
            read_request(105, 0, 0),  # illegal quantity
        ]))
        answers = [await recv_frame(reader) for _ in range(5)]
        assert answers == [
            (101, 1, bytes([3, 2, 0x12, 0x34])),
            (102, 1, struct.pack(">BHH", 6, Reg.RECIPE, 9)),
            (103, 1, bytes([3, 2, 0, 9])),
            (104, 1, b"\xe3\x01"),
            (105, 1, b"\x83\x03"),
        ]
        # Many more than one batch (the link answers 64 at a time, then serves others).
        n = 1000
        writer.write(b"".join(read_request(i, Reg.MAP_VERSION, 1) for i in range(n)))
        tids = [(await recv_frame(reader))[0] for _ in range(n)]
        assert tids == list(range(n))
    finally:
        await close_quietly(writer)


async def test_pipelined_trigger_and_poll_in_one_segment(served: Served) -> None:
    reader, writer = await served.connect()
    try:
        writer.write(mbap(1, struct.pack(">BHHB3H", 16, Reg.CMD, 3, 6, 1, 5, 2))
                     + read_request(2, Reg.STATE, 1))
        assert (await recv_frame(reader))[2] == struct.pack(">BHH", 16, Reg.CMD, 3)
        assert (await recv_frame(reader))[2] == bytes([3, 2, 0, 1])  # TRIGGERED
        t = await asyncio.wait_for(served.triggers.get(), 5)
        assert (t.seq, t.recipe) == (5, 2)
    finally:
        await close_quietly(writer)


# --- clients that do not read ---------------------------------------------------------------

async def test_clients_that_do_not_read_are_dropped_and_their_output_is_bounded() -> None:
    """Today: 4 such clients grow the daemon by +0.78 MB/s without bound. Each of them sends
    60,000 reads of the whole map and reads nothing: 5.5 MB of answers, more than the kernel's
    socket buffers take (up to 4 MB with Linux' default tcp_wmem), so the rest waits in the
    link, and only up to ``max_unsent_bytes``."""
    bound = 16384
    served = await Served.open(max_unsent_bytes=bound)
    loop = asyncio.get_running_loop()
    socks: list[socket.socket] = []
    try:
        requests = b"".join(read_request(i & 0xFFFF, 0, MAP_SIZE) for i in range(60000))
        for _ in range(4):
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.setblocking(False)
            await loop.sock_connect(s, ("127.0.0.1", served.link.port))
            socks.append(s)
        await served.until(lambda: served.link.peers() == 4)

        async def flood(s: socket.socket) -> bool:
            """Send everything, read nothing; True once the server has closed or reset us
            (the kernel's view of the socket, so that nothing is read)."""
            try:
                await loop.sock_sendall(s, requests)
            except OSError:
                return True
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(20):
                    while True:
                        state = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)[0]
                        if state in (TCP_CLOSE, TCP_CLOSE_WAIT):
                            return True
                        await asyncio.sleep(0.02)
            return False

        senders = [asyncio.create_task(flood(s)) for s in socks]
        async with MockPlc("127.0.0.1", served.link.port) as plc:  # a reading client is fine
            assert all(await asyncio.gather(*senders)), "a client that does not read was kept"
            await plc.check_byte_order()
            assert served.link.peers() == 1
        assert served.link.faults["not_reading"] == 4
        # what waited for a client never exceeded the bound by more than one answer
        assert bound < served.link.peak_unsent <= bound + 9 + 2 * MAP_SIZE
    finally:
        for s in socks:
            s.close()
        await served.link.close()


# --- connection cap, eviction, idle timeout, keepalive --------------------------------------

async def test_connection_cap_evicts_never_answered_ones_and_a_new_plc_is_served() -> None:
    """Today (before the cap): 1,100 idle connections exhaust the file limit and nothing new
    connects. Then: a newcomer evicted the longest-idle connection, so a
    flood evicted clients that had been polling. Now only connections that never got a normal
    answer are evicted; when every one has, the newcomer is refused."""
    served = await Served.open(max_connections=4)
    link = served.link
    conns: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []
    try:
        for _ in range(4):
            reader, writer = await served.connect()
            conns.append((reader, writer))
            await served.until(lambda: link.peers() == len(conns))
        # #0, #1, #3 get normal answers; #2 never sends anything
        for i in (0, 1, 3):
            conns[i][1].write(read_request(i, Reg.CHECK_U16, 1))
            await recv_frame(conns[i][0])
        conns.append(await served.connect())
        assert await closed_by_server(conns[2][0])
        assert link.peers() == 4
        for i in (0, 1, 3):
            assert await silent(conns[i][0], 0.05)
        conns.append(await served.connect())  # #5 evicts #4, the one that never asked
        assert await closed_by_server(conns[4][0])
        for i in (0, 1, 3):  # the clients that have talked are still answered
            conns[i][1].write(read_request(10 + i, Reg.CHECK_U16, 1))
            assert (await recv_frame(conns[i][0]))[0] == 10 + i

        # max + N idle connections: the link never holds more than max, and a PLC still works
        flood = [await served.connect() for _ in range(40)]
        conns += flood
        assert link.peers() <= 4
        async with MockPlc("127.0.0.1", link.port, poll_s=0.002) as plc:
            seq = await plc.trigger()
            t = await served.triggers.get()
            await link.image_captured(t.seq, 1)
            await link.publish(t.seq, JobResult(job_id=1, status=Status.OK, target=RobotTarget(
                "kuka", tuple("XYZABC"), (1.0, 2.0, 3.0, 0.0, 0.0, 0.0))))
            result = await plc.wait_answer(seq)
            assert result.status is Status.OK
        assert link.peers() <= 4
        assert link.faults["evicted"] >= 40
        for i in (0, 1, 3):
            conns[i][1].write(read_request(20 + i, Reg.CHECK_U16, 1))
            assert (await recv_frame(conns[i][0]))[0] == 20 + i
        # all four slots answered once: a newcomer is refused, nobody evicted
        fourth = await served.connect()
        conns.append(fourth)
        fourth[1].write(read_request(30, Reg.CHECK_U16, 1))
        assert (await recv_frame(fourth[0]))[0] == 30
        conns.append(await served.connect())
        assert await closed_by_server(conns[-1][0])
        assert link.faults["full"] >= 1
        for i in (0, 1, 3):
            conns[i][1].write(read_request(40 + i, Reg.CHECK_U16, 1))
            assert (await recv_frame(conns[i][0]))[0] == 40 + i
    finally:
        for _, writer in conns:
            await close_quietly(writer)
        await link.close()


async def test_flood_of_never_valid_newcomers_never_evicts_a_polling_plc() -> None:
    """A PLC polling every 100 ms was evicted 15 times in 12 s by newcomers
    that never sent a request (the longest-idle connection went first, and a newcomer's clock
    starts at its connect). Now the flood evicts only itself; the PLC's connection stays."""
    served = await Served.open(max_connections=4)
    link = served.link
    flood: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []
    try:
        async with MockPlc("127.0.0.1", link.port) as plc:
            await plc.read(Reg.CHECK_U16, 1)
            assert len(link.connections()) == 1
            the_plc = link.connections()[0]
            stop = asyncio.Event()
            polls = 0

            async def poll() -> None:
                nonlocal polls
                while not stop.is_set():
                    await plc.read(Reg.CHECK_U16, 1)
                    polls += 1
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(stop.wait(), 0.1)

            poller = asyncio.create_task(poll())
            for _ in range(200):
                flood.append(await served.connect())
            await served.until(lambda: link.faults["evicted"] >= 190)
            stop.set()
            await poller
            assert polls >= 1
            assert the_plc in link.connections()
            assert not the_plc.closing
            assert link.peers() <= 4
    finally:
        for _, writer in flood:
            await close_quietly(writer)
        await link.close()


async def test_allow_list_closes_other_addresses_at_accept(
        caplog: pytest.LogCaptureFixture) -> None:
    """``allow``: a client from 127.0.0.2 is closed at accept with one rate-limited log line;
    127.0.0.1 is served. Today the option does not exist (the config is refused)."""
    caplog.set_level(logging.INFO, logger="drivers.links.modbus_server")
    served = await Served.open(allow=["127.0.0.1"])
    link = served.link
    try:
        for _ in range(5):
            sock = socket.socket()
            sock.bind(("127.0.0.2", 0))
            sock.setblocking(False)
            await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", link.port))
            reader, writer = await asyncio.open_connection(sock=sock)
            writer.write(read_request(1, Reg.CHECK_U16, 1))
            assert await closed_by_server(reader)
            await close_quietly(writer)
        async with MockPlc("127.0.0.1", link.port) as plc:
            assert await plc.read(Reg.CHECK_U16, 1) == [CHECK_U16]
        assert link.faults["not_allowed"] == 5
        lines = [r for r in caplog.records if "not in allow" in r.getMessage()]
        assert len(lines) == 1, [r.getMessage() for r in lines]
        assert "127.0.0.2" in lines[0].getMessage()
    finally:
        await link.close()


async def test_silent_clients_are_closed_by_the_idle_timeout() -> None:
    """Today: of 20 clients that vanished without FIN, 19 are still ESTABLISHED after 180 s.
    A silent client is what a vanished one looks like to the server (no data, no FIN); the
    idle timeout closes both."""
    served = await Served.open(idle_timeout_s=0.5, max_connections=32)
    link = served.link
    conns = []
    try:
        for i in range(20):
            reader, writer = await served.connect()
            writer.write(read_request(i, Reg.CHECK_U16, 1))
            assert (await recv_frame(reader))[0] == i
            conns.append((reader, writer))
        # a PLC that keeps polling is not idle
        async with MockPlc("127.0.0.1", link.port) as plc:
            stop = asyncio.Event()

            async def poll() -> int:
                polls = 0
                while not stop.is_set():
                    assert (await plc.read(Reg.CHECK_U16, 1)) == [CHECK_U16]
                    polls += 1
                    await asyncio.sleep(0.1)
                return polls

            poller = asyncio.create_task(poll())
            for reader, _ in conns:
                assert await closed_by_server(reader, 3.0)
            await asyncio.sleep(0.7)  # past the timeout once more
            stop.set()
            assert await poller > 10
            assert link.peers() == 1
        assert link.faults["idle"] == 20
    finally:
        for _, writer in conns:
            await close_quietly(writer)
        await link.close()


async def test_keepalive_is_set_on_every_client_connection() -> None:
    """Keepalive finds a peer that vanished on a real network (loopback cannot lose one)."""
    served = await Served.open(keepalive_idle_s=7, keepalive_interval_s=2, keepalive_count=4)
    writers = []
    try:
        for _ in range(3):
            writers.append((await served.connect())[1])
        await served.until(lambda: served.link.peers() == 3)
        for conn in served.link.connections():
            assert conn.transport is not None
            sock = conn.transport.get_extra_info("socket")
            assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
            assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == 7
            assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL) == 2
            assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == 4
            assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 15000
    finally:
        for writer in writers:
            await close_quietly(writer)
        await served.link.close()


async def test_idle_timeout_0_keeps_silent_clients() -> None:
    served = await Served.open(idle_timeout_s=0, keepalive=False)
    try:
        reader, writer = await served.connect()
        await served.until(lambda: served.link.peers() == 1)
        assert await silent(reader, 1.5)
        assert served.link.peers() == 1
        sock = served.link.connections()[0].transport.get_extra_info("socket")  # type: ignore[union-attr]
        assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 0
        await close_quietly(writer)
    finally:
        await served.link.close()


# --- unit ids -------------------------------------------------------------------------------

@pytest.mark.parametrize(("wildcards", "answered"), [(True, {7, 0, 255}), (False, {7})])
async def test_unit_id_and_wildcards(wildcards: bool, answered: set[int]) -> None:
    served = await Served.open(unit_id=7, unit_id_wildcards=wildcards)
    reader, writer = await served.connect()
    try:
        for unit in (7, 0, 255, 1, 8):
            writer.write(read_request(unit, Reg.CHECK_U16, 1, unit=unit))
            if unit in answered:
                assert await recv_frame(reader) == (unit, unit, bytes([3, 2, 0x12, 0x34]))
            else:
                assert await silent(reader, 0.2)  # not answered, connection kept
        writer.write(read_request(99, Reg.CHECK_U16, 1, unit=7))
        assert (await recv_frame(reader))[0] == 99
        assert served.link.faults["unit"] == 5 - len(answered)
    finally:
        await close_quietly(writer)
        await served.link.close()


async def test_options_are_bounded() -> None:
    from pydantic import ValidationError

    from drivers.links.modbus_server import TcpOptions

    for bad in ({"max_connections": 0}, {"idle_timeout_s": -1}, {"idle_timeout_s": 0.01},
                {"keepalive_idle_s": 0}, {"max_unsent_bytes": 100}, {"log_interval_s": 0},
                {"unit_id": 256}, {"max_conections": 4}, {"allow": []},
                {"allow": ["10.0.0.300"]}):
        with pytest.raises(ValidationError):
            TcpOptions.model_validate(bad)
