"""The worker process on its own (``WorkerClient``, no daemon): results equal to the in-process
pipeline's, images through shared memory both ways, and every way a worker can fail: killed,
segfault, an abandoned request, an exception, a request or an answer that cannot be unpickled,
a worker that cannot start. Shared memory is gone from /dev/shm after ``close``.

The processors below are built in the worker process from their ``module:Class`` path.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from vgripd.config import Config, config_from_dict
from vgripd.errors import CameraError
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.host.children import helper_niceness
from vgripd.service.worker.child import WORKER_NICE, WORKER_NICE_FLOOR
from vgripd.service.worker.imageshm import read_images
from vgripd.service.worker.process import (
    SHM_DIR,
    WorkerClient,
    WorkerError,
    describe_exit,
    images_nbytes,
    segments_of,
    write_images,
)
from vgripd.types import ImagePair, JobResult, Status
from vgripd.vision.pipeline import Pipeline

pytestmark = pytest.mark.timeout(120)

HERE = "tests.unit.service.worker.test_worker"
WAIT_S = 60.0


class SlowPipeline(Pipeline):
    """The pipeline, after sleeping ``pair.meta["sleep_s"]`` seconds (having created the file
    ``pair.meta["started"]`` first, when given: the test's sign that the sleep has begun)."""

    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        if "started" in pair.meta:
            Path(pair.meta["started"]).touch()
        time.sleep(float(pair.meta.get("sleep_s", 0.0)))
        return super().process(pair, job_id)


class RaisingPipeline(Pipeline):
    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        if pair.meta.get("raise"):
            raise ValueError(f"job {job_id} refused")
        return super().process(pair, job_id)


class AbbBrokenPipeline(Pipeline):
    """Cannot be built for a recipe whose output is ABB's (what no judge foresaw)."""

    def __init__(self, config: Config) -> None:
        if config.output.vendor == "abb":
            raise RuntimeError("a locator that cannot be built")
        super().__init__(config)


def _explode() -> None:
    raise RuntimeError("cannot be unpickled")


class Unpicklable:
    """Pickles fine; unpickling it raises."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (_explode, ())


class BadAnswerPipeline(Pipeline):
    """Answers with a result the daemon cannot unpickle when asked to."""

    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        result = super().process(pair, job_id)
        if pair.meta.get("bad_answer"):
            return JobResult(job_id=job_id, status=Status.NOT_FOUND,
                             residuals={"x": Unpicklable()})  # type: ignore[dict-item]
        return result


def _config(**sections: Any) -> Config:
    return config_from_dict({
        "camera": {"type": "synthetic", "seed": 7, "max_tilt_deg": 2.0},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}],
        **sections,
    })


async def _local_pair(config: Config, **meta: Any) -> ImagePair:
    cls = load_class(CAMERAS, "camera", config.camera.type)
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    await camera.open()
    try:
        pair: ImagePair = await camera.grab(WAIT_S)
    finally:
        await camera.close()
    return ImagePair(left=pair.left, right=pair.right, t_mono_ns=pair.t_mono_ns,
                     source=pair.source, meta={**pair.meta, **meta},
                     T_base_flange=pair.T_base_flange, truth=pair.truth)


def _with(pair: ImagePair, **meta: Any) -> ImagePair:
    """The same images (so the worker gets them again through shared memory), other meta."""
    return ImagePair(left=pair.left.copy(), right=None if pair.right is None else
                     pair.right.copy(), t_mono_ns=pair.t_mono_ns, meta=meta, truth=pair.truth)


def _same(a: JobResult, b: JobResult) -> None:
    assert a.status is b.status
    assert a.target == b.target
    assert a.T_base_obj is not None
    assert b.T_base_obj is not None
    np.testing.assert_allclose(a.T_base_obj, b.T_base_obj, rtol=0, atol=1e-9)
    assert dict(a.residuals) == pytest.approx(dict(b.residuals), abs=1e-12)


@contextlib.asynccontextmanager
async def running(config: Config, processor: str | None = None) -> AsyncIterator[WorkerClient]:
    client = WorkerClient(config, processor) if processor else WorkerClient(config)
    await client.start()
    try:
        async with asyncio.timeout(WAIT_S):
            await client.wait_ready()
        yield client
    finally:
        await client.close()
        assert segments_of(client.prefix) == []


@pytest.fixture
async def worker() -> AsyncIterator[WorkerClient]:
    async with running(_config(), f"{HERE}:SlowPipeline") as client:
        yield client


def test_images_round_trip_through_a_buffer() -> None:
    rng = np.random.default_rng(1)
    for images in ([rng.integers(0, 256, (7, 13), np.uint8), None],
                   [rng.integers(0, 256, (5, 9, 3), np.uint8),
                    rng.integers(0, 65535, (4, 6), np.uint16)],
                   [rng.integers(0, 256, (8, 10, 3), np.uint8)[:, ::2], None]):  # strided
        buf = memoryview(bytearray(images_nbytes(images)))
        layout = write_images(buf, images)
        back = read_images(buf, layout)
        for a, b in zip(images, back, strict=True):
            if a is None:
                assert b is None
            else:
                assert b is not None
                assert b.dtype == a.dtype
                assert np.array_equal(a, b)
        buf.release()


def test_exit_descriptions() -> None:
    assert describe_exit(-9) == "worker process exited with signal 9 (SIGKILL)"
    assert describe_exit(-11) == "worker process exited with signal 11 (SIGSEGV)"
    assert describe_exit(3) == "worker process exited with code 3"


async def test_the_worker_warms_each_recipes_pipeline_before_it_reports_ready() -> None:
    """The first job as fast as the tenth. The worker runs each recipe's pipeline
    once (``vgripd.vision.warmup.warm_up``) before its ready answer, so the daemon's READY=1 (which waits
    for the camera opened through the worker) comes after it; the snapshot says which."""
    config = _config(recipes={"4": {"name": "narrow", "limits": {"max_translation_mm": 50.0}}})
    client = WorkerClient(config)
    try:
        await client.start()
        await client.wait_ready()
        warmed = client.snapshot()["warmed"]
        assert sorted(warmed) == [0, 4]
        assert all(ms > 0 for ms in warmed.values())
    finally:
        await client.close()


async def test_results_equal_the_in_process_pipeline_both_ways() -> None:
    config = _config()
    pipeline = Pipeline(config)
    async with running(config) as client:
        assert client.pid is not None
        assert client.pid != os.getpid()
        assert len(segments_of(client.prefix)) == 1  # preallocated at start
        # A pair from this process goes to the worker through shared memory ...
        mine = await _local_pair(config)
        _same(await client.process(mine, 1), pipeline.process(mine, 1))
        # ... and a pair the worker's camera grabs comes back through it.
        await client.camera.open()
        grabbed = await client.camera.grab(WAIT_S)
        assert grabbed.left.shape == (1024, 1280)
        assert grabbed.right is not None
        assert "T_base_obj" in grabbed.truth
        result = await client.process(grabbed, 2)
        assert result.status is Status.OK
        _same(result, pipeline.process(grabbed, 2))
        await client.camera.close()
        assert len(segments_of(client.prefix)) == 1  # reused, not one per job


async def test_grabbed_images_are_read_only_views_that_later_grabs_never_overwrite() -> None:
    async with running(_config()) as client:
        grabbed = await client.camera.grab(WAIT_S)  # opens the camera in the worker
        first = client.snapshot()["shm"]
        assert not grabbed.left.flags.writeable
        kept = grabbed.left.copy()
        corner = grabbed.left[:8, :8]  # a slice alone keeps the images alive too
        del grabbed
        again = await client.camera.grab(WAIT_S)
        second = client.snapshot()["shm"]
        assert second != first  # the kept images' segment is not written again
        assert segments_of(client.prefix) == [second]  # the old one is unlinked already
        assert np.array_equal(corner, kept[:8, :8])
        assert not np.array_equal(again.left, kept)
        del corner, again
        await client.camera.grab(WAIT_S)
        assert client.snapshot()["shm"] == second  # nothing kept: reused


async def test_images_that_do_not_fit_get_a_bigger_segment_both_ways(tmp_path: Path) -> None:
    # Uncalibrated replay camera: no segment at start, so the first grab grows one.
    rng = np.random.default_rng(2)
    left = rng.integers(0, 256, (480, 640), np.uint8)
    right = rng.integers(0, 256, (480, 640), np.uint8)
    cv2.imwrite(str(tmp_path / "left_1.png"), left)
    cv2.imwrite(str(tmp_path / "right_1.png"), right)
    config = config_from_dict({"camera": {"type": "replay", "folder": str(tmp_path),
                                          "left_glob": "left_*.png",
                                          "right_glob": "right_*.png"}})
    async with running(config) as client:
        assert client.snapshot()["shm"] is None
        grabbed = await client.camera.grab(WAIT_S)
        assert np.array_equal(grabbed.left, left)
        assert grabbed.right is not None
        assert np.array_equal(grabbed.right, right)
        assert client.snapshot()["shm"] is not None
        del grabbed
        # A bigger (colour) pair from this side: a new segment, the old one unlinked.
        first = client.snapshot()["shm"]
        big = ImagePair(left=np.zeros((960, 1280, 3), np.uint8), right=None, t_mono_ns=1)
        with pytest.raises(WorkerError, match="NotCalibratedError"):
            await client.process(big, 1)
        assert segments_of(client.prefix) == [client.snapshot()["shm"]]
        assert client.snapshot()["shm"] != first


async def test_the_worker_drops_a_real_time_policy_meant_for_the_event_loop() -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        pytest.skip("needs permission for SCHED_FIFO (CAP_SYS_NICE)")
    client = WorkerClient(_config())
    try:
        await client.start()
        await client.wait_ready()  # spawned from this real-time thread
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    try:
        assert client.pid is not None
        assert os.sched_getscheduler(client.pid) == os.SCHED_BATCH  # time sharing, CPU-bound
        assert os.getpriority(os.PRIO_PROCESS, client.pid) == helper_niceness(
            os.getpriority(os.PRIO_PROCESS, 0), WORKER_NICE, WORKER_NICE_FLOOR)
    finally:
        await client.close()


async def test_segments_of_daemons_that_no_longer_run_are_removed_at_start() -> None:
    gone = await asyncio.create_subprocess_exec("true")
    await gone.wait()  # its pid is free now
    stale = SHM_DIR / f"vgripd-{gone.pid}-abc123-1"
    alive = SHM_DIR / f"vgripd-{os.getpid()}-abc123-1"  # this process: not swept
    stale.write_bytes(b"x")
    alive.write_bytes(b"x")
    try:
        async with running(_config()):
            assert not stale.exists()
            assert alive.exists()
    finally:
        stale.unlink(missing_ok=True)
        alive.unlink(missing_ok=True)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSEGV], ids=["SIGKILL", "SIGSEGV"])
async def test_a_worker_that_dies_fails_the_request_naming_why_and_is_replaced(
    worker: WorkerClient, sig: signal.Signals, tmp_path: Path
) -> None:
    pair = await _local_pair(worker.config)
    first = worker.pid
    assert first is not None
    started = tmp_path / "started"
    job = asyncio.create_task(worker.process(_with(pair, sleep_s=60, started=str(started)), 1))
    async with asyncio.timeout(WAIT_S):  # until the worker is sleeping in process()
        while not started.exists():  # noqa: ASYNC110 - another process's file, no event
            await asyncio.sleep(0.02)
    os.kill(first, sig)
    with pytest.raises(WorkerError, match=f"worker process exited with signal {int(sig)} "
                                          rf"\({sig.name}\)"):
        await job
    result = await worker.process(pair, 2)  # waits for the new worker
    assert result.status is Status.OK
    assert worker.pid not in (None, first)
    assert worker.restarts == 1
    assert worker.snapshot()["last_exit"] == f"worker process exited with signal {int(sig)} " \
                                             f"({sig.name})"


async def test_an_abandoned_request_kills_the_worker_and_a_new_one_serves(
    worker: WorkerClient,
) -> None:
    pair = await _local_pair(worker.config)
    first = worker.pid
    t0 = time.monotonic()
    with pytest.raises(TimeoutError):
        async with asyncio.timeout(1.0):
            await worker.process(_with(pair, sleep_s=60), 1)
    assert (await worker.process(pair, 2)).status is Status.OK
    assert worker.pid not in (None, first)
    assert time.monotonic() - t0 < 30  # not the 60 s the stale computation would take


async def test_requests_and_answers_that_cannot_be_unpickled_fail_only_themselves() -> None:
    async with running(_config(), f"{HERE}:BadAnswerPipeline") as client:
        pair = await _local_pair(client.config)
        pid = client.pid
        with pytest.raises(WorkerError, match="the worker cannot read the request: "
                                              "RuntimeError: cannot be unpickled"):
            await client.process(_with(pair, bomb=Unpicklable()), 1)
        with pytest.raises(WorkerError, match="cannot read the worker's answer: "
                                              "RuntimeError: cannot be unpickled"):
            await client.process(_with(pair, bad_answer=True), 2)
        assert (await client.process(pair, 3)).status is Status.OK
        assert client.pid == pid
        assert client.restarts == 0


async def test_an_exception_in_the_worker_fails_the_request_and_the_worker_stays() -> None:
    async with running(_config(), f"{HERE}:RaisingPipeline") as client:
        pair = await _local_pair(client.config)
        pid = client.pid
        with pytest.raises(WorkerError, match=r"ValueError: job 1 refused \(in the worker"):
            await client.process(_with(pair, **{"raise": True}), 1)
        assert (await client.process(pair, 2)).status is Status.OK
        assert client.pid == pid


async def test_a_recipe_whose_pipeline_cannot_be_built_fails_only_its_own_jobs() -> None:
    """The worker starts (no restart loop), names the recipe and the reason in its answer, and
    the other recipes run."""
    config = _config(recipes={"1": {"name": "abb", "output": {"vendor": "abb"}}})
    async with running(config, f"{HERE}:AbbBrokenPipeline") as client:
        pair = await _local_pair(client.config)
        pid = client.pid
        with pytest.raises(WorkerError, match=r"recipe 1: its pipeline cannot be built: "
                                              r"RuntimeError: a locator that cannot be built"):
            await client.process(pair, 1, 1)
        pair = await _local_pair(client.config)  # a request's images are its own
        assert (await client.process(pair, 2, 0)).status is Status.OK
        assert (client.pid, client.restarts) == (pid, 0)


async def test_a_camera_failure_in_the_worker_is_a_camera_error(tmp_path: Path) -> None:
    config = _config(camera={"type": "replay", "folder": str(tmp_path / "missing"),
                             "glob": "*.png"})
    async with running(config) as client:
        with pytest.raises(CameraError, match="missing"):
            await client.camera.open()
        with pytest.raises(CameraError, match="missing"):
            await client.camera.grab(5.0)
        assert client.restarts == 0


async def test_a_worker_that_cannot_start_is_retried_with_back_off() -> None:
    client = WorkerClient(_config(), f"{HERE}:NoSuchPipeline")
    await client.start()
    try:
        with pytest.raises(WorkerError, match="failed to start: AttributeError.*NoSuchPipeline"):
            await client.wait_ready()
        # Meanwhile requests fail at once, naming the reason and the next try: one worker
        # has died so far (a request that waited for the next start would see it die too).
        with pytest.raises(WorkerError, match="NoSuchPipeline.*next start in"):
            await client.wait_ready()
        assert client.restarts == 1
    finally:
        await client.close()
    assert segments_of(client.prefix) == []


def test_the_wire_format_carries_pick_instances() -> None:
    """A result with a pick list pickles (an instance's residuals default to a mappingproxy,
    which does not) and comes back equal."""
    import pickle
    from types import MappingProxyType

    from vgripd.service.worker.child import _wire_result
    from vgripd.types import PickInstance

    instances = (PickInstance(status=Status.OK, T_base_obj=np.eye(4), pick_id=2, score=0.9,
                              residuals=MappingProxyType({"fit_rms_mm": 0.1})),
                 PickInstance(status=Status.PARTIAL, message="3 feature(s) matched, need 4"))
    result = JobResult(job_id=1, status=Status.OK, instances=instances)
    with pytest.raises(TypeError):
        pickle.dumps(result)
    back = pickle.loads(pickle.dumps(_wire_result(result)))
    assert [i.status for i in back.instances] == [Status.OK, Status.PARTIAL]
    assert back.instances[0].residuals == {"fit_rms_mm": 0.1}
    assert back.instances[0].pick_id == 2
    assert back.instances[1].message == "3 feature(s) matched, need 4"
    np.testing.assert_array_equal(back.instances[0].T_base_obj, np.eye(4))
