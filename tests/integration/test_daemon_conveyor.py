"""Conveyor tracking end to end: the daemon in-process with a conveyor recipe, a PLC (a real
pymodbus client over TCP, map version 4) that latches the encoder count with each trigger,
walks the part queue with NEXT and asks PREDICT for an intercept.

The belt is simulated here, independently of the code under test: five parts at known places
along a straight belt at count ``COUNT0``, carried ``travel`` mm at each image; every image is
rendered (the synthetic camera's renderer, fixed poses) with the parts under the camera at that
travel and replayed to the daemon in order. Every answer is checked against this belt's truth at
the count the answer names: the pose in the registers, ALONG/ACROSS/THETA, each part served
once, a part seen in two images served once, a part past the window dropped, PREDICT answered
inside the window and refused past it. The belt and its PLC: tests/integration/belt_cell.py."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest

from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    PARTS,
    WINDOW,
    BeltPlc,
    conveyor_config,
    conveyor_data,
    count_at,
    f32,
    render,
    travel_of,
    u32,
    visible,
    which,
)
from tests.integration.test_daemon import running
from vgripd.config import load_config
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import Reg
from vgripd.serialize import toml_from_dict
from vgripd.service.daemon import Daemon
from vgripd.service.ops.reload import Reloader
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)


async def test_a_belt_served_once_per_part_in_belt_order_at_the_latched_counts(
        tmp_path: Path) -> None:
    frames = [0.0, 150.0, 300.0, 450.0, 600.0]
    await render(tmp_path, frames)
    config = conveyor_config({"type": "replay", "folder": str(tmp_path),
                              "left_glob": "left_*.png", "right_glob": "right_*.png"})
    T_ref = T_base_obj_ref(config)
    served: list[int] = []

    async def trigger(frame: int) -> None:
        words = await plc.request(Command.TRIGGER, count_at(frames[frame]))
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        assert u32(words, Reg.RESULT_COUNT) == count_at(frames[frame])
        assert words[Reg.LATCH_SOURCE] == 1
        assert f32(words, Reg.LATCH_ERR_MM) == pytest.approx(0.5 / COUNTS_PER_MM, abs=1e-4)
        assert words[Reg.COUNT] == len(visible(frames[frame]))
        assert which(words, frames[frame], T_ref) in visible(frames[frame])

    async def next_part(travel_now: float) -> int | None:
        words = await plc.request(Command.NEXT, count_at(travel_now))
        if words[Reg.STATUS] == Status.NOT_FOUND:
            assert words[Reg.N_VALUES] == 0
            return None
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        # the pose at its own latched count: a count of an image, not the count now
        at = travel_of(u32(words, Reg.RESULT_COUNT))
        assert at in frames
        part = which(words, at, T_ref)
        assert PARTS[part][0] + travel_now <= WINDOW[1]  # still in reach now
        served.append(part)
        return part

    async with running(config) as run, BeltPlc(run.port()) as plc:
        await trigger(0)  # parts 0 and 1
        await trigger(1)  # parts 1 (again) and 2
        await trigger(2)  # parts 2 (again) and 3
        # at travel 350 part 0 is at 1050, past the window's end (1000): dropped, not served
        assert await next_part(350.0) == 1
        # PREDICT: where part 1 will be at travel 380 (inside the window), and at 500 (past)
        words = await plc.request(Command.PREDICT, count_at(380.0))
        assert words[Reg.STATUS] == Status.OK
        assert u32(words, Reg.RESULT_COUNT) == count_at(380.0)
        assert which(words, 380.0, T_ref) == 1
        words = await plc.request(Command.PREDICT, count_at(500.0))
        assert (words[Reg.STATUS], words[Reg.N_VALUES]) == (Status.OUT_OF_WORKSPACE, 0)
        await trigger(3)  # parts 3 (again) and 4
        assert [await next_part(455.0) for _ in range(3)] == [2, 3, 4]
        await trigger(4)  # part 4 again, already served: not queued again
        assert await next_part(610.0) is None
        conveyor = run.daemon.snapshot()["conveyor"]["0"]
    assert served == [1, 2, 3, 4]  # each once, downstream first; part 0 missed
    sightings = sum(len(visible(t)) for t in frames)
    assert conveyor["seen"] == sightings == 9
    assert conveyor["duplicates"] == sightings - len(PARTS) == 4
    assert (conveyor["dropped"], conveyor["served"], conveyor["queued"]) == (1, 4, 0)


async def test_a_reload_applies_a_changed_added_and_removed_conveyor(tmp_path: Path) -> None:
    frames = [0.0, 150.0]
    await render(tmp_path, frames)
    data = conveyor_data({"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    main = tmp_path / "vgripd.toml"

    def write(conveyor: dict[str, Any] | None) -> None:
        d = copy.deepcopy(data)
        d.pop("conveyor")
        if conveyor is not None:
            d["conveyor"] = conveyor
        main.write_text(toml_from_dict(d))

    belt = dict(data["conveyor"])
    write(belt)
    daemon = Daemon(load_config(main))
    reloader = daemon.reloader = Reloader(daemon, main)
    await daemon.start()
    try:
        async with BeltPlc(list(daemon.rooms.links.links.values())[0].port) as plc:
            words = await plc.request(Command.TRIGGER, count_at(frames[0]))
            assert words[Reg.STATUS] == Status.OK
            assert words[Reg.QUEUED] == 2
            line = daemon.rooms.jobs.core.lines[0]

            # a file whose belt did not change keeps the queue
            (tmp_path / "note.txt").write_text("unrelated")
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert daemon.rooms.jobs.core.lines[0] is line
            assert len(line.queue) == 2

            # a belt refused by the judge: the running one stays, queue and all
            write({**belt, "window_mm": [900.0, 300.0]})
            out = await reloader.reload("test")
            assert not out.applied
            assert "window_mm" in out.message
            assert daemon.rooms.jobs.core.lines[0] is line

            # a changed window: applied, a new queue on the new belt
            write({**belt, "window_mm": [300.0, 700.0]})
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert any(d.startswith("conveyor.window_mm") for d in out.diff), out.diff
            now = daemon.rooms.jobs.core.lines[0]
            assert now.queue.window_mm == (300.0, 700.0)
            assert len(now.queue) == 0
            words = await plc.request(Command.TRIGGER, count_at(frames[1]))
            assert (words[Reg.STATUS], words[Reg.QUEUED]) == (Status.OK, 2)

            # removed: the recipe's jobs are a standing part's again (no latch, no queue)
            write(None)
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert daemon.rooms.jobs.core.lines == {}
            assert daemon.snapshot()["conveyor"] == {}

            # added back: a conveyor again, its queue empty; NEXT answers from it
            write(belt)
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert len(daemon.rooms.jobs.core.lines[0].queue) == 0
            words = await plc.request(Command.NEXT, count_at(200.0))
            assert words[Reg.STATUS] == Status.NOT_FOUND
            assert daemon.snapshot()["conveyor"]["0"]["queued"] == 0
    finally:
        await reloader.close()
        await daemon.stop()


async def test_a_conveyor_added_by_a_reload_reaches_the_links(tmp_path: Path) -> None:
    """A daemon started without a belt: its links refuse NEXT without a pick list. A reload
    that adds a ``[conveyor]`` tells them, so NEXT is answered from the (empty) part queue, and
    a reload that removes it again makes them refuse it again."""
    frames = [0.0]
    await render(tmp_path, frames)
    data = conveyor_data({"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    belt = data.pop("conveyor")
    main = tmp_path / "vgripd.toml"
    main.write_text(toml_from_dict(data))
    daemon = Daemon(load_config(main))
    reloader = daemon.reloader = Reloader(daemon, main)
    await daemon.start()
    try:
        async with BeltPlc(list(daemon.rooms.links.links.values())[0].port) as plc:
            await refused(plc)  # no list, no queue
            main.write_text(toml_from_dict({**data, "conveyor": belt}))
            out = await reloader.reload("test")
            assert out.applied, out.message
            words = await plc.request(Command.NEXT, count_at(0.0))
            assert words[Reg.STATUS] == Status.NOT_FOUND  # the queue answered: it is empty
            main.write_text(toml_from_dict(data))
            out = await reloader.reload("test")
            assert out.applied, out.message
            await refused(plc)
    finally:
        await reloader.close()
        await daemon.stop()


async def refused(plc: BeltPlc) -> None:
    """NEXT refused by the link's handshake (REJECT_SEQ, REJECT_CODE BAD_REQUEST): no job."""
    plc.seq += 1
    rr = await plc.client.write_registers(Reg.CMD, [Command.NEXT, plc.seq])
    assert not rr.isError(), rr
    words = await plc.until(lambda w: w[Reg.REJECT_SEQ] == plc.seq)
    assert words[Reg.REJECT_CODE] == Status.BAD_REQUEST
