"""Synthetic camera: rendered marks against OpenCV's projection of the 3D circles."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.cameras.replay import ReplayCamera, ReplayOptions
from drivers.cameras.synthetic import SyntheticCamera
from vgripd.config import (
    Config,
    DriverSection,
    IntrinsicsConfig,
    PoseConfig,
    config_from_dict,
)
from vgripd.errors import CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.types import ImagePair
from vgripd.vision import scene

DEMO = config_from_dict({})
QUIET = {"noise_std": 0, "blur_px": 0}
SAMPLES = Path(__file__).resolve().parents[3] / "config" / "samples"
SAMPLE_TRUTH = (SAMPLES / "truth.json").read_text(encoding="utf-8")


def make_camera(cfg: Config = DEMO, **options: Any) -> SyntheticCamera:
    cls = load_class(CAMERAS, "camera", "synthetic")
    section = DriverSection.model_validate({"type": "synthetic", **options})
    camera = cls(validate_options(cls, section, "camera"), cfg)
    assert isinstance(camera, SyntheticCamera)
    return camera


async def grab(cfg: Config = DEMO, n: int = 1, **options: Any) -> list[ImagePair]:
    camera = make_camera(cfg, **options)
    await camera.open()
    try:
        return [await camera.grab(30.0) for _ in range(n)]
    finally:
        await camera.close()


def opencv_projection(intr: IntrinsicsConfig, T_cam_obj: np.ndarray, pts: np.ndarray) -> np.ndarray:
    K = np.array([[intr.fx, intr.skew, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]])
    rvec = cv2.Rodrigues(T_cam_obj[:3, :3])[0]
    px, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, T_cam_obj[:3, 3], K, np.array(intr.dist))
    return px.reshape(-1, 2)


def cameras(pair: ImagePair) -> list[tuple[str, IntrinsicsConfig, np.ndarray, np.ndarray]]:
    """(side, intrinsics, T_cam_obj, image) for both cameras of the demo rig."""
    calib = DEMO.calibration
    assert calib is not None
    assert calib.right is not None
    assert pair.right is not None
    T_rl = scene.T_right_left(DEMO)
    T_left = pair.truth["T_cam_obj"]
    return [("left", calib.left, T_left, pair.left),
            ("right", calib.right, T_rl @ T_left, pair.right)]


async def test_rendered_marks_match_the_projected_discs() -> None:
    (pair,) = await grab(seed=3, **QUIET)
    theta = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    worst_vs_polygon = worst_vs_truth = 0.0
    for side, intr, T, image in cameras(pair):
        truth_px = pair.truth[f"pixels_{side}"]
        for f, truth in zip(DEMO.object.features, truth_px, strict=True):
            centre = np.array(f.xyz_mm)
            # Independent oracle: OpenCV projects the 3D rim; polygon moments give its centroid.
            rim = centre + 5.0 * np.c_[np.cos(theta), np.sin(theta), np.zeros_like(theta)]
            rim_px = opencv_projection(intr, T, rim)
            m = cv2.moments(rim_px.astype(np.float32).reshape(-1, 1, 2))
            oracle = np.array([m["m10"], m["m01"]]) / m["m00"]
            # The projected 3D centre reported as truth is what OpenCV projects too.
            np.testing.assert_allclose(truth, opencv_projection(intr, T, centre)[0], atol=1e-6)
            # Centroid of the rendered darkness over a window around the mark.
            x0, y0 = np.floor(oracle).astype(int) - 25
            patch = 190.0 - image[y0:y0 + 51, x0:x0 + 51].astype(float)
            mp = cv2.moments(patch)
            rendered = np.array([mp["m10"], mp["m01"]]) / mp["m00"] + (x0, y0)
            # Area matches too: (190 - 35) grey levels per fully covered pixel.
            assert abs(mp["m00"] / 155.0 - m["m00"]) < 0.01 * m["m00"]
            worst_vs_polygon = max(worst_vs_polygon, float(np.abs(rendered - oracle).max()))
            worst_vs_truth = max(worst_vs_truth, float(np.abs(rendered - truth).max()))
    print(f"max |rendered - polygon centroid| = {worst_vs_polygon:.4f} px, "
          f"max |rendered - projected centre| = {worst_vs_truth:.4f} px")
    assert worst_vs_polygon < 0.01
    assert worst_vs_truth < 0.03


async def test_same_seed_same_frames_other_seed_other_frames() -> None:
    a = await grab(n=2, seed=7)
    b = await grab(n=2, seed=7)
    c = await grab(n=1, seed=8)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.left, y.left)
        np.testing.assert_array_equal(x.right, y.right)
        np.testing.assert_array_equal(x.truth["T_base_obj"], y.truth["T_base_obj"])
    assert not np.array_equal(a[0].truth["T_base_obj"], a[1].truth["T_base_obj"])
    assert not np.array_equal(a[0].truth["T_base_obj"], c[0].truth["T_base_obj"])


async def test_random_poses_stay_within_the_ranges() -> None:
    ref = scene.T_base_obj_ref(DEMO)
    centroid = scene.object_points(DEMO).mean(axis=0)
    for pair in await grab(n=8, seed=11, max_shift_mm=4.0, max_tilt_deg=2.0, black=True):
        delta = pair.truth["T_base_obj"] @ np.linalg.inv(ref)
        angle = np.degrees(np.linalg.norm(cv2.Rodrigues(delta[:3, :3])[0]))
        assert angle <= 2.0 * np.sqrt(3) + 1e-9
        moved = (pair.truth["T_base_obj"] - ref) @ np.r_[centroid, 1.0]
        assert np.all(np.abs(moved[:3]) <= 4.0 + 1e-9)


async def test_fixed_pose_and_single_camera() -> None:
    pose = {"translation_mm": [610, 95, 12], "rotvec_rad": [0.02, -0.01, 0.3]}
    mono = DEMO.model_copy(update={"calibration": DEMO.calibration.model_copy(  # type: ignore[union-attr]
        update={"right": None, "stereo": None})})
    (pair,) = await grab(mono, pose=pose, seed=1)
    assert pair.right is None
    assert pair.truth["pixels_right"] is None
    expected = scene.matrix_from_pose(PoseConfig.model_validate(pose))
    np.testing.assert_allclose(pair.truth["T_base_obj"], expected)
    assert pair.left.shape == (1024, 1280)
    assert pair.left.dtype == np.uint8


def dark_blobs(image: np.ndarray) -> int:
    _, mask = cv2.threshold(image, 110, 255, cv2.THRESH_BINARY_INV)
    n, _ = cv2.connectedComponents(mask)
    return n - 1


async def test_faults() -> None:
    (clean,) = await grab(seed=5)
    assert dark_blobs(clean.left) == 6
    (dropped,) = await grab(seed=5, drop_features=["m2", "m5"])
    assert dark_blobs(dropped.left) == 4
    assert dropped.truth["dropped"] == ("m2", "m5")
    for name in ("m2", "m5"):
        i = dropped.truth["feature_names"].index(name)
        u, v = np.rint(dropped.truth["pixels_left"][i]).astype(int)
        assert dropped.left[v, u] > 150  # background where the mark would be
    (extra,) = await grab(seed=5, extra_blobs=3)
    assert dark_blobs(extra.left) == 9
    assert extra.truth["extra_blobs_px"].shape == (3, 2)
    (black,) = await grab(seed=5, black=True)
    assert not black.left.any()
    assert black.right is not None
    assert not black.right.any()


def test_only_circles_and_known_names() -> None:
    feats = [{"name": n, "xyz_mm": [i * 20, i * i, 0], "kind": "circle", "diameter_mm": 8}
             for i, n in enumerate("abc")]
    tag = {"name": "tag", "xyz_mm": [0, 40, 0], "kind": "aruco", "marker_id": 1, "size_mm": 20}
    cfg = config_from_dict({"object": {"features": [*feats, tag]}})
    with pytest.raises(ConfigError, match="object.features.3: .*'tag' is 'aruco'"):
        make_camera(cfg)
    with pytest.raises(ConfigError, match=r"drop_features: no such features \['m9'\]"):
        make_camera(drop_features=["m9"])
    with pytest.raises(ConfigError, match="camera: blur_px: Input should be less than"):
        make_camera(blur_px=100)


async def test_scene_problems_are_camera_errors() -> None:
    robot = DEMO.model_copy(update={"calibration": DEMO.calibration.model_copy(  # type: ignore[union-attr]
        update={"hand_eye": DEMO.calibration.hand_eye.model_copy(  # type: ignore[union-attr]
            update={"mounting": "robot", "T_base_camera": None,
                    "T_flange_camera": DEMO.calibration.hand_eye.T_base_camera})})})  # type: ignore[union-attr]
    camera = make_camera(robot)
    with pytest.raises(CameraError, match="flange pose"):
        await camera.open()
    # With the flange pose given, the camera sits at flange @ T_flange_camera.
    (pair,) = await grab(robot, seed=2, flange_pose={"translation_mm": [0, 0, 0]})
    np.testing.assert_array_equal(pair.T_base_flange, np.eye(4))
    # An object pose behind the camera.
    camera = make_camera(pose={"translation_mm": [600, 100, 2000]})
    await camera.open()
    try:
        with pytest.raises(CameraError, match="mark 'm1' in camera left: .*not in front"):
            await camera.grab(10.0)
    finally:
        await camera.close()


async def test_bundled_samples_are_current_renders() -> None:
    """config/samples (replayed as the example config does) equals a fresh render of its truth."""
    truth = json.loads(SAMPLE_TRUTH)
    replay = ReplayCamera(ReplayOptions(folder=str(SAMPLES), left_glob="left_*.png",
                                        right_glob="right_*.png"), DEMO)
    rendered = await grab(n=len(truth["frames"]), **truth["options"])
    await replay.open()
    try:
        for frame, fresh in zip(truth["frames"], rendered, strict=True):
            pair = await replay.grab(10.0)
            assert pair.meta["left_path"].endswith(frame["left"])
            assert pair.right is not None
            assert fresh.right is not None
            assert np.abs(pair.left.astype(int) - fresh.left).max() <= 1
            assert np.abs(pair.right.astype(int) - fresh.right).max() <= 1
            np.testing.assert_allclose(frame["T_base_obj"], fresh.truth["T_base_obj"], atol=1e-8)
            np.testing.assert_allclose(frame["pixels_left"], fresh.truth["pixels_left"], atol=1e-5)
    finally:
        await replay.close()


async def test_pallet_renders_every_instance_with_its_truth() -> None:
    """Several objects: each instance's marks are dark where OpenCV projects them from the
    instance's true pose (a dropped mark stays background), no two marks of different
    instances overlap, and touching footprints sit one pitch apart."""
    (pair,) = await grab(seed=4, pallet={"count": 5, "cols": 3, "gap_mm": 0.0},
                         drop_features=["1/m3"], **QUIET)
    poses = pair.truth["instances_T_base_obj"]
    assert poses.shape == (5, 4, 4)
    assert pair.truth["instances_dropped"] == ((), ("m3",), (), (), ())
    np.testing.assert_allclose(pair.truth["T_base_obj"], poses[0])
    calib = DEMO.calibration
    assert calib is not None
    assert calib.right is not None
    T_base_cam = scene.T_base_camera(DEMO)
    T_rl = scene.T_right_left(DEMO)
    assert T_rl is not None
    pts = scene.object_points(DEMO)
    marks = [pts @ T[:3, :3].T + T[:3, 3] for T in poses]
    for a in range(5):
        for b in range(a + 1, 5):
            gap = np.linalg.norm(marks[a][:, None] - marks[b][None], axis=2).min()
            assert gap > 10.0, (a, b, gap)
    for k, T in enumerate(poses):
        T_cam = np.linalg.inv(T_base_cam) @ T
        for intr, T_side, image in ((calib.left, T_cam, pair.left),
                                    (calib.right, T_rl @ T_cam, pair.right)):
            assert image is not None
            px = opencv_projection(intr, T_side, pts)
            for name, (x, y) in zip(pair.truth["feature_names"], px, strict=True):
                grey = int(image[int(round(y)), int(round(x))])
                if k == 1 and name == "m3":
                    assert grey > 150, (k, name, grey)
                else:
                    assert grey < 80, (k, name, grey)
    # Neighbours in a row: one footprint apart (marks' box + one diameter), give or take the
    # jitter (2 mm, 3 deg about the centroid).
    centroids = np.array([m.mean(axis=0) for m in marks])
    pitch_x = np.ptp(pts[:, 0]) + 10.0
    assert abs(np.linalg.norm(centroids[1] - centroids[0]) - pitch_x) < 12.0


async def test_explicit_instances_and_option_conflicts() -> None:
    ref = scene.T_base_obj_ref(DEMO)
    poses = [{"translation_mm": [600.0, 100.0, 10.0]},
             {"translation_mm": [600.0, 250.0, 10.0], "rotvec_rad": [0.0, 0.0, 0.5]}]
    (pair,) = await grab(instances=poses, **QUIET)
    got = pair.truth["instances_T_base_obj"]
    assert got.shape == (2, 4, 4)
    np.testing.assert_allclose(got[1][:3, 3], [600.0, 250.0, 10.0])
    assert not np.allclose(got[0], ref)  # rotvec 0 vs the reference's 0.05 about z
    with pytest.raises(ConfigError, match="one of pose, instances and pallet"):
        make_camera(pose=poses[0], pallet={"count": 2})
    with pytest.raises(ConfigError, match="instance '7' is not one of 0..1"):
        make_camera(instances=poses, drop_features=["7/m1"])


async def test_pallet_pitch_and_its_limits() -> None:
    (pair,) = await grab(pallet={"count": 3, "cols": 3, "pitch_mm": [150.0, 110.0],
                                 "jitter_mm": 0.0, "jitter_deg": 0.0}, **QUIET)
    x = pair.truth["instances_T_base_obj"][:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(np.diff(x, axis=0), axis=1), 150.0, atol=1e-9)
    with pytest.raises(ConfigError, match="gap_mm or pitch_mm"):
        make_camera(pallet={"count": 2, "gap_mm": 0.0, "pitch_mm": [150.0, 110.0]})
    with pytest.raises(ConfigError, match="must be positive"):
        make_camera(pallet={"count": 2, "pitch_mm": [0.0, 110.0]})
    # Marks cannot overlap: a pitch under the marks' spacing is refused at the grab.
    with pytest.raises(CameraError, match="cannot place the objects without overlapping"):
        await grab(pallet={"count": 2, "pitch_mm": [2.0, 2.0], "jitter_mm": 0.0,
                           "jitter_deg": 0.0})


# --- disc coverage: only the pixels the rim crosses are sampled ----------------------------

def _coverage_sampling_every_pixel(rim_px: np.ndarray, inside_px: np.ndarray, x0: int, y0: int,
                                   w: int, h: int, supersample: int) -> np.ndarray:
    """The coverage by sampling every pixel of the box, each with supersample^2 points: the
    plain method (and the renderer before it skipped the pixels inside and outside the rim)."""
    rel = rim_px - inside_px
    angles = np.arctan2(rel[:, 1], rel[:, 0])
    order = np.argsort(angles)
    angles, rel = angles[order], rel[order]
    angles = np.concatenate(([angles[-1] - 2 * np.pi], angles, [angles[0] + 2 * np.pi]))
    rel = np.concatenate((rel[-1:], rel, rel[:1]))
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    xs = (np.arange(x0, x0 + w)[:, None] + offsets).ravel() - inside_px[0]
    ys = (np.arange(y0, y0 + h)[:, None] + offsets).ravel() - inside_px[1]
    dx, dy = np.meshgrid(xs, ys)
    k = np.clip(np.searchsorted(angles, np.arctan2(dy, dx)), 1, len(angles) - 1)
    a, b = rel[k - 1], rel[k]
    cross = (b[..., 0] - a[..., 0]) * (dy - a[..., 1]) - (b[..., 1] - a[..., 1]) * (dx - a[..., 0])
    inside = (cross >= 0).astype(np.float64)
    return inside.reshape(h, supersample, w, supersample).mean(axis=(1, 3))


@pytest.mark.parametrize("seed", range(40))
def test_disc_coverage_is_bit_identical_to_sampling_every_pixel(seed: int) -> None:
    """Random perspective rims (ellipses under a random tilt, the centre off the middle, radii
    from sub-pixel to 60 px, centres on pixel centres and pixel edges) and supersampling 1-8:
    the same coverage, bit for bit, as sampling every pixel of the box."""
    from drivers.cameras.synthetic import RIM_VERTICES, disc_coverage

    rng = np.random.default_rng(seed)
    theta = np.linspace(0.0, 2 * np.pi, RIM_VERTICES, endpoint=False)
    radius = float(rng.choice([0.4, 1.5, rng.uniform(2, 60)]))
    tilt = rng.uniform(0.0, 1.4)
    rim = np.c_[radius * np.cos(theta), radius * np.cos(tilt) * np.sin(theta)]
    turn = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    centre = rng.integers(20, 200, 2) + rng.choice([0.0, 0.5, rng.uniform()], 2)
    # perspective: the projected centre is off the rim's middle, towards the near side
    shift = rng.uniform(-0.4, 0.4, 2) * radius * min(np.sin(tilt), np.cos(tilt))
    rim_px = rim @ rot.T + centre + shift
    inside_px = centre.astype(float)
    x0 = int(np.floor(rim_px[:, 0].min())) - 2
    y0 = int(np.floor(rim_px[:, 1].min())) - 2
    w = int(np.ceil(rim_px[:, 0].max())) + 3 - x0
    h = int(np.ceil(rim_px[:, 1].max())) + 3 - y0
    s = int(rng.integers(1, 9))
    got = disc_coverage(rim_px, inside_px, x0, y0, w, h, s)
    want = _coverage_sampling_every_pixel(rim_px, inside_px, x0, y0, w, h, s)
    assert got.shape == want.shape == (h, w)
    assert np.array_equal(got, want), np.argwhere(got != want)[:5]
    assert want.max() == 1.0 or radius < 2  # a disc of some pixels covers whole pixels
