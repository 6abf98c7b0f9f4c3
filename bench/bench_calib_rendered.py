"""Do the reported sigmas cover the error, on rendered images? Intrinsics, stereo, cameras.

Run from the repository root with the project's interpreter::

    .venv/bin/python bench/bench_calib_rendered.py [--sets 30] [--print-only]

Per set and profile: a two-camera rig (both cameras with the profile's intrinsics, the right
one turned and moved by the profile's ``T_right_left``) sees a chessboard in 14 poses (tilt
5-35 deg about a random axis, roll up to 0.5 rad, anywhere in the left image with the whole
board inside both); every image is rendered by ``bench/render_board.py`` (OpenCV and numpy
only: the truth is ``cv2.projectPoints``, not vgripd's camera model), then the real detector
(``vgripd.calib.boards.detect``, what ``detect_files`` runs on each file) finds the corners and
the commands' calibration functions run on them:

* ``intrinsics``: ``calibrate_intrinsics`` on the left images (automatic model choice), as
  ``vgripd calibrate intrinsics``;
* ``stereo``: ``calibrate_rig`` on the pairs, as ``vgripd calibrate stereo``;
* ``cameras``: each camera's intrinsics from its own images, then ``calibrate_cameras`` with
  them (and their richest model's covariance), as ``vgripd calibrate cameras`` without
  ``--intrinsics``.

``far_noisy`` is the 2.2 m profile with 12 grey levels of noise and 1.2 px blur (the others: 2
and 0.8), where the model choice drops p1 p2 as in the issue.

Per estimated parameter, the error against the truth over the reported sigma. Printed per
profile, path and parameter group: the share within 2 sigma (95 % expected), the largest |z|,
and the same with the sigmas the code on main reported before this change (``old``: for
intrinsics and stereo the chosen model's own sigma with the shift to the richest model in
quadrature; for cameras the fit's own sigma, the intrinsics taken as exact), plus the median
|error| (the point estimates do not depend on how the sigma is computed). The camera rotation
is one number per set: the error angle over ``rotation_std_deg`` (the root of the three
variances). Detections are cached (``--cache``), so a rerun only recalibrates.
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from bench.render_board import Camera  # noqa: E402
from vgripd.calib.boards import Board, Detection, detect  # noqa: E402
from vgripd.calib.camera_poses import Observation, calibrate_cameras  # noqa: E402
from vgripd.calib.intrinsics import calibrate_intrinsics  # noqa: E402
from vgripd.calib.rig import calibrate_rig  # noqa: E402
from vgripd.errors import CalibrationError  # noqa: E402

NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
GROUPS = {"fx": "f", "fy": "f", "cx": "c", "cy": "c", "k1": "k1 k2", "k2": "k1 k2",
          "p1": "p1 p2 k3", "p2": "p1 p2 k3", "k3": "p1 p2 k3"}
_TOE = math.atan2(200.0, 840.0)
#: Profiles: the issue's 2.2 m and wide cameras, and the default stereo cell of the locate
#: benchmark (bench/render_independent.py: 2448x2048, f 3500, 200 mm baseline toed in).
PROFILES: dict[str, dict[str, Any]] = {
    "far": {"camera": (3000.0, 3000.0, 1230.0, 1018.0, (-0.08, 0.12, 0.0002, 0.0002, 0.0),
                       2448, 2048),
            "board": (9, 7, 60.0), "distance": 2200.0,
            "rig": ((0.01, -0.12, 0.02), (-300.0, 4.0, 20.0))},
    "wide": {"camera": (800.0, 800.0, 645.0, 508.0, (-0.25, 0.08, 0.0, 0.0, -0.01), 1280, 1024),
             "board": (9, 7, 30.0), "distance": 500.0,
             "rig": ((0.01, -0.12, 0.02), (-300.0, 4.0, 20.0))},
    "cell": {"camera": (3500.0, 3500.0, 1226.7, 1021.4, (-0.05, 0.08, 0.0002, -0.0001, 0.0),
                        2448, 2048),
             "board": (9, 7, 30.0), "distance": 840.0,
             "rig": ((0.0, _TOE, 0.0), (-200.0 * math.cos(_TOE), 0.0, 200.0 * math.sin(_TOE)))},
}
#: The 2.2 m profile with a noisier sensor (12 grey levels, blur 1.2 px): corners ~5x noisier,
#: so p1 p2 = 0.0002 are near what the views can show and the choice drops them (the issue's
#: case; with 2 grey levels they are kept in 29 of 30 sets).
PROFILES["far_noisy"] = {**PROFILES["far"], "noise": 12.0, "blur": 1.2}
VIEWS = 14
NOISE_GREY = 2.0
BLUR_PX = 0.8


def board_points(cols: int, rows: int, pitch: float) -> np.ndarray:
    """(N, 3) inner corners, row by row (the project's chessboard order), mm."""
    return np.array([[c * pitch, r * pitch, 0.0] for r in range(rows) for c in range(cols)])


def _inside(px: np.ndarray, size: tuple[int, int], margin: float) -> bool:
    return bool(px.min() >= margin and px[:, 0].max() <= size[0] - margin
                and px[:, 1].max() <= size[1] - margin)


def render_set(name: str, seed: int, cams: dict[str, Camera],
               images: dict[str, list[np.ndarray]] | None = None) -> dict[str, Any]:
    """Render and detect one set: per view the true pose, and per camera the detections
    (``images``: per camera the rendered images are appended there too)."""
    p = PROFILES[name]
    cols, rows, pitch = p["board"]
    board = Board.parse(f"chessboard:{cols}x{rows}:{pitch:g}")
    obj = board_points(cols, rows, pitch)
    paper = np.array([[x, y, 0.0] for x in np.linspace(-2 * pitch, (cols + 1) * pitch, 12)
                      for y in np.linspace(-2 * pitch, (rows + 1) * pitch, 10)])
    R_rl = cv2.Rodrigues(np.array(p["rig"][0]))[0]
    t_rl = np.array(p["rig"][1])
    left, right = cams["left"], cams["right"]
    w, h = left.size
    fx = left.K[0, 0]
    rng = np.random.default_rng(seed)
    out: dict[str, Any] = {"poses": [], "left": [], "right": []}
    tries = 0
    while len(out["poses"]) < VIEWS:
        tries += 1
        if tries > 2000:
            raise RuntimeError(f"{name}: no board pose fits both images")
        axis = rng.normal(size=2)
        tilt = np.array([*axis / np.linalg.norm(axis), 0.0]) * math.radians(rng.uniform(5, 35))
        R = cv2.Rodrigues(tilt)[0] @ cv2.Rodrigues(np.array([0, 0, rng.uniform(-0.5, 0.5)]))[0]
        shift = np.array([rng.uniform(-0.35, 0.35) * w / fx, rng.uniform(-0.35, 0.35) * h / fx,
                          1.0])
        t = shift * p["distance"] * rng.uniform(0.85, 1.15) - R @ obj.mean(axis=0)
        rv = cv2.Rodrigues(R)[0].ravel()
        rv_r = cv2.Rodrigues(R_rl @ R)[0].ravel()
        t_r = R_rl @ t + t_rl
        if not (_inside(left.project(paper, rv, t), left.size, 4)
                and _inside(right.project(paper, rv_r, t_r), right.size, 4)):
            continue
        out["poses"].append((rv, t))
        for side, cam, (r_, t_) in (("left", left, (rv, t)), ("right", right, (rv_r, t_r))):
            img = cam.render(cols, rows, pitch, r_, t_, rng, p.get("blur", BLUR_PX),
                             p.get("noise", NOISE_GREY))
            if images is not None:
                images[side].append(img)
            try:
                d = detect(board, img, f"{side}{len(out['poses'])}")
                out[side].append((d.ids, d.px))
            except CalibrationError:
                out[side].append(None)
    return out


def load_set(name: str, seed: int, cache: Path, cams: dict[str, Camera]) -> dict[str, Any]:
    path = cache / f"{name}_{seed:03d}.npz"
    if path.exists():
        z = np.load(path, allow_pickle=True)
        return z["data"].item()  # type: ignore[no-any-return]
    data = render_set(name, seed, cams)
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, data=np.array(data, dtype=object))
    return data


def truth_intrinsics(name: str) -> dict[str, float]:
    fx, fy, cx, cy, dist, _, _ = PROFILES[name]["camera"]
    return dict(zip(NAMES, (fx, fy, cx, cy, *dist), strict=True))


def _flat(cam: dict[str, Any]) -> dict[str, float]:
    return dict(zip(NAMES, (cam["fx"], cam["fy"], cam["cx"], cam["cy"], *cam["dist"]),
                    strict=True))


def _old_std(std_model: dict[str, Any], bias: dict[str, Any] | None) -> dict[str, float]:
    """main's rule before this change: the chosen model's own sigma with the shift to the
    richest model in quadrature."""
    s = _flat(std_model)
    if bias is None:
        return s
    shift = dict(zip(NAMES, (bias["fx"], bias["fy"], bias["cx"], bias["cy"], *bias["dist"]),
                     strict=True))
    return {k: math.hypot(v, shift[k]) if v > 0 else 0.0 for k, v in s.items()}


def intrinsic_rows(path: str, est: dict[str, Any], std: dict[str, Any], old: dict[str, float],
                   truth: dict[str, float], prefix: str = "") -> list[tuple[str, str, float,
                                                                            float, float]]:
    """(path, group, z_new, z_old, |error|) per estimated intrinsic parameter."""
    e, s = _flat(est), _flat(std)
    rows = []
    for k in NAMES:
        if s[k] == 0:  # held at 0, not estimated
            continue
        err = e[k] - truth[k]
        rows.append((path, prefix + GROUPS[k], err / s[k], err / old[k], abs(err)))
    return rows


def analyse(name: str, data: dict[str, Any]) -> tuple[list[tuple[str, str, float, float, float]],
                                                        dict[str, str]]:
    p = PROFILES[name]
    cols, rows_, pitch = p["board"]
    board = Board.parse(f"chessboard:{cols}x{rows_}:{pitch:g}")
    obj = board_points(cols, rows_, pitch)
    w, h = p["camera"][5], p["camera"][6]
    truth = truth_intrinsics(name)
    out: list[tuple[str, str, float, float, float]] = []
    models: dict[str, str] = {}
    dets = {side: [Detection(f"{side}{i}", (w, h), d[0], d[1])
                   for i, d in enumerate(data[side]) if d is not None]
            for side in ("left", "right")}
    # intrinsics (left camera)
    r = calibrate_intrinsics(board, dets["left"], (w, h))
    models["intrinsics"] = r.model.model.name
    out += intrinsic_rows("intrinsics", r.camera, r.std,
                          _old_std(r.std_model or r.std, r.model.model_bias), truth)
    # stereo (pairs where both found the board and the same corners)
    objs, pl, pr = [], [], []
    for a, b in zip(data["left"], data["right"], strict=True):
        if a is None or b is None:
            continue
        common, ia, ib = np.intersect1d(a[0], b[0], return_indices=True)
        objs.append(obj[common])
        pl.append(a[1][ia])
        pr.append(b[1][ib])
    g = calibrate_rig(objs, pl, pr, (w, h))
    models["stereo"] = g.model.model.name
    bias = g.model.model_bias
    for side, est, std in (("left", g.left, g.left_std), ("right", g.right, g.right_std)):
        old = _old_std(g.std_model[side], bias[side] if bias else None)
        out += intrinsic_rows("stereo", est, std, old, truth, "intrinsics ")
    rv_true = np.array(p["rig"][0])
    t_true = np.array(p["rig"][1])
    old_rv, old_t = np.asarray(g.std_model["rotvec_rad"]), np.asarray(g.std_model["translation_mm"])
    if bias:
        old_rv = np.hypot(old_rv, bias["rotvec_rad"])
        old_t = np.hypot(old_t, bias["translation_mm"])
    for group, est, tru, new, old in (
            ("rotation", g.rotvec_rad, rv_true, g.rotvec_std, old_rv),
            ("translation", g.translation_mm, t_true, g.translation_std, old_t)):
        err = np.asarray(est) - tru
        for e_, n_, o_ in zip(err, np.asarray(new), old, strict=True):
            out.append(("stereo", group, e_ / n_, e_ / o_, abs(e_)))
    # cameras: own intrinsics per camera, then the joint fit
    intr, priors, obs = [], [], []
    for c, side in enumerate(("left", "right")):
        rc = calibrate_intrinsics(board, dets[side], (w, h))
        intr.append(rc.camera)
        priors.append(rc.richest)
        obs += [Observation(c, d.image[len(side):], obj[d.ids], d.px, d.image)
                for d in dets[side]]
    m = calibrate_cameras(["left", "right"], intr, obs, intrinsics_prior=priors)
    T_lr = np.eye(4)
    T_lr[:3, :3] = cv2.Rodrigues(rv_true)[0].T
    T_lr[:3, 3] = -T_lr[:3, :3] @ t_true
    est = m.T_ref_camera[1]
    row = m.cameras[1]
    dpos = est[:3, 3] - T_lr[:3, 3]
    for e_, n_, o_ in zip(dpos, row["position_std_mm"], row["std_model"]["position_std_mm"],
                          strict=True):
        out.append(("cameras", "position", e_ / n_, e_ / o_, abs(e_)))
    dR = est[:3, :3] @ T_lr[:3, :3].T
    angle = float(np.linalg.norm(cv2.Rodrigues(dR)[0]))
    out.append(("cameras", "rotation angle", angle / math.radians(row["rotation_std_deg"]),
                angle / math.radians(row["std_model"]["rotation_std_deg"]), angle))
    return out, models


def summarise(rows: list[tuple[str, str, float, float, float]]) -> list[str]:
    lines = []
    by: dict[tuple[str, str], list[tuple[float, float, float]]] = defaultdict(list)
    for path, group, zn, zo, err in rows:
        by[(path, group)].append((abs(zn), abs(zo), err))
        by[(path, "all")].append((abs(zn), abs(zo), err))
    for (path, group), v in sorted(by.items(), key=lambda kv: (kv[0][0], kv[0][1] != "all",
                                                              kv[0][1])):
        a = np.array(v)
        lines.append(f"  {path:10s} {group:22s} n {len(a):4d}  within 2 sigma new "
                     f"{100 * np.mean(a[:, 0] <= 2):5.1f} % (old {100 * np.mean(a[:, 1] <= 2):5.1f}"
                     f" %)  largest |z| new {a[:, 0].max():5.1f} (old {a[:, 1].max():6.1f})"
                     + (f"  median |error| {np.median(a[:, 2]):.3g}" if group != "all" else ""))
    return lines


def main() -> int:
    ap = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    ap.add_argument("--sets", type=int, default=30)
    ap.add_argument("--profiles", default="far,far_noisy,wide,cell",
                    help="comma-separated; NAME:N runs N sets of that profile")
    ap.add_argument("--cache", default="/tmp/vgripd_calib_rendered")
    args = ap.parse_args()
    text = []
    t0 = time.monotonic()
    for item in args.profiles.split(","):
        name, _, count = item.partition(":")
        n_sets = int(count) if count else args.sets
        fx, fy, cx, cy, dist, w, h = PROFILES[name]["camera"]
        cam = Camera(fx, fy, cx, cy, dist, w, h)
        assert cam.check() < 1e-6, "the renderer's rays do not project back to their pixels"
        cams = {"left": cam, "right": cam}
        rows: list[tuple[str, str, float, float, float]] = []
        models: dict[str, Counter[str]] = defaultdict(Counter)
        failed = 0
        for seed in range(n_sets):
            data = load_set(name, seed, Path(args.cache), cams)
            failed += sum(d is None for side in ("left", "right") for d in data[side])
            try:
                r, m = analyse(name, data)
            except CalibrationError as err:
                print(f"{name} set {seed}: {err}", flush=True)
                continue
            rows += r
            for k, v in m.items():
                models[k][v] += 1
        head = (f"{name}: {n_sets} sets, {VIEWS} views per camera, detector misses {failed}; "
                f"models chosen: " + "; ".join(f"{k} {dict(v)}" for k, v in models.items()))
        block = [head, *summarise(rows)]
        print("\n".join(block), f"[{time.monotonic() - t0:.0f} s]", flush=True)
        text += block
    body = "\n".join(text)
    harness.report("Calibration", "Coverage of the reported calibration uncertainties, rendered",
                   f"```\n{body}\n```", stamp, args.print_only)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
