"""The S7 link on map version 4 (the conveyor's latch and belt result) against snap7's own
server in a child process, driven by the mock PLC program over ISO-on-TCP on 127.0.0.1.

The PLC side reads the block through the types of the version 4 UDT that ``vgripd s7-udt``
prints (parsed back here), never through vgripd's codec. The daemon is stood in for (the
conveyor end to end with the real daemon: tests/integration/test_daemon_conveyor_links.py).
"""

from __future__ import annotations

import asyncio
import logging
import re
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drivers.links.s7 import S7Link, S7Options
from tests.conftest import REPO
from tests.drivers.links.test_s7 import DB, FORMATS, SIZES, WAIT_S, Daemon, make_link, parse_udt
from vgripd.cli.s7_udt import db_source, udt_source
from vgripd.configbase import DriverSection
from vgripd.errors import ConfigError
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import LATCH_AREA, MAP_SIZE_V4, Reg
from vgripd.peer.s7_block import db_bytes
from vgripd.registry import validate_options
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.s7_plc import MockS7Plc, S7PlcServer
from vgripd.types import BeltPose, JobResult, RobotTarget, Status

pytestmark = pytest.mark.timeout(300)  # a busy machine

V4_BYTES = 2 * MAP_SIZE_V4
LATCH_BYTES = range(2 * LATCH_AREA.start, 2 * LATCH_AREA.stop)  # 92..99, the PLC's
WRAP = 1 << 32


@pytest.fixture
async def server() -> AsyncIterator[S7PlcServer]:
    async with S7PlcServer(DB, size=V4_BYTES) as s:
        yield s


@pytest.fixture
async def plc(server: S7PlcServer) -> AsyncIterator[MockS7Plc]:
    async with MockS7Plc(server.host, server.port, DB, size=V4_BYTES) as p:
        yield p


def belt_result(trigger: Trigger) -> JobResult:
    """An answer in belt terms at the count the request carried (PREDICT: its N)."""
    assert trigger.latch_count is not None
    along = 400.0 + trigger.seq
    target = RobotTarget("kuka", tuple("XYZABC"), (along, 12.5, 10.0, 30.0, 0.0, 180.0))
    belt = BeltPose(count=trigger.latch_count, source=1, error_mm=0.05, along_mm=along,
                    across_mm=-7.25, theta_deg=30.0, queued=4 - trigger.seq % 4)
    return JobResult(job_id=100 + trigger.seq, status=Status.OK, target=target, belt=belt)


def field(raw: bytes, name: str, layout: dict[str, tuple[int, str, int]]) -> float:
    offset, typ, _ = layout[name]
    value: float = struct.unpack_from(FORMATS[typ], raw, offset)[0]
    return value


async def test_the_latch_travels_with_the_request_and_the_belt_result_back_across_the_wrap(
        server: S7PlcServer, plc: MockS7Plc, caplog: pytest.LogCaptureFixture) -> None:
    """The PLC writes LATCH_COUNT with each request (TRIGGER, NEXT from the queue, PREDICT with
    N) across the 32-bit wrap; the request carries it, the answer shows RESULT_COUNT and the
    belt fields, read through the UDT's DInt and Real; vgripd never writes bytes 92-99."""
    link = make_link(server, map_version=4)
    link.set_conveyor(True)  # the daemon's word: a recipe has a belt (NEXT, PREDICT go on)
    daemon = Daemon(link, belt_result)
    layout = parse_udt(udt_source("float32", version=4))
    counts = [WRAP - 1500, WRAP - 1, 5, 1200]  # the counter wraps between the 2nd and 3rd
    commands = [Command.TRIGGER, Command.NEXT, Command.PREDICT, Command.TRIGGER]
    with caplog.at_level(logging.INFO, logger="drivers.links.s7"):
        await link.open(daemon.on_trigger)
        try:
            seen = [await plc.run_job(seq, WAIT_S, command=command, latch=count)
                    for seq, (command, count) in enumerate(zip(commands, counts, strict=True),
                                                          start=1)]
            triggers = [daemon.triggers.get_nowait() for _ in seen]
            # The PLC latches the next count ahead of its request: vgripd leaves it alone while
            # it writes heartbeats (no "changed from the PLC side", never written over).
            await plc.write(Reg.LATCH_COUNT, struct.pack(">I", 0xDEADBEEF))
            beats = {struct.unpack_from(">H", await plc.read(), 2 * Reg.HEARTBEAT)[0]}
            async with asyncio.timeout(WAIT_S):
                while len(beats) < 3:
                    beats.add(struct.unpack_from(">H", await plc.read(), 2 * Reg.HEARTBEAT)[0])
                    await asyncio.sleep(0.02)
            raw = await plc.read()
            assert struct.unpack_from(">I", raw, 2 * Reg.LATCH_COUNT)[0] == 0xDEADBEEF
            assert link.health().state is LinkState.UP
        finally:
            await link.close()
    assert [(t.command, t.latch_count) for t in triggers] == list(zip(commands, counts,
                                                                      strict=True))
    for s, trigger, count in zip(seen, triggers, counts, strict=True):
        assert (field(s.raw, "ACK_SEQ", layout), field(s.raw, "STATUS", layout)) == (
            trigger.seq, Status.OK)
        assert field(s.raw, "MAP_VERSION", layout) == 4
        assert int(field(s.raw, "RESULT_COUNT", layout)) % WRAP == count  # DInt: signed
        assert field(s.raw, "LATCH_SOURCE", layout) == 1
        assert field(s.raw, "LATCH_ERR_MM", layout) == pytest.approx(0.05)
        assert field(s.raw, "ALONG", layout) == 400.0 + trigger.seq
        assert field(s.raw, "ACROSS", layout) == -7.25
        assert field(s.raw, "THETA", layout) == 30.0
        assert field(s.raw, "QUEUED", layout) == 4 - trigger.seq % 4
        assert field(s.raw, "VALUES", layout) == 400.0 + trigger.seq  # X, the first value
    assert field(seen[1].raw, "CAPTURED_SEQ", layout) == 1  # no image for a NEXT
    # Every write into the latch bytes was the PLC program's own (4-byte DInt writes).
    into_latch = [w for w in server.writes
                  if w.start < LATCH_BYTES.stop and w.start + len(w.data) > LATCH_BYTES.start]
    assert [(w.start, len(w.data)) for w in into_latch] == [(2 * Reg.LATCH_COUNT, 4)] * 5
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.records


async def test_a_version_4_block_on_a_version_3_db_is_refused_naming_it() -> None:
    """A DB downloaded for version 3 (92 bytes) is too short for a version 4 link: DOWN,
    naming the 124 bytes it needs."""
    async with S7PlcServer(DB) as server:
        link = make_link(server, map_version=4)
        try:
            await link.open(Daemon(link).on_trigger)
            health = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, WAIT_S)
            assert health.state is LinkState.DOWN
            assert "DB10 bytes 0..123" in health.last_error
        finally:
            await link.close()


def test_start_leaves_room_for_the_version_4_block() -> None:
    ok = S7Options(host="h", db=1, start=65536 - V4_BYTES, map_version=4)
    assert ok.start == 65536 - db_bytes(4)
    assert S7Options(host="h", db=1, start=65536 - 92).start == 65444  # version 3 fits there
    with pytest.raises(ValueError, match=r"start 65444: the block of map version 4 \(124 bytes"):
        S7Options(host="h", db=1, start=65444, map_version=4)


def test_the_version_4_udt_matches_the_register_map() -> None:
    for value_format, value_type in (("float32", "Real"), ("int32", "DInt")):
        layout = parse_udt(udt_source(value_format, version=4))  # type: ignore[arg-type]
        assert list(layout) == [r.name for r in sorted(Reg, key=int)]
        assert all(layout[r.name][0] == 2 * r for r in Reg)
        end = max(o + SIZES[t] * c for o, t, c in layout.values())
        assert end == V4_BYTES
        assert {layout[n][1] for n in ("LATCH_COUNT", "LATCH_FRAME", "RESULT_COUNT")} == {"DInt"}
        assert {layout[n][1] for n in ("LATCH_SOURCE", "QUEUED")} == {"Int"}
        assert {layout[n][1] for n in ("LATCH_ERR_MM", "ALONG", "ACROSS", "THETA")} == {
            value_type}
    assert "never CMD, REQ_SEQ, RECIPE, LATCH_COUNT, LATCH_FRAME (the PLC's)" in db_source(
        10, 0, version=4)
    assert "writes bytes 6..123 except 92..99" in db_source(10, 0, version=4)


def test_s7_udt_prints_the_links_map_version(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    from vgripd.__main__ import main

    cfg = tmp_path / "vgripd.toml"
    cfg.write_text('[camera]\ntype = "synthetic"\n\n[[links]]\ntype = "s7"\nhost = "10.0.0.5"\n'
                   "db = 12\nmap_version = 4\n")
    assert main(["s7-udt", "-c", str(cfg)]) == 0
    text = capsys.readouterr().out
    assert "//vgripd register map 4 as an S7 block: 124 bytes" in text
    assert parse_udt(text)["QUEUED"] == (122, "Int", 1)
    assert main(["s7-udt", "--map-version", "4", "--udt-only"]) == 0
    assert parse_udt(capsys.readouterr().out)["THETA"] == (118, "Real", 1)
    assert main(["s7-udt", "-c", str(cfg), "--map-version", "4"]) == 78  # one or the other


def test_a_version_3_link_block_and_options_are_unchanged() -> None:
    link = S7Link("plc", S7Options(host="h", db=1))
    assert link.bank.image.size == 46
    section = DriverSection.model_validate({"type": "s7", "host": "h", "db": 1,
                                            "map_version": 5})
    with pytest.raises(ConfigError, match="map_version"):
        validate_options(S7Link, section, "links.0")


def test_the_docs_conveyor_table_is_the_version_4_udt() -> None:
    """docs/s7.md, "Conveyor: map version 4": each row's byte, item and S7 type are the
    version 4 UDT's (in the Real value format), and the PLC writes exactly the latch."""
    text = (REPO / "docs" / "s7.md").read_text()
    part = text[text.index("## Conveyor: map version 4"):]
    part = part[:part.index("\n## ", 1)]
    rows = re.findall(r"^\| (\d+) \| (\w+) \| (\w+)[^|]* \| (PLC|vgripd) \|", part, re.M)
    layout = parse_udt(udt_source("float32", version=4))
    beyond = [r for r in sorted(Reg, key=int) if r >= Reg.LATCH_COUNT]
    assert [(int(b), n, t) for b, n, t, _ in rows] == [
        (layout[r.name][0], r.name, layout[r.name][1]) for r in beyond]
    assert {n for _, n, _, who in rows if who == "PLC"} == {
        r.name for r in Reg if r in LATCH_AREA} == {"LATCH_COUNT", "LATCH_FRAME"}
