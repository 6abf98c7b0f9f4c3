"""The web view's belt strip in headless Chromium: a daemon with a conveyor recipe (the shared
belt cell, tests/integration/belt_cell.py), a PLC (pymodbus, map version 4) filling and
emptying the part queue; the page draws one part per queued part, where the belt's truth puts
it at the newest count, and the pick window from /status's ``conveyor`` entry."""

from __future__ import annotations

from pathlib import Path

import aiohttp
import pytest

from tests.integration.belt_cell import (
    PARTS,
    WINDOW,
    BeltPlc,
    conveyor_config,
    count_at,
    render,
    visible,
)
from tests.integration.test_daemon import running
from tests.integration.test_web import _base, _chromium, _until
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import Reg
from vgripd.types import Status

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

STRIP = "document.querySelectorAll('#belt-0 .belt-part')"


async def test_the_belt_strip_shows_each_queued_part_at_its_place_and_the_window(
        tmp_path: Path) -> None:
    frames = [0.0, 150.0]
    await render(tmp_path, frames)
    config = conveyor_config({"type": "replay", "folder": str(tmp_path),
                              "left_glob": "left_*.png", "right_glob": "right_*.png"})
    async with running(config) as run, BeltPlc(run.port()) as plc, \
            aiohttp.ClientSession() as http:
        base = _base(run)
        async with _chromium(tmp_path, base + "/") as evaluate:
            # no image yet: the strip is there, empty
            await _until(evaluate, "document.getElementById('belt-0')?.textContent"
                                   "?.includes('0 queued')")
            assert await evaluate(f"{STRIP}.length") == 0

            for travel in frames:  # parts 0, 1; then 1 again and 2
                words = await plc.request(Command.TRIGGER, count_at(travel))
                assert words[Reg.STATUS] == Status.OK
            queued = sorted({k for t in frames for k in visible(t)})
            assert queued == [0, 1, 2]
            async with http.get(base + "/api/status") as resp:
                belt = (await resp.json())["conveyor"]["0"]
            assert belt["window_mm"] == list(WINDOW)
            assert belt["last_count"] == count_at(frames[-1])
            # the queue's parts at the newest count against the belt's truth, downstream first
            assert [round(p["along_mm"]) for p in belt["parts"]] == [
                round(PARTS[k][0] + frames[-1]) for k in queued]
            assert [round(p["across_mm"]) for p in belt["parts"]] == [
                round(PARTS[k][1]) for k in queued]

            await _until(evaluate, f"{STRIP}.length === 3")
            drawn = await evaluate(f"[...{STRIP}].map(g => Number(g.dataset.along))")
            assert drawn == [p["along_mm"] for p in belt["parts"]]
            # drawn left to right in travel order: downstream (larger along) further right
            xs = await evaluate(f"[...{STRIP}].map(g => g.getCTM().e)")
            assert xs == sorted(xs, reverse=True)
            window = await evaluate("(() => { const r = document.querySelector("
                                    "'#belt-0 .belt-window').getBBox(); "
                                    "return [r.x, r.x + r.width]; })()")
            # all three inside it
            assert window[0] < min(xs)
            assert max(xs) < window[1]

            # NEXT serves the most downstream part: two left on the strip
            words = await plc.request(Command.NEXT, count_at(frames[-1] + 10.0))
            assert words[Reg.STATUS] == Status.OK
            await _until(evaluate, f"{STRIP}.length === 2")
            assert "2 queued" in await evaluate(
                "document.querySelector('#belt-0 figcaption').textContent")
