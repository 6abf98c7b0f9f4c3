"""One daemon, every recipe's plate in turn (the synthetic camera's ``recipe = "job"``): the
job's recipe reaches the camera as a grab hint, in-process and through the worker process.

Each recipe carries its own output vendor over the same Modbus link (KUKA A,B,C next to the ABB
quaternion); the values the PLC reads are checked against scipy's rotations, never vgripd's own
conversion.
"""

from __future__ import annotations

import copy
import os
import signal
import tomllib
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import REPO
from tests.integration.test_daemon import WAIT_S, running
from vgripd.cli.demo import PALLET_SCENE
from vgripd.config import config_from_dict
from vgripd.geometry.transforms import pose_error
from vgripd.sim.plc import MockPlc
from vgripd.types import Status

SAMPLE = REPO / "config" / "samples" / "recipes.toml"


def switching_config(worker: bool) -> Any:
    data = tomllib.loads(SAMPLE.read_text())
    data["camera"].update(recipe="job", seed=7, max_tilt_deg=2.0)
    data["links"][0]["port"] = 0
    data["status"] = {"port": 0}
    # 60 s: after a worker kill the next job waits for the new worker's start, which a busy
    # machine can take longer than the default 10 s for (not what these tests are about)
    data["daemon"] = {"worker": worker, "job_timeout_s": 60.0}
    data["recipes"]["2"]["output"] = {"vendor": "abb"}  # recipe 1 and 0: kuka (the default)
    return config_from_dict(data, str(SAMPLE))


def rotation_of(values: tuple[float, ...], vendor: str) -> np.ndarray:
    """The rotation matrix the robot makes of the values, by scipy."""
    if vendor == "abb":  # q1..q4 = w, x, y, z
        w, x, y, z = values[3:7]
        return Rotation.from_quat([x, y, z, w]).as_matrix()
    a, b, c = values[3:6]  # KUKA: A about z, B about y', C about x''
    return Rotation.from_euler("ZYX", [a, b, c], degrees=True).as_matrix()


@pytest.mark.parametrize("worker", [False, True])
async def test_the_camera_renders_the_plate_of_each_jobs_recipe(worker: bool) -> None:
    config = switching_config(worker)
    async with running(config) as run, MockPlc("127.0.0.1", run.port(), timeout_s=WAIT_S) as plc:
        for n, recipe in enumerate((1, 2, 0, 2, 1), start=1):
            answer = await plc.cycle(recipe)
            pair, record = await run.job_done(n)
            assert answer.status is Status.OK, (recipe, record.result.message)
            assert pair is not None
            names = {f.name for f in config.for_recipe(recipe).object.features}
            assert set(pair.truth["feature_names"]) == names  # that recipe's plate was drawn
            T = record.result.T_base_obj
            assert T is not None
            err_mm, err_deg = pose_error(T, pair.truth["T_base_obj"])
            assert err_mm < 0.1
            assert err_deg < 0.1
            vendor = config.for_recipe(recipe).output.vendor
            assert len(answer.values) == (7 if vendor == "abb" else 6)
            offset = record.result.offset
            assert offset is not None
            # float32 registers: about 1e-4 mm at 600 mm, 1e-6 in a rotation entry
            np.testing.assert_allclose(answer.values[:3], offset[:3, 3], atol=1e-3)
            np.testing.assert_allclose(rotation_of(answer.values, vendor), offset[:3, :3],
                                       atol=1e-5)


async def test_recipes_survive_a_worker_restart() -> None:
    """The worker process is killed between jobs: the new one builds every recipe's pipeline
    and renders every plate again (recipe 2's jobs, then 1's, then 2's, all OK)."""
    config = switching_config(worker=True)
    async with running(config) as run, MockPlc("127.0.0.1", run.port(), timeout_s=WAIT_S) as plc:
        assert (await plc.cycle(2)).status is Status.OK
        first = run.daemon.snapshot()["worker"]["pid"]
        os.kill(first, signal.SIGKILL)  # the next job waits for the new worker
        for n, recipe in enumerate((1, 2, 0), start=2):
            answer = await plc.cycle(recipe)
            pair, record = await run.job_done(n)
            assert answer.status is Status.OK, (recipe, record.result.message)
            assert pair is not None
            assert {f.name for f in config.for_recipe(recipe).object.features} == set(
                pair.truth["feature_names"])
        worker = run.daemon.snapshot()["worker"]
        assert (worker["restarts"], worker["pid"] != first) == (1, True)


async def test_a_pick_list_recipe_next_to_a_single_object_recipe() -> None:
    """A pallet in view; recipe 7 walks it as a pick list (KUKA), recipe 8 too (ABB
    quaternion), recipe 0 is a single-object job: on six plates it is AMBIGUOUS, never a pose,
    and a NEXT after it is refused (BAD_REQUEST), never a pose of the earlier list."""
    scene = copy.deepcopy(PALLET_SCENE)
    picking = {"picking": scene["picking"], "limits": scene["limits"]}
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 3, **scene["camera"]},
        "limits": {"max_translation_mm": 200.0},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}],
        "status": {"port": 0}, "daemon": {"worker": False},
        "recipes": {"7": {"name": "pallet", **picking, "output": scene["output"]},
                    "8": {"name": "pallet-abb", **picking,
                          "output": {"vendor": "abb", **scene["output"]}}}})
    async with running(config) as run, MockPlc("127.0.0.1", run.port(), timeout_s=WAIT_S) as plc:
        seen = []
        for step in ("T7", "N", "N", "T0", "N", "T8", "N", "T0", "N"):
            if step == "N":
                answer = await plc.next()  # checks index, job id and age against the list
            else:
                answer = await plc.cycle(int(step[1:]))
            seen.append((step, answer.status, answer.job_id, answer.index, len(answer.values)))
        assert seen == [
            ("T7", Status.OK, 1, 1, 6), ("N", Status.OK, 1, 2, 6), ("N", Status.OK, 1, 3, 6),
            ("T0", Status.AMBIGUOUS, 2, 0, 0), ("N", Status.BAD_REQUEST, 0, 0, 0),
            ("T8", Status.OK, 3, 1, 7), ("N", Status.OK, 3, 2, 7),
            ("T0", Status.AMBIGUOUS, 4, 0, 0), ("N", Status.BAD_REQUEST, 0, 0, 0)]
        assert [r.result.recipe for _, r in run.jobs] == [7, 0, 8, 0]
