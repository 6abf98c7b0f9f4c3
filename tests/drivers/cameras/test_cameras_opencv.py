"""OpenCV VideoCapture camera: real video files written with cv2.VideoWriter, real open failures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.cameras.opencv import OpenCVCamera
from vgripd.config import DriverSection, config_from_dict
from vgripd.errors import CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class, validate_options

CFG = config_from_dict({})


def make_camera(**options: Any) -> OpenCVCamera:
    cls = load_class(CAMERAS, "camera", "opencv")
    section = DriverSection.model_validate({"type": "opencv", **options})
    camera = cls(validate_options(cls, section, "camera"), CFG)
    assert isinstance(camera, OpenCVCamera)
    return camera


def write_video(path: Path, levels: list[int], fourcc: str = "FFV1") -> None:
    """A lossless grey video: frame i is uniform at levels[i] with a bright square at x = 8 i."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (96, 64), isColor=False)
    assert writer.isOpened(), f"{fourcc} writer not available in this OpenCV build"
    for i, level in enumerate(levels):
        frame = np.full((64, 96), level, np.uint8)
        frame[8:16, 8 * i:8 * i + 8] = 255
        writer.write(frame)
    writer.release()


async def test_reads_a_stereo_pair_of_video_files(tmp_path: Path) -> None:
    write_video(tmp_path / "left.avi", [10, 50, 90])
    write_video(tmp_path / "right.avi", [20, 60, 100], fourcc="MJPG")
    camera = make_camera(left=str(tmp_path / "left.avi"), right=str(tmp_path / "right.avi"))
    await camera.open()
    try:
        for i, (lo, ro) in enumerate([(10, 20), (50, 60), (90, 100)]):
            pair = await camera.grab(10.0)
            assert pair.right is not None
            assert pair.left.shape == (64, 96)
            assert pair.left.dtype == np.uint8
            assert pair.left[40, 50] == lo  # FFV1 is lossless
            assert abs(int(pair.right[40, 50]) - ro) <= 2  # MJPG is not
            assert pair.left[12, 8 * i + 4] == 255
            assert pair.meta["frame"] == i + 1
            assert "left.avi" in pair.source
        with pytest.raises(CameraError, match="no frame from .*left.avi.*end of stream"):
            await camera.grab(10.0)
    finally:
        await camera.close()


async def test_discard_frames_and_colour(tmp_path: Path) -> None:
    write_video(tmp_path / "v.avi", [0, 30, 60, 90, 120])
    camera = make_camera(left=str(tmp_path / "v.avi"), discard_frames=1, grayscale=False)
    await camera.open()
    try:
        first = await camera.grab(10.0)
        second = await camera.grab(10.0)
    finally:
        await camera.close()
    assert first.right is None
    assert first.left.shape == (64, 96, 3)
    assert (first.left[40, 50, 0], second.left[40, 50, 0]) == (30, 90)


async def test_open_failure_names_the_device(tmp_path: Path) -> None:
    missing = str(tmp_path / "no_such_video.avi")
    camera = make_camera(left=missing)
    with pytest.raises(CameraError, match="cannot open capture device '.*no_such_video.avi'"):
        await camera.open()
    camera = make_camera(left=97, backend="v4l2")  # no /dev/video97 on a test machine
    with pytest.raises(CameraError, match="cannot open capture device 97 \\(v4l2\\)"):
        await camera.open()


async def test_second_device_failure_releases_the_first(tmp_path: Path) -> None:
    write_video(tmp_path / "ok.avi", [1, 2])
    camera = make_camera(left=str(tmp_path / "ok.avi"), right=str(tmp_path / "gone.avi"))
    with pytest.raises(CameraError, match="gone.avi"):
        await camera.open()
    with pytest.raises(CameraError, match="not open"):
        await camera.grab(1.0)


def test_options() -> None:
    with pytest.raises(ConfigError, match="camera: left: Field required"):
        make_camera()
    with pytest.raises(ConfigError, match="camera: backend: Input should be"):
        make_camera(left=0, backend="directshow")
