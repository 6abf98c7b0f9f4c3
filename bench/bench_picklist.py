"""Pick lists: accuracy and time per instance, against the single-object path on the same plates.

The cell is ``bench/render_independent.py``'s 5 MP stereo rig (2x 2448x2048, f = 3500 px,
200 mm baseline, 850 mm above the plate) with the demo plate of ``config/example.toml``. A
pallet of ``--plates`` plates (3 columns, footprints touching: pitch = the marks' box plus
one mark diameter, each plate jittered by +-2 mm and +-3 deg about z, seeded) is laid out and
rendered *here*, with ``render_independent``'s OpenCV projection and scan-line rasteriser and
no vgripd code; the truth is the pose drawn for each plate.

Per scene, on the same plates and the same noise:

* **pick list** (vgripd, ``picking.max_objects = plates``): one job on the pallet image pair;
  every plate must come back once, pickable; its error against the truth and the job's time
  divided by the plates found;
* **single-object path** (the peer, vgripd as before pick lists, ``max_objects = 1``): one job
  per plate on an image pair of that plate alone (rendered with the same pose and noise
  generator state), as a cell without pick lists would have to be used: one plate at a time.

Prints per-instance error (translation mm, rotation deg: RMS, max), time per instance and the
ratio, and its section of bench/RESULTS.md (``--print-only``: printed only).

    .venv/bin/python bench/bench_picklist.py [--scenes 3] [--plates 6] [--print-only]
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import harness  # noqa: E402
from bench import render_independent as indep  # noqa: E402
from vgripd.config import Config, config_from_dict  # noqa: E402
from vgripd.geometry.transforms import pose_error  # noqa: E402
from vgripd.types import ImagePair  # noqa: E402
from vgripd.vision.pipeline import Pipeline  # noqa: E402

SECTION = "Pick lists: accuracy and time per instance"
JITTER_MM, JITTER_DEG = 2.0, 3.0


def cell_config(plate: indep.Plate, max_objects: int) -> Config:
    """vgripd's configuration of the cell (the renderer's numbers as calibration)."""
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
        "limits": {"max_translation_mm": 400.0, "max_rotation_deg": 20.0},
        "picking": {"max_objects": max_objects, "order": "axis", "axis": [1.0, 0.0, 0.0]},
    })


def pallet(plate: indep.Plate, count: int, rng: np.random.Generator, columns: int = 3
           ) -> list[np.ndarray]:
    """T_base_obj of each plate: a grid of ``columns`` columns in the reference's xy plane
    centred on it, footprints touching, each jittered; redrawn while two marks of different
    plates overlap."""
    ref = plate.T_base_obj_ref
    pts = plate.centres
    d = float(plate.diameters.max())
    pitch = np.ptp(pts[:, :2], axis=0) + d
    cols = min(columns, count)
    rows = math.ceil(count / columns)
    centroid = pts.mean(axis=0)
    poses: list[np.ndarray] = []
    placed: list[np.ndarray] = []
    for k in range(count):
        r, c = divmod(k, columns)
        for _ in range(1000):
            grid = np.array([(c - (cols - 1) / 2) * pitch[0] + rng.uniform(-JITTER_MM, JITTER_MM),
                             (r - (rows - 1) / 2) * pitch[1] + rng.uniform(-JITTER_MM, JITTER_MM),
                             0.0])
            turn = np.eye(4)
            turn[:3, :3] = cv2.Rodrigues(
                np.array([0.0, 0.0, math.radians(rng.uniform(-JITTER_DEG, JITTER_DEG))]))[0]
            move = indep.transform([0.0, 0.0, 0.0], grid)
            pivot = indep.transform([0.0, 0.0, 0.0], centroid)
            T = ref @ move @ pivot @ turn @ indep.rigid_inverse(pivot)
            marks = pts @ T[:3, :3].T + T[:3, 3]
            if not placed or np.min(np.linalg.norm(
                    marks[:, None] - np.vstack(placed)[None], axis=2)) > d:
                break
        poses.append(T)
        placed.append(marks)
    return poses


def render(cell: indep.Cell, poses: list[np.ndarray], seed: int) -> ImagePair:
    """The pair of every plate in ``poses`` (render_independent's rasteriser and imaging)."""
    rng = np.random.default_rng(seed)
    images = []
    for cam, T_right in ((cell.left, np.eye(4)), (cell.right, cell.T_right_left)):
        albedo = np.full((cam.height, cam.width), indep.BACKGROUND)
        for T_base_obj in poses:
            T_cam_obj = T_right @ indep.rigid_inverse(cell.T_base_camera) @ T_base_obj
            for i in range(len(cell.plate.names)):
                rim = indep.rim_pixels(cam, T_cam_obj, cell.plate.centres[i],
                                       cell.plate.diameters[i])
                box = indep.bounding_box(rim, cam.width, cam.height)
                if box is None:
                    continue
                x0, y0, w, h = box
                cov = indep.polygon_coverage(rim, x0, y0, w, h)
                level = indep.DARK if cell.plate.dark[i] else indep.BRIGHT
                patch = albedo[y0:y0 + h, x0:x0 + w]
                patch += cov * (level - patch)
        xs = np.arange(cam.width) / cam.width
        ys = np.arange(cam.height) / cam.height
        albedo *= 1.0 + indep.GRADIENT * ((xs[None, :] + ys[:, None]) / 2.0 - 0.5)
        albedo = np.asarray(cv2.GaussianBlur(albedo, (0, 0), indep.BLUR_PX), dtype=np.float64)
        albedo += rng.normal(0.0, indep.NOISE_STD, albedo.shape)
        images.append(np.clip(np.rint(albedo), 0, 255).astype(np.uint8))
    return ImagePair(left=images[0], right=images[1], t_mono_ns=time.monotonic_ns(),
                     source="bench_picklist")


def main() -> None:
    ap = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--plates", type=int, default=6)
    ap.add_argument("--seed", type=int, default=15)
    args = ap.parse_args()

    plate = indep.Plate.from_toml()
    cell = indep.Cell(plate)
    many = Pipeline(cell_config(plate, args.plates))
    one = Pipeline(cell_config(plate, 1))
    rng = np.random.default_rng(args.seed)
    rows: dict[str, list[tuple[float, float, float]]] = {"pick list": [], "single object": []}
    missed: dict[str, int] = {"pick list": 0, "single object": 0}
    render_s = 0.0
    jobs_ms: list[float] = []
    for s in range(args.scenes):
        poses = pallet(plate, args.plates, rng)
        t = time.perf_counter()
        pair = render(cell, poses, seed=1000 + s)
        render_s += time.perf_counter() - t
        t = time.perf_counter()
        result = many.process(pair, s)
        jobs_ms.append((time.perf_counter() - t) * 1e3)
        per = jobs_ms[-1] / max(1, len(result.instances))
        found = [i for i in result.instances if i.status.pose_valid and i.T_base_obj is not None]
        taken: set[int] = set()
        for inst in found:
            assert inst.T_base_obj is not None
            errs = [pose_error(inst.T_base_obj, T) for T in poses]
            k = int(np.argmin([e[0] for e in errs]))
            if k in taken or errs[k][0] > 5.0:
                continue
            taken.add(k)
            rows["pick list"].append((per, *errs[k]))
        missed["pick list"] += args.plates - len(taken)
        for k, T in enumerate(poses):
            t = time.perf_counter()
            alone = render(cell, [T], seed=1000 + s)
            render_s += time.perf_counter() - t
            t = time.perf_counter()
            single = one.process(alone, k)
            dt = (time.perf_counter() - t) * 1e3
            if single.status.pose_valid and single.T_base_obj is not None:
                rows["single object"].append((dt, *pose_error(single.T_base_obj, T)))
            else:
                missed["single object"] += 1
        statuses = Counter(i.status.name for i in result.instances)
        print(f"scene {s}: pick list {len(taken)}/{args.plates} plates, {dict(statuses)}",
              flush=True)

    table = ["| path | instances | time per instance ms (median) | translation RMS / max mm | "
             "rotation RMS / max deg | missed |", "|---|---:|---:|---:|---:|---:|"]
    med: dict[str, float] = {}
    for name, r in rows.items():
        a = np.array(r) if r else np.zeros((0, 3))
        med[name] = float(np.median(a[:, 0])) if len(a) else math.nan
        rms = np.sqrt(np.mean(a[:, 1:] ** 2, axis=0)) if len(a) else [math.nan] * 2
        mx = a[:, 1:].max(axis=0) if len(a) else [math.nan] * 2
        table.append(f"| {name} | {len(a)} | {med[name]:.1f} | {rms[0]:.4f} / {mx[0]:.4f} | "
                     f"{rms[1]:.4f} / {mx[1]:.4f} | {missed[name]} |")
    ratio = med["pick list"] / med["single object"]
    text = "\n".join(table)
    print(text)
    print(f"time per instance, pick list / single object: {ratio:.2f}; pick-list job median "
          f"{np.median(jobs_ms):.1f} ms for {args.plates} plates")
    print(f"rendering: {render_s:.1f} s")
    body = (
        f"render_independent's 5 MP stereo cell; {args.scenes} "
        f"pallets of {args.plates} demo plates (3 columns, footprints touching, +-{JITTER_MM:g}"
        f" mm, +-{JITTER_DEG:g} deg), rendered by the bench with OpenCV's projection (no "
        "vgripd code); truth = the poses drawn. Pick list: one job per pallet "
        f"(`picking.max_objects = {args.plates}`), its time divided by the instances "
        "returned. Peer: the single-object path (`max_objects = 1`), one job per plate on a "
        "pair of that plate alone, same pose and noise.\n\n"
        f"{text}\n\n"
        f"Time per instance, pick list / single object: **{ratio:.2f}** (median); a whole "
        f"pick-list job took {np.median(jobs_ms):.0f} ms (median) for {args.plates} plates, "
        f"against {args.plates} x {med['single object']:.0f} ms one plate at a time.\n"
    )
    harness.report("Pick lists", SECTION, body, stamp, args.print_only)


if __name__ == "__main__":
    main()
