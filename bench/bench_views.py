"""Several views per job: one robot-mounted camera taking 1, 2, 4 or 8 views of a 1.5 m frame.

The object and the view poses are bench/bench_multiview.py's: config/samples/two_rigs_frame.toml's
frame (eight 30 mm marks on each face, each face seen only from its side) and camera poses
about 2 m from it in pairs 400 mm apart (views 1-2 in front, 3-4 behind, 5-6 and 7-8 at
45 deg). Here they are the poses one camera on the flange is carried to: flange pose =
camera pose @ inv(T_flange_camera), and vgripd gets the config ``vision.views = N`` with the
N flange poses (``scene.views_config``: each view its own camera), not a cell of N cameras.

Images are rendered with bench_multiview's OpenCV-only renderer (nothing from vgripd); the
truth is the pose drawn here. One view of circle marks carries neither depth nor identity,
so vgripd refuses a one-view job of this object (single-camera mode needs ArUco/template
marks); the one-view row is the named peer alone: OpenCV ``solvePnP`` (iterative) on view 1's
blob centroids, each identified as the nearest mark projected at the taught pose (the peer is
given the identities; vgripd finds them). For N >= 2 the peer is bench_multiview's plain OpenCV
multi-view pipeline (triangulatePoints per pair of views, averaging, Kabsch) on the same images.

Errors: ``mm`` = the largest displacement of any of the 16 marks between found and true pose
(the far face included); ``deg`` = rotation angle.

    .venv/bin/python bench/bench_views.py [--poses 6] [--print-only]
"""

from __future__ import annotations

import copy
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
from bench.bench_multiview import INTRINSICS, SAMPLE, Frame, Peer, cell, errors, stats  # noqa: E402
from vgripd.config import config_from_dict  # noqa: E402
from vgripd.types import ImagePair  # noqa: E402
from vgripd.vision.pipeline import Pipeline  # noqa: E402

SECTION = "Several views per job: one robot-mounted camera, 1 to 8 views of a 1.5 m frame"
#: The camera on the flange (independent of vgripd: composed here with OpenCV's Rodrigues).
FC_ROTVEC, FC_T = np.array([0.02, -0.01, 0.03]), np.array([10.0, 60.0, 120.0])


def T_flange_camera() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(FC_ROTVEC)[0]
    T[:3, 3] = FC_T
    return T


def views_pipeline(n: int, doc: dict) -> tuple[Pipeline, list[np.ndarray], Peer, list]:
    """vgripd for N views, the N camera poses, the flange poses and the peer."""
    data, poses, rigs = cell(n, copy.deepcopy(doc))
    T_fc = T_flange_camera()
    flanges = [T @ indep.rigid_inverse(T_fc) for T in poses]
    cfg = {"object": data["object"], "reference": data["reference"],
           "vision": {**data["vision"], "views": n},
           "camera": {"type": "synthetic"},
           "calibration": {"left": INTRINSICS, "hand_eye": {
               "mounting": "robot", "T_flange_camera": {
                   "translation_mm": FC_T.tolist(), "rotvec_rad": FC_ROTVEC.tolist()}}}}
    return Pipeline(config_from_dict(cfg)), poses, Peer(Frame(doc), poses, rigs), flanges


class PnpPeer:
    """One view: OpenCV solvePnP on blob centroids identified at the taught pose."""

    def __init__(self, frame: Frame, T_base_cam: np.ndarray, peer: Peer) -> None:
        self.frame, self.T_base_cam, self.peer = frame, T_base_cam, peer
        T_cam_ref = indep.rigid_inverse(T_base_cam) @ frame.T_ref
        self.expected = frame.camera.project(frame.centres @ T_cam_ref[:3, :3].T
                                             + T_cam_ref[:3, 3])
        eye = indep.rigid_inverse(T_cam_ref)[:3, 3]
        self.facing = ((eye - frame.centres) * frame.normals).sum(axis=1) > 0

    def locate(self, image: np.ndarray) -> np.ndarray | None:
        pts = self.peer.centroids(image)
        obj, img = [], []
        for i in np.flatnonzero(self.facing):
            if len(pts) == 0:
                break
            d = np.linalg.norm(pts - self.expected[i], axis=1)
            if d.min() < 40.0:
                obj.append(self.frame.centres[i])
                img.append(pts[d.argmin()])
        if len(obj) < 4:
            return None
        ok, rvec, tvec = cv2.solvePnP(np.array(obj), np.array(img), self.frame.camera.K,
                                      self.frame.camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return None
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        return self.T_base_cam @ T


def main() -> None:
    parser = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    parser.add_argument("--poses", type=int, default=6)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()
    with SAMPLE.open("rb") as fh:
        doc = tomllib.load(fh)
    frame = Frame(doc)
    rng = np.random.default_rng(args.seed)
    truths = [frame.random_pose(rng) for _ in range(args.poses)]
    load_before = os.getloadavg()
    t_start = time.perf_counter()
    setups = {n: views_pipeline(n, doc) for n in (2, 4, 8)}
    poses8 = setups[8][1]
    pnp = PnpPeer(frame, poses8[0], setups[8][2])
    ours: dict[int, dict[str, list[float]]] = {n: {"mm": [], "deg": [], "cpu_ms": []}
                                               for n in setups}
    theirs: dict[int, dict[str, list[float]]] = {n: {"mm": [], "deg": []}
                                                 for n in (1, *setups)}
    statuses: dict[int, dict[str, int]] = {n: {} for n in setups}
    render_rng = np.random.default_rng(args.seed + 100)
    for k, truth in enumerate(truths):
        # The 8 views of this pose; N views are the first N (the same images for every N).
        images = [frame.render(T_cam, truth, render_rng) for T_cam in poses8]
        T = pnp.locate(images[0])
        if T is not None:
            mm, deg = errors(T, truth, frame.centres)
            theirs[1]["mm"].append(mm)
            theirs[1]["deg"].append(deg)
        for n, (pipe, _, peer, flanges) in setups.items():
            pair = ImagePair.of_views(images[:n], 0, T_base_flange=np.stack(flanges))
            c0 = time.process_time()
            result = pipe.process(pair, k)
            ours[n]["cpu_ms"].append((time.process_time() - c0) * 1e3)
            statuses[n][result.status.name] = statuses[n].get(result.status.name, 0) + 1
            if result.T_base_obj is not None and result.status.pose_valid:
                mm, deg = errors(result.T_base_obj, truth, frame.centres)
                ours[n]["mm"].append(mm)
                ours[n]["deg"].append(deg)
            T = peer.locate(images[:n])
            if T is not None:
                mm, deg = errors(T, truth, frame.centres)
                theirs[n]["mm"].append(mm)
                theirs[n]["deg"].append(deg)
    elapsed = time.perf_counter() - t_start
    load_after = os.getloadavg()

    def cellfmt(values: list[float], digits: int) -> str:
        if not values:
            return "no pose"
        rms, worst = stats(values)
        return f"{rms:.{digits}f} / {worst:.{digits}f}"

    table = ["| views | vgripd mark error RMS / max mm | vgripd rotation RMS / max deg | "
             "peer mm RMS / max | peer deg RMS / max | peer | vgripd CPU ms median | "
             "vgripd statuses | peer poses |", "|---|---|---|---|---|---|---|---|---|"]
    table.append(f"| 1 | refused (circle marks, one image) | - | {cellfmt(theirs[1]['mm'], 3)} "
                 f"| {cellfmt(theirs[1]['deg'], 4)} | solvePnP | - | - | "
                 f"{len(theirs[1]['mm'])}/{args.poses} |")
    for n in setups:
        table.append(
            f"| {n} | {cellfmt(ours[n]['mm'], 3)} | {cellfmt(ours[n]['deg'], 4)} | "
            f"{cellfmt(theirs[n]['mm'], 3)} | {cellfmt(theirs[n]['deg'], 4)} | "
            f"triangulate + Kabsch | {float(np.median(ours[n]['cpu_ms'])):.1f} | "
            f"{statuses[n]} | {len(theirs[n]['mm'])}/{args.poses} |")
    text = "\n".join(table)
    print(f"{elapsed:.0f} s, load {load_before} -> {load_after}")
    head = [f"{args.poses} poses of the frame, each rendered "
            "independently of vgripd from 8 view poses; N views use the first N images "
            "(1-2 front face, 3-4 back face, 5-8 at 45 deg). vgripd: `vision.views = N` "
            "through `Pipeline.process` (the daemon's path after the last CAPTURE). Errors "
            "against the rendered truth (largest displacement of the 16 marks, rotation "
            "angle).", "", text, ""]
    harness.report("Vision: accuracy and locate time", SECTION, "\n".join(head), stamp,
                   args.print_only)


if __name__ == "__main__":
    main()
