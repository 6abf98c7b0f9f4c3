"""Replay camera over real image files written with cv2.imwrite."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.cameras.replay import ReplayCamera
from vgripd.config import DriverSection, config_from_dict
from vgripd.errors import CameraError, ConfigError
from vgripd.imagefiles import list_frames, natural_key
from vgripd.registry import CAMERAS, load_class, validate_options

CFG = config_from_dict({})


def make_camera(**options: object) -> ReplayCamera:
    """Through the registry, as the daemon builds it."""
    cls = load_class(CAMERAS, "camera", "replay")
    section = DriverSection.model_validate({"type": "replay", **options})
    camera = cls(validate_options(cls, section, "camera"), CFG)
    assert isinstance(camera, ReplayCamera)
    return camera


def frame(value: int, shape: tuple[int, int] = (24, 32)) -> np.ndarray:
    img = np.full(shape, value, np.uint8)
    img[0, 0] = 255 - value
    return img


def write_pairs(folder: Path, n: int, start: int = 0) -> None:
    for i in range(start, start + n):
        cv2.imwrite(str(folder / f"left_{i}.png"), frame(i))
        cv2.imwrite(str(folder / f"right_{i}.png"), frame(100 + i))


async def test_pairs_in_natural_order(tmp_path: Path) -> None:
    write_pairs(tmp_path, 12)  # left_2 must come before left_10
    camera = make_camera(folder=str(tmp_path), left_glob="left_*.png", right_glob="right_*.png")
    await camera.open()
    try:
        for i in range(12):
            pair = await camera.grab(5.0)
            assert pair.is_stereo
            assert pair.right is not None
            np.testing.assert_array_equal(pair.left, frame(i))
            np.testing.assert_array_equal(pair.right, frame(100 + i))
            assert pair.meta["frame"] == i
            assert pair.meta["left_path"].endswith(f"left_{i}.png")
            assert pair.t_mono_ns > 0
            assert pair.T_base_flange is None
        with pytest.raises(CameraError, match="no more images"):
            await camera.grab(5.0)
    finally:
        await camera.close()


async def test_single_images_loop_and_colour(tmp_path: Path) -> None:
    for i in range(3):
        img = np.zeros((8, 8, 3), np.uint8)
        img[..., 2] = 50 * i + 10  # red channel
        cv2.imwrite(str(tmp_path / f"cam{i}.png"), img)
    camera = make_camera(folder=str(tmp_path), glob="cam*.png", loop=True, grayscale=False)
    await camera.open()
    try:
        reds = []
        for _ in range(7):
            pair = await camera.grab(5.0)
            assert pair.right is None
            assert pair.left.shape == (8, 8, 3)
            reds.append(int(pair.left[0, 0, 2]))
        assert reds == [10, 60, 110, 10, 60, 110, 10]
    finally:
        await camera.close()


async def test_mismatched_counts_fail_at_open(tmp_path: Path) -> None:
    write_pairs(tmp_path, 3)
    (tmp_path / "right_2.png").unlink()
    camera = make_camera(folder=str(tmp_path), left_glob="left_*.png", right_glob="right_*.png")
    with pytest.raises(CameraError, match="3 left images .* but 2 right images"):
        await camera.open()
    await camera.close()


async def test_no_match_and_missing_folder(tmp_path: Path) -> None:
    camera = make_camera(folder=str(tmp_path), glob="*.png")
    with pytest.raises(CameraError, match=r"no image files match '\*\.png' in /"):
        await camera.open()
    camera = make_camera(folder=str(tmp_path / "nope"), glob="*.png")
    with pytest.raises(CameraError, match="nope does not exist"):
        await camera.open()


async def test_missing_and_corrupt_files_are_camera_errors(tmp_path: Path) -> None:
    write_pairs(tmp_path, 3)
    (tmp_path / "right_1.png").write_bytes(b"\x89PNG\r\n\x1a\nthis is not an image")
    camera = make_camera(folder=str(tmp_path), left_glob="left_*.png", right_glob="right_*.png")
    await camera.open()
    try:
        (tmp_path / "left_2.png").unlink()  # vanishes after open()
        await camera.grab(5.0)
        with pytest.raises(CameraError, match=r"right_1\.png \(corrupt"):
            await camera.grab(5.0)
        with pytest.raises(CameraError, match=r"left_2\.png is missing"):
            await camera.grab(5.0)
    finally:
        await camera.close()


async def test_flange_pose_file(tmp_path: Path) -> None:
    write_pairs(tmp_path, 3)
    T2 = np.eye(4)
    T2[:3, :3] = Rotation.from_euler("zyx", [30, -10, 170], degrees=True).as_matrix()
    T2[:3, 3] = [-100.5, 20, 900]
    (tmp_path / "flange.txt").write_text(
        "# x y z rx ry rz (mm, rad) or 16 numbers\n"
        "400, 0, 600, 0, 0, 0\n\n"
        "450 10 620 0.1 -0.2 3.0\n"
        + " ".join(repr(float(v)) for v in T2.ravel()) + "\n"
    )
    camera = make_camera(folder=str(tmp_path), left_glob="left_*.png", right_glob="right_*.png",
                         flange_poses="flange.txt")
    await camera.open()
    try:
        poses = [(await camera.grab(5.0)).T_base_flange for _ in range(3)]
    finally:
        await camera.close()
    assert poses[0] is not None
    assert poses[1] is not None
    np.testing.assert_allclose(poses[0], np.r_[np.c_[np.eye(3), [400, 0, 600]], [[0, 0, 0, 1]]])
    np.testing.assert_allclose(poses[1][:3, :3],
                               Rotation.from_rotvec([0.1, -0.2, 3.0]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(poses[1][:3, 3], [450, 10, 620])
    np.testing.assert_allclose(poses[2], T2, atol=1e-12)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("1 2 3 0 0 0\n1 2 3 0 0\n3 4 5 0 0 0\n", "flange.txt line 2: expected 6 or 16 numbers, got 5"),
        ("1 2 3 0 0 0\n1 2 3 0 0 x\n3 4 5 0 0 0\n", "flange.txt line 2: could not convert"),
        ("1 2 3 0 0 0\n" + " ".join(["2"] * 16) + "\n3 4 5 0 0 0\n", "flange.txt line 2: .*matrix"),
        ("1 2 3 0 0 0\n", r"flange.txt has 1 poses for 3 frames"),
    ],
)
async def test_bad_flange_pose_file(tmp_path: Path, content: str, message: str) -> None:
    write_pairs(tmp_path, 3)
    (tmp_path / "flange.txt").write_text(content)
    camera = make_camera(folder=str(tmp_path), left_glob="left_*.png", right_glob="right_*.png",
                         flange_poses="flange.txt")
    with pytest.raises(CameraError, match=message):
        await camera.open()


def test_options_are_validated_with_their_path() -> None:
    for bad in ({"glob": "*.png", "left_glob": "l*.png", "right_glob": "r*.png"},
                {"left_glob": "l*.png"}, {}):
        with pytest.raises(ConfigError, match="camera: <root>: Value error"):
            make_camera(**bad)
    with pytest.raises(ConfigError, match="camera: lop: Extra inputs are not permitted"):
        make_camera(glob="*.png", lop=True)


async def test_grab_before_open_is_a_camera_error() -> None:
    camera = make_camera(glob="*.png")
    with pytest.raises(CameraError, match="not open"):
        await camera.grab(1.0)


def test_natural_sort() -> None:
    names = ["a10.png", "a2.png", "a1.png", "b.png", "a02b.png"]
    assert [p.name for p in sorted(map(Path, names), key=natural_key)] == [
        "a1.png", "a2.png", "a02b.png", "a10.png", "b.png"]


# ------------------------------------------------------------- listing and pairing


def names(paths: list[Path] | None) -> list[str]:
    assert paths is not None
    return [p.name for p in paths]


def test_pairs_by_the_wildcard_part_of_the_name(tmp_path: Path) -> None:
    """``*_left.png`` / ``*_right.png``: scene_007_left pairs with scene_007_right; files of
    other kinds that the patterns match are skipped, not read."""
    for i in (0, 1, 2, 10):
        cv2.imwrite(str(tmp_path / f"scene_{i:03d}_left.png"), frame(i))
        cv2.imwrite(str(tmp_path / f"scene_{i:03d}_right.png"), frame(100 + i))
    (tmp_path / "truth.json").write_text("{}")
    (tmp_path / "notes_left.txt").write_text("not an image")
    frames = list_frames(tmp_path, left_glob="*_left*", right_glob="*_right*")
    assert frames.paired_by == "name"
    assert names(frames.left) == [f"scene_{i:03d}_left.png" for i in (0, 1, 2, 10)]
    assert names(frames.right) == [f"scene_{i:03d}_right.png" for i in (0, 1, 2, 10)]
    assert names(frames.skipped) == ["notes_left.txt"]
    single = list_frames(tmp_path, glob="*")
    assert len(single) == 8
    assert names(single.skipped) == ["notes_left.txt", "truth.json"]


def test_a_missing_partner_is_named_instead_of_shifting_the_pairs(tmp_path: Path) -> None:
    write_pairs(tmp_path, 5)
    (tmp_path / "right_1.png").unlink()
    (tmp_path / "right_9.png").write_bytes((tmp_path / "right_0.png").read_bytes())
    with pytest.raises(CameraError, match=(
            r"unpaired files in .* \(left_glob 'left_\*\.png', right_glob 'right_\*\.png'\): "
            r"no right image for left_1\.png; no left image for right_9\.png")):
        list_frames(tmp_path, left_glob="left_*.png", right_glob="right_*.png")


def test_names_without_a_common_part_pair_by_position(tmp_path: Path) -> None:
    (tmp_path / "cam0").mkdir()
    (tmp_path / "cam1").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "cam0" / f"t{1000 + i}.png"), frame(i))
        cv2.imwrite(str(tmp_path / "cam1" / f"t{2000 + i}.png"), frame(100 + i))
    frames = list_frames(tmp_path, left_glob="cam0/*.png", right_glob="cam1/*.png")
    assert frames.paired_by == "position"
    assert names(frames.right) == ["t2000.png", "t2001.png", "t2002.png"]
    (tmp_path / "cam1" / "t2002.png").unlink()
    with pytest.raises(CameraError, match="3 left images .* but 2 right images .* sorted position"):
        list_frames(tmp_path, left_glob="cam0/*.png", right_glob="cam1/*.png")


async def test_stereo_layout_with_only_left_images_is_refused_at_open(tmp_path: Path) -> None:
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"left_{i}.png"), frame(i))
    (tmp_path / "right_notes.txt").write_text("no images here")
    camera = make_camera(folder=str(tmp_path), left_glob="left_*.png", right_glob="right_*")
    with pytest.raises(CameraError, match=(
            r"stereo layout but no image files match right_glob 'right_\*' in .* \(3 match "
            r"left_glob 'left_\*\.png'\): no pairs to replay")):
        await camera.open()
    await camera.close()
