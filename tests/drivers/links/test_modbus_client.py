"""ModbusClientLink against the mock robot Modbus server, over real sockets on 127.0.0.1.

The robot side decodes the result words with ``struct`` here (not with vgripd's codec), so a
word-order or scaling bug in the link cannot cancel out.
"""

from __future__ import annotations

import asyncio
import re
import struct
from collections.abc import AsyncIterator, Callable

import numpy as np
import pytest

from drivers.links.modbus_client import ModbusClientLink, ModbusClientOptions, plan_writes
from tests.conftest import need_tool, stop_task
from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command, next_answer
from vgripd.peer.registers import (
    MAP_SIZE,
    MAP_VERSIONS,
    BlockWrite,
    Reg,
    RegisterBank,
    ValueCodec,
    Warnings,
)
from vgripd.service.links.protocol import LinkHealth, LinkState, Trigger
from vgripd.sim.robot_modbus import MockRobotModbus, RegisterWrite, RobotMode
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

BASE = 128
WAIT_S = 5.0
UR_POSE = (412.5, -133.25, 287.0625, 0.1234, -2.9, 3.14159)  # mm and rad (UR rotation vector)


def ur_result(job_id: int, values: tuple[float, ...] = UR_POSE) -> JobResult:
    target = RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"), values)
    return JobResult(job_id=job_id, status=Status.OK, target=target,
                     residuals={"fit_rms_mm": 0.042})


def words_to_bytes(words: tuple[int, ...], word_order: str) -> bytes:
    hi, lo = words if word_order == "ABCD" else words[::-1]
    return struct.pack(">HH", hi, lo)


@pytest.fixture
async def robot() -> AsyncIterator[MockRobotModbus]:
    r = MockRobotModbus()
    await r.start()
    yield r
    await r.stop()


class Daemon:
    """Stands in for vgripd's daemon: answers every trigger with ``result_for``."""

    def __init__(self, link: ModbusClientLink,
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


def make_link(robot: MockRobotModbus, **options: object) -> ModbusClientLink:
    opts = {"host": robot.host, "port": robot.port, "timeout_s": 0.3,
            "backoff_initial_s": 0.02, "backoff_max_s": 0.2, "poll_interval_s": 0.005}
    opts.update(options)
    return ModbusClientLink("robot", ModbusClientOptions.model_validate(opts))


@pytest.mark.parametrize(("word_order", "value_format"),
                         [("ABCD", "float32"), ("CDAB", "float32"), ("CDAB", "int32")])
async def test_job_end_to_end_pose_exact_and_ack_last(
    robot: MockRobotModbus, word_order: str, value_format: str
) -> None:
    link = make_link(robot, word_order=word_order, value_format=value_format, scale=10000)
    daemon = Daemon(link, lambda t: ur_result(100 + t.seq))
    await link.open(daemon.on_trigger)
    try:
        assert link.health().state is LinkState.UP
        codec = ValueCodec(word_order, value_format, 10000)  # type: ignore[arg-type]
        seen = await robot.run_job(7, WAIT_S, recipe=3, codec=codec)
        trigger = daemon.triggers.get_nowait()
        assert (trigger.seq, trigger.command, trigger.recipe) == (7, 1, 3)
    finally:
        await link.close()

    w = seen.words
    assert w[Reg.ACK_SEQ] == 7
    assert w[Reg.CAPTURED_SEQ] == 7
    assert w[Reg.STATUS] == Status.OK
    assert w[Reg.N_VALUES] == 6
    job_id = struct.unpack(">I", words_to_bytes(w[Reg.JOB_ID:Reg.JOB_ID + 2], word_order))[0]
    assert job_id == 107
    fmt = ">f" if value_format == "float32" else ">i"
    got = [struct.unpack(fmt, words_to_bytes(w[Reg.VALUES + 2 * i:Reg.VALUES + 2 * i + 2],
                                             word_order))[0] for i in range(6)]
    if value_format == "float32":
        assert got == [float(np.float32(v)) for v in UR_POSE]  # bit-exact float32
    else:
        assert got == [round(v * 10000) for v in UR_POSE]
    # The acknowledge is the last write, alone, and every result word came before it.
    ack = RegisterWrite(BASE + Reg.ACK_SEQ, (7,))
    assert seen.writes[-1] == ack
    data_writes = [x for x in seen.writes[:-1] if x.address >= BASE + Reg.STATUS]
    assert data_writes, "result data not written before the acknowledge"
    assert all(len(x.values) == 1 for x in seen.writes if x.address == BASE + Reg.ACK_SEQ)
    # The robot's command area was never written by the link.
    assert all(x.address >= BASE + 3 for x in seen.writes)


async def test_header_words_and_heartbeat_reach_the_robot(robot: MockRobotModbus) -> None:
    link = make_link(robot, heartbeat_ms=100)
    await link.open(Daemon(link).on_trigger)
    try:
        header = robot.read(BASE + Reg.MAP_VERSION, 9)
        assert header[:2] == [MAP_VERSIONS[0], 0x1234]
        assert struct.unpack(">I", words_to_bytes(tuple(header[2:4]), "ABCD"))[0] == 0x12345678
        assert struct.unpack(">f", words_to_bytes(tuple(header[4:6]), "ABCD"))[0] == pytest.approx(123.456, abs=1e-4)
        beats = {robot.read(BASE + Reg.HEARTBEAT)[0]}
        async with asyncio.timeout(WAIT_S):
            while len(beats) < 3:
                await robot.changed()
                beats.add(robot.read(BASE + Reg.HEARTBEAT)[0])
    finally:
        await link.close()


async def test_busy_refusal_and_old_request_not_rerun(robot: MockRobotModbus) -> None:
    # An already answered request in the robot (ACK == REQ) is not run again at start.
    await robot.write(BASE + Reg.REQ_SEQ, [4])
    await robot.write(BASE + Reg.ACK_SEQ, [4])
    link = make_link(robot)
    daemon = Daemon(link)  # never answers: the first job stays running
    await link.open(daemon.on_trigger)
    try:
        first = asyncio.create_task(robot.run_job(5, WAIT_S))
        assert (await asyncio.wait_for(daemon.triggers.get(), WAIT_S)).seq == 5
        # a second request while the first runs is refused with BUSY, nothing else changes
        await robot.write(BASE + Reg.REQ_SEQ, [6])
        async with asyncio.timeout(WAIT_S):
            while robot.read(BASE + Reg.REJECT_SEQ)[0] != 6:
                await robot.changed()
        assert robot.read(BASE + Reg.REJECT_CODE)[0] == Status.BUSY
        assert daemon.triggers.empty()
        await link.publish(5, ur_result(1))
        seen = await first  # the running job is still answered under its own sequence
        assert seen.words[Reg.ACK_SEQ] == 5
        assert seen.words[Reg.STATUS] == Status.OK
    finally:
        await link.close()


async def test_robot_drops_mid_job_and_comes_back(robot: MockRobotModbus) -> None:
    link = make_link(robot)
    daemon = Daemon(link)
    await link.open(daemon.on_trigger)
    try:
        job = asyncio.create_task(robot.run_job(1, WAIT_S))
        trigger = await asyncio.wait_for(daemon.triggers.get(), WAIT_S)
        await link.image_captured(trigger.seq, 1)
        await robot.go_offline()  # the controller reboots while the job is processed
        down = await link.wait_state(LinkState.DOWN, WAIT_S)
        assert f"{robot.host}:{robot.port}" in down.last_error
        with pytest.raises(LinkError, match="kept for the reconnect"):
            await link.publish(1, ur_result(1))
        await robot.come_back()
        up = await link.wait_state(LinkState.UP, WAIT_S)
        assert up.reconnects == 1
        seen = await job  # the result published while away reaches the waiting program
        assert seen.words[Reg.ACK_SEQ] == 1
        assert seen.words[Reg.STATUS] == Status.OK
        assert seen.writes[-1] == RegisterWrite(BASE + Reg.ACK_SEQ, (1,))
        # and the next job works normally
        nxt = asyncio.create_task(robot.run_job(2, WAIT_S))
        assert (await asyncio.wait_for(daemon.triggers.get(), WAIT_S)).seq == 2
        await link.image_captured(2, 2)
        await link.publish(2, ur_result(2))
        assert (await nxt).words[Reg.ACK_SEQ] == 2
    finally:
        await link.close()


async def test_robot_drops_connection_detected_at_once(robot: MockRobotModbus) -> None:
    link = make_link(robot, timeout_s=30.0)  # a drop must not wait for the request timeout
    await link.open(Daemon(link).on_trigger)
    try:
        robot.drop_connections()
        down = await link.wait_state(LinkState.DOWN, WAIT_S)
        assert "lost" in down.last_error
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()


async def test_silent_robot_times_out_and_loop_stays_responsive(robot: MockRobotModbus) -> None:
    link = make_link(robot)
    await link.open(Daemon(link).on_trigger)
    try:
        robot.mode = RobotMode.SILENT
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                await asyncio.sleep(0)

        tick_task = asyncio.create_task(ticker())
        down = await link.wait_state(LinkState.DOWN, WAIT_S)
        await stop_task(tick_task)
        assert "no answer within 0.3 s" in down.last_error
        assert f"{robot.host}:{robot.port}" in down.last_error
        assert ticks > 100  # the loop kept running other tasks while the link waited
        robot.mode = RobotMode.NORMAL
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()
    assert link.health().state is LinkState.STOPPED


async def _refused_and_retried(link: ModbusClientLink,
                               caplog: pytest.LogCaptureFixture) -> LinkHealth:
    """Open ``link`` on a robot that refuses part of its block: DOWN with the reason, retried
    (never FAILED: the robot's setup can change while vgripd runs), one ERROR line."""
    with caplog.at_level("INFO", logger="drivers.links.modbus_client"):
        await link.open(Daemon(link).on_trigger)
        for _ in range(3):
            await link.wait_state(LinkState.CONNECTING, WAIT_S)
            health = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, WAIT_S)
            assert health.state is LinkState.DOWN
    records = [r for r in caplog.records if r.name == "drivers.links.modbus_client"]
    assert [r.levelname for r in records] == ["ERROR"]
    return health


async def test_refused_range_at_start_is_an_outage_naming_the_register(
        caplog: pytest.LogCaptureFixture) -> None:
    robot = MockRobotModbus()
    await robot.start()
    link = make_link(robot, base_address=240)  # 240 + 40 words runs past UR's 255
    try:
        health = await _refused_and_retried(link, caplog)
        assert re.search(r"registers 256\.\.256 .*map register REJECT_CODE", health.last_error)
        assert "exception 2 (ILLEGAL_ADDRESS)" in health.last_error
    finally:
        await link.close()
        await robot.stop()


async def test_warnings_reach_the_robot_and_are_rewritten_after_an_outage(
    robot: MockRobotModbus,
) -> None:
    await robot.write(BASE + Reg.WARNINGS, [1])  # stale, from an earlier vgripd run
    link = make_link(robot)
    await link.open(Daemon(link).on_trigger)
    try:
        assert robot.read(BASE + Reg.WARNINGS) == [0]  # the first contact writes the mirror
        await link.set_warnings(Warnings.RECALIBRATE)  # returns once the robot has it
        assert robot.read(BASE + Reg.WARNINGS) == [1]
        assert RegisterWrite(BASE + Reg.WARNINGS, (1,)) in robot.writes  # over the network
        await robot.go_offline()
        await link.wait_state(LinkState.DOWN, WAIT_S)
        await link.set_warnings(0)  # no error while away: kept for the reconnect
        await robot.come_back()
        await link.wait_state(LinkState.UP, WAIT_S)
        assert robot.read(BASE + Reg.WARNINGS) == [0]
    finally:
        await link.close()


async def test_block_one_word_too_long_for_the_robot_names_warnings(
        caplog: pytest.LogCaptureFixture) -> None:
    robot = MockRobotModbus()
    await robot.start()
    link = make_link(robot, base_address=216)  # 216 + 40 = 256: only WARNINGS is missing
    try:
        health = await _refused_and_retried(link, caplog)
        assert re.search(r"registers 256\.\.256 .*map register WARNINGS", health.last_error)
    finally:
        await link.close()
        await robot.stop()


async def test_refusing_robot_mid_run_is_down_then_recovers(robot: MockRobotModbus) -> None:
    link = make_link(robot)
    await link.open(Daemon(link).on_trigger)
    try:
        robot.refuse_code = 4  # SLAVE_DEVICE_FAILURE / DEVICE_FAILURE
        robot.mode = RobotMode.REFUSE
        down = await link.wait_state(LinkState.DOWN, WAIT_S)
        assert "exception 4 (DEVICE_FAILURE)" in down.last_error
        assert f"registers {BASE}.." in down.last_error
        robot.mode = RobotMode.NORMAL
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()


async def test_unreachable_at_open_is_down_and_connects_later() -> None:
    robot = MockRobotModbus()
    await robot.start()
    await robot.go_offline()  # a port nobody listens on
    link = make_link(robot)
    try:
        await link.open(Daemon(link).on_trigger)
        assert link.health().state in (LinkState.DOWN, LinkState.CONNECTING)
        assert "cannot connect" in link.health().last_error
        await robot.come_back()
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()
        await robot.stop()


def test_plan_keeps_ack_alone_and_last() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(ValueCodec(), journal)
    bank.write(0, [1, 9, 0])
    bank.captured(9, 3)
    bank.publish(9, ur_result(3), 0)
    plan = plan_writes(journal)
    assert all(w.address >= 3 for w in plan)
    acks = [i for i, w in enumerate(plan) if w.address <= Reg.ACK_SEQ < w.address + len(w.words)]
    assert [plan[i] for i in acks] == [BlockWrite(Reg.ACK_SEQ, (0,)), BlockWrite(Reg.ACK_SEQ, (9,))]
    assert acks[-1] == len(plan) - 1
    # replaying the plan on a copy gives the bank's image outside the command area
    image = [0] * MAP_SIZE
    for w in plan:
        image[w.address:w.address + len(w.words)] = w.words
    assert image[3:] == bank.image.words[3:]


async def test_a_job_costs_eight_writes_and_its_polls(robot: MockRobotModbus) -> None:
    """Per job the link writes: the retract (ACK_SEQ 0), the cleared result, STATE; at the
    capture JOB_ID, then STATE with CAPTURED_SEQ; the result (STATUS through SCORE in one
    write, across WARNINGS), STATE, ACK_SEQ. Everything else it sends is a read of the command
    area: one per poll and one after each flush."""
    poll_s = 0.05
    link = make_link(robot, poll_interval_s=poll_s, heartbeat_ms=1000)
    daemon = Daemon(link, lambda t: ur_result(100 + t.seq))
    await link.open(daemon.on_trigger)
    try:
        for seq in range(1, 6):
            before = robot.requests
            t0 = asyncio.get_running_loop().time()
            seen = await robot.run_job(seq, WAIT_S)
            elapsed = asyncio.get_running_loop().time() - t0
            await link.wait_state({LinkState.UP}, WAIT_S)
            writes = [w for w in seen.writes
                      if w.address != BASE + Reg.HEARTBEAT or len(w.values) != 1]
            assert len(writes) == 8, writes
            result = writes[-3]
            assert (result.address, len(result.values)) == (BASE + Reg.STATUS,
                                                             Reg.SCORE + 2 - Reg.STATUS)
            assert result.values[Reg.N_VALUES - Reg.STATUS] == 6
            assert writes[-1] == RegisterWrite(BASE + Reg.ACK_SEQ, (seq,))
            reads = robot.requests - before - len(seen.writes)
            # the ACK_SEQ write can be counted before or after run_job returns
            assert 1 <= reads <= 4 + elapsed / poll_s, (reads, elapsed)
    finally:
        await link.close()


@pytest.mark.parametrize(("word_order", "flags"), [("ABCD", ["-B"]), ("CDAB", [])])
async def test_mbpoll_reads_the_pose_vgripd_wrote(
    robot: MockRobotModbus, word_order: str, flags: list[str]
) -> None:
    """mbpoll (an independent Modbus client, Debian) reads the robot's registers as a robot
    integrator would, decoding the floats with its own word-order option."""
    link = make_link(robot, word_order=word_order)
    await link.open(Daemon(link, lambda t: ur_result(1)).on_trigger)
    try:
        await robot.run_job(3, WAIT_S, codec=ValueCodec(word_order))  # type: ignore[arg-type]
    finally:
        await link.close()
    proc = await asyncio.create_subprocess_exec(
        need_tool("mbpoll"), "-m", "tcp", "-a", "1", "-0", "-1", "-t", "4:float", *flags,
        "-r", str(BASE + Reg.VALUES), "-c", "6", "-p", str(robot.port), robot.host,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), WAIT_S)
    assert proc.returncode == 0, err.decode()
    values = [float(line.split(":")[1]) for line in out.decode().splitlines()
              if line.startswith("[")]
    assert len(values) == 6
    np.testing.assert_allclose(values, UR_POSE, rtol=1e-5)  # mbpoll prints 6 significant digits


async def test_busy_robot_at_start_is_retried_not_failed(robot: MockRobotModbus) -> None:
    robot.refuse_code = 6  # SLAVE_DEVICE_BUSY: transient, unlike a missing register
    robot.mode = RobotMode.REFUSE
    link = make_link(robot)
    try:
        await link.open(Daemon(link).on_trigger)
        assert link.health().state in (LinkState.DOWN, LinkState.CONNECTING)
        assert "exception 6 (DEVICE_BUSY)" in link.health().last_error
        robot.mode = RobotMode.NORMAL
        await link.wait_state(LinkState.UP, WAIT_S)
    finally:
        await link.close()


async def test_outage_logged_once_and_recovery_once(
    robot: MockRobotModbus, caplog: pytest.LogCaptureFixture
) -> None:
    link = make_link(robot)
    await link.open(Daemon(link).on_trigger)
    try:
        with caplog.at_level("INFO", logger="drivers.links.modbus_client"):
            await robot.go_offline()
            await link.wait_state(LinkState.DOWN, WAIT_S)
            for _ in range(3):  # three more failed attempts with back-off
                await link.wait_state(LinkState.CONNECTING, WAIT_S)
                await link.wait_state(LinkState.DOWN, WAIT_S)
            await robot.come_back()
            await link.wait_state(LinkState.UP, WAIT_S)
        records = [r for r in caplog.records if r.name == "drivers.links.modbus_client"]
        assert [r.levelname for r in records] == ["WARNING", "INFO"]
        assert f"{robot.host}:{robot.port}" in records[0].getMessage()
        assert link.health().reconnects == 1
    finally:
        await link.close()


async def test_daemon_jobs_through_the_robot_modbus_server(robot: MockRobotModbus) -> None:
    """The real daemon (synthetic camera, full pipeline) with a modbus_client link: the robot
    program gets the pose the daemon computed, bit-exact in float32, ACK_SEQ last."""
    from vgripd.config import config_from_dict
    from vgripd.service.daemon import Daemon as VgripDaemon
    from vgripd.service.jobs.jobrecord import JobRecord

    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "modbus_client", "host": robot.host, "port": robot.port,
                   "poll_interval_s": 0.005}],
        "status": {"enabled": False},
    })
    daemon = VgripDaemon(config)
    jobs: list[JobRecord] = []
    daemon.rooms.jobs.listeners.append(lambda pair, rec: jobs.append(rec))
    await daemon.start()
    try:
        for seq in (1, 2):
            seen = await robot.run_job(seq, 30.0)
            await daemon.wait_for(lambda: len(jobs) >= seq, WAIT_S)  # noqa: B023
            rec = jobs[seq - 1]
            assert rec.result.status is Status.OK
            assert rec.result.target is not None
            assert seen.words[Reg.STATUS] == Status.OK
            n = seen.words[Reg.N_VALUES]
            got = [struct.unpack(">f", words_to_bytes(seen.words[Reg.VALUES + 2 * i:Reg.VALUES + 2 * i + 2], "ABCD"))[0]
                   for i in range(n)]
            assert got == [float(np.float32(v)) for v in rec.result.target.values]
            assert seen.writes[-1] == RegisterWrite(BASE + Reg.ACK_SEQ, (seq,))
    finally:
        await daemon.stop()


def test_options_typo_and_bounds_are_config_errors_naming_the_field() -> None:
    from vgripd.config import DriverSection
    from vgripd.errors import ConfigError
    from vgripd.registry import LINKS, load_class, validate_options

    cls = load_class(LINKS, "link", "modbus_client")
    assert cls is ModbusClientLink
    ok = validate_options(cls, DriverSection.model_validate(
        {"type": "modbus_client", "host": "10.0.0.5"}), "links.0")
    assert (ok.port, ok.base_address, ok.word_order) == (502, 128, "ABCD")
    with pytest.raises(ConfigError, match="hots"):
        validate_options(cls, DriverSection.model_validate(
            {"type": "modbus_client", "hots": "10.0.0.5"}), "links.0")
    with pytest.raises(ConfigError, match="base_address"):
        validate_options(cls, DriverSection.model_validate(
            {"type": "modbus_client", "host": "h", "base_address": 65530}), "links.0")


async def test_next_walks_the_pick_list_in_the_robot(robot: MockRobotModbus) -> None:
    instances = tuple(PickInstance(Status.OK, target=RobotTarget(
        "ur", ("x", "y", "z", "rx", "ry", "rz"), (100.0 * (i + 1), *UR_POSE[1:])), pick_id=7)
        for i in range(2))
    job = JobResult(job_id=5, status=Status.OK, target=instances[0].target, instances=instances)
    link = make_link(robot)
    daemon = Daemon(link, lambda t: job if t.command == Command.TRIGGER else next_answer(
        job, t.seq))  # seq 2 -> instance 2, seq 3 -> past the end
    await link.open(daemon.on_trigger)
    try:
        refused = await robot.run_job(1, WAIT_S, command=Command.NEXT)  # no list yet
        seen = [await robot.run_job(seq, WAIT_S, command=cmd)
                for seq, cmd in ((11, Command.TRIGGER), (2, Command.NEXT), (3, Command.NEXT))]
    finally:
        await link.close()
    assert (refused.words[Reg.REJECT_SEQ], refused.words[Reg.REJECT_CODE]) == (
        1, Status.BAD_REQUEST)
    assert [(w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.COUNT], w[Reg.INDEX], w[Reg.PICK_ID])
            for w in (s.words for s in seen)] == [
        (11, Status.OK, 2, 1, 7), (2, Status.OK, 2, 2, 7), (3, Status.NOT_FOUND, 2, 3, 0)]
    xs = [struct.unpack(">f", words_to_bytes(s.words[Reg.VALUES:Reg.VALUES + 2], "ABCD"))[0]
          for s in seen]
    assert xs == [100.0, 200.0, 0.0]
    assert seen[-1].writes[-1] == RegisterWrite(BASE + Reg.ACK_SEQ, (3,))  # ACK last


@pytest.mark.parametrize("garbage", [
    b"\xde\xad\xbe\xef" * 8,  # not Modbus/TCP at all
    b"\x00\x01\x00\x00\x00\x03\x01\x83",  # an MBAP header whose PDU is cut short
    b"HTTP/1.1 400 Bad Request\r\n\r\n",  # another server on the port
])
async def test_a_peer_answering_garbage_is_retried_and_the_robot_comes_back(
        garbage: bytes, caplog: pytest.LogCaptureFixture) -> None:
    """Any peer error is an outage: DOWN, retried with back-off (never FAILED), logged once;
    the real robot on the same port brings the link UP."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while await reader.read(1024):
                writer.write(garbage)
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    peer = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = peer.sockets[0].getsockname()[1]
    robot = MockRobotModbus(port=port)
    link = make_link(robot)
    try:
        with caplog.at_level("INFO", logger="drivers.links.modbus_client"):
            await link.open(Daemon(link).on_trigger)
            for _ in range(3):
                await link.wait_state(LinkState.CONNECTING, WAIT_S)
                down = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, WAIT_S)
                assert down.state is LinkState.DOWN
            peer.close()
            await peer.wait_closed()
            await robot.start()
            up = await link.wait_state(LinkState.UP, WAIT_S)
            assert up.reconnects == 1
            records = [r for r in caplog.records
                       if r.name == "drivers.links.modbus_client"]
        assert [r.levelname for r in records] == ["WARNING", "INFO"], records
        assert all(r.exc_info is None for r in records)
    finally:
        await link.close()
        peer.close()
        await robot.stop()
