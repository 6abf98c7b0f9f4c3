"""Multi-camera locating: accuracy and time against the number of cameras and a plain OpenCV peer.

The object is config/samples/two_rigs_frame.toml's frame (1.5 m x 0.8 m, eight 30 mm marks on
each face, each face's marks visible only from its side). The cell has N = 2, 4, 6 or 8 cameras
as N/2 stereo rigs (400 mm baseline, about 2 m from the frame): rig 1 in front (north), rig 2
behind (south), rigs 3 and 4 at 45 deg to the faces (north-east, south-west). N = 2 is the
single rig of today's vgripd: it sees one face only.

Images are rendered here with OpenCV's camera model and nothing from vgripd (the scan-line
coverage of bench/render_independent.py, each rim projected with ``cv2.projectPoints``); the
truth is the 3-D pose drawn here. Every N sees the same poses (same seed), so the rows pair up.

vgripd: ``Pipeline.process`` on the N images (features, tracks, identification, joint fit,
rig check). Peer, the plain OpenCV multi-view pipeline at its fair best: adaptive-threshold
blob centroids (moments) per image, for each rig the left/right pairs by the epipolar
constraint (nearest within 3 px in normalised coordinates, undistortion iterated to
convergence), ``cv2.triangulatePoints`` per rig, each triangulated point identified as the
nearest model mark at the taught pose (the marks are 200+ mm apart, the object moves at most
20 mm), marks seen by several rigs averaged, and one Kabsch fit (SVD) of the model onto them.
The peer is given the rigs (which cameras pair) and the taught pose; vgripd finds both itself.

Errors: ``mm`` = the largest displacement of any of the 16 marks between the found and the true
pose (the far face included: what a gripper at the far end would miss by); ``deg`` = rotation.

    .venv/bin/python bench/bench_multiview.py [--poses 8] [--print-only]
"""

from __future__ import annotations

import copy
import math
import os
import sys
import time
import tomllib
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import harness  # noqa: E402
from bench import render_independent as indep  # noqa: E402
from vgripd.config import config_from_dict  # noqa: E402
from vgripd.types import ImagePair  # noqa: E402
from vgripd.vision.pipeline import Pipeline  # noqa: E402

SAMPLE = ROOT / "config" / "samples" / "two_rigs_frame.toml"
SECTION = "Multi-camera locating: N cameras around a 1.5 m frame"
W, H = 1280, 1024
DIST = [-0.05, 0.08, 0.0002, -0.0001, 0.0]
INTRINSICS = {"fx": 1400.0, "fy": 1400.0, "cx": 639.5 + 1.7, "cy": 511.5 - 0.9, "dist": DIST,
              "width": W, "height": H}
RANGE_MM, BASELINE_MM = 1960.0, 400.0
#: Rig directions (deg about the vertical, 0 = in front of the front face, -y).
RIG_ANGLES = {"north": 0.0, "south": 180.0, "east": 45.0, "west": 225.0}
ROWS_PER_PX = 16
MAX_SHIFT_MM, MAX_TILT_DEG = 20.0, 2.0


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.c_[x, np.cross(z, x), z]
    T[:3, 3] = eye
    return T


def cell(n_cams: int, doc: dict) -> tuple[dict, list[np.ndarray], list[tuple[int, int]]]:
    """The config (a dict) of an N-camera cell, its camera poses and its rigs."""
    target = np.array(doc["reference"]["T_base_obj"]["translation_mm"], dtype=float)
    cams, poses, rigs = [], [], []
    for name, angle in list(RIG_ANGLES.items())[:n_cams // 2]:
        a = math.radians(angle)
        toward = np.array([math.sin(a), -math.cos(a), 0.0])  # from the frame to the rig
        side = np.cross([0.0, 0.0, 1.0], toward)
        rigs.append((len(poses), len(poses) + 1))
        for k, sign in enumerate((-1.0, 1.0)):
            eye = target + RANGE_MM * toward + sign * BASELINE_MM / 2 * side + [0, 0, 50.0]
            T = look_at(eye, target)
            poses.append(T)
            rv = cv2.Rodrigues(T[:3, :3])[0].ravel()
            cams.append({"name": f"{name}_{k}", "intrinsics": INTRINSICS,
                         "T_base_camera": {"translation_mm": eye.tolist(),
                                           "rotvec_rad": rv.tolist()}})
    data = {"camera": {"type": "replay", "globs": [f"{c['name']}_*.png" for c in cams],
                       "folder": "."},
            "object": doc["object"], "reference": doc["reference"], "vision": doc["vision"],
            "calibration": {"cameras": cams, "rigs": [
                {"name": name, "cameras": [f"{name}_0", f"{name}_1"]}
                for name in list(RIG_ANGLES)[:n_cams // 2]]}}
    if n_cams == 2:  # one pair: the pipeline's 2-camera path via calibration.cameras too
        data["calibration"]["rigs"] = []
    return data, poses, rigs


class Frame:
    """The object read with tomllib (centres, normals, diameters), rendered with OpenCV."""

    def __init__(self, doc: dict) -> None:
        feats = doc["object"]["features"]
        self.centres = np.array([f["xyz_mm"] for f in feats], dtype=float)
        self.normals = np.array([f["normal"] for f in feats], dtype=float)
        self.diameters = np.array([f["diameter_mm"] for f in feats], dtype=float)
        self.T_ref = indep.pose_matrix(doc["reference"]["T_base_obj"])
        self.camera = indep.Camera.from_dict(INTRINSICS)

    def random_pose(self, rng: np.random.Generator) -> np.ndarray:
        pivot = self.T_ref[:3, 3]
        R = cv2.Rodrigues(np.radians(rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG, 3)))[0]
        move = np.eye(4)
        move[:3, :3] = R
        move[:3, 3] = pivot - R @ pivot + rng.uniform(-MAX_SHIFT_MM, MAX_SHIFT_MM, 3)
        return move @ self.T_ref

    def render(self, T_base_cam: np.ndarray, T_base_obj: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
        T = indep.rigid_inverse(T_base_cam) @ T_base_obj
        eye_obj = indep.rigid_inverse(T)[:3, 3]
        albedo = np.full((H, W), indep.BACKGROUND)
        a = 2 * np.pi * np.arange(1024) / 1024
        for c, n, d in zip(self.centres, self.normals, self.diameters, strict=True):
            if (eye_obj - c) @ n <= 0:
                continue  # the mark faces away: the frame hides it
            u = np.cross([0.0, 0.0, 1.0], n)
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            rim = c + 0.5 * d * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)
            poly = self.camera.project(rim @ T[:3, :3].T + T[:3, 3])
            box = indep.bounding_box(poly, W, H)
            if box is None:
                continue
            x0, y0, w, h = box
            cov = indep.polygon_coverage(poly, x0, y0, w, h, ROWS_PER_PX)
            patch = albedo[y0:y0 + h, x0:x0 + w]
            patch += cov * (indep.DARK - patch)
        albedo = np.asarray(cv2.GaussianBlur(albedo, (0, 0), indep.BLUR_PX), dtype=np.float64)
        albedo += rng.normal(0.0, indep.NOISE_STD, albedo.shape)
        return np.clip(np.rint(albedo), 0, 255).astype(np.uint8)


class Peer:
    """Plain OpenCV: pairwise triangulatePoints per rig, averaging, Kabsch (module docstring)."""

    CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)

    def __init__(self, frame: Frame, poses: list[np.ndarray], rigs: list[tuple[int, int]]) -> None:
        self.frame, self.poses, self.rigs = frame, poses, rigs
        self.K, self.dist = frame.camera.K, frame.camera.dist
        self.model_ref = frame.centres @ frame.T_ref[:3, :3].T + frame.T_ref[:3, 3]
        area = np.pi / 4 * (INTRINSICS["fx"] * 30.0 / 2600) ** 2
        self.area = (area * 0.5, np.pi / 4 * (INTRINSICS["fx"] * 30.0 / 1500) ** 2)

    def centroids(self, gray: np.ndarray) -> np.ndarray:
        mask = cv2.adaptiveThreshold(gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C,
                                     cv2.THRESH_BINARY_INV, 61, 20)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        pts = []
        for c in contours:
            m = cv2.moments(c)
            if not self.area[0] <= m["m00"] <= self.area[1]:
                continue
            if 4 * np.pi * m["m00"] / cv2.arcLength(c, True) ** 2 < 0.6:
                continue
            pts.append((m["m10"] / m["m00"], m["m01"] / m["m00"]))
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def locate(self, images: list[np.ndarray]) -> np.ndarray | None:
        sums = np.zeros((len(self.model_ref), 3))
        counts = np.zeros(len(self.model_ref))
        for a, b in self.rigs:
            pa, pb = self.centroids(images[a]), self.centroids(images[b])
            if len(pa) < 3 or len(pb) < 3:
                continue
            na = cv2.undistortPoints(pa.reshape(-1, 1, 2), self.K, self.dist,
                                     criteria=self.CRITERIA).reshape(-1, 2)
            nb = cv2.undistortPoints(pb.reshape(-1, 1, 2), self.K, self.dist,
                                     criteria=self.CRITERIA).reshape(-1, 2)
            T_b_a = indep.rigid_inverse(self.poses[b]) @ self.poses[a]
            R, t = T_b_a[:3, :3], T_b_a[:3, 3]
            E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
            lines = np.c_[na, np.ones(len(na))] @ E.T
            d = np.abs(lines @ np.c_[nb, np.ones(len(nb))].T) / np.hypot(lines[:, :1],
                                                                         lines[:, 1:2])
            j = d.argmin(axis=1)
            keep = d[np.arange(len(na)), j] * INTRINSICS["fx"] < 3.0
            if keep.sum() < 3:
                continue
            X = cv2.triangulatePoints(np.eye(4)[:3], T_b_a[:3], na[keep].T.copy(),
                                      nb[j[keep]].T.copy())
            pts = (X[:3] / X[3]).T @ self.poses[a][:3, :3].T + self.poses[a][:3, 3]
            dist = np.linalg.norm(pts[:, None] - self.model_ref[None], axis=2)
            near = dist.argmin(axis=1)
            for p, i, dd in zip(pts, near, dist[np.arange(len(pts)), near], strict=True):
                if dd < 60.0:
                    sums[i] += p
                    counts[i] += 1
        seen = counts > 0
        if seen.sum() < 3:
            return None
        a, b = self.frame.centres[seen], sums[seen] / counts[seen, None]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        R = vt.T @ np.diag([1, 1, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, cb - R @ ca
        return T


def errors(T: np.ndarray, truth: np.ndarray, model: np.ndarray) -> tuple[float, float]:
    """Largest mark displacement (mm) and rotation angle (deg) between two poses."""
    p = model @ T[:3, :3].T + T[:3, 3]
    q = model @ truth[:3, :3].T + truth[:3, 3]
    R = truth[:3, :3].T @ T[:3, :3]
    deg = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2))))
    return float(np.linalg.norm(p - q, axis=1).max()), deg


def stats(values: list[float]) -> tuple[float, float]:
    v = np.asarray(values)
    return float(np.sqrt(np.mean(v * v))), float(v.max())


def main() -> None:
    parser = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    parser.add_argument("--poses", type=int, default=8)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()
    with SAMPLE.open("rb") as fh:
        doc = tomllib.load(fh)
    frame = Frame(doc)
    rng = np.random.default_rng(args.seed)
    truths = [frame.random_pose(rng) for _ in range(args.poses)]
    load_before = os.getloadavg()
    t_start = time.perf_counter()
    cells = {}
    for n_cams in (2, 4, 6, 8):
        data, poses, rigs = cell(n_cams, copy.deepcopy(doc))
        cells[n_cams] = (Pipeline(config_from_dict(data)), Peer(frame, poses, rigs), poses)
    ours = {n: {"mm": [], "deg": [], "ms": [], "cpu_ms": [], "pose_ms": []} for n in cells}
    theirs = {n: {"mm": [], "deg": [], "ms": [], "cpu_ms": []} for n in cells}
    statuses: dict[int, dict[str, int]] = {n: {} for n in cells}
    peer_failed = dict.fromkeys(cells, 0)
    render_rng = np.random.default_rng(args.seed + 100)
    # Pose by pose, every cell in turn: the machine's load (shared, 2 cores) falls on all rows
    # alike. The first pose warms up and is not counted.
    for k, truth in enumerate([truths[0], *truths]):
        for n_cams, (pipe, peer, poses) in cells.items():
            images = [frame.render(T_cam, truth, render_rng) for T_cam in poses]
            t0, c0 = time.perf_counter(), time.process_time()
            result = pipe.process(ImagePair.of_views(images, 0), k)
            t1, c1 = time.perf_counter(), time.process_time()
            T = peer.locate(images)
            t2, c2 = time.perf_counter(), time.process_time()
            if k == 0:
                continue
            o, p = ours[n_cams], theirs[n_cams]
            o["ms"].append((t1 - t0) * 1e3)
            o["cpu_ms"].append((c1 - c0) * 1e3)
            p["ms"].append((t2 - t1) * 1e3)
            p["cpu_ms"].append((c2 - c1) * 1e3)
            name = result.status.name
            statuses[n_cams][name] = statuses[n_cams].get(name, 0) + 1
            if result.T_base_obj is not None and result.status.pose_valid:
                mm, deg = errors(result.T_base_obj, truth, frame.centres)
                o["mm"].append(mm)
                o["deg"].append(deg)
                o["pose_ms"].append(result.timings_ms["pose"])
            if T is None:
                peer_failed[n_cams] += 1
            else:
                mm, deg = errors(T, truth, frame.centres)
                p["mm"].append(mm)
                p["deg"].append(deg)
    rows = [(n, ours[n], theirs[n], statuses[n], peer_failed[n]) for n in cells]
    elapsed = time.perf_counter() - t_start
    load_after = os.getloadavg()
    table = ["| cameras (rigs) | vgripd mark error RMS / max mm | vgripd rotation RMS / max "
             "deg | peer mm RMS / max | peer deg RMS / max | vgripd job median ms wall / CPU "
             "(CPU per camera) | of it pose stage ms | peer median ms wall / CPU | statuses |",
             "|---|---|---|---|---|---|---|---|---|"]
    for n_cams, o, p, st, failed in rows:
        om, od, pm, pd = stats(o["mm"]), stats(o["deg"]), stats(p["mm"]), stats(p["deg"])
        wall, cpu = float(np.median(o["ms"])), float(np.median(o["cpu_ms"]))
        fail = f", peer failed {failed}" if failed else ""
        table.append(
            f"| {n_cams} ({n_cams // 2}) | {om[0]:.3f} / {om[1]:.3f} | {od[0]:.4f} / {od[1]:.4f} "
            f"| {pm[0]:.3f} / {pm[1]:.3f} | {pd[0]:.4f} / {pd[1]:.4f} | {wall:.1f} / {cpu:.1f} "
            f"({cpu / n_cams:.1f}) | {float(np.median(o['pose_ms'])):.1f} | "
            f"{float(np.median(p['ms'])):.1f} / {float(np.median(p['cpu_ms'])):.1f} | "
            f"{st}{fail} |")
    text = "\n".join(table)
    print(f"{elapsed:.0f} s, load {load_before} -> {load_after}")
    head = [f"{args.poses} poses of the frame (shift +-"
            f"{MAX_SHIFT_MM:g} mm, tilt +-{MAX_TILT_DEG:g} deg), the same for every row, "
            f"rendered independently of vgripd at {W}x{H}; errors are the largest "
            "displacement of any of the 16 marks (far face included) and the rotation "
            "angle, against the rendered truth. Peer: pairwise cv2.triangulatePoints per "
            "rig, averaging, Kabsch (bench/bench_multiview.py docstring).", "", text, ""]
    harness.report("Vision: accuracy and locate time", SECTION, "\n".join(head), stamp,
                   args.print_only)


if __name__ == "__main__":
    main()
