"""A pick list through the daemon and its worker process: a pallet of six plates triggered by a
PLC (a real pymodbus client over TCP) arrives in the daemon's job record with every instance
intact (the worker pickles the result: the instances' mappings must travel as plain dicts) and
equal to the in-process pipeline's on the same images. The registers that carry the list to the
PLC (map version 3, NEXT) are the links' part (docs/registers.md)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

import numpy as np
import pytest

from tests.integration.test_daemon import Plc, Run, make_config
from vgripd.peer.registers import Reg
from vgripd.service.daemon import Daemon
from vgripd.types import Status
from vgripd.vision.pipeline import Pipeline

pytestmark = pytest.mark.timeout(120)

PALLET = {"type": "synthetic", "seed": 5,
          "pallet": {"count": 6, "cols": 3, "gap_mm": 0.0}, "drop_features": ["1/m2"]}
PICKS = [{"id": 1, "priority": 1, "pose": {"translation_mm": [-10.0, 0.0, 0.0],
                                           "rotvec_rad": [3.14159265, 0.0, 0.0]}}]


@contextlib.asynccontextmanager
async def running(config: object) -> AsyncIterator[Run]:
    daemon = Daemon(config)
    run = Run(daemon)
    await daemon.start()
    try:
        yield run
    finally:
        await daemon.stop()


async def test_a_pallet_pick_list_arrives_intact_through_the_worker() -> None:
    config = make_config(PALLET, picking={"max_objects": 6, "pick_points": PICKS},
                         limits={"max_translation_mm": 300.0, "max_rotation_deg": 10.0})
    assert config.daemon.worker
    async with running(config) as run, Plc(run.port()) as plc:
        assert run.daemon.snapshot()["worker"]["pid"] is not None
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        pair, rec = await run.job_done(1)
    assert pair is not None
    got = rec.result.instances
    assert len(got) == 6
    expected = Pipeline(config).process(pair, 1).instances
    assert len(expected) == 6
    for a, b in zip(got, expected, strict=True):
        assert a.status is b.status is Status.OK
        assert a.target == b.target
        assert a.pick_id == b.pick_id == 1
        assert a.score == b.score
        assert a.features_used == b.features_used
        assert type(a.residuals) is dict
        assert a.residuals == pytest.approx(dict(b.residuals), abs=1e-12)
        assert a.T_base_obj is not None
        assert b.T_base_obj is not None
        np.testing.assert_allclose(a.T_base_obj, b.T_base_obj, rtol=0, atol=1e-9)
    assert rec.result.target == got[0].target
    assert [len(i.features_used) for i in got].count(5) == 1  # the plate with m2 covered
