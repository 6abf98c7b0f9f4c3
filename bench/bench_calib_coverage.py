"""Do the reported standard deviations of an intrinsic calibration cover its error?

Run from the repository root with the project's interpreter::

    .venv/bin/python bench/bench_calib_coverage.py [--trials 40] [--print-only]

Intrinsics: per trial 14 views of a 9x7-corner chessboard at random tilts (up to 35 deg) and rolls, the
corners projected through a known camera with 0.1 px Gaussian noise (projected, not rendered:
what is measured is the model choice, not the detector), calibrated by ``calibrate_intrinsics``
with the automatic model choice and with p1 p2 k3 all free. For each parameter (fx, fy, cx,
cy, k1, k2, p1, p2, k3) the error against the truth in units of the reported sigma; printed:
the share of estimated parameters within 2 sigma (95 % expected), per parameter the largest
|z|, and how often each model was chosen. A held term (sigma 0, not estimated) is not counted.

Then the same profiles as a stereo rig (``rig_z``: the rig rotation vector and translation)
and through ``calibrate cameras``' path (``cameras_z``: each camera's intrinsics from its own
views, then the joint fit; the second camera's position and rotation). Each printed with the
reported sigma and with the rule main had before (``old``: the chosen model's own sigma with
the shift to the richest model; for cameras the fit's own sigma, intrinsics taken as exact),
and the median |error| of each intrinsic (the point estimates do not depend on the rule).
bench/bench_calib_rendered.py measures the same on rendered images.

Profiles (from the issue): ``far`` a 2448x2048 camera (f 3000 px) seeing a 60 mm board at
2.2 m with p1 = p2 = 0.0002; ``wide`` a 1280x1024 camera (f 800 px) with k3 = -0.01 and a 30 mm
board at 500 mm.
"""

from __future__ import annotations

import math
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from vgripd.calib.boards import Board, Detection  # noqa: E402
from vgripd.calib.intrinsics import calibrate_intrinsics  # noqa: E402
from vgripd.errors import CalibrationError  # noqa: E402
from vgripd.geometry.camera_model import CameraModel  # noqa: E402
from vgripd.geometry.transforms import matrix_from_rotvec  # noqa: E402

PROFILES = {
    "far": dict(camera=CameraModel(3000.0, 3000.0, 1230.0, 1018.0, 0.0,
                                   (-0.08, 0.12, 0.0002, 0.0002, 0.0), 2448, 2048),
                board="chessboard:9x7:60", distance=2200.0),
    "wide": dict(camera=CameraModel(800.0, 800.0, 645.0, 508.0, 0.0,
                                    (-0.25, 0.08, 0.0, 0.0, -0.01), 1280, 1024),
                 board="chessboard:9x7:30", distance=500.0),
}
NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def views(camera: CameraModel, board: Board, distance: float, rng: np.random.Generator,
          n: int = 14) -> list[Detection]:
    obj = board.object_points()
    centre = obj.mean(axis=0)
    out: list[Detection] = []
    while len(out) < n:
        axis = rng.normal(size=2)
        tilt = np.array([*axis / np.linalg.norm(axis), 0.0]) * math.radians(rng.uniform(5, 35))
        R = matrix_from_rotvec(tilt) @ matrix_from_rotvec([0, 0, rng.uniform(-0.5, 0.5)])
        # the board anywhere in the image (distortion shows at the edges)
        shift = np.array([rng.uniform(-0.35, 0.35) * camera.width / camera.fx,
                          rng.uniform(-0.35, 0.35) * camera.height / camera.fy, 1.0])
        t = shift * distance * rng.uniform(0.85, 1.15) - R @ centre
        pts = obj @ R.T + t
        px = camera.project(pts) + rng.normal(0, 0.1, (len(obj), 2))
        if (px.min() < 5 or px[:, 0].max() > camera.width - 5
                or px[:, 1].max() > camera.height - 5):
            continue
        out.append(Detection(f"v{len(out)}", (camera.width, camera.height),
                             np.arange(len(obj), dtype=np.int64), px))
    return out


def old_std(result: Any) -> dict[str, Any]:
    """The sigmas main reported before the richest model's sigma was used: the chosen
    model's own with the shift to the richest model in quadrature."""
    std = result.std_model or result.std
    bias = result.model.model_bias
    if bias is None:
        return dict(std)
    out = {k: math.hypot(std[k], bias[k]) for k in ("fx", "fy", "cx", "cy")}
    out["dist"] = [math.hypot(s, b) if s > 0 else 0.0
                   for s, b in zip(std["dist"], bias["dist"], strict=True)]
    return out


def z_scores(result: object, camera: CameraModel, old: bool = False) -> dict[str, float]:
    cam = result.camera  # type: ignore[attr-defined]
    std = old_std(result) if old else result.std  # type: ignore[attr-defined]
    truth = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
             **dict(zip(("k1", "k2", "p1", "p2", "k3"), camera.dist, strict=True))}
    est = {k: cam[k] for k in ("fx", "fy", "cx", "cy")}
    est.update(zip(("k1", "k2", "p1", "p2", "k3"), cam["dist"], strict=True))
    sig = {k: std[k] for k in ("fx", "fy", "cx", "cy")}
    sig.update(zip(("k1", "k2", "p1", "p2", "k3"), std["dist"], strict=True))
    out = {}
    for k in NAMES:
        if sig[k] == 0:  # held at 0, not estimated: not a reported uncertainty
            continue
        out[k] = (est[k] - truth[k]) / sig[k]
    return out


def _share(z: np.ndarray) -> str:
    return f"{100 * np.mean(np.abs(z) <= 2):5.1f} %, largest {np.abs(z).max():5.1f}"


def main() -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--trials", type=int, default=40)
    args = ap.parse_args()
    stamp = harness.Stamp(harness.bench_command())
    lines: list[str] = []

    def say(line: str) -> None:
        say(line, flush=True)
        lines.append(line)

    for name, p in PROFILES.items():
        board = Board.parse(p["board"])
        for label, opts in (("auto", {}), ("all free", {"fix_k3": False,
                                                        "fix_tangential": False})):
            zs: list[dict[str, float]] = []
            zs_old: list[dict[str, float]] = []
            errors: dict[str, list[float]] = {k: [] for k in NAMES}
            models: Counter[str] = Counter()
            for trial in range(args.trials):
                rng = np.random.default_rng(trial)
                dets = views(p["camera"], board, p["distance"], rng)
                try:
                    r = calibrate_intrinsics(board, dets, (p["camera"].width,
                                                           p["camera"].height), **opts)
                except CalibrationError as err:
                    say(f"  {name} trial {trial}: {err}")
                    continue
                models[r.model.model.name] += 1
                z = z_scores(r, p["camera"])
                zs.append(z)
                zs_old.append(z_scores(r, p["camera"], old=True))
                for k, v in z.items():
                    errors[k].append(abs(v) * _sigma(r, k))
            flat = np.array([v for z in zs for v in z.values()])
            flat_old = np.array([v for z in zs_old for v in z.values()])
            worst = {k: max((abs(z[k]) for z in zs if k in z), default=0.0) for k in NAMES}
            worst_text = " ".join(f"{k} {v:.1f}" for k, v in worst.items())
            med = " ".join(f"{k} {np.median(v):.3g}" for k, v in errors.items() if v)
            say(f"{name:5s} {label:8s} within 2 sigma {_share(flat)} (old rule "
                  f"{_share(flat_old)}) | largest |z|: {worst_text} | models {dict(models)}")
            say(f"      median |error|: {med}")
    for name in PROFILES:
        new_z, old_z = rig_z_both(args.trials, name)
        new, old = np.array(new_z), np.array(old_z)
        say(f"{name:5s} stereo rotation + translation: within 2 sigma {_share(new)} (old rule "
              f"{_share(old)})")
    for name in PROFILES:
        rows = cameras_z(args.trials, name)
        new = np.array([r["new"][:3] for r in rows])
        old = np.array([r["old"][:3] for r in rows])
        rot = np.array([r["new"][3] for r in rows])
        rot_old = np.array([r["old"][3] for r in rows])
        say(f"{name:5s} cameras position: within 2 sigma {_share(new)} (fit's own "
              f"{_share(old)}); rotation angle / rotation_std: {_share(rot)} (fit's own "
              f"{_share(rot_old)})")
    harness.report("Calibration", "Coverage of the reported intrinsic uncertainties",
                   f"{args.trials} sets per profile, projected corners (0.1 px noise); profiles, "
                   "paths and the old rule: bench/bench_calib_coverage.py's docstring.\n\n```\n"
                   + "\n".join(lines) + "\n```", stamp, args.print_only)
    return 0


def _sigma(result: Any, k: str) -> float:
    std = result.std
    if k in std:
        return float(std[k])
    return float(std["dist"][("k1", "k2", "p1", "p2", "k3").index(k)])


def stereo_views(camera: CameraModel, board: Board, distance: float, T_right_left: np.ndarray,
                 rng: np.random.Generator, n: int = 14):
    """Board views seen by both cameras of a rig (the right one: the same model)."""
    obj = board.object_points()
    centre = obj.mean(axis=0)
    objs, left, right = [], [], []
    while len(objs) < n:
        axis = rng.normal(size=2)
        tilt = np.array([*axis / np.linalg.norm(axis), 0.0]) * math.radians(rng.uniform(5, 35))
        R = matrix_from_rotvec(tilt) @ matrix_from_rotvec([0, 0, rng.uniform(-0.5, 0.5)])
        shift = np.array([rng.uniform(-0.3, 0.3) * camera.width / camera.fx,
                          rng.uniform(-0.3, 0.3) * camera.height / camera.fy, 1.0])
        t = shift * distance * rng.uniform(0.85, 1.15) - R @ centre
        pl = obj @ R.T + t
        pr = pl @ T_right_left[:3, :3].T + T_right_left[:3, 3]
        a = camera.project(pl) + rng.normal(0, 0.1, (len(obj), 2))
        b = camera.project(pr) + rng.normal(0, 0.1, (len(obj), 2))
        if any(p.min() < 5 or p[:, 0].max() > camera.width - 5
               or p[:, 1].max() > camera.height - 5 for p in (a, b)):
            continue
        objs.append(obj)
        left.append(a)
        right.append(b)
    return objs, left, right


def rig_z(trials: int, profile: str = "far", old: bool = False) -> list[np.ndarray]:
    """Per trial: the rig rotation and translation errors in units of the reported sigma
    (``old``: of the sigma main reported before, the chosen model's own with the shift)."""
    return rig_z_both(trials, profile)[1 if old else 0]


def rig_z_both(trials: int, profile: str = "far",
               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """:func:`rig_z` with the reported sigma and with the old rule, from the same fits."""
    from vgripd.calib.rig import calibrate_rig
    from vgripd.geometry.transforms import make_transform, rotvec_from_matrix

    p = PROFILES[profile]
    camera = p["camera"]
    board = Board.parse(str(p["board"]))
    T = make_transform(matrix_from_rotvec([0.01, -0.12, 0.02]), [-300.0, 4.0, 20.0])
    out, out_old = [], []
    for trial in range(trials):
        rng = np.random.default_rng(100 + trial)
        objs, left, right = stereo_views(camera, board, float(p["distance"]), T, rng)
        r = calibrate_rig(objs, left, right, (camera.width, camera.height))
        R_est = matrix_from_rotvec(r.rotvec_rad)
        drot = rotvec_from_matrix(R_est @ T[:3, :3].T)  # small: error rotation vector
        dt = np.asarray(r.translation_mm) - T[:3, 3]
        out.append(np.concatenate([drot / np.asarray(r.rotvec_std),
                                   dt / np.asarray(r.translation_std)]))
        s_rot = np.asarray(r.std_model["rotvec_rad"])
        s_t = np.asarray(r.std_model["translation_mm"])
        bias = r.model.model_bias
        if bias:
            s_rot = np.hypot(s_rot, bias["rotvec_rad"])
            s_t = np.hypot(s_t, bias["translation_mm"])
        out_old.append(np.concatenate([drot / s_rot, dt / s_t]))
    return out, out_old


def cameras_z(trials: int, profile: str = "far") -> list[dict[str, np.ndarray]]:
    """``calibrate cameras``' path on the profile as two cameras (the rig of :func:`rig_z`):
    each camera's intrinsics from its own views (automatic model choice), then the joint fit.
    Per trial the second camera's position error (x y z, in the reference camera) in units of
    its reported sigma (``new``) and of the fit's own sigma (``old``, ``std_model``: the
    intrinsics taken as exact), and the rotation error angle over ``rotation_std_deg``."""
    from vgripd.calib.camera_poses import Observation, calibrate_cameras
    from vgripd.geometry.transforms import invert_transform, make_transform, rotation_angle

    p = PROFILES[profile]
    camera = p["camera"]
    board = Board.parse(str(p["board"]))
    T = make_transform(matrix_from_rotvec([0.01, -0.12, 0.02]), [-300.0, 4.0, 20.0])
    T_left_right = invert_transform(T)
    size = (camera.width, camera.height)
    out = []
    for trial in range(trials):
        rng = np.random.default_rng(100 + trial)
        objs, left, right = stereo_views(camera, board, float(p["distance"]), T, rng)
        ids = np.arange(len(objs[0]), dtype=np.int64)
        intr, priors, obs = [], [], []
        for c, pxs in enumerate((left, right)):
            dets = [Detection(f"c{c}_{i}", size, ids, px) for i, px in enumerate(pxs)]
            r = calibrate_intrinsics(board, dets, size)
            intr.append(r.camera)
            priors.append(r.richest)
            obs += [Observation(c, str(i), o, px, f"c{c}_{i}")
                    for i, (o, px) in enumerate(zip(objs, pxs, strict=True))]
        m = calibrate_cameras(["a", "b"], intr, obs, intrinsics_prior=priors)
        est = m.T_ref_camera[1]
        dpos = est[:3, 3] - T_left_right[:3, 3]
        angle = rotation_angle(est[:3, :3] @ T_left_right[:3, :3].T)
        row = m.cameras[1]
        own = row["std_model"]
        out.append({
            "new": np.concatenate([dpos / np.asarray(row["position_std_mm"]),
                                   [angle / np.radians(row["rotation_std_deg"])]]),
            "old": np.concatenate([dpos / np.asarray(own["position_std_mm"]),
                                   [angle / np.radians(own["rotation_std_deg"])]])})
    return out


if __name__ == "__main__":
    raise SystemExit(main())
