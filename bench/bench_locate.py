"""Locate latency and accuracy: vgripd's pipeline against a plain OpenCV peer, same images.

A 5 MP stereo cell (2x 2448x2048 8-bit, f = 3500 px, 200 mm baseline toed in to meet at
840 mm, the demo plate with six 10 mm dark marks ~42 px across) is imaged with blur 0.8 px,
noise 2 grey levels and a 30 % lighting gradient, at random poses (+-20 mm, +-8 deg), by two
renderers:

* independent (the headline): ``bench/render_independent.py`` -- OpenCV's ``projectPoints`` and
  distortion, supersampled rasterisation, no vgripd code; the truth is the pose it drew;
* vgripd's own model: the synthetic camera driver, which projects through
  ``vgripd.geometry.camera_model`` -- the model the pipeline's circle-centre correction uses, so
  a modelling error common to both would not show there.

Both renderers take the cell's numbers from the same place (``render_independent``'s
``CAMERAS``, ``T_RIGHT_LEFT``, ``T_BASE_CAMERA`` and the plate in ``config/example.toml``); vgripd
gets them as its calibration. Each pair is located from memory by

* vgripd: ``Pipeline.process`` (features at 1/4 resolution + full-resolution refinement,
  epipolar matching, model correspondence by distances, robust Horn, circle-centre correction,
  offset, vendor, gates);
* the peer: adaptive (local mean) threshold + ``findContours`` + contour moments on the full image,
  ``cv2.undistortPoints``, epipolar nearest neighbour with the essential matrix,
  ``cv2.triangulatePoints``, model correspondence by sorted distance signatures, Kabsch (SVD).

Poses are compared with the truth (object pose in the base frame) by
``vgripd.geometry.transforms.pose_error``. Prints latency, RMS / median / max errors and the
markdown section for bench/RESULTS.md (single-camera mode is not benchmarked: circle marks carry
no identity, so vgripd locates them in stereo only).

    .venv/bin/python bench/bench_locate.py [--pairs 100] [--print-only]
"""

from __future__ import annotations

import asyncio
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import harness  # noqa: E402
from bench import render_independent as indep  # noqa: E402
from drivers.cameras.synthetic import SyntheticCamera, SyntheticOptions  # noqa: E402
from vgripd.config import Config, config_from_dict  # noqa: E402
from vgripd.geometry.transforms import make_transform, pose_error  # noqa: E402
from vgripd.types import ImagePair  # noqa: E402
from vgripd.vision import pipeline as pipeline_module  # noqa: E402
from vgripd.vision import scene  # noqa: E402
from vgripd.vision.pipeline import Pipeline  # noqa: E402

W, H, F = indep.W, indep.H, indep.F
SECTION = "Locate latency and accuracy"


def cell_config(plate: indep.Plate) -> Config:
    """vgripd's configuration of the benchmark cell: the renderer's numbers as calibration."""
    return config_from_dict({
        "camera": {"type": "synthetic"},
        "calibration": {
            "left": indep.CAMERAS["left"],
            "right": indep.CAMERAS["right"],
            "stereo": {"T_right_left": indep.T_RIGHT_LEFT},
            "hand_eye": {"mounting": "fixed", "T_base_camera": indep.T_BASE_CAMERA},
        },
        **plate.toml,
        "vision": {"working_distance_mm": [600.0, 1200.0], "downscale": 4},
        "limits": {"max_translation_mm": 100.0, "max_rotation_deg": 20.0},
    })


Images = Iterator[tuple[ImagePair, np.ndarray]]  # (pair, truth T_base_obj), made one at a time


def render_independent(plate: indep.Plate, n: int, seed: int) -> Images:
    cell = indep.Cell(plate)
    rng = np.random.default_rng(seed)
    for _ in range(n):
        T_base_obj = cell.random_pose(rng)
        left, right = cell.render_pair(T_base_obj, rng)
        yield ImagePair(left=left, right=right, t_mono_ns=time.monotonic_ns(),
                        source="render_independent"), T_base_obj


def render_vgripd(config: Config, n: int, seed: int, supersample: int) -> Images:
    options = SyntheticOptions(seed=seed, max_shift_mm=indep.MAX_SHIFT_MM,
                               max_tilt_deg=indep.MAX_TILT_DEG, blur_px=indep.BLUR_PX,
                               noise_std=indep.NOISE_STD, gradient=indep.GRADIENT,
                               supersample=supersample)
    camera = SyntheticCamera(options, config)
    loop = asyncio.new_event_loop()
    try:
        loop.run_until_complete(camera.open())
        for _ in range(n):
            pair = loop.run_until_complete(camera.grab(60.0))
            yield pair, pair.truth["T_base_obj"]
        loop.run_until_complete(camera.close())
    finally:
        loop.close()


class Peer:
    """The plain OpenCV pipeline a practitioner would write first."""

    def __init__(self, config: Config) -> None:
        left, right = scene.camera_models(config)
        assert right is not None
        self.K1, self.d1 = left.K, left.dist_array
        self.K2, self.d2 = right.K, right.dist_array
        T = scene.T_right_left(config)
        assert T is not None
        R, t = T[:3, :3], T[:3, 3]
        self.P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
        self.P2 = np.hstack([R, t[:, None]])
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        self.E = tx @ R  # normalised coordinates: x2^T E x1 = 0
        self.model = scene.object_points(config)
        self.T_base_camera = scene.T_base_camera(config)
        d = np.linalg.norm(self.model[:, None] - self.model[None], axis=2)
        self.signature = np.sort(d, axis=1)[:, 1:]
        self.area = (np.pi / 4 * (F * 10.0 / 1200.0) ** 2, np.pi / 4 * (F * 10.0 / 600.0) ** 2)
        self.block = int(2 * F * 10.0 / 600.0) | 1  # twice the largest mark (px), odd

    def centroids(self, gray: np.ndarray) -> np.ndarray:
        # Adaptive (local mean) threshold: a global Otsu level fails under the lighting gradient.
        mask = cv2.adaptiveThreshold(gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV,
                                     self.block, 20)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        pts = []
        for c in contours:
            m = cv2.moments(c)
            if not self.area[0] <= m["m00"] <= self.area[1]:
                continue
            perimeter = cv2.arcLength(c, True)
            if 4 * np.pi * m["m00"] / perimeter**2 < 0.7:
                continue
            pts.append((m["m10"] / m["m00"], m["m01"] / m["m00"]))
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def locate(self, pair: ImagePair) -> np.ndarray | None:
        assert pair.right is not None
        pl, pr = self.centroids(pair.left), self.centroids(pair.right)
        if len(pl) < 3 or len(pr) < 3:
            return None
        nl = cv2.undistortPoints(pl.reshape(-1, 1, 2), self.K1, self.d1).reshape(-1, 2)
        nr = cv2.undistortPoints(pr.reshape(-1, 1, 2), self.K2, self.d2).reshape(-1, 2)
        lines = np.c_[nl, np.ones(len(nl))] @ self.E.T  # epipolar lines in the right image
        dist = np.abs(lines @ np.c_[nr, np.ones(len(nr))].T) / np.hypot(lines[:, :1], lines[:, 1:2])
        j = dist.argmin(axis=1)
        X = cv2.triangulatePoints(self.P1, self.P2, nl.T, nr[j].T)
        pts = (X[:3] / X[3]).T
        d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
        if len(pts) != len(self.model):
            return None
        sig = np.sort(d, axis=1)[:, 1:]
        assign = np.linalg.norm(self.signature[:, None] - sig[None], axis=2).argmin(axis=1)
        a, b = self.model, pts[assign]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        R = vt.T @ np.diag([1, 1, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        return self.T_base_camera @ make_transform(R, cb - R @ ca)


Row = tuple[float, float, float]  # latency ms, translation error mm, rotation error deg


def run(pipeline: Pipeline, peer: Peer, images: Images, ablation: bool = False
        ) -> tuple[dict[str, list[Row]], dict[str, int]]:
    """Both pipelines on every pair in turn; per-pair rows and vgripd's status counts.

    ``ablation``: also vgripd with its circle-centre correction switched off (the bias it
    predicts replaced by zero), to show what the correction is worth against this truth.
    """
    rows: dict[str, list[Row]] = {"vgripd": [], "opencv peer": []}
    if ablation:
        rows[NO_CORRECTION] = []
    statuses: dict[str, int] = {}

    def vgripd(name: str, pair: ImagePair, truth: np.ndarray, i: int) -> None:
        t = time.perf_counter()
        result = pipeline.process(pair, i)
        dt = (time.perf_counter() - t) * 1e3
        if name == "vgripd":
            statuses[result.status.name] = statuses.get(result.status.name, 0) + 1
        T = result.T_base_obj
        rows[name].append((dt, *(pose_error(T, truth) if T is not None else (np.inf, np.inf))))

    for i, (pair, truth) in enumerate(images):
        vgripd("vgripd", pair, truth, i)
        t = time.perf_counter()
        T_peer = peer.locate(pair)
        dt = (time.perf_counter() - t) * 1e3
        rows["opencv peer"].append((dt, *(pose_error(T_peer, truth) if T_peer is not None
                                          else (np.inf, np.inf))))
        if ablation:
            saved = pipeline_module._circle_centre_bias
            pipeline_module._circle_centre_bias = _no_bias
            try:
                vgripd(NO_CORRECTION, pair, truth, i)
            finally:
                pipeline_module._circle_centre_bias = saved
    return rows, statuses


NO_CORRECTION = "vgripd, circle-centre correction off"


def _no_bias(camera: object, T_cam_obj: np.ndarray, centres: np.ndarray,
             diameters: np.ndarray) -> np.ndarray:
    return np.zeros((len(centres), 2))


def collect(images: Images, truths: list[np.ndarray]) -> Images:
    for pair, truth in images:
        truths.append(truth)
        yield pair, truth


def bias_check(plate: indep.Plate, config: Config, poses: int, seed: int
               ) -> tuple[float, float, float, float]:
    """vgripd's predicted circle-centre bias against the independent renderer's geometry.

    Returns the largest differences (px) between (1) the area centroid of the rendered disc
    minus ``cv2.projectPoints`` of its 3-D centre and the bias vgripd predicts, (2)
    ``cv2.projectPoints`` and ``CameraModel.project`` of the centres; then the smallest and the
    largest predicted bias (px).
    """
    cell = indep.Cell(plate)
    models = scene.camera_models(config)
    rng = np.random.default_rng(seed)
    worst_bias = worst_projection = 0.0
    sizes: list[float] = []
    for _ in range(poses):
        for (cam, T), model in zip(cell.views(cell.random_pose(rng)), models, strict=True):
            assert model is not None
            predicted = pipeline_module._circle_centre_bias(model, T, plate.centres,
                                                            plate.diameters)
            sizes += np.linalg.norm(predicted, axis=1).tolist()
            centres_cam = plate.centres @ T[:3, :3].T + T[:3, 3]
            projected = cam.project(centres_cam)
            worst_projection = max(worst_projection, float(
                np.abs(projected - model.project(centres_cam)).max()))
            for i in range(len(plate.names)):
                rim = indep.rim_pixels(cam, T, plate.centres[i], plate.diameters[i])
                box = indep.bounding_box(rim, cam.width, cam.height)
                assert box is not None
                measured = indep.scan_centroid(rim, box[1], box[3]) - projected[i]
                worst_bias = max(worst_bias, float(np.linalg.norm(measured - predicted[i])))
    return worst_bias, worst_projection, min(sizes), max(sizes)


def summary(data: list[Row]) -> dict[str, float]:
    a = np.array(data)
    ok = np.isfinite(a[:, 1])
    t, r = a[ok, 1], a[ok, 2]
    return {"lat_med": float(np.median(a[:, 0])), "lat_p99": float(np.percentile(a[:, 0], 99)),
            "t_rms": float(np.sqrt(np.mean(t**2))), "t_med": float(np.median(t)), "t_max": float(t.max()),
            "r_rms": float(np.sqrt(np.mean(r**2))), "r_med": float(np.median(r)), "r_max": float(r.max()),
            "failed": int((~ok).sum())}


def table(results: dict[str, dict[str, list[Row]]]) -> list[str]:
    lines = [
        "| images | pipeline | translation err RMS / median / max mm | rotation err RMS / median / "
        "max deg | failed | latency median / p99 ms |",
        "|---|---|---|---|---|---|",
    ]
    for images, rows in results.items():
        for name, data in rows.items():
            s = summary(data)
            lines.append(
                f"| {images} | {name} | {s['t_rms']:.4f} / {s['t_med']:.4f} / {s['t_max']:.4f} | "
                f"{s['r_rms']:.4f} / {s['r_med']:.4f} / {s['r_max']:.4f} | {s['failed']} | "
                f"{s['lat_med']:.1f} / {s['lat_p99']:.1f} |")
    return lines


def main() -> None:
    parser = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    parser.add_argument("--pairs", type=int, default=100)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--supersample", type=int, default=4,
                        help="samples per pixel and axis of the synthetic camera (vgripd's model)")
    args = parser.parse_args()
    plate = indep.Plate.from_toml()
    config = cell_config(plate)
    if not np.array_equal(scene.object_points(config), plate.centres):
        raise SystemExit("the plate vgripd was given differs from the renderer's")
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    truths: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    sets = {
        "independent (OpenCV projectPoints)":
            lambda: collect(render_independent(plate, args.pairs, args.seed), truths[0]),
        "vgripd's own model (synthetic camera)":
            lambda: collect(render_vgripd(config, args.pairs, args.seed, args.supersample),
                            truths[1]),
    }
    pipeline, peer = Pipeline(config), Peer(config)
    for pair, _ in render_independent(plate, 3, args.seed + 1):  # warm up both
        pipeline.process(pair, 0)
        peer.locate(pair)
    results: dict[str, dict[str, list[Row]]] = {}
    statuses: dict[str, dict[str, int]] = {}
    for k, (name, images) in enumerate(sets.items()):
        results[name], statuses[name] = run(pipeline, peer, images(), ablation=k == 0)
    print(f"rendered and located 2 x {args.pairs} pairs of {W}x{H} in "
          f"{time.perf_counter() - t0:.1f} s")
    load_after = os.getloadavg()[0]
    first = next(iter(results))
    v, p = summary(results[first]["vgripd"]), summary(results[first]["opencv peer"])
    own = summary(results[list(results)[1]]["vgripd"])
    off = summary(results[first][NO_CORRECTION])
    worst_bias, worst_projection, bias_lo, bias_hi = bias_check(plate, config, 10, args.seed + 2)
    paired = max(float(np.abs(a - b).max()) for a, b in zip(*truths, strict=True)) < 1e-9
    check = indep.verify(indep.Cell(plate), 1, args.seed + 3)
    lines = [
        "A 2-core machine shared with other work (load average "
        f"{load_before:.2f} before, {load_after:.2f} after). {W}x{H} 8-bit stereo pairs in memory "
        "-> object pose in the base frame; demo plate (six 10 mm dark marks, ~42 px) at ~840 mm, "
        "f = 3500 px, 200 mm baseline toed in, Brown distortion k1 = -0.05, blur 0.8 px, noise 2 "
        "grey levels, 30 % lighting gradient, random pose (+-20 mm, +-8 deg). Both pipelines "
        "locate the same images in the same run; errors are `pose_error` against the drawn "
        "3-D pose.",
        "",
        "Two sets of images. *Independent*: `bench/render_independent.py`, which imports nothing "
        "from vgripd or drivers: each mark's rim is projected by `cv2.projectPoints` (4096 "
        "points) and rasterised with 128 scan lines per pixel row, exact along each line; its "
        "self-check, run as part of this bench (a ray-casting render through "
        "`cv2.undistortPoints` is the second path; its 16x16 grid limits that comparison to "
        "~1e-3 px):",
        "",
        "```",
        *check,
        "```",
        "",
        "*vgripd's own model*: the synthetic camera driver, which projects through "
        "`vgripd.geometry.camera_model`, the model the pipeline's circle-centre correction also "
        "uses (kept for comparison: an error shared by renderer and pipeline would cancel there), "
        f"with {args.supersample}x{args.supersample} samples per pixel. "
        + ("Both sets draw the same poses and the same noise (same seed, same order of draws): "
           "the images differ only in how the marks are rendered." if paired else
           "The two sets draw different poses and noise."),
        "",
        *table(results),
        "",
        f"**Headline (independent images): vgripd {v['t_rms']:.4f} mm / {v['r_rms']:.4f} deg RMS "
        f"(max {v['t_max']:.4f} mm / {v['r_max']:.4f} deg), the OpenCV peer {p['t_rms']:.4f} mm / "
        f"{p['r_rms']:.4f} deg RMS (max {p['t_max']:.4f} mm / {p['r_max']:.4f} deg); ratio "
        f"vgripd / peer {v['t_rms'] / p['t_rms']:.2f} (translation), "
        f"{v['r_rms'] / p['r_rms']:.2f} (rotation).** On images rendered by vgripd's own model "
        f"vgripd measures {own['t_rms']:.4f} mm / {own['r_rms']:.4f} deg RMS (median "
        f"{own['t_med']:.4f} mm): "
        + ("the independent figure is no worse" if v["t_rms"] <= own["t_rms"] else
           f"the independent figure is {v['t_rms'] / own['t_rms']:.2f}x the self-rendered one")
        + ". On 2026-11-24 the self-rendered figure was the higher one; the cause is the synthetic "
        "camera's sampling, not the model: with `--pairs 30 --supersample 16` (16x16 samples per "
        "pixel instead of 4x4, same poses and noise) the two sets gave vgripd 0.0039 and 0.0040 "
        "mm RMS (0.0047 mm at 4x4).",
        "",
        "Cross-checks of the pipeline against the independent geometry (10 further poses, 2 "
        f"cameras, 6 marks): `cv2.projectPoints` and vgripd's `CameraModel.project` agree to "
        f"{worst_projection:.0e} px on the mark centres; the perspective bias of circle centres "
        "that vgripd predicts (area centroid of its 48-vertex projected rim minus the projected "
        f"centre, {bias_lo:.3f}-{bias_hi:.3f} px here) agrees with the area centroid of the independently rendered "
        f"disc to {worst_bias:.1e} px. With that correction switched off, vgripd's error on the "
        f"independent images is {off['t_rms']:.4f} mm / {off['r_rms']:.4f} deg RMS (max "
        f"{off['t_max']:.4f} mm), as against {v['t_rms']:.4f} mm with it: without the correction "
        "vgripd's translation error is the peer's size (the bias shifts every mark by about the "
        "same depth), its rotation error hardly changes. The correction holds against a truth it "
        "did not render.",
        "",
        "vgripd statuses: " + "; ".join(f"{k}: {d}" for k, d in statuses.items()) + " "
        "(OUT_OF_LIMITS is the offset gate, 100 mm / 20 deg, on the largest random poses: the "
        "pose is measured all the same and counted). vgripd's "
        f"latency (median ratio vgripd / peer {v['lat_med'] / p['lat_med']:.2f} on the "
        "independent images) includes the gates, offset and vendor conversion; the peer has no "
        "spurious-blob rejection (it fails when the blob count differs from the model) and no "
        "circle-centre correction. Latencies swing with the machine's load (load average above; "
        "other work shares the 2 cores), the errors do not. No target is stated for this "
        "benchmark.",
    ]
    harness.report("Vision: accuracy and locate time", SECTION, "\n".join(lines), stamp,
                   args.print_only)


if __name__ == "__main__":
    main()
