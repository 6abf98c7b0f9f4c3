"""N-camera calibration benchmark: our joint bundle adjustment (``vgripd calibrate cameras``'
solver) vs chaining OpenCV's pairwise ``cv2.stereoCalibrate``, on the same board corners.

Run from the repository root::

    .venv/bin/python bench/bench_multicam.py [--trials 5] [--print-only]

Synthetic cell: N cameras (2..8) in a row, 150 mm apart, 900 mm above the table, looking down,
each tilted and rolled a little differently (fx ~800 px, 640x480, Brown distortion); a 7x5
chessboard (25 mm) at random poses 550-750 mm below them, tilted up to ~23 deg, 10 image sets
per camera, placed mostly where two or three neighbours see it at once. A camera takes a set
when the whole board is inside its image. Corner pixels are projected by OpenCV
(``cv2.projectPoints``, the truth; nothing from vgripd) and get Gaussian noise of 0.15 px.

Both methods get the true intrinsics, held fixed (``CALIB_FIX_INTRINSIC``: the peer's best
settings for a rig whose cameras were calibrated beforehand; tight termination criteria). The
peer links each camera to its left neighbour with ``stereoCalibrate`` over the sets both saw
and composes the chain c0 -> c1 -> ... (the usual way to extend a stereo tool to N cameras);
ours fits every camera and board pose to all corners at once. Printed per N: the pose error of
every camera relative to camera 0 against the truth (mean over cameras and trials, and the
worst camera, the chain's far end, as median over trials), and the time per calibration
(ours: the whole ``calibrate_cameras``, PnP to the report and the pose uncertainty; the peer:
its stereoCalibrate calls), the fastest of 3 runs.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

# One BLAS thread: the fit's dense algebra is small (a few hundred parameters), and on a
# shared, loaded machine OpenBLAS's thread hand-offs cost more than they save (one step took
# 0.5 ms or 40 ms by the scheduler's mood). OpenCV's own threading (the peer) is untouched.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from vgripd.calib.camera_poses import Observation, calibrate_cameras  # noqa: E402
from vgripd.geometry.transforms import pose_error  # noqa: E402

SIZE = (640, 480)
BOARD = np.array([[c * 25.0, r * 25.0, 0.0] for r in range(5) for c in range(7)])
SPACING_MM = 150.0
NOISE_PX = 0.15
SETS_PER_CAMERA = 10
REPEATS = 3  # each calibration timed 3 times, the fastest kept (load on a shared machine)
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-14)


def transform(rvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    T[:3, 3] = t
    return T


def cell(n: int) -> tuple[list[dict], list[np.ndarray]]:
    cams = [{"fx": 800.0 + 7 * i, "fy": 803.0 + 5 * i, "cx": 321.0 - i, "cy": 238.0 + 2 * i,
             "skew": 0.0, "dist": [-0.21 + 0.01 * (i % 3), 0.11, 0.0008, -0.0004, 0.0],
             "width": SIZE[0], "height": SIZE[1]} for i in range(n)]
    poses = [transform([np.pi + 0.02 * (i % 3), 0.03 * (i % 4) - 0.04, 0.05 * (i % 5)],
                       [SPACING_MM * i, 10.0 * (i % 2), 900.0]) for i in range(n)]
    return cams, poses


def opencv(cam: dict) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    return K, np.asarray(cam["dist"], float)


def scene(n: int, seed: int) -> tuple[list[dict], list[np.ndarray], list[Observation]]:
    cams, poses = cell(n)
    rng = np.random.default_rng(seed)
    obs: list[Observation] = []
    n_sets = 0
    while n_sets < SETS_PER_CAMERA * n:
        R = cv2.Rodrigues(rng.uniform(-0.4, 0.4, 3))[0]
        x = (SPACING_MM * rng.integers(0, 2 * n - 1) / 2 + rng.uniform(-40, 40)
             if rng.random() < 0.8 else rng.uniform(-100, SPACING_MM * (n - 1) + 100))
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([x, rng.uniform(-90, 120), rng.uniform(150, 350)]) - R @ BOARD.mean(0)
        seen = []
        for c in range(n):
            Tc = np.linalg.inv(poses[c]) @ T
            K, d = opencv(cams[c])
            px = cv2.projectPoints(BOARD, cv2.Rodrigues(Tc[:3, :3])[0], Tc[:3, 3], K, d)[0]
            px = px.reshape(-1, 2)
            if Tc[2, 3] > 0 and np.all((px > 5) & (px < np.array(SIZE) - 5)):
                seen.append(Observation(c, str(n_sets), BOARD, px + rng.normal(
                    0, NOISE_PX, px.shape), f"cam{c}_{n_sets}"))
        if seen:
            obs += seen
            n_sets += 1
    return cams, poses, obs


def peer_chain(cams: list[dict], obs: list[Observation]) -> tuple[list[np.ndarray], float]:
    """Camera poses in camera 0 from stereoCalibrate on neighbours, composed; seconds."""
    by_set: dict[str, dict[int, Observation]] = {}
    for o in obs:
        by_set.setdefault(o.set_key, {})[o.camera] = o
    T_0_c = [np.eye(4)]
    elapsed = 0.0
    for c in range(1, len(cams)):
        both = [s for s in by_set.values() if c - 1 in s and c in s]
        if not both:
            raise RuntimeError(f"cameras {c - 1} and {c} share no set")
        (Ka, da), (Kb, db) = opencv(cams[c - 1]), opencv(cams[c])
        t0 = time.perf_counter()
        _, *_, R, T, _E, _F = cv2.stereoCalibrate(
            [BOARD.astype(np.float32)] * len(both),
            [s[c - 1].px.astype(np.float32) for s in both],
            [s[c].px.astype(np.float32) for s in both], Ka, da, Kb, db, SIZE,
            flags=cv2.CALIB_FIX_INTRINSIC, criteria=CRITERIA)
        elapsed += time.perf_counter() - t0
        T_c_prev = transform(cv2.Rodrigues(R)[0].ravel(), T.ravel())  # X_c = R X_prev + T
        T_0_c.append(T_0_c[-1] @ np.linalg.inv(T_c_prev))
    return T_0_c, elapsed


def errors(T_0_c: list[np.ndarray], poses: list[np.ndarray]) -> np.ndarray:
    truth = [np.linalg.inv(poses[0]) @ P for P in poses]
    return np.array([pose_error(T, G) for T, G in zip(T_0_c, truth, strict=True)][1:])


def main() -> None:
    ap = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--cameras", default="2,3,4,6,8")
    args = ap.parse_args()
    load_before = os.getloadavg()
    rows = []
    for n in [int(v) for v in args.cameras.split(",")]:
        ours_err, peer_err, ours_far, peer_far, t_ours, t_peer, n_obs = [], [], [], [], [], [], []
        for trial in range(args.trials):
            cams, poses, obs = scene(n, seed=1000 * n + trial)
            times = []
            for _ in range(REPEATS):
                t0 = time.perf_counter()
                r = calibrate_cameras([f"c{i}" for i in range(n)], cams, obs)
                times.append(time.perf_counter() - t0)
            t_ours.append(min(times))
            peer_times = []
            for _ in range(REPEATS):
                peer, t = peer_chain(cams, obs)
                peer_times.append(t)
            t_peer.append(min(peer_times))
            e_ours, e_peer = errors(r.T_ref_camera, poses), errors(peer, poses)
            ours_err.append(e_ours)
            peer_err.append(e_peer)
            ours_far.append(e_ours.max(axis=0))
            peer_far.append(e_peer.max(axis=0))
            n_obs.append(len(obs))
        oe, pe = np.concatenate(ours_err), np.concatenate(peer_err)
        row = {"n": n, "obs": float(np.median(n_obs)),
               "ours_mm": oe[:, 0].mean(), "ours_deg": oe[:, 1].mean(),
               "peer_mm": pe[:, 0].mean(), "peer_deg": pe[:, 1].mean(),
               "ours_far": np.median(ours_far, axis=0), "peer_far": np.median(peer_far, axis=0),
               "t_ours": float(np.median(t_ours)), "t_peer": float(np.median(t_peer))}
        rows.append(row)
        print(f"N={n}: {row['obs']:.0f} images; mean error ours {row['ours_mm']:.3f} mm "
              f"{row['ours_deg']:.4f} deg, peer {row['peer_mm']:.3f} mm {row['peer_deg']:.4f} "
              f"deg; time ours {1e3 * row['t_ours']:.1f} ms, peer {1e3 * row['t_peer']:.1f} ms",
              flush=True)
    text = report(rows, args, load_before, os.getloadavg())
    harness.report("Calibration", "N-camera calibration: joint bundle adjustment vs chained "
                   "stereoCalibrate", text, stamp, args.print_only)


def report(rows: list[dict], args: argparse.Namespace, load_before: tuple[float, ...],
           load_after: tuple[float, ...]) -> str:
    lines = [
        f"`.venv/bin/python bench/bench_multicam.py --trials {args.trials} --cameras "
        f"{args.cameras}`, {time.strftime('%Y-%m-%d')}, {platform.machine()}, 2 cores shared "
        f"with other work (load average {load_before[0]:.2f} before, {load_after[0]:.2f} "
        f"after), Python {platform.python_version()}, OpenCV {cv2.__version__}. "
        f"Cameras in a row {SPACING_MM:g} mm apart, 900 mm up, 7x5 board (25 mm) 550-750 mm "
        f"away, {SETS_PER_CAMERA} image sets per camera, mostly where 2-3 neighbours see the "
        f"board; corners projected by OpenCV with {NOISE_PX} px noise; true intrinsics held "
        "by both. Peer: `cv2.stereoCalibrate` (CALIB_FIX_INTRINSIC) on each neighbour pair's "
        "shared sets, chained from camera 0. Errors of every camera's pose in camera 0 against "
        f"the truth: mean over cameras and {args.trials} trials; far end = the worst camera "
        f"(median over trials). Time: per calibration, the fastest of {REPEATS} runs, median "
        "over trials; one OpenBLAS thread (OPENBLAS_NUM_THREADS=1).",
        "",
        "| N | images | ours mm | ours deg | peer mm | peer deg | far end ours mm / deg | "
        "far end peer mm / deg | ours ms | peer ms | ours ms per image |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {r['obs']:.0f} | {r['ours_mm']:.3f} | {r['ours_deg']:.4f} | "
            f"{r['peer_mm']:.3f} | {r['peer_deg']:.4f} | {r['ours_far'][0]:.3f} / "
            f"{r['ours_far'][1]:.4f} | {r['peer_far'][0]:.3f} / {r['peer_far'][1]:.4f} | "
            f"{1e3 * r['t_ours']:.1f} | {1e3 * r['t_peer']:.1f} | "
            f"{1e3 * r['t_ours'] / r['obs']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
