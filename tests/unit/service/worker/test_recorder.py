"""Recorder: what lands on disk reads back identically (OpenCV, json), the cap holds, a broken
disk is logged once and never raises into the job."""

from __future__ import annotations

import json
import logging
import os
import stat
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from vgripd.config import Config, config_from_dict
from vgripd.serialize import toml_from_dict
from vgripd.service.worker.recorder import Recorder, dict_from_result
from vgripd.types import ImagePair, JobResult, RobotTarget, Status


def _pair(seed: int, stereo: bool = True) -> ImagePair:
    rng = np.random.default_rng(seed)
    left = rng.integers(0, 256, (120, 160), dtype=np.uint8)
    right = rng.integers(0, 256, (120, 160), dtype=np.uint8) if stereo else None
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    return ImagePair(left=left, right=right, t_mono_ns=123, source="test",
                     meta={"exposure_ms": 4.0}, T_base_flange=T, truth={"T_cam_obj": T})


def _ok(job_id: int) -> JobResult:
    target = RobotTarget("kuka", ("X", "Y", "Z", "A", "B", "C"), (1.0, 2.0, 3.0, 4.0, 5.0, 6.0))
    return JobResult(job_id=job_id, status=Status.OK, target=target, offset=np.eye(4),
                     residuals={"epipolar_px": np.float64(0.25)})


def test_a_recorded_job_reads_back_identically(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, 10_000_000, {"daemon": {"job_timeout_s": 10.0}})
    rec.scan()
    pair = _pair(1)
    folder = rec.write(pair, _ok(7))
    assert folder.name.endswith("-job000007")
    assert sorted(p.name for p in folder.iterdir()) == [
        "config.toml", "left.png", "pair.json", "result.json", "right.png"]
    assert np.array_equal(cv2.imread(str(folder / "left.png"), cv2.IMREAD_UNCHANGED), pair.left)
    assert np.array_equal(cv2.imread(str(folder / "right.png"), cv2.IMREAD_UNCHANGED), pair.right)
    meta = json.loads((folder / "pair.json").read_text())
    assert np.allclose(meta["T_base_flange"], pair.T_base_flange)
    assert meta["meta"] == {"exposure_ms": 4.0}
    result = json.loads((folder / "result.json").read_text())
    assert result["status"] == "OK"
    assert result["status_code"] == 1
    assert result["target"]["fields"] == ["X", "Y", "Z", "A", "B", "C"]
    assert result["residuals"] == {"epipolar_px": 0.25}
    assert tomllib.loads((folder / "config.toml").read_text()) == {"daemon": {"job_timeout_s": 10.0}}


def test_config_snapshot_toml_loads_back_to_the_same_config() -> None:
    links = [{"type": "modbus_server", "host": "127.0.0.1", "port": 1502},
             {"type": "ur_rtde", "host": "ur \"cell\" 3", "upper": True}]
    config = config_from_dict({"links": links, "output": {"vendor": "ur"},
                               "record": {"enabled": True, "max_mb": 1.5}})
    data = config.model_dump(mode="json", exclude_none=True)
    text = toml_from_dict(data)
    assert tomllib.loads(text) == data
    again = config_from_dict(tomllib.loads(text))
    assert again == config
    assert again != Config()


def test_single_camera_job_has_no_right_image(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, 10_000_000, {})
    rec.scan()
    folder = rec.write(_pair(2, stereo=False), JobResult(job_id=1, status=Status.NOT_FOUND))
    assert not (folder / "right.png").exists()
    assert dict_from_result(JobResult(job_id=1, status=Status.NOT_FOUND))["target"] is None


def test_size_cap_deletes_oldest_jobs(tmp_path: Path) -> None:
    probe = Recorder(tmp_path / "probe", 10**9, {})
    probe.scan()
    one_job = sum(f.stat().st_size for f in probe.write(_pair(0), _ok(0)).iterdir())
    cap = int(one_job * 3.5)  # room for three jobs
    rec = Recorder(tmp_path / "rec", cap, {})
    rec.scan()
    written = [rec.write(_pair(0), _ok(i)).name for i in range(1, 7)]
    on_disk = sorted(p.name for p in (tmp_path / "rec").iterdir())
    assert on_disk == written[-3:]
    assert rec.total_bytes <= cap
    # A new recorder on the same folder counts what is there and drops interrupted writes.
    (tmp_path / "rec" / ".partial-x").mkdir()
    again = Recorder(tmp_path / "rec", cap, {})
    again.scan()
    assert again.total_bytes == rec.total_bytes
    assert not (tmp_path / "rec" / ".partial-x").exists()


def test_broken_disk_is_logged_once_and_never_raises(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    rec = Recorder(blocker / "record", 10**9, {})
    with caplog.at_level(logging.ERROR, logger="vgripd.service.worker.recorder"):
        rec.start()
        for i in range(3):
            rec.submit(_pair(i), _ok(i))
        rec.close()
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1
    assert "not-a-dir" in errors[0].getMessage()


def test_submit_writes_on_the_recorder_thread(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, 10**9, {})
    rec.start()
    assert rec.submit(_pair(3), _ok(1))
    rec.close()
    assert len([p for p in tmp_path.iterdir() if p.name.endswith("-job000001")]) == 1


async def test_the_worker_process_records_the_same_files(tmp_path: Path) -> None:
    """Through the worker (images through shared memory, written there) a job's folder holds
    the same files with the same contents as the in-process recorder writes."""
    from vgripd.service.worker.process import WorkerClient

    config = config_from_dict({"record": {"enabled": True, "folder": str(tmp_path / "worker"),
                                          "max_mb": 50}})
    pair, result = _pair(4), _ok(9)
    client = WorkerClient(config)
    await client.start()
    try:
        await client.wait_ready()
        assert client.recorder.submit(pair, result)
    finally:
        await client.close()  # queued writes finish first
    rec = Recorder(tmp_path / "here", 10**9, config.model_dump(mode="json", exclude_none=True))
    rec.scan()
    here = rec.write(pair, result)
    (there,) = (tmp_path / "worker").iterdir()
    assert there.name.endswith("-job000009")
    names = sorted(p.name for p in here.iterdir())
    assert sorted(p.name for p in there.iterdir()) == names
    for name in names:
        if name.endswith(".png"):
            a = cv2.imread(str(here / name), cv2.IMREAD_UNCHANGED)
            b = cv2.imread(str(there / name), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(a, b)
        else:
            assert (here / name).read_text() == (there / name).read_text(), name


def test_modes_and_redaction_hold_under_a_wide_umask(tmp_path: Path) -> None:
    """The recorder sets its modes itself (0640 files, 0750 folders, also under a umask of 0)
    and writes no secret: the token and a camera URL's password are redacted."""
    token = "a-test-token-of-32-characters-xx"
    url = "rtsp://admin:pw-of-the-camera@cam.local/stream"
    old = os.umask(0)
    try:
        rec = Recorder(tmp_path / "rec", 10**8, {"status": {"token": token}, "about": {"u": url}})
        rec.scan()
        pair = ImagePair.of_views([np.zeros((8, 8), np.uint8)], 0, source=url)
        job = rec.write(pair, JobResult(job_id=1, status=Status.OK, message=f"from {url}"))
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "rec").stat().st_mode) == 0o750
    assert stat.S_IMODE(job.stat().st_mode) == 0o750
    for f in job.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o640, f.name
        assert b"pw-of-the-camera" not in f.read_bytes(), f.name
        assert token.encode() not in f.read_bytes(), f.name
    assert json.loads((job / "pair.json").read_text())["source"] == (
        "rtsp://<redacted>@cam.local/stream")
    assert tomllib.loads((job / "config.toml").read_text())["status"]["token"] == "<redacted>"
