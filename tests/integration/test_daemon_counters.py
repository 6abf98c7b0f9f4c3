"""The daemon's counters count what the peers were told, refusals included.

- A link that publishes another status than the job's (here a register link whose int32 format
  cannot hold the absolute grip pose: OUT_OF_LIMITS instead of OK) is counted as published.
- A publish that fails is counted apart ("undelivered"), not as an answer.
- Refusals a register link makes on its own handshake (REJECT_SEQ/REJECT_CODE: BUSY,
  BAD_REQUEST) are counted by code next to the daemon's own BUSY refusals.

Real daemon, synthetic camera, Modbus/TCP server links on 127.0.0.1, a pymodbus client as PLC.
"""

from __future__ import annotations

from typing import Any

import pytest

from tests.integration.test_daemon import Plc, running
from vgripd.cli.status import format_status
from vgripd.config import Config, config_from_dict
from vgripd.errors import LinkError
from vgripd.peer.registers import Reg
from vgripd.types import JobResult, Status

pytestmark = pytest.mark.timeout(90)

LINK = {"type": "modbus_server", "host": "127.0.0.1", "port": 0}


def config(links: list[dict[str, Any]] | None = None, **sections: Any) -> Config:
    return config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": links or [LINK],
        "status": {"port": 0},
        **sections,
    })


async def test_a_status_the_link_put_in_place_of_the_jobs_is_what_is_counted() -> None:
    # The grip pose 3 m out does not fit int32 at scale 1e6 (+-2147.48): the job is OK, the
    # PLC is told OUT_OF_LIMITS, and that is what the counters say.
    cfg = config(
        [{**LINK, "value_format": "int32", "scale": 1_000_000}],
        output={"vendor": "kuka", "mode": "grip"},
        reference={"T_base_obj": {"translation_mm": [600.0, 100.0, 10.0],
                                  "rotvec_rad": [0.0, 0.0, 0.05]},
                   "grip": {"translation_mm": [3000.0, 100.0, 500.0]}})
    async with running(cfg) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        words = await plc.result(1)
        _, record = await run.job_done(1)
        snapshot = run.daemon.snapshot()
        line = run.daemon.status_line()
    assert words[Reg.STATUS] == Status.OUT_OF_LIMITS
    assert record.result.status is Status.OK
    assert record.published is Status.OUT_OF_LIMITS
    assert run.daemon.rooms.jobs.counters == {"OUT_OF_LIMITS": 1}
    assert snapshot["counters"] == {"OUT_OF_LIMITS": 1}
    assert snapshot["last_job"]["published"] == "OUT_OF_LIMITS"
    text = format_status(snapshot)
    assert "last job 1: OK (1), published as OUT_OF_LIMITS" in text
    assert "counters: OUT_OF_LIMITS 1" in text
    assert "1 triggers (OUT_OF_LIMITS 1)" in line


async def test_a_failed_publish_is_counted_as_not_delivered(monkeypatch: pytest.MonkeyPatch) -> None:
    async with running(config()) as run, Plc(run.port()) as plc:
        link = next(iter(run.daemon.rooms.links.links.values()))

        async def unplugged(seq: int, result: JobResult) -> Status:
            raise LinkError("cable pulled")

        monkeypatch.setattr(link, "publish", unplugged)
        await plc.trigger(1)
        _, record = await run.job_done(1)
        snapshot = run.daemon.snapshot()
        line = run.daemon.status_line()
    assert record.result.status is Status.OK
    assert record.published is None
    assert run.daemon.rooms.jobs.counters == {}
    assert snapshot["counters"] == {}
    assert snapshot["undelivered"] == {"OK": 1}
    assert snapshot["last_job"]["published"] is None
    text = format_status(snapshot)
    assert "NOT DELIVERED" in text
    assert "not delivered (the link's publish failed): OK 1" in text
    assert "1 triggers (1 not delivered)" in line


async def test_handshake_refusals_are_counted_by_code_with_the_daemons() -> None:
    async with running(config([LINK, LINK])) as run, \
            Plc(run.port(0)) as plc_a, Plc(run.port(1)) as plc_b:
        await plc_a.trigger(7)
        await run.busy()
        # Link A's own handshake refuses a second request (BUSY) and an unknown command.
        await plc_a.trigger(8)
        assert (await plc_a.until(lambda w: w[Reg.REJECT_SEQ] == 8))[Reg.REJECT_CODE] == Status.BUSY
        rr = await plc_a.client.write_registers(Reg.CMD, [9, 9])
        assert not rr.isError()
        words = await plc_a.until(lambda w: w[Reg.REJECT_SEQ] == 9)
        assert words[Reg.REJECT_CODE] == Status.BAD_REQUEST
        # Link B is refused by the daemon (BUSY, published to B).
        await plc_b.trigger(1)
        assert (await plc_b.result(1))[Reg.STATUS] == Status.BUSY
        assert (await plc_a.result(7))[Reg.STATUS] == Status.OK
        await run.job_done(1)
        snapshot = run.daemon.snapshot()
        line = run.daemon.status_line()
    assert run.daemon.rooms.jobs.counters == {"OK": 1, "BUSY": 1}  # the daemon's own answers
    assert snapshot["counters"] == {"OK": 1, "BUSY": 2, "BAD_REQUEST": 1}
    assert snapshot["refusals"] == {"BUSY": 2, "BAD_REQUEST": 1}
    assert snapshot["undelivered"] == {}
    by_link = {entry["name"]: entry["refusals"] for entry in snapshot["links"]}
    assert by_link == {"modbus_server.0": {"BUSY": 1, "BAD_REQUEST": 1}, "modbus_server.1": {}}
    text = format_status(snapshot)
    assert "counters: BAD_REQUEST 1, BUSY 2, OK 1" in text
    assert "of which refusals: BAD_REQUEST 1, BUSY 2" in text
    assert "modbus_server.0: up" in text
    assert "refused BAD_REQUEST 1, BUSY 1" in text
    assert "4 triggers (BAD_REQUEST 1, BUSY 2, OK 1)" in line
