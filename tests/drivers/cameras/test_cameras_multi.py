"""N-camera acquisition: the synthetic camera rendering one object through every camera of
config/samples/two_rigs_frame.toml (per-mark normals, back-face culling, concurrency), the
replay camera with one glob per camera, and ImagePair.views."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.cameras.replay import ReplayCamera
from drivers.cameras.synthetic import SyntheticCamera
from tests.conftest import REPO
from vgripd.config import DriverSection, config_from_dict, read_config_data
from vgripd.errors import CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.types import ImagePair
from vgripd.vision import scene

DATA = read_config_data(REPO / "config" / "samples" / "two_rigs_frame.toml")
CELL = config_from_dict(DATA)


def make(type_: str, cfg: Any = CELL, **options: Any) -> Any:
    cls = load_class(CAMERAS, "camera", type_)
    section = DriverSection.model_validate({"type": type_, **options})
    return cls(validate_options(cls, section, "camera"), cfg)


async def test_synthetic_renders_every_camera_and_culls_the_far_face() -> None:
    camera = make("synthetic", seed=3, noise_std=0, blur_px=0)
    assert isinstance(camera, SyntheticCamera)
    await camera.open()
    try:
        pair = await camera.grab(30.0)
        again = make("synthetic", seed=3, noise_std=0, blur_px=0)
        await again.open()
        try:
            twin = await again.grab(30.0)
        finally:
            await again.close()
    finally:
        await camera.close()
    assert len(pair.views) == 4
    assert pair.left is pair.views[0]
    assert pair.right is pair.views[1]
    # The same seed renders the same images, whatever order the camera threads ran in.
    assert all(np.array_equal(a, b) for a, b in zip(pair.views, twin.views, strict=True))
    px = pair.truth["pixels_views"]
    T_base_obj = pair.truth["T_base_obj"]
    model = scene.object_points(CELL)
    Ts = scene.T_base_cameras(CELL)
    for j, cam in enumerate(scene.multi_camera_models(CELL)):
        T = np.linalg.inv(Ts[j]) @ T_base_obj
        K, dist = cam.to_opencv()
        ref, _ = cv2.projectPoints(model, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)
        seen = ~np.isnan(px[:, j, 0])
        front = j < 2  # the north rig faces the marks f1..f8
        assert seen.tolist() == [front] * 8 + [not front] * 8
        # The truth is OpenCV's projection of the mark centres, and each mark is drawn there.
        np.testing.assert_allclose(px[seen, j], ref.reshape(-1, 2)[seen], atol=1e-6)
        image = pair.views[j]
        for u, v in px[seen, j]:
            assert image[int(round(v)), int(round(u))] < 60
        # Where the hidden marks would project, the image is background.
        for u, v in ref.reshape(-1, 2)[~seen]:
            if 0 <= u < cam.width and 0 <= v < cam.height:
                assert image[int(round(v)), int(round(u))] > 150


async def test_replay_reads_one_glob_per_camera_in_camera_order(tmp_path: Path) -> None:
    names = ["north_left", "north_right", "south_left", "south_right"]
    for k in range(3):
        for j, name in enumerate(names):
            img = np.full((1024, 1280), 10 * k + j, np.uint8)
            assert cv2.imwrite(str(tmp_path / f"{name}_{k}.png"), img)
    camera = make("replay", folder=str(tmp_path), globs=[f"{n}_*.png" for n in names])
    assert isinstance(camera, ReplayCamera)
    await camera.open()
    try:
        for k in range(3):
            pair = await camera.grab(5.0)
            assert [int(v[0, 0]) for v in pair.views] == [10 * k + j for j in range(4)]
            assert pair.meta["paths"] == [str(tmp_path / f"{n}_{k}.png") for n in names]
        with pytest.raises(CameraError, match="no more images"):
            await camera.grab(5.0)
    finally:
        await camera.close()


async def test_replay_globs_must_match_the_cameras_and_pair_up(tmp_path: Path) -> None:
    for k in range(2):
        for name in ("a", "b", "c"):
            cv2.imwrite(str(tmp_path / f"{name}_{k}.png"), np.zeros((4, 4), np.uint8))
    (tmp_path / "c_1.png").unlink()
    camera = make("replay", folder=str(tmp_path), globs=["a_*.png", "b_*.png", "c_*.png"])
    with pytest.raises(CameraError, match="c_1|a_1"):
        await camera.open()
    two = make("replay", folder=str(tmp_path), globs=["a_*.png", "b_*.png"])
    with pytest.raises(CameraError, match="2 globs for the 4 cameras of calibration.cameras"):
        await two.open()
    with pytest.raises(ConfigError, match="give one of glob"):
        make("replay", folder=str(tmp_path), glob="a_*.png", globs=["a_*.png", "b_*.png"])
    with pytest.raises(ConfigError, match="2 to 8"):
        make("replay", folder=str(tmp_path), globs=["a_*.png"])


def test_image_pair_views_default_and_consistency() -> None:
    a, b, c = (np.zeros((2, 2), np.uint8) for _ in range(3))
    assert ImagePair(left=a, right=None, t_mono_ns=0).views == (a,)
    assert ImagePair(left=a, right=b, t_mono_ns=0).views == (a, b)
    three = ImagePair.of_views([a, b, c], 5, source="x")
    assert three.left is a
    assert three.right is b
    assert three.views[2] is c
    with pytest.raises(ValueError, match="views\\[0\\] and views\\[1\\]"):
        ImagePair(left=a, right=c, t_mono_ns=0, views=(a, b, c))
    with pytest.raises(ValueError, match="no images"):
        ImagePair.of_views([], 0)


async def test_a_mark_without_normal_is_seen_from_both_sides() -> None:
    data = copy.deepcopy(DATA)
    for f in data["object"]["features"]:
        f.pop("normal")
    camera = make("synthetic", cfg=config_from_dict(data), supersample=1)
    await camera.open()
    try:
        pair = await camera.grab(30.0)
    finally:
        await camera.close()
    seen = ~np.isnan(pair.truth["pixels_views"][..., 0])
    assert seen.all()  # no normals: nothing culled (a frame with see-through marks)


def _write(folder: Path, name: str, frames: int, value: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(frames):
        assert cv2.imwrite(str(folder / f"{name}_{k}.png"), np.full((8, 8), value + k, np.uint8))


async def test_multi_driver_grabs_its_drivers_together_in_order(tmp_path: Path) -> None:
    _write(tmp_path / "a", "img", 2, 10)
    _write(tmp_path / "pair", "l", 2, 20)
    _write(tmp_path / "pair", "r", 2, 30)
    _write(tmp_path / "d", "img", 2, 40)
    camera = make("multi", cameras=[
        {"type": "replay", "folder": str(tmp_path / "a"), "glob": "img_*.png"},
        {"type": "replay", "folder": str(tmp_path / "pair"), "left_glob": "l_*.png",
         "right_glob": "r_*.png"},  # one driver, two images (a synchronised pair)
        {"type": "replay", "folder": str(tmp_path / "d"), "glob": "img_*.png"},
    ])
    await camera.open()
    try:
        for k in range(2):
            pair = await camera.grab(5.0)
            assert [int(v[0, 0]) for v in pair.views] == [10 + k, 20 + k, 30 + k, 40 + k]
            assert len(pair.meta["cameras"]) == 3
        with pytest.raises(CameraError, match=r"camera.cameras.0 \(replay\): replay: no more"):
            await camera.grab(5.0)
    finally:
        await camera.close()


async def test_multi_driver_refuses_what_cannot_work(tmp_path: Path) -> None:
    _write(tmp_path / "a", "img", 1, 10)
    one = {"type": "replay", "folder": str(tmp_path / "a"), "glob": "img_*.png"}
    camera = make("multi", cameras=[one, one])
    await camera.open()
    try:
        with pytest.raises(CameraError, match="delivered 2 images for the 4 cameras"):
            await camera.grab(5.0)
    finally:
        await camera.close()
    with pytest.raises(ConfigError, match=r"camera.cameras.1: .*glob"):
        make("multi", cameras=[one, {"type": "replay", "folder": "x"}])
    with pytest.raises(ConfigError, match="unknown camera.cameras.0 type 'nope'"):
        make("multi", cameras=[{"type": "nope"}])
    with pytest.raises(ConfigError, match="cannot hold another"):
        make("multi", cameras=[{"type": "multi", "cameras": [one]}])
    missing = make("multi", cameras=[one, {**one, "folder": str(tmp_path / "gone")}])
    with pytest.raises(CameraError, match=r"camera.cameras.1 \(replay\): replay: folder"):
        await missing.open()


async def test_multi_driver_names_the_calibrated_camera_that_failed(tmp_path: Path) -> None:
    """One driver of several fails: the error names the cameras of calibration.cameras whose
    images it stands for, a single camera or a synchronised pair."""
    _write(tmp_path / "a", "img", 3, 10)
    _write(tmp_path / "pair", "l", 2, 20)
    _write(tmp_path / "pair", "r", 2, 30)
    _write(tmp_path / "d", "img", 3, 40)
    camera = make("multi", cameras=[
        {"type": "replay", "folder": str(tmp_path / "a"), "glob": "img_*.png"},
        {"type": "replay", "folder": str(tmp_path / "pair"), "left_glob": "l_*.png",
         "right_glob": "r_*.png"},
        {"type": "replay", "folder": str(tmp_path / "d"), "glob": "img_*.png"},
    ])
    await camera.open()
    try:
        for _ in range(2):
            await camera.grab(5.0)
        with pytest.raises(CameraError) as err:
            await camera.grab(5.0)
    finally:
        await camera.close()
    assert str(err.value).startswith(
        "camera.cameras.1 (replay, cameras north_right, south_left): replay: no more")
    _write(tmp_path / "e", "img", 1, 50)
    camera = make("multi", cameras=[
        {"type": "replay", "folder": str(tmp_path / "a"), "glob": "img_*.png"},
        {"type": "replay", "folder": str(tmp_path / "a"), "glob": "img_*.png"},
        {"type": "replay", "folder": str(tmp_path / "a"), "glob": "img_*.png"},
        {"type": "replay", "folder": str(tmp_path / "e"), "glob": "img_*.png"},
    ])
    await camera.open()
    try:
        await camera.grab(5.0)
        with pytest.raises(CameraError, match=r"^camera.cameras.3 \(replay, camera south_right\)"):
            await camera.grab(5.0)
    finally:
        await camera.close()
