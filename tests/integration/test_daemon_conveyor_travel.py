"""Triggering by belt travel end to end: the daemon in-process with ``conveyor.trigger =
"travel"`` and the Modbus/TCP server link; the PLC (a real pymodbus client over TCP, map
version 4) only writes the belt's moving count into LATCH_COUNT, and asks NEXT for the parts.

The belt is tests/integration/belt_cell.py's, simulated independently of the code under test;
its images are rendered at the travels where the daemon must trigger (the first count, then
every 150 mm) and replayed in order. Each image is held in processing (the job thread kept
busy by the test) until the PLC has written the count once more, so the belt provably stood
during the exposure: the latch must then be that count exactly, and every answer is checked
against the belt's truth there. Checked: one job per trigger distance and none between, none
while the count stands still, the PLC's answer area untouched by the belt's jobs, each part
queued once and NEXT serving them downstream first, a trigger point passed while a job runs
skipped, counted and logged once, a jump in the count re-based into one image, the counts in
/api/status and /metrics."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest

from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    PARTS,
    WINDOW,
    BeltPlc,
    conveyor_data,
    count_at,
    f32,
    render,
    travel_of,
    u32,
    visible,
    which,
)
from tests.integration.test_daemon import CODEC, Run, running
from vgripd.config import config_from_dict
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import Reg
from vgripd.service.jobs.runner import JobState
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)

WAIT_S = 60.0
FRAMES = [0.0, 150.0, 300.0, 450.0, 600.0]  # the last one is the re-based image's


class CountingPlc(BeltPlc):
    """The PLC of a belt triggered by travel: it writes the count now into LATCH_COUNT."""

    async def count(self, travel_mm: float) -> None:
        await self.raw(count_at(travel_mm))

    async def raw(self, count: int) -> None:
        rr = await self.client.write_registers(Reg.LATCH_COUNT, CODEC.u32(count))
        assert not rr.isError(), rr


@contextlib.asynccontextmanager
async def processing_held(run: Run) -> AsyncIterator[threading.Event]:
    """The daemon's job thread kept busy until the block ends (or the event is set): the next
    job waits in PROCESSING, its image taken."""
    runner = run.daemon.rooms.jobs
    assert runner._executor is not None
    gate = threading.Event()
    runner._executor.submit(gate.wait, WAIT_S * 2)
    try:
        yield gate
    finally:
        gate.set()


async def image_at(run: Run, plc: CountingPlc, travel: float, job: int,
                   meanwhile: tuple[float, ...] = ()) -> None:
    """The count reaches ``travel``, where job ``job`` must start; the count is written again
    once its image is taken (the belt stood), then the ``meanwhile`` counts while it is still
    processing; then the job is let finish."""
    d, runner = run.daemon, run.daemon.rooms.jobs
    async with processing_held(run):
        await plc.count(travel)
        await d.wait_for(lambda: runner.job_seq == job and d.rooms.jobs.state is JobState.PROCESSING,
                         WAIT_S)
        await plc.count(travel)
        for t in meanwhile:
            await plc.count(t)
            assert runner.job_seq == job  # a job runs: no other starts
    await run.job_done(job)
    record = run.jobs[job - 1][1]
    assert record.link == "belt"
    assert record.result.status is Status.OK, record.result.message
    belt = record.result.belt
    assert belt is not None
    assert (belt.count, belt.source) == (count_at(travel), 3)  # the count it stood at
    assert belt.error_mm == pytest.approx(0.5 / COUNTS_PER_MM)  # it stood: resolution only


async def moves(run: Run, plc: CountingPlc, start: float, end: float, job: int) -> None:
    """The belt moves from ``start`` to before ``end`` in 30 mm steps: no job starts."""
    travel = start + 30.0
    while travel < end:
        await plc.count(travel)
        assert run.daemon.rooms.jobs.job_seq == job, travel
        travel += 30.0


def metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in /metrics")


async def test_the_belt_travel_starts_the_jobs_and_next_serves_their_parts(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    await render(tmp_path, FRAMES)
    data = conveyor_data({"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    data["conveyor"] = {**data["conveyor"], "trigger": "travel", "latch": "timestamp"}
    config = config_from_dict(data)
    T_ref = T_base_obj_ref(config)
    served: list[int] = []
    caplog.set_level(logging.INFO, logger="vgripd")

    async def next_part(travel_now: float) -> int | None:
        words = await plc.request(Command.NEXT, count_at(travel_now))
        if words[Reg.STATUS] == Status.NOT_FOUND:
            assert words[Reg.N_VALUES] == 0
            return None
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        at = travel_of(u32(words, Reg.RESULT_COUNT))
        assert at in FRAMES  # its pose at its own image's count
        assert words[Reg.LATCH_SOURCE] == 3
        assert f32(words, Reg.LATCH_ERR_MM) == pytest.approx(0.5 / COUNTS_PER_MM, abs=1e-4)
        part = which(words, at, T_ref)
        assert PARTS[part][0] + travel_now <= WINDOW[1]  # still in reach now
        served.append(part)
        return part

    async with running(config) as run, CountingPlc(run.port()) as plc:
        runner = run.daemon.rooms.jobs
        await image_at(run, plc, FRAMES[0], 1)  # the first count seen: parts 0 and 1
        await moves(run, plc, 0.0, 150.0, 1)
        await image_at(run, plc, FRAMES[1], 2)  # parts 1 (again) and 2
        await moves(run, plc, 150.0, 300.0, 2)
        await image_at(run, plc, FRAMES[2], 3)  # parts 2 (again) and 3
        words = await plc.read()
        assert (words[Reg.ACK_SEQ], words[Reg.STATUS], words[Reg.JOB_ID + 1]) == (0, 0, 0)
        # at travel 330 part 0 is at 1030, past the window's end (1000): dropped
        assert await next_part(330.0) == 1
        await moves(run, plc, 330.0, 450.0, 3)
        caplog.clear()
        # parts 3 (again) and 4; the trigger point at 600 passes while the job runs: skipped
        await image_at(run, plc, FRAMES[3], 4, meanwhile=(520.0, 600.0))
        skips = [r for r in caplog.records if "image skipped" in r.getMessage()]
        assert len(skips) == 1, [r.getMessage() for r in caplog.records]
        assert f"count {count_at(600.0)}" in skips[0].getMessage()
        for _ in range(20):  # the belt stands: no job
            await plc.count(610.0)
        await asyncio.sleep(0)
        assert (runner.job_seq, runner.job) == (4, None)
        assert [await next_part(610.0) for _ in range(4)] == [2, 3, 4, None]
        status = run.daemon.snapshot()
        conveyor = status["conveyor"]["0"]
        assert run.daemon.rooms.jobs.counters["OK"] >= 4
        belt_link = next(link for link in status["links"] if link["name"] == "belt")
        assert (belt_link["state"], belt_link["peer"]) == ("up", "belt travel (count from "
                                                                  "modbus_server)")

        # a PLC restart: the count jumps to 7; one image at it, then one per 150 mm again
        caplog.clear()
        await plc.raw(7)
        await run.job_done(5)
        for step in (1, 2, 3):
            await plc.raw(7 + 400 * step)  # 40 .. 120 mm
        assert (runner.job_seq, len(run.jobs)) == (5, 5)
        jumps = [r for r in caplog.records if "re-based" in r.getMessage()]
        assert len(jumps) == 1, [r.getMessage() for r in caplog.records]
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        async with aiohttp.ClientSession() as http, http.get(f"{base}/metrics") as resp:
            metrics = await resp.text()
    assert served == [1, 2, 3, 4]  # each once, downstream first; part 0 missed
    sightings = sum(len(visible(t)) for t in FRAMES[:4])
    assert (conveyor["seen"], conveyor["duplicates"]) == (sightings, sightings - len(PARTS)) \
        == (8, 3)
    assert (conveyor["dropped"], conveyor["served"], conveyor["queued"]) == (1, 4, 0)
    assert (conveyor["trigger"], conveyor["travel_images"], conveyor["skipped"],
            conveyor["rebased"]) == ("travel", 4, 1, 0)
    assert metric(metrics, 'vgripd_conveyor_travel_images_total{recipe="0"}') == 5
    assert metric(metrics, 'vgripd_conveyor_skipped_total{recipe="0"}') == 1
    assert metric(metrics, 'vgripd_conveyor_rebased_total{recipe="0"}') == 1
