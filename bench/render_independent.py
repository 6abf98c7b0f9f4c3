"""An independent renderer for the locate benchmark: OpenCV's camera model, no vgripd code.

The synthetic camera driver (``drivers/cameras/synthetic.py``) draws its images through
``vgripd.geometry.camera_model`` -- the same model the pipeline uses to undo the perspective bias
of circle centres. An error shared by both would cancel and never show in the benchmark. This
module renders the same cell with nothing from ``vgripd`` or ``drivers``:

* the plate (mark centres, diameters, polarity) and its taught reference pose are read with
  ``tomllib`` from ``config/example.toml``; the cameras, the stereo rig and the camera's place
  above the plate are plain numbers defined here (``CAMERAS``, ``T_RIGHT_LEFT``,
  ``T_BASE_CAMERA``), which ``bench_locate.py`` hands to vgripd as its calibration;
* the rim of each disc is sampled at ``RIM_POINTS`` points in the object frame and projected with
  ``cv2.projectPoints`` (OpenCV's pinhole + k1 k2 p1 p2 k3 distortion);
* the polygon is rasterised by supersampling: ``ROWS_PER_PX`` scan lines per pixel row, each cut
  exactly by the polygon's edges (even-odd rule), the covered length of every pixel summed, so a
  pixel's grey level is its area coverage (sampled in y, exact in x);
* lighting gradient, Gaussian blur and sensor noise as in the bench's synthetic camera settings.

The truth is the 3-D pose ``T_base_obj`` drawn here, never a 2-D centre: under perspective the
image of a circle's centre is not the centroid of the imaged disc (the nearer half looks bigger).

``main`` checks the renderer (no noise, no blur): (1) the coverage of every mark against a
second, unrelated rendering path -- each of 16 x 16 sub-pixel samples undistorted with
``cv2.undistortPoints`` (iterated to convergence), cast as a ray and intersected with the mark's
plane -- and (2) each mark's coverage centroid against the area centroid of its projected rim
polygon (shoelace formula, exact for the polygon) and against ``cv2.projectPoints`` of the 3-D
centre; the latter difference is the perspective bias the pipeline must remove.

    .venv/bin/python bench/render_independent.py [--poses 3]
"""

from __future__ import annotations

import argparse
import math
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PLATE_TOML = ROOT / "config" / "example.toml"

# ------------------------------------------------------------------------------- the cell
W, H, F = 2448, 2048, 3500.0
BASELINE_MM, DEPTH_MM = 200.0, 840.0
_DIST = (-0.05, 0.08, 0.0002, -0.0001, 0.0)
_CX, _CY = (W - 1) / 2 + 3.2, (H - 1) / 2 - 2.1
#: Intrinsics (OpenCV conventions: pixel centres at integers, dist = k1 k2 p1 p2 k3).
CAMERAS = {
    "left": {"fx": F, "fy": F, "cx": _CX, "cy": _CY, "dist": list(_DIST), "width": W, "height": H},
    "right": {"fx": F * 1.002, "fy": F, "cx": _CX - 5.0, "cy": _CY, "dist": list(_DIST),
              "width": W, "height": H},
}
# The right camera sits 200 mm along the left camera's x axis, turned about y so that the two
# optical axes meet at 840 mm: T_left_right = (Ry(-toe), [200, 0, 0]); its inverse as rotvec + t.
_TOE = math.atan2(BASELINE_MM, DEPTH_MM)
#: Pose of the left camera in the right camera frame (X_R = R X_L + t), rotvec (rad) and mm.
T_RIGHT_LEFT = {"rotvec_rad": [0.0, _TOE, 0.0],
                "translation_mm": [-BASELINE_MM * math.cos(_TOE), 0.0, BASELINE_MM * math.sin(_TOE)]}
#: Pose of the left camera in the robot base frame: 850 mm up, looking straight down.
T_BASE_CAMERA = {"rotvec_rad": [math.pi, 0.0, 0.0], "translation_mm": [600.0, 100.0, 850.0]}

BACKGROUND, DARK, BRIGHT = 190.0, 35.0, 250.0
#: The bench's imaging conditions (same as bench_locate's synthetic camera options).
BLUR_PX, NOISE_STD, GRADIENT = 0.8, 2.0, 0.3
MAX_SHIFT_MM, MAX_TILT_DEG = 20.0, 8.0
#: Rim samples per mark: the inscribed polygon is within 3e-6 px of the ~42 px rim.
RIM_POINTS = 4096
#: Scan lines per pixel row (coverage is exact along each line).
ROWS_PER_PX = 128


def transform(rotvec: list[float] | np.ndarray, translation: list[float] | np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from an axis-angle vector (rad) and a translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64).reshape(3, 1))[0]
    T[:3, 3] = translation
    return T


def pose_matrix(table: dict) -> np.ndarray:
    """4x4 transform of a ``{translation_mm, rotvec_rad}`` table (as in the TOML files)."""
    return transform(table.get("rotvec_rad", [0.0, 0.0, 0.0]), table["translation_mm"])


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


@dataclass(frozen=True)
class Camera:
    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        K = np.array([[d["fx"], 0.0, d["cx"]], [0.0, d["fy"], d["cy"]], [0.0, 0.0, 1.0]])
        return cls(K, np.asarray(d["dist"], dtype=np.float64), int(d["width"]), int(d["height"]))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(n, 2) pixels of (n, 3) points given in this camera's frame (``cv2.projectPoints``)."""
        px, _ = cv2.projectPoints(np.ascontiguousarray(points_cam, dtype=np.float64).reshape(-1, 1, 3),
                                  np.zeros(3), np.zeros(3), self.K, self.dist)
        return px.reshape(-1, 2)


@dataclass(frozen=True)
class Plate:
    """The object's circular marks (object frame, mm) and its taught reference pose."""

    names: tuple[str, ...]
    centres: np.ndarray  # (n, 3)
    diameters: np.ndarray  # (n,)
    dark: np.ndarray  # (n,) bool
    T_base_obj_ref: np.ndarray  # (4, 4)
    toml: dict  # the [object] and [reference] tables as read

    @classmethod
    def from_toml(cls, path: Path = PLATE_TOML) -> Plate:
        with path.open("rb") as fh:
            doc = tomllib.load(fh)
        obj, ref = doc["object"], doc["reference"]
        if obj.get("definition", "cad") != "cad":
            raise ValueError(f"{path}: the renderer needs object.definition = 'cad'")
        feats = obj["features"]
        if any(f.get("kind") != "circle" for f in feats):
            raise ValueError(f"{path}: the renderer draws circular marks only")
        return cls(
            names=tuple(f["name"] for f in feats),
            centres=np.array([f["xyz_mm"] for f in feats], dtype=np.float64),
            diameters=np.array([f["diameter_mm"] for f in feats], dtype=np.float64),
            dark=np.array([f.get("polarity", "dark") == "dark" for f in feats]),
            T_base_obj_ref=pose_matrix(ref["T_base_obj"]),
            toml={"object": obj, "reference": ref},
        )


class Cell:
    """Stereo cell + plate; draws random object poses and renders image pairs of them."""

    def __init__(self, plate: Plate | None = None) -> None:
        self.plate = plate or Plate.from_toml()
        self.left = Camera.from_dict(CAMERAS["left"])
        self.right = Camera.from_dict(CAMERAS["right"])
        self.T_right_left = pose_matrix(T_RIGHT_LEFT)
        self.T_base_camera = pose_matrix(T_BASE_CAMERA)

    def random_pose(self, rng: np.random.Generator) -> np.ndarray:
        """T_base_obj: the reference turned about the marks' centroid (rotation vector with each
        component uniform in +-MAX_TILT_DEG, base axes), then shifted uniformly in +-MAX_SHIFT_MM."""
        ref = self.plate.T_base_obj_ref
        pivot = ref[:3, :3] @ self.plate.centres.mean(axis=0) + ref[:3, 3]
        shift = rng.uniform(-MAX_SHIFT_MM, MAX_SHIFT_MM, 3)
        R = cv2.Rodrigues(np.radians(rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG, 3)))[0]
        move = np.eye(4)
        move[:3, :3] = R
        move[:3, 3] = pivot - R @ pivot + shift
        return move @ ref

    def views(self, T_base_obj: np.ndarray) -> list[tuple[Camera, np.ndarray]]:
        """(camera, T_cam_obj) for the left and the right camera."""
        T_left_obj = rigid_inverse(self.T_base_camera) @ T_base_obj
        return [(self.left, T_left_obj), (self.right, self.T_right_left @ T_left_obj)]

    def render_pair(self, T_base_obj: np.ndarray, rng: np.random.Generator,
                    clean: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """8-bit (left, right) images of the plate at ``T_base_obj``."""
        left, right = (self.render(cam, T, rng, clean) for cam, T in self.views(T_base_obj))
        return left, right

    def render(self, cam: Camera, T_cam_obj: np.ndarray, rng: np.random.Generator,
               clean: bool = False) -> np.ndarray:
        """One 8-bit view; ``clean`` leaves out gradient, blur and noise (returns float64)."""
        albedo = np.full((cam.height, cam.width), BACKGROUND)
        for i in range(len(self.plate.names)):
            rim = rim_pixels(cam, T_cam_obj, self.plate.centres[i], self.plate.diameters[i])
            box = bounding_box(rim, cam.width, cam.height)
            if box is None:
                continue
            x0, y0, w, h = box
            cov = polygon_coverage(rim, x0, y0, w, h)
            level = DARK if self.plate.dark[i] else BRIGHT
            patch = albedo[y0:y0 + h, x0:x0 + w]
            patch += cov * (level - patch)
        if clean:
            return albedo
        xs = np.arange(cam.width) / cam.width
        ys = np.arange(cam.height) / cam.height
        albedo *= 1.0 + GRADIENT * ((xs[None, :] + ys[:, None]) / 2.0 - 0.5)
        albedo = np.asarray(cv2.GaussianBlur(albedo, (0, 0), BLUR_PX), dtype=np.float64)
        albedo += rng.normal(0.0, NOISE_STD, albedo.shape)
        return np.clip(np.rint(albedo), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------- geometry
def rim_points_obj(centre: np.ndarray, diameter: float, n: int = RIM_POINTS) -> np.ndarray:
    """(n, 3) points on a mark's rim (object frame; the mark lies in the plane z = centre z)."""
    a = 2.0 * np.pi * np.arange(n) / n
    return centre + 0.5 * diameter * np.c_[np.cos(a), np.sin(a), np.zeros(n)]


def rim_pixels(cam: Camera, T_cam_obj: np.ndarray, centre: np.ndarray, diameter: float,
               n: int = RIM_POINTS) -> np.ndarray:
    pts = rim_points_obj(centre, diameter, n)
    return cam.project(pts @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3])


def bounding_box(poly: np.ndarray, width: int, height: int) -> tuple[int, int, int, int] | None:
    """(x0, y0, w, h) of the pixels the polygon can touch, clipped to the image."""
    x0 = max(int(np.floor(poly[:, 0].min() + 0.5)) - 1, 0)
    y0 = max(int(np.floor(poly[:, 1].min() + 0.5)) - 1, 0)
    x1 = min(int(np.floor(poly[:, 0].max() + 0.5)) + 2, width)
    y1 = min(int(np.floor(poly[:, 1].max() + 0.5)) + 2, height)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1 - x0, y1 - y0


def scan_intervals(poly: np.ndarray, y0: int, h: int, rows_per_px: int = ROWS_PER_PX
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inside intervals of a closed polygon on the scan lines of pixel rows ``[y0, y0+h)``.

    Pixel row y spans [y-0.5, y+0.5); it is cut by ``rows_per_px`` horizontal lines at the
    centres of equal sub-rows. On each line the polygon's edge crossings, sorted, bound the
    inside intervals (even-odd rule: any simple polygon, convexity is not assumed).
    Returns (line index from the top, start x, end x), one entry per interval.
    """
    a = poly
    b = np.roll(poly, -1, axis=0)
    top = y0 - 0.5
    n_lines = h * rows_per_px
    lo = np.minimum(a[:, 1], b[:, 1])
    hi = np.maximum(a[:, 1], b[:, 1])
    # Line j is at y_j = top + (j + 0.5) / rows_per_px; an edge crosses it iff lo <= y_j < hi.
    first = np.clip(np.ceil((lo - top) * rows_per_px - 0.5).astype(np.int64), 0, n_lines)
    stop = np.clip(np.ceil((hi - top) * rows_per_px - 0.5).astype(np.int64), 0, n_lines)
    count = np.maximum(stop - first, 0)
    edge = np.repeat(np.arange(len(a)), count)
    line = np.repeat(first - np.cumsum(count) + count, count) + np.arange(count.sum())
    y = top + (line + 0.5) / rows_per_px
    ea, eb = a[edge], b[edge]
    x = ea[:, 0] + (y - ea[:, 1]) * (eb[:, 0] - ea[:, 0]) / (eb[:, 1] - ea[:, 1])
    order = np.lexsort((x, line))
    line, x = line[order], x[order]
    if len(line) % 2 or np.any(line[0::2] != line[1::2]):
        raise ValueError("polygon is not closed within the rows (odd number of crossings)")
    return line[0::2], x[0::2], x[1::2]


def polygon_coverage(poly: np.ndarray, x0: int, y0: int, w: int, h: int,
                     rows_per_px: int = ROWS_PER_PX) -> np.ndarray:
    """(h, w) area fraction of the pixels ``[x0, x0+w) x [y0, y0+h)`` inside a closed polygon.

    Pixel (x, y) is the square [x-0.5, x+0.5) x [y-0.5, y+0.5); each gets the length of its
    overlap with the inside intervals of its scan lines (``scan_intervals``), averaged.
    """
    line, start, end = scan_intervals(poly, y0, h, rows_per_px)
    left_edge = x0 - 0.5 + np.arange(w)
    overlap = np.clip(np.minimum(end[:, None], left_edge + 1.0) - np.maximum(start[:, None], left_edge),
                      0.0, None)
    cov = np.zeros((h, w))
    np.add.at(cov, line // rows_per_px, overlap)
    return cov / rows_per_px


def scan_centroid(poly: np.ndarray, y0: int, h: int, rows_per_px: int = ROWS_PER_PX) -> np.ndarray:
    """Area centroid of the region the scan lines see (exact in x, sampled in y)."""
    line, start, end = scan_intervals(poly, y0, h, rows_per_px)
    y = y0 - 0.5 + (line + 0.5) / rows_per_px
    length = end - start
    return np.array([((end**2 - start**2) / 2).sum(), (y * length).sum()]) / length.sum()


def disc_centroid_by_rays(cam: Camera, T_cam_obj: np.ndarray, centre: np.ndarray,
                          diameter: float, x0: int, y0: int, w: int, h: int,
                          samples: int = 16) -> tuple[np.ndarray, float]:
    """The other path: sub-pixel samples -> rays -> the mark's plane -> inside the disc?

    Returns the centroid (px) of the samples inside and the largest reprojection residual (px)
    of the undistorted samples (how far ``cv2.undistortPoints`` is from inverting
    ``cv2.projectPoints``).
    """
    off = (np.arange(samples) + 0.5) / samples - 0.5
    xs = (x0 + np.arange(w))[:, None] + off
    ys = (y0 + np.arange(h))[:, None] + off
    gx, gy = np.meshgrid(xs.ravel(), ys.ravel())
    px = np.c_[gx.ravel(), gy.ravel()]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    norm = cv2.undistortPoints(px.reshape(-1, 1, 2), cam.K, cam.dist, criteria=crit).reshape(-1, 2)
    rays = np.c_[norm, np.ones(len(norm))]
    residual = float(np.abs(cam.project(rays) - px).max())
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    normal = R[:, 2]
    c_cam = R @ centre + t
    hit = rays * ((normal @ c_cam) / (rays @ normal))[:, None]
    local = (hit - c_cam) @ R  # back in object axes, relative to the centre
    inside = np.hypot(local[:, 0], local[:, 1]) < 0.5 * diameter
    return px[inside].mean(axis=0), residual


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid of a closed polygon (shoelace)."""
    x, y = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    area = cross.sum() / 2.0
    return np.array([((x + x1) * cross).sum(), ((y + y1) * cross).sum()]) / (6.0 * area)


def coverage_centroid(cov: np.ndarray, x0: int, y0: int) -> np.ndarray:
    ys, xs = np.mgrid[y0:y0 + cov.shape[0], x0:x0 + cov.shape[1]]
    return np.array([(cov * xs).sum(), (cov * ys).sum()]) / cov.sum()


# ---------------------------------------------------------------------------- self-check
def verify(cell: Cell, poses: int, seed: int) -> list[str]:
    """Lines of text: the renderer against two independent references (see module docstring)."""
    rng = np.random.default_rng(seed)
    plate = cell.plate
    worst_res = worst_paths = worst_centroid = 0.0
    bias: list[float] = []
    locking: list[float] = []
    for _ in range(poses):
        T_base_obj = cell.random_pose(rng)
        for cam, T in cell.views(T_base_obj):
            for i in range(len(plate.names)):
                rim = rim_pixels(cam, T, plate.centres[i], plate.diameters[i])
                box = bounding_box(rim, cam.width, cam.height)
                assert box is not None
                c = scan_centroid(rim, box[1], box[3])
                rays, residual = disc_centroid_by_rays(cam, T, plate.centres[i],
                                                       plate.diameters[i], *box)
                worst_res = max(worst_res, residual)
                worst_paths = max(worst_paths, float(np.linalg.norm(c - rays)))
                worst_centroid = max(worst_centroid, float(np.linalg.norm(c - polygon_centroid(rim))))
                cov = polygon_coverage(rim, *box)
                locking.append(float(np.linalg.norm(coverage_centroid(cov, box[0], box[1]) - c)))
                projected = cam.project((T[:3, :3] @ plate.centres[i] + T[:3, 3])[None])[0]
                bias.append(float(np.linalg.norm(c - projected)))
    return [
        f"independent renderer self-check: {poses} pose{'s' * (poses != 1)} x 2 cameras x {len(plate.names)} marks "
        f"= {len(bias)} marks, no gradient, blur or noise",
        f"  area centroid, scan lines ({ROWS_PER_PX}/px, exact in x) vs shoelace formula on the "
        f"projectPoints rim: <= {worst_centroid:.1e} px",
        f"  area centroid, scan lines vs ray casting (16x16 samples/px through "
        f"cv2.undistortPoints, reprojection residual <= {worst_res:.1e} px): <= {worst_paths:.1e} px",
        f"  centroid of the pixel grey levels vs area centroid (pixel sampling): median "
        f"{np.median(locking):.1e} px, max {max(locking):.1e} px",
        f"  area centroid vs projectPoints of the 3-D centre (the perspective bias the pipeline "
        f"must remove): median {np.median(bias):.4f} px, max {max(bias):.4f} px",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=3)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()
    cell = Cell()
    t = time.perf_counter()
    print("\n".join(verify(cell, args.poses, args.seed)))
    print(f"  ({time.perf_counter() - t:.1f} s)")
    t = time.perf_counter()
    cell.render_pair(cell.random_pose(np.random.default_rng(0)), np.random.default_rng(1))
    print(f"one {W}x{H} stereo pair with gradient, blur and noise: {time.perf_counter() - t:.2f} s")


if __name__ == "__main__":
    main()
