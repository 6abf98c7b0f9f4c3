"""S7Link against snap7's own server in a child process (the PLC stand-in), driven by the mock
PLC program (a snap7 asyncio client), over real ISO-on-TCP on 127.0.0.1.

The PLC side decodes the block with ``struct`` at the map's offsets, or with the types of the
UDT that ``vgripd s7-udt`` prints (parsed back here), never with vgripd's codec, so an encoding
bug in the link cannot cancel out.
"""

from __future__ import annotations

import asyncio
import os
import re
import signal
import struct
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import numpy as np
import pytest

from drivers.links.s7 import S7Link, S7Options
from tests.conftest import REPO, stop_task
from vgripd.cli.s7_udt import udt_source
from vgripd.errors import ConfigError, LinkError
from vgripd.peer.jobcore import Command, next_answer
from vgripd.peer.registers import (
    MAP_SIZE,
    MAP_VERSIONS,
    Reg,
    Warnings,
)
from vgripd.peer.s7_block import DB_BYTES
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.s7_plc import DbWrite, MockS7Plc, S7PlcServer
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

pytestmark = pytest.mark.timeout(300)  # link outages and recoveries, on a busy machine

DB = 10
WAIT_S = 10.0
POSE = (412.5, -133.25, 287.0625, 12.34, -29.0, 179.5)  # KUKA X Y Z A B C (mm, deg)
ACK_AT = 2 * Reg.ACK_SEQ


def kuka_result(job_id: int, values: tuple[float, ...] = POSE) -> JobResult:
    target = RobotTarget("kuka", ("x", "y", "z", "a", "b", "c"), values)
    return JobResult(job_id=job_id, status=Status.OK, target=target,
                     residuals={"fit_rms_mm": 0.042})


@pytest.fixture
async def server() -> AsyncIterator[S7PlcServer]:
    async with S7PlcServer(DB) as s:
        yield s


@pytest.fixture
async def plc(server: S7PlcServer) -> AsyncIterator[MockS7Plc]:
    async with MockS7Plc(server.host, server.port, DB) as p:
        yield p


class Daemon:
    """Stands in for vgripd's daemon: answers every trigger with ``result_for``."""

    def __init__(self, link: S7Link,
                 result_for: Callable[[Trigger], JobResult] | None = None) -> None:
        self.link = link
        self.triggers: asyncio.Queue[Trigger] = asyncio.Queue()
        self.result_for = result_for
        self.tasks: set[asyncio.Task[None]] = set()

    def on_trigger(self, trigger: Trigger) -> None:
        self.triggers.put_nowait(trigger)
        if self.result_for is not None:
            task = asyncio.create_task(self.answer(trigger))
            self.tasks.add(task)
            task.add_done_callback(self.tasks.discard)

    async def answer(self, trigger: Trigger) -> None:
        assert self.result_for is not None
        if trigger.command != Command.NEXT:  # a NEXT takes no image
            await self.link.image_captured(trigger.seq, 100 + trigger.seq)
        await self.link.publish(trigger.seq, self.result_for(trigger))


def make_link(server: S7PlcServer, **options: object) -> S7Link:
    opts: dict[str, object] = {"host": server.host, "port": server.port, "db": DB,
                               "timeout_s": 0.3, "backoff_initial_s": 0.02,
                               "backoff_max_s": 0.2, "poll_ms": 2}
    opts.update(options)
    return S7Link("plc", S7Options.model_validate(opts))


def vgripd_writes(server: S7PlcServer, since: int = 0) -> list[DbWrite]:
    """The writes outside the PLC's command area (bytes 0-5), i.e. vgripd's."""
    return [w for w in server.writes[since:] if w.start >= 6]


# -- jobs ------------------------------------------------------------------------------------


@pytest.mark.parametrize("value_format", ["float32", "int32"])
async def test_job_end_to_end_pose_exact_and_ack_last(
    server: S7PlcServer, plc: MockS7Plc, value_format: str
) -> None:
    link = make_link(server, value_format=value_format, scale=10000)
    daemon = Daemon(link, lambda t: kuka_result(100 + t.seq))
    await link.open(daemon.on_trigger)
    try:
        assert link.health().state is LinkState.UP
        before = len(server.writes)
        seen = await plc.run_job(7, WAIT_S, recipe=3)
        trigger = daemon.triggers.get_nowait()
        assert (trigger.seq, trigger.command, trigger.recipe) == (7, 1, 3)
        ack = await server.wait_write(lambda w: w.start == ACK_AT and w.data == b"\x00\x07",
                                      WAIT_S)
    finally:
        await link.close()

    raw = seen.raw
    w = seen.words
    assert (w[Reg.ACK_SEQ], w[Reg.CAPTURED_SEQ], w[Reg.STATUS], w[Reg.N_VALUES]) == (
        7, 7, Status.OK, 6)
    assert struct.unpack_from(">I", raw, 2 * Reg.JOB_ID)[0] == 107
    if value_format == "float32":
        got = struct.unpack_from(">6f", raw, 2 * Reg.VALUES)
        assert got == tuple(float(np.float32(v)) for v in POSE)  # bit-exact float32
        assert struct.unpack_from(">f", raw, 2 * Reg.FIT_RMS)[0] == pytest.approx(0.042)
    else:
        assert struct.unpack_from(">6i", raw, 2 * Reg.VALUES) == tuple(
            round(v * 10000) for v in POSE)
    # ACK_SEQ: a write of its own (2 bytes), after the write that carried the result data.
    job_writes = server.writes[before:ack + 1]
    assert job_writes[-1] == DbWrite(DB, ACK_AT, b"\x00\x07")
    data = [x for x in job_writes[:-1] if x.start <= 2 * Reg.STATUS
            and x.start + len(x.data) >= 2 * Reg.WARNINGS]
    assert data, "result data not written before the acknowledge"
    assert struct.unpack_from(">H", data[-1].data, 2 * Reg.STATUS - data[-1].start)[0] == Status.OK
    # vgripd never wrote the PLC's command area (the PLC program's own writes end at byte 6).
    assert all(x.start >= 6 or x.start + len(x.data) <= 6 for x in server.writes)


async def test_header_words_and_heartbeat_reach_the_plc(
    server: S7PlcServer, plc: MockS7Plc
) -> None:
    link = make_link(server, heartbeat_ms=100)
    await link.open(Daemon(link).on_trigger)
    try:
        raw = await plc.read()
        assert struct.unpack_from(">HHIf", raw, 2 * Reg.MAP_VERSION)[:3] == (
            MAP_VERSIONS[0], 0x1234, 0x12345678)  # S7: map version 3
        assert struct.unpack_from(">f", raw, 2 * Reg.CHECK_F32)[0] == pytest.approx(123.456)
        assert struct.unpack_from(">I", raw, 2 * Reg.RESULT_AGE_MS)[0] == 0xFFFFFFFF
        beats = set()
        async with asyncio.timeout(WAIT_S):
            while len(beats) < 3:
                beats.add(struct.unpack_from(">H", await plc.read(), 2 * Reg.HEARTBEAT)[0])
                await asyncio.sleep(0.02)
    finally:
        await link.close()


async def test_busy_refusal_and_old_request_not_rerun(
    server: S7PlcServer, plc: MockS7Plc
) -> None:
    # An already answered request in the DB (ACK == REQ) is not run again at start.
    await plc.write_words(Reg.REQ_SEQ, [4])
    await plc.write_words(Reg.ACK_SEQ, [4])
    link = make_link(server)
    daemon = Daemon(link)  # never answers by itself: the first job stays running
    await link.open(daemon.on_trigger)
    try:
        first = asyncio.create_task(plc.run_job(5, WAIT_S))
        assert (await asyncio.wait_for(daemon.triggers.get(), WAIT_S)).seq == 5
        await link.image_captured(5, 1)
        # a second request while the first runs is refused with BUSY, nothing else changes
        await plc.write_words(Reg.REQ_SEQ, [6])
        raw = await plc.until(
            lambda b: struct.unpack_from(">H", b, 2 * Reg.REJECT_SEQ)[0] == 6, WAIT_S)
        assert struct.unpack_from(">H", raw, 2 * Reg.REJECT_CODE)[0] == Status.BUSY
        assert daemon.triggers.empty()
        assert link.refusals() == {"BUSY": 1}
        await link.publish(5, kuka_result(1))
        seen = await first  # the running job is still answered under its own sequence
        assert (seen.words[Reg.ACK_SEQ], seen.words[Reg.STATUS]) == (5, Status.OK)
    finally:
        await link.close()


async def test_unknown_command_is_bad_request(server: S7PlcServer, plc: MockS7Plc) -> None:
    link = make_link(server)
    daemon = Daemon(link, lambda t: kuka_result(1))
    await link.open(daemon.on_trigger)
    try:
        seen = await plc.run_job(3, WAIT_S, command=99)
        assert seen.rejected
        assert seen.words[Reg.REJECT_CODE] == Status.BAD_REQUEST
        assert daemon.triggers.empty()
        assert link.refusals() == {"BAD_REQUEST": 1}
        # the link is still serving: the next good request runs
        ok = await plc.run_job(4, WAIT_S)
        assert (ok.words[Reg.ACK_SEQ], ok.words[Reg.STATUS]) == (4, Status.OK)
    finally:
        await link.close()


async def test_garbage_in_the_db_is_rewritten_and_logged_once(
    server: S7PlcServer, plc: MockS7Plc, caplog: pytest.LogCaptureFixture
) -> None:
    # A DB full of junk before vgripd starts (REQ_SEQ == ACK_SEQ: not a request).
    await plc.write(Reg.CMD, bytes([0xA5]) * DB_BYTES)
    link = make_link(server)
    daemon = Daemon(link, lambda t: kuka_result(1))
    with caplog.at_level("INFO", logger="drivers.links.s7"):
        await link.open(daemon.on_trigger)
        try:
            raw = await plc.read()
            assert raw[:6] == bytes([0xA5]) * 6  # the PLC's own words are left alone
            assert struct.unpack_from(">HH", raw, 2 * Reg.MAP_VERSION) == (MAP_VERSIONS[0], 0x1234)
            assert struct.unpack_from(">H", raw, ACK_AT)[0] == 0
            assert daemon.triggers.empty()
            # A PLC program keeps scribbling over vgripd's part (the wrong DB, a bad offset):
            # each time it is written again, and one log line says so.
            loop = asyncio.get_running_loop()
            until = loop.time() + 0.3
            while loop.time() < until:
                await plc.write(Reg.STATUS, b"\xff" * (DB_BYTES - 2 * Reg.STATUS))
                await asyncio.sleep(0.002)
            mirror = struct.pack(f">{MAP_SIZE - Reg.STATUS}H", *link.bank.image.words[Reg.STATUS:])
            await plc.until(lambda b: b[2 * Reg.STATUS:] == mirror, WAIT_S)
            seen = await plc.run_job(0xA5A6, WAIT_S)
            assert seen.words[Reg.STATUS] == Status.OK
            assert link.health().state is LinkState.UP
        finally:
            await link.close()
    records = [r for r in caplog.records if r.name == "drivers.links.s7"]
    assert [r.levelname for r in records] == ["WARNING"], [r.getMessage() for r in records]
    assert records[0].exc_info is None
    assert "changed from the PLC side (first at block byte 36, STATUS" in records[0].getMessage()


# -- faults ----------------------------------------------------------------------------------


async def test_plc_gone_mid_job_then_back_logged_once(
    server: S7PlcServer, plc: MockS7Plc, caplog: pytest.LogCaptureFixture
) -> None:
    link = make_link(server)
    daemon = Daemon(link)
    await link.open(daemon.on_trigger)
    try:
        with caplog.at_level("INFO", logger="drivers.links.s7"):
            job = asyncio.create_task(plc.run_job(1, WAIT_S))
            trigger = await asyncio.wait_for(daemon.triggers.get(), WAIT_S)
            await link.image_captured(trigger.seq, 1)
            await stop_task(job)
            await server.kill()  # the PLC is gone while the job is processed
            down = await link.wait_state(LinkState.DOWN, WAIT_S)
            assert f"{server.host}:{server.port}" in down.last_error
            with pytest.raises(LinkError, match="kept for the reconnect"):
                await link.publish(1, kuka_result(1))
            for _ in range(3):  # more failed attempts, with back-off, and no more log lines
                await link.wait_state(LinkState.CONNECTING, WAIT_S)
                await link.wait_state(LinkState.DOWN, WAIT_S)
            await server.start()  # same port, a fresh (zeroed) DB
            up = await link.wait_state(LinkState.UP, WAIT_S)
        assert up.reconnects == 1
        records = [r for r in caplog.records if r.name == "drivers.links.s7"]
        assert [r.levelname for r in records] == ["WARNING", "INFO"], [
            r.getMessage() for r in records]
        assert records[0].exc_info is None
        # The result published while the PLC was away reaches it, ACK_SEQ last.
        await plc.connect()
        ack = await server.wait_write(lambda w: w.start == ACK_AT and w.data == b"\x00\x01",
                                      WAIT_S)
        assert server.writes[ack - 1].start < ACK_AT < 2 * Reg.FIT_RMS  # the data just before
        raw = await plc.read()
        assert struct.unpack_from(">HH", raw, ACK_AT) == (1, Status.OK)
        assert struct.unpack_from(">6f", raw, 2 * Reg.VALUES) == tuple(
            float(np.float32(v)) for v in POSE)
        # and the next job works normally
        daemon.result_for = lambda t: kuka_result(2)
        seen = await plc.run_job(2, WAIT_S)
        assert (seen.words[Reg.ACK_SEQ], seen.words[Reg.STATUS]) == (2, Status.OK)
    finally:
        await link.close()


async def test_silent_plc_times_out_and_loop_stays_responsive(server: S7PlcServer) -> None:
    link = make_link(server)
    await link.open(Daemon(link).on_trigger)
    try:
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                await asyncio.sleep(0)

        tick_task = asyncio.create_task(ticker())
        server.freeze()
        try:
            down = await link.wait_state(LinkState.DOWN, WAIT_S)
        finally:
            server.thaw()
            await stop_task(tick_task)
        assert "no answer within 0.3 s" in down.last_error
        assert f"{server.host}:{server.port}" in down.last_error
        assert ticks > 100  # the loop kept running other tasks while the link waited
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()
    assert link.health().state is LinkState.STOPPED


async def test_unreachable_at_open_is_down_and_connects_later(server: S7PlcServer) -> None:
    await server.kill()
    link = make_link(server)
    try:
        await link.open(Daemon(link).on_trigger)
        health = link.health()
        assert health.state in (LinkState.DOWN, LinkState.CONNECTING)
        assert "connecting" in health.last_error
        await server.start()
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()


async def test_a_peer_that_is_not_an_s7_plc_is_an_outage_without_traceback(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Port 102 answered by something else (a web server, a wrong IP): DOWN, retried, logged
    once, never FAILED or a traceback."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read(1024)
        writer.write(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
        await writer.drain()
        writer.close()

    tcp = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = tcp.sockets[0].getsockname()[1]
    link = S7Link("plc", S7Options(host="127.0.0.1", port=port, db=DB, timeout_s=0.3,
                                   backoff_initial_s=0.02, backoff_max_s=0.1))
    try:
        with caplog.at_level("INFO", logger="drivers.links.s7"):
            await link.open(Daemon(link).on_trigger)
            for _ in range(3):
                await link.wait_state(LinkState.CONNECTING, WAIT_S)
                down = await link.wait_state(LinkState.DOWN, WAIT_S)
        assert f"127.0.0.1:{port}" in down.last_error
        records = [r for r in caplog.records if r.name == "drivers.links.s7"]
        assert [r.levelname for r in records] == ["WARNING"]
        assert records[0].exc_info is None
    finally:
        await link.close()
        tcp.close()
        await tcp.wait_closed()


@pytest.mark.parametrize(("db", "size", "message"), [
    (11, DB_BYTES, r"Object does not exist.*DB11 bytes 0\.\.91"),
    (DB, DB_BYTES - 2, r"Invalid address.*DB10 bytes 0\.\.91"),
])
async def test_block_the_plc_refuses_is_an_outage_naming_it_and_retried(
    db: int, size: int, message: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A refused block (a DB not downloaded yet, PUT/GET not allowed yet) can be fixed while
    vgripd runs: DOWN naming the block and what to check, one ERROR line, retried."""
    async with S7PlcServer(DB, size=size) as server:
        link = make_link(server, db=db)
        try:
            with caplog.at_level("INFO", logger="drivers.links.s7"):
                await link.open(Daemon(link).on_trigger)
                for _ in range(3):
                    await link.wait_state(LinkState.CONNECTING, WAIT_S)
                    health = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, WAIT_S)
                    assert health.state is LinkState.DOWN
            assert re.search(message, health.last_error), health.last_error
            assert "PUT/GET" in health.last_error
            records = [r for r in caplog.records if r.name == "drivers.links.s7"]
            assert [r.levelname for r in records] == ["ERROR"]
        finally:
            await link.close()


async def test_warnings_reach_the_plc_and_survive_an_outage(
    server: S7PlcServer, plc: MockS7Plc
) -> None:
    link = make_link(server)
    await link.open(Daemon(link).on_trigger)
    try:
        await link.set_warnings(Warnings.RECALIBRATE)  # returns once the PLC has it
        assert struct.unpack_from(">H", await plc.read(), 2 * Reg.WARNINGS)[0] == 1
        await server.kill()
        await link.wait_state(LinkState.DOWN, WAIT_S)
        await link.set_warnings(Warnings.RECALIBRATE)  # no error while away
        await server.start()
        await link.wait_state(LinkState.UP, WAIT_S)
        await plc.connect()
        assert struct.unpack_from(">H", await plc.read(), 2 * Reg.WARNINGS)[0] == 1
    finally:
        await link.close()


# -- planning, options, registry -------------------------------------------------------------


def test_options_and_registry() -> None:
    from vgripd.config import DriverSection, config_from_dict
    from vgripd.registry import LINKS, load_class, validate_options

    cls = load_class(LINKS, "link", "s7")
    assert cls is S7Link
    ok = validate_options(cls, DriverSection.model_validate(
        {"type": "s7", "host": "10.0.0.5", "db": 10}), "links.0")
    assert (ok.port, ok.rack, ok.slot, ok.start, ok.poll_ms, ok.word_order) == (
        102, 0, 1, 0, 20, "ABCD")
    for bad, field in [({"word_order": "CDAB"}, "big-endian"), ({"start": 3}, "start"),
                       ({"dbb": 1}, "dbb"), ({"db": 0}, "db")]:
        with pytest.raises(ConfigError, match=field):
            validate_options(cls, DriverSection.model_validate(
                {"type": "s7", "host": "h", "db": 10, **bad}), "links.0")
    # 7 values (ABB quaternion) fit; a 4x4 matrix does not, refused when the config loads.
    base = {"camera": {"type": "synthetic"}, "links": [{"type": "s7", "host": "h", "db": 1}]}
    config_from_dict({**base, "output": {"vendor": "abb"}})
    with pytest.raises(ConfigError, match='links\\[0\\].type = "s7"'):
        config_from_dict({**base, "output": {"vendor": "matrix"}})


# -- the UDT -----------------------------------------------------------------------------------

SIZES = {"Int": 2, "Word": 2, "DInt": 4, "DWord": 4, "Real": 4, "Byte": 1}
FORMATS = {"Int": ">h", "Word": ">H", "DInt": ">i", "DWord": ">I", "Real": ">f"}
MEMBER = re.compile(r"^\s*(\w+)\s*:\s*(?:Array\[0\.\.(\d+)\] of\s+)?(\w+)\s*;", re.M)


def parse_udt(text: str) -> dict[str, tuple[int, str, int]]:
    """name -> (byte offset, element type, count) of a ``TYPE .. STRUCT .. END_TYPE`` source,
    laid out as S7 standard (not optimized) access does: 2- and 4-byte items and arrays start
    on an even byte, bytes pack."""
    body = re.search(r'^TYPE "\w+"\nVERSION : 0\.1\n(?://.*\n)*\s*STRUCT\n(.*?)\n\s*END_STRUCT;'
                     r"\s*END_TYPE", text, re.S | re.M)
    assert body, text
    out, at = {}, 0
    for name, last, typ in MEMBER.findall(body.group(1)):
        count = int(last) + 1 if last else 1
        if SIZES[typ] > 1 or count > 1:
            at += at % 2
        out[name] = (at, typ, count)
        at += SIZES[typ] * count
    return out


@pytest.mark.parametrize(("value_format", "value_type"), [("float32", "Real"), ("int32", "DInt")])
def test_udt_matches_the_register_map(value_format: str, value_type: str) -> None:
    layout = parse_udt(udt_source(value_format))  # type: ignore[arg-type]
    assert list(layout) == [r.name for r in sorted(Reg, key=int) if r < MAP_SIZE]
    for reg in (r for r in Reg if r < MAP_SIZE):
        offset, typ, count = layout[reg.name]
        assert offset == 2 * reg, reg.name
    end = max(o + SIZES[t] * c for o, t, c in layout.values())
    assert end == DB_BYTES == 2 * MAP_SIZE
    assert layout["VALUES"] == (2 * Reg.VALUES, value_type, 7)
    assert layout["FIT_RMS"][1] == value_type
    assert layout["CHECK_F32"][1] == "Real"
    assert {layout[n][1] for n in ("CMD", "REQ_SEQ", "ACK_SEQ", "STATUS")} == {"Int"}
    assert {layout[n][1] for n in ("JOB_ID", "RESULT_AGE_MS")} == {"DInt"}


async def test_udt_types_decode_what_the_link_wrote(server: S7PlcServer, plc: MockS7Plc) -> None:
    """The PLC programmer's view: the block read through the UDT's own types."""
    link = make_link(server)
    await link.open(Daemon(link, lambda t: kuka_result(5)).on_trigger)
    try:
        seen = await plc.run_job(5, WAIT_S)
    finally:
        await link.close()
    layout = parse_udt(udt_source("float32"))

    def field(name: str) -> tuple[float, ...]:
        offset, typ, count = layout[name]
        return struct.unpack_from(">" + FORMATS[typ][1] * count, seen.raw, offset)

    assert field("ACK_SEQ") == (5,)
    assert field("STATUS") == (Status.OK,)
    assert field("CHECK_U32") == (0x12345678,)
    assert field("CHECK_F32")[0] == pytest.approx(123.456, abs=1e-4)
    assert field("JOB_ID") == (5,)  # the published result's job id
    n = int(field("N_VALUES")[0])
    np.testing.assert_allclose(field("VALUES")[:n], POSE, rtol=1e-6)


def test_docs_carry_the_generated_udt() -> None:
    text = (REPO / "docs" / "s7.md").read_text()
    assert udt_source("float32") in text


def test_s7_udt_command_takes_the_config(tmp_path: Path) -> None:
    from vgripd.__main__ import main

    cfg = tmp_path / "vgripd.toml"
    cfg.write_text('[camera]\ntype = "synthetic"\n\n[[links]]\ntype = "s7"\nhost = "10.0.0.5"\n'
                   'db = 12\nstart = 100\nvalue_format = "int32"\n')
    out = tmp_path / "vgripd.scl"
    assert main(["s7-udt", "-c", str(cfg), "-o", str(out)]) == 0
    text = out.read_text()
    assert parse_udt(text)["VALUES"] == (48, "DInt", 7)
    assert "number 12" in text
    assert "reserved : Array[0..99] of Byte;" in text
    assert "S7_Optimized_Access := 'FALSE'" in text
    cfg.write_text('[camera]\ntype = "synthetic"\n')
    assert main(["s7-udt", "-c", str(cfg)]) == 78


# -- the daemon ------------------------------------------------------------------------------


async def test_daemon_jobs_through_the_s7_link(server: S7PlcServer, plc: MockS7Plc) -> None:
    """The real daemon (synthetic camera, full pipeline) with an s7 link: the PLC program gets
    the pose the daemon computed, bit-exact in float32 (S7 Real)."""
    from vgripd.config import config_from_dict
    from vgripd.service.daemon import Daemon as VgripDaemon
    from vgripd.service.jobs.jobrecord import JobRecord

    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "s7", "host": server.host, "port": server.port, "db": DB,
                   "poll_ms": 5}],
        "status": {"enabled": False},
    })
    daemon = VgripDaemon(config)
    jobs: list[JobRecord] = []
    daemon.rooms.jobs.listeners.append(lambda pair, rec: jobs.append(rec))
    await daemon.start()
    try:
        for seq in (1, 2):
            seen = await plc.run_job(seq, 60.0)
            await daemon.wait_for(lambda: len(jobs) >= seq, WAIT_S)  # noqa: B023
            rec = jobs[seq - 1]
            assert rec.result.status is Status.OK
            assert rec.result.target is not None
            assert seen.words[Reg.STATUS] == Status.OK
            assert seen.u32(Reg.JOB_ID) == rec.job_id
            assert seen.values() == [float(np.float32(v)) for v in rec.result.target.values]
        assert daemon.snapshot()["links"][0]["state"] == "up"
    finally:
        await daemon.stop()


async def test_vgripd_run_completes_jobs_with_an_s7_link(
    server: S7PlcServer, plc: MockS7Plc, tmp_path: Path
) -> None:
    """``vgripd run`` as a process (what systemd starts) with an s7 link to the PLC stand-in."""
    cfg = tmp_path / "vgripd.toml"
    cfg.write_text(f"""
[camera]
type = "synthetic"
seed = 3

[[links]]
type = "s7"
host = "{server.host}"
port = {server.port}
db = {DB}
poll_ms = 5

[status]
enabled = false

[daemon]
job_timeout_s = 60.0             # the first job waits for the worker's start: busy machines
""")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        for seq in (1, 2):
            seen = await plc.run_job(seq, 90.0)
            assert seen.words[Reg.STATUS] == Status.OK, seen.words
            assert seen.words[Reg.N_VALUES] == 6
            assert all(abs(v) < 1000 for v in seen.values())
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(60):
            _, err = await proc.communicate()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    stderr = err.decode()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr


def kuka_pallet(job_id: int, n: int) -> JobResult:
    """``n`` pickable instances (X = 100, 200, ... mm; pick ids 1..n), the first on top."""
    instances = tuple(PickInstance(Status.OK, target=RobotTarget(
        "kuka", tuple("XYZABC"), (100.0 * (i + 1), *POSE[1:])), pick_id=i + 1, score=0.75)
        for i in range(n))
    return JobResult(job_id=job_id, status=Status.OK, target=instances[0].target,
                     instances=instances)


async def test_next_walks_the_pick_list_through_the_db(server: S7PlcServer,
                                                       plc: MockS7Plc) -> None:
    """snap7's server as the PLC: TRIGGER, then NEXT (CMD 3) until the list is used up; the
    pick items are read through the UDT's own layout."""
    job = kuka_pallet(101, 2)
    link = make_link(server)
    daemon = Daemon(link, lambda t: job if t.command == Command.TRIGGER else next_answer(
        job, t.seq))  # seq 2 -> instance 2, seq 3 -> past the end
    await link.open(daemon.on_trigger)
    layout = parse_udt(udt_source("float32"))

    def field(raw: bytes, name: str) -> tuple[float, ...]:
        offset, typ, count = layout[name]
        return struct.unpack_from(">" + FORMATS[typ][1] * count, raw, offset)

    try:
        seen = [await plc.run_job(1, WAIT_S)]
        seen += [await plc.run_job(seq, WAIT_S, command=Command.NEXT) for seq in (2, 3)]
    finally:
        await link.close()
    assert [(field(r.raw, "ACK_SEQ")[0], field(r.raw, "STATUS")[0], field(r.raw, "JOB_ID")[0],
             field(r.raw, "COUNT")[0], field(r.raw, "INDEX")[0], field(r.raw, "PICK_ID")[0])
            for r in seen] == [(1, Status.OK, 101, 2, 1, 1), (2, Status.OK, 101, 2, 2, 2),
                               (3, Status.NOT_FOUND, 101, 2, 3, 0)]
    assert [field(r.raw, "VALUES")[0] for r in seen] == [100.0, 200.0, 0.0]
    assert field(seen[1].raw, "SCORE")[0] == pytest.approx(0.75)
    assert field(seen[2].raw, "SCORE")[0] == -1.0
    assert field(seen[1].raw, "CAPTURED_SEQ") == (1,)  # no image for a NEXT


# -- a misbehaving peer --------------------------------------------------------------------


async def _garbage_peer(port: int, garbage: bytes) -> asyncio.Server:
    """A TCP peer on 127.0.0.1:``port`` that answers the COTP connect request with a connect
    confirm (the request echoed with type CC), then answers everything with ``garbage``."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await reader.readexactly(4)  # TPKT: version, reserved, length
            body = await reader.readexactly(struct.unpack(">H", head[2:])[0] - 4)
            cc = bytearray(head + body)
            cc[5] = 0xD0  # COTP CR (0xE0) -> CC
            writer.write(bytes(cc))
            while await reader.read(1024):
                writer.write(garbage)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    return await asyncio.start_server(handle, "127.0.0.1", port)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.mark.parametrize("garbage", [
    b"\x03\x00\x00\x0b\x02\xf0\x80\xde\xad\xbe\xef",  # a TPKT + COTP DT holding no S7 header
    b"\x03\x00\x00\x1b\x02\xf0\x80\x32\x03" + bytes(18),  # an S7 ack-data that makes no sense
    b"\x03\x00\x00\x07\x02\xf0\x80",  # an empty COTP data frame
])
async def test_garbage_after_cotp_connect_is_retried_and_comes_back_with_a_real_plc(
        garbage: bytes, caplog: pytest.LogCaptureFixture) -> None:
    """A peer that completes the COTP connect, then sends garbage: the link is DOWN and retried
    with back-off (never FAILED), logged once; snap7's server on the same port brings it UP."""
    port = _free_port()
    peer = await _garbage_peer(port, garbage)
    link = S7Link("plc", S7Options(host="127.0.0.1", port=port, db=DB, timeout_s=0.3,
                                   backoff_initial_s=0.02, backoff_max_s=0.1, poll_ms=2))
    daemon = Daemon(link, lambda t: kuka_result(100 + t.seq))
    try:
        with caplog.at_level("INFO", logger="drivers.links.s7"):
            await link.open(daemon.on_trigger)  # the daemon starts; the link retries
            for _ in range(3):  # retried, each attempt ending DOWN again
                await link.wait_state(LinkState.CONNECTING, WAIT_S)
                down = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, WAIT_S)
                assert down.state is LinkState.DOWN, down
            assert f"127.0.0.1:{port}" in down.last_error
            peer.close()
            await peer.wait_closed()
            async with S7PlcServer(DB, port=port) as server:
                up = await link.wait_state(LinkState.UP, WAIT_S)
                assert up.reconnects == 1
                async with MockS7Plc(server.host, server.port, DB) as plc:
                    seen = await plc.run_job(5, WAIT_S)
                    assert (seen.words[Reg.ACK_SEQ], seen.words[Reg.STATUS]) == (5, Status.OK)
                records = [r for r in caplog.records if r.name == "drivers.links.s7"]
        assert [r.levelname for r in records] == ["WARNING", "INFO"], records  # down, back
        assert "is back" in records[1].getMessage()
        assert all(r.exc_info is None for r in records)
    finally:
        await link.close()
        peer.close()
