"""Planned hand-eye poses against a hand-made set of the same size.

Run from the repository root with the project's interpreter::

    .venv/bin/python bench/bench_handeye_plan.py [--seeds 10] [--count 15] [--print-only]

Scene (each seed draws its own hand-eye X and start pose): a 1280 x 960 camera (f 1500 px), a
9 x 6 chessboard (25 mm) seen at 420 mm at the start pose, eye-in-hand and eye-to-hand. Two sets
of ``--count`` flange poses around the same start pose:

- planned: ``plan_hand_eye`` in a box of 250 mm travel and 30 deg tilt (what
  ``vgripd calibrate handeye plan`` makes);
- by hand: what people do when they jog the robot: the start pose turned by up to 10 deg about
  random axes and moved by up to 40 mm per axis (uniform), drawn until the board is inside the
  image (the same visibility rule as the plan).

Samples: the board corners projected from each pose with 0.1 px Gaussian noise, the reported
robot poses with 0.02 deg and 0.05 mm per axis (an industrial robot's repeatability). Solved
by ``calibrate_hand_eye`` (default likelihood objective, no leave-one-out). Written (bench/RESULTS.md) per mode and
set: median and worst over seeds of the result's error (mm, deg) and of the condition figure
(``plan_condition``: condition, effective rotation).
"""

from __future__ import annotations

import math
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from vgripd.calib.boards import Board  # noqa: E402
from vgripd.calib.handeye import Sample, calibrate_hand_eye  # noqa: E402
from vgripd.calib.handeye.plan import _view, plan_condition, plan_hand_eye  # noqa: E402
from vgripd.geometry.camera_model import CameraModel  # noqa: E402
from vgripd.geometry.transforms import (  # noqa: E402
    invert_transform,
    make_transform,
    matrix_from_rotvec,
    pose_error,
    transforms_from_vectors,
)

BOARD = Board.parse("chessboard:9x6:25")
CAMERA = CameraModel(1500.0, 1500.0, 641.0, 479.0, 0.0, (0.0,) * 5, 1280, 960)
DISTANCE = 420.0
CENTRE = BOARD.object_points().mean(axis=0)
B0 = make_transform(np.eye(3), np.array([0.0, 0.0, DISTANCE]) - CENTRE)
FLIP = make_transform(matrix_from_rotvec([math.pi, 0.0, 0.0]), np.zeros(3))
T_FLANGE_BOARD = make_transform(np.eye(3), [0.0, 0.0, 30.0]) @ FLIP @ make_transform(
    np.eye(3), -CENTRE)


def scene(mode: str, rng: np.random.Generator):
    axis = rng.normal(size=3)
    R = matrix_from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0, 0.3))
    if mode == "eye-in-hand":
        X = make_transform(matrix_from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)]) @ R,
                           rng.uniform(-80, 80, 3))
        T_base_board = make_transform(matrix_from_rotvec([np.pi, 0, rng.uniform(-1, 1)]),
                                      [650, rng.uniform(-100, 100), 20])
        T0 = T_base_board @ invert_transform(B0) @ invert_transform(X)

        def board(T):
            return invert_transform(X) @ invert_transform(T) @ T_base_board
    else:
        X = make_transform(matrix_from_rotvec([0, np.pi, 0]) @ R,
                           [600, rng.uniform(-100, 100), -250])
        T0 = X @ B0 @ invert_transform(T_FLANGE_BOARD)

        def board(T):
            return invert_transform(X) @ T @ T_FLANGE_BOARD
    return X, T0, board


def by_hand(T0, board, n, rng):
    poses = [T0]
    while len(poses) < n:
        axis = rng.normal(size=3)
        rot = axis / np.linalg.norm(axis) * math.radians(rng.uniform(0, 10))
        T = T0 @ transforms_from_vectors(np.concatenate([rot, rng.uniform(-40, 40, 3)]))
        if _view(CAMERA, board(T), BOARD.object_points(), BOARD.cols) is not None:
            poses.append(T)
    return poses


def solve(mode, X, poses, board, rng):
    obj = BOARD.object_points()
    samples = []
    for k, T in enumerate(poses):
        B = board(T)
        px = CAMERA.project(obj @ B[:3, :3].T + B[:3, 3]) + rng.normal(0, 0.1, (len(obj), 2))
        noise = np.concatenate([np.radians(rng.normal(0, 0.02, 3)), rng.normal(0, 0.05, 3)])
        samples.append(Sample(T @ transforms_from_vectors(noise), None, f"p{k}", obj, px))
    result = calibrate_hand_eye(samples, mode, CAMERA, stability=False)
    return pose_error(result.T, X)


def main() -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--count", type=int, default=15)
    args = ap.parse_args()
    stamp = harness.Stamp(harness.bench_command())
    lines: list[str] = []
    for mode in ("eye-in-hand", "eye-to-hand"):
        rows: dict[str, list[tuple[float, float, float, float]]] = {"planned": [], "by hand": []}
        for seed in range(args.seeds):
            rng = np.random.default_rng(seed)
            X, T0, board = scene(mode, rng)
            guess = X @ transforms_from_vectors(np.array([0.02, -0.02, 0.03, 5.0, -4.0, 3.0]))
            plan = plan_hand_eye(mode, T0, CAMERA, BOARD.object_points(), BOARD.cols,
                                 distance_mm=DISTANCE, travel_mm=250, tilt_deg=30,
                                 n=args.count, X_guess=guess, board_offset_mm=(0, 0, 30))
            for name, poses in (("planned", plan.poses),
                                ("by hand", by_hand(T0, board, args.count, rng))):
                c = plan_condition(poses)
                mm, deg = solve(mode, X, poses, board, rng)
                rows[name].append((mm, deg, c.condition, c.effective_deg))
        for name, r in rows.items():
            mm, deg, cond, eff = (list(col) for col in zip(*r, strict=True))
            lines.append(f"{mode:12s} {name:8s} error median {statistics.median(mm):7.3f} mm "
                  f"{statistics.median(deg):6.4f} deg, worst {max(mm):7.3f} mm "
                  f"{max(deg):6.4f} deg | condition median {statistics.median(cond):5.2f} "
                  f"(worst {max(cond):5.2f}), effective rotation median "
                  f"{statistics.median(eff):5.1f} deg (least {min(eff):4.1f})")
    head = (f"{args.count} poses per set, {args.seeds} seeds, each drawing its own hand-eye X "
            "and start pose; 1280x960 camera (f 1500 px), 9x6 chessboard (25 mm) at 420 mm; "
            "corners 0.1 px, robot poses 0.02 deg / 0.05 mm per axis. Planned: `plan_hand_eye` "
            "in a 250 mm / 30 deg box; by hand: the start pose turned by up to 10 deg about "
            "random axes and moved up to 40 mm per axis (what people do when they jog the "
            "robot), both with the board inside the image. Solved by `calibrate_hand_eye` "
            "(likelihood); error against the truth, median and worst over seeds.")
    harness.report("Calibration", "Planned hand-eye poses against a hand-made set",
                   head + "\n\n```\n" + "\n".join(lines) + "\n```", stamp, args.print_only)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
