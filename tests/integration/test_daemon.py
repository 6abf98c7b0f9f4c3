"""The daemon in-process with the synthetic (or replay) camera and the Modbus/TCP server link on
127.0.0.1, driven by a real pymodbus client over real TCP, as a PLC would.

Every wait is on a register value or a daemon state, with a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from pymodbus.client import AsyncModbusTcpClient

from tests.conftest import REPO
from vgripd.cli.status import format_status
from vgripd.cli.status import run as status_run
from vgripd.config import Config, config_from_dict
from vgripd.geometry.transforms import pose_error
from vgripd.peer.jobcore import Command, HandshakeState
from vgripd.peer.registers import MAP_SIZE, MAX_VALUES, Reg, ValueCodec
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.daemon import Daemon
from vgripd.service.jobs.jobrecord import JobRecord
from vgripd.service.jobs.runner import JobState
from vgripd.types import ImagePair, Status

WAIT_S = 30.0
CODEC = ValueCodec("ABCD", "float32")


def make_config(camera: dict[str, Any] | None = None, links: int = 1, **sections: Any) -> Any:
    data: dict[str, Any] = {
        "camera": camera or {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}] * links,
        "status": {"port": 0},
        **sections,
    }
    return config_from_dict(data)


class Run:
    """A started daemon plus what its listeners saw."""

    def __init__(self, daemon: Daemon) -> None:
        self.daemon = daemon
        self.jobs: list[tuple[ImagePair | None, JobRecord]] = []
        daemon.rooms.jobs.listeners.append(lambda pair, rec: self.jobs.append((pair, rec)))

    def port(self, index: int = 0) -> int:
        port: int = list(self.daemon.rooms.links.links.values())[index].port
        return port

    async def job_done(self, n: int) -> tuple[ImagePair | None, JobRecord]:
        await self.daemon.wait_for(lambda: len(self.jobs) >= n, WAIT_S)
        return self.jobs[n - 1]

    async def busy(self) -> None:
        await self.daemon.wait_for(lambda: self.daemon.rooms.jobs.state is not JobState.IDLE, WAIT_S)


@contextlib.asynccontextmanager
async def running(config: Any) -> AsyncIterator[Run]:
    daemon = Daemon(config)
    run = Run(daemon)
    await daemon.start()
    try:
        yield run
    finally:
        await daemon.stop()


class Plc:
    """The PLC side: a pymodbus client writing the command area and polling the map."""

    def __init__(self, port: int) -> None:
        self.client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)

    async def __aenter__(self) -> Plc:
        assert await self.client.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.client.close()

    async def read(self) -> list[int]:
        rr = await self.client.read_holding_registers(0, count=MAP_SIZE)
        assert not rr.isError(), rr
        return list(rr.registers)

    async def trigger(self, seq: int) -> None:
        rr = await self.client.write_registers(Reg.CMD, [Command.TRIGGER, seq])
        assert not rr.isError(), rr

    async def until(self, pred: Callable[[list[int]], bool]) -> list[int]:
        async with asyncio.timeout(WAIT_S):
            while True:
                words = await self.read()
                if pred(words):
                    return words
                await asyncio.sleep(0.005)  # the PLC's poll period

    async def result(self, seq: int) -> list[int]:
        return await self.until(lambda w: w[Reg.ACK_SEQ] == seq)


def values(words: list[int]) -> list[float]:
    n = words[Reg.N_VALUES]
    return [CODEC.decode_value(words[Reg.VALUES + 2 * i:Reg.VALUES + 2 * i + 2]) for i in range(n)]


async def test_cycles_publish_accurate_poses_in_the_registers() -> None:
    async with running(make_config()) as run, Plc(run.port()) as plc:
        for seq in (1, 2, 3):
            await plc.trigger(seq)
            words = await plc.result(seq)
            pair, rec = await run.job_done(seq)
            assert words[Reg.STATUS] == Status.OK
            assert words[Reg.STATE] == HandshakeState.DONE
            assert words[Reg.CAPTURED_SEQ] == seq
            assert CODEC.decode_u32(words[Reg.JOB_ID:Reg.JOB_ID + 2]) == rec.job_id == seq
            assert rec.result.target is not None
            assert values(words) == pytest.approx(rec.result.target.values, rel=1e-6, abs=1e-4)
            assert pair is not None
            assert rec.result.T_base_obj is not None
            dt, dr = pose_error(pair.truth["T_base_obj"], rec.result.T_base_obj)
            assert dt < 0.5
            assert dr < 0.1
        assert run.daemon.rooms.jobs.counters == {"OK": 3}
        assert run.daemon.snapshot()["cycle_ms"]["window"] == 3


async def test_status_endpoint_and_modbus_answer_while_a_job_runs() -> None:
    async with running(make_config()) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        await run.busy()
        assert run.daemon.status_server is not None
        reader, writer = await asyncio.open_connection("127.0.0.1", run.daemon.status_server.port)
        writer.write(b"GET /status HTTP/1.0\r\n\r\n")
        head, _, body = (await reader.read()).partition(b"\r\n\r\n")
        writer.close()
        await writer.wait_closed()
        words = await plc.read()  # Modbus answers mid-job too
        assert head.startswith(b"HTTP/1.0 200")
        status = json.loads(body)
        assert status["state"] in ("triggered", "acquiring", "processing")
        assert status["job"]["seq"] == 1
        assert words[Reg.STATE] in (HandshakeState.TRIGGERED, HandshakeState.BUSY)
        assert words[Reg.ACK_SEQ] == 0
        assert (await plc.result(1))[Reg.STATUS] == Status.OK

        # `vgripd status` against the live endpoint, from a thread (it blocks, the loop serves).
        url = f"http://127.0.0.1:{run.daemon.status_server.port}/status"
        text = format_status(run.daemon.snapshot())
        assert "last job 1: OK (1)" in text
        assert "modbus_server: up" in text
        with ThreadPoolExecutor(1) as pool:
            rc = await asyncio.get_running_loop().run_in_executor(
                pool, lambda: status_run(_status_args(url)))
        assert rc == 0


def _status_args(url: str) -> Any:
    import argparse
    return argparse.Namespace(url=url, config=None, json=False, timeout=5.0)


async def test_trigger_while_busy_is_refused_and_the_running_job_completes() -> None:
    async with running(make_config(links=2)) as run, \
            Plc(run.port(0)) as plc_a, Plc(run.port(1)) as plc_b:
        await plc_a.trigger(7)
        await run.busy()
        # Same link: the handshake refuses it (REJECT_SEQ/REJECT_CODE), nothing else changes.
        await plc_a.trigger(8)
        words = await plc_a.until(lambda w: w[Reg.REJECT_SEQ] == 8)
        assert words[Reg.REJECT_CODE] == Status.BUSY
        # Other link: the daemon refuses it with BUSY, published to that link only.
        await plc_b.trigger(1)
        words_b = await plc_b.result(1)
        assert words_b[Reg.STATUS] == Status.BUSY
        assert words_b[Reg.N_VALUES] == 0
        words_a = await plc_a.result(7)
        assert words_a[Reg.STATUS] == Status.OK
        _, rec = await run.job_done(1)
        assert rec.seq == 7
        assert rec.link == "modbus_server.0"
        # Link B still shows its own answer, not A's result.
        assert (await plc_b.read())[Reg.ACK_SEQ] == 1
        assert (await plc_b.read())[Reg.STATUS] == Status.BUSY
        assert run.daemon.rooms.jobs.counters == {"OK": 1, "BUSY": 1}


async def test_camera_timeout_is_camera_error_and_the_daemon_keeps_serving() -> None:
    config = make_config(daemon={"job_timeout_s": 0.02})
    async with running(config) as run, Plc(run.port()) as plc:
        for seq in (1, 2):
            await plc.trigger(seq)
            words = await plc.result(seq)
            assert words[Reg.STATUS] == Status.CAMERA_ERROR
            assert words[Reg.N_VALUES] == 0
        _, rec = await run.job_done(2)
        assert "within" in rec.result.message or "exceeded" in rec.result.message
        assert run.daemon.snapshot()["links"][0]["state"] == "up"


async def _synthetic_pair(seed: int) -> ImagePair:
    config = make_config({"type": "synthetic", "seed": seed, "max_tilt_deg": 2.0})
    cls = load_class(CAMERAS, "camera", "synthetic")
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    await camera.open()
    try:
        pair: ImagePair = await camera.grab(WAIT_S)
    finally:
        await camera.close()
    return pair


async def test_corrupt_image_is_camera_error_then_the_next_job_is_ok(tmp_path: Path) -> None:
    pair = await _synthetic_pair(5)
    (tmp_path / "left_1.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    (tmp_path / "right_1.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    cv2.imwrite(str(tmp_path / "left_2.png"), pair.left)
    cv2.imwrite(str(tmp_path / "right_2.png"), pair.right)
    camera = {"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
              "right_glob": "right_*.png"}
    demo = Config().calibration
    assert demo is not None
    config = make_config(camera, calibration=demo.model_dump(mode="json", exclude_none=True))
    async with running(config) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.CAMERA_ERROR
        _, rec = await run.job_done(1)
        assert "left_1.png" in rec.result.message
        await plc.trigger(2)
        assert (await plc.result(2))[Reg.STATUS] == Status.OK
        _, rec = await run.job_done(2)
        assert rec.result.T_base_obj is not None
        dt, dr = pose_error(pair.truth["T_base_obj"], rec.result.T_base_obj)
        assert dt < 0.5
        assert dr < 0.1


async def test_plc_disconnect_mid_job_result_is_there_for_a_new_client() -> None:
    async with running(make_config()) as run:
        async with Plc(run.port()) as plc:
            await plc.trigger(3)
            await run.busy()
        _, rec = await run.job_done(1)
        assert rec.result.status is Status.OK
        async with Plc(run.port()) as plc2:
            words = await plc2.read()
        assert words[Reg.ACK_SEQ] == 3
        assert words[Reg.STATUS] == Status.OK
        assert rec.result.target is not None
        assert values(words) == pytest.approx(rec.result.target.values, rel=1e-6, abs=1e-4)


async def test_garbage_frames_do_not_stop_the_server() -> None:
    rng = np.random.default_rng(0)
    async with running(make_config()) as run:
        reader, writer = await asyncio.open_connection("127.0.0.1", run.port())
        # A header that lies about its length, an unknown function code, then random bytes.
        writer.write(bytes.fromhex("0001 0000 00ff 01 03 0000"))
        writer.write(bytes.fromhex("0002 0000 0002 01 63"))
        writer.write(rng.integers(0, 256, 512, dtype=np.uint8).tobytes())
        await writer.drain()
        async with Plc(run.port()) as plc:  # while the garbage connection is still open
            await plc.trigger(1)
            assert (await plc.result(1))[Reg.STATUS] == Status.OK
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()
        async with Plc(run.port()) as plc:
            await plc.trigger(2)
            assert (await plc.result(2))[Reg.STATUS] == Status.OK


async def test_out_of_limits_pose_is_never_published_as_valid() -> None:
    # 80 mm from the taught reference (600, 100, 10); the limit is 50 mm.
    camera = {"type": "synthetic", "seed": 1,
              "pose": {"translation_mm": [680.0, 100.0, 10.0], "rotvec_rad": [0.0, 0.0, 0.05]}}
    async with running(make_config(camera)) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        words = await plc.result(1)
        assert words[Reg.STATUS] == Status.OUT_OF_LIMITS
        assert words[Reg.N_VALUES] == 0
        assert words[Reg.VALUES:Reg.VALUES + 2 * MAX_VALUES] == [0] * (2 * MAX_VALUES)
        pair, rec = await run.job_done(1)
        assert rec.result.target is None
        # The pose was measured (and is right), it just was not sent.
        assert pair is not None
        assert rec.result.T_base_obj is not None
        assert pose_error(pair.truth["T_base_obj"], rec.result.T_base_obj)[0] < 0.5


async def test_recorded_jobs_replay_to_the_same_result(tmp_path: Path) -> None:
    record = {"enabled": True, "folder": str(tmp_path / "rec"), "max_mb": 50}
    async with running(make_config(record=record)) as run, Plc(run.port()) as plc:
        for seq in (1, 2):
            await plc.trigger(seq)
            await plc.result(seq)
        _, rec = await run.job_done(2)
    jobs = sorted((tmp_path / "rec").iterdir())  # the daemon stopped: writes are finished
    assert [j.name[-9:] for j in jobs] == ["job000001", "job000002"]
    job = jobs[1]
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "replay", "-c", str(job / "config.toml"), str(job),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)})
    async with asyncio.timeout(120):
        out, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    replayed = json.loads(out.decode().splitlines()[0])
    recorded = json.loads((job / "result.json").read_text())
    assert replayed["status"] == recorded["status"] == "OK"
    assert replayed["target"]["values"] == pytest.approx(recorded["target"]["values"], abs=1e-9)
    assert recorded["target"]["values"] == pytest.approx(list(rec.result.target.values))


async def test_without_calibration_every_job_answers_not_calibrated(tmp_path: Path) -> None:
    pair = await _synthetic_pair(2)
    cv2.imwrite(str(tmp_path / "left_1.png"), pair.left)
    cv2.imwrite(str(tmp_path / "right_1.png"), pair.right)
    camera = {"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
              "right_glob": "right_*.png"}
    async with running(make_config(camera)) as run, Plc(run.port()) as plc:
        assert run.daemon.snapshot()["calibrated"] is False
        await plc.trigger(1)
        words = await plc.result(1)
        assert words[Reg.STATUS] == Status.NOT_CALIBRATED
        assert words[Reg.N_VALUES] == 0
        # Anything but GET /status is refused by the status endpoint.
        assert run.daemon.status_server is not None
        reader, writer = await asyncio.open_connection("127.0.0.1", run.daemon.status_server.port)
        writer.write(b"POST /status HTTP/1.0\r\n\r\n")
        assert (await reader.read()).startswith(b"HTTP/1.0 404")
        writer.close()
        await writer.wait_closed()


async def test_out_of_files_on_accept_is_one_line_without_traceback(
        caplog: pytest.LogCaptureFixture) -> None:
    """asyncio reports an accept() that hits the file limit (a connection flood) through the
    loop's error handler, by default with a traceback per accept. The daemon writes one line
    per 10 s instead, and still hands every other loop error to asyncio's default handler."""
    import errno

    async with running(make_config()) as run:
        loop = asyncio.get_running_loop()
        emfile = {"message": "socket.accept() out of system resource",
                  "exception": OSError(errno.EMFILE, "Too many open files")}
        with caplog.at_level("WARNING"):
            for _ in range(50):
                loop.call_exception_handler(dict(emfile))
            loop.call_exception_handler({"message": "something else broke",
                                         "exception": ValueError("not a resource error")})
        lines = [r for r in caplog.records if "out of system resource" in r.getMessage()]
        assert len(lines) == 1, [r.getMessage() for r in lines]
        assert "EMFILE" in lines[0].getMessage()
        assert lines[0].exc_info is None
        others = [r for r in caplog.records if "something else broke" in r.getMessage()]
        assert len(others) == 1
        assert others[0].exc_info is not None  # asyncio's default handler, traceback kept
        assert run.daemon.run_state.name == "RUNNING"
