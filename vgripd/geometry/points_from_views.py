"""N calibrated cameras in one base frame: viewing rays and triangulation from all of them.

The chapter's eq. (14) finds a point from two viewing rays; a cell with several cameras (two
stereo rigs on opposite sides of a large frame, or up to 8 cameras) sees a mark in any number of
them. Here everything lives in the robot ``base`` frame, where every camera has its pose
``T_base_camera`` (from the config, or flange pose @ ``T_flange_camera``):

* :meth:`MultiView.triangulate`: the point nearest to all its rays in the least-squares sense,
  ``min_X sum_j |(I - d_j d_j^T)(X - o_j)|^2`` (o_j the camera centre, d_j the unit ray). For
  two rays this is eq. (14)'s midpoint of the common perpendicular; for more it is the same
  criterion over all of them. Per-ray distances are returned as residuals.
* :meth:`MultiView.refine_points`: Gauss-Newton on the reprojection error of each point in all
  cameras that see it (the gold-standard criterion, which the ray criterion approximates).

The object pose over all cameras is :mod:`vgripd.geometry.pose_from_views`.

Pixels of a set of points are given as an (m, N, 2) array, N = number of cameras in the order
of ``MultiView.cameras``, NaN where a camera does not see the point. Millimetres, radians,
pixels with OpenCV's origin (centre of the top-left pixel is 0, 0).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from vgripd.errors import DegenerateInputError
from vgripd.geometry.camera_model import CameraModel, project_with_jacobian
from vgripd.geometry.transforms import check_transform, invert_transforms
from vgripd.types import FloatArray

__all__ = ["MultiView", "MultiViewTriangulation", "pixel_table"]

#: Rays meeting at a smaller angle than this do not determine a depth (as in StereoRig).
MIN_RAY_ANGLE_RAD = 1e-6
#: Gauss-Newton steps of :meth:`MultiView.refine_points`.
POINT_ITERATIONS = 10
#: Smallest depth (mm) a trial point may have in a camera that sees it; nearer counts as
#: behind the camera.
MIN_DEPTH_MM = 1e-3


@dataclass(frozen=True, eq=False)
class MultiViewTriangulation:
    """Result of :meth:`MultiView.triangulate` for m points.

    Attributes
    ----------
    points_mm : (m, 3) float64
        Base-frame points (mm); NaN rows for points seen by fewer than two cameras (and, with
        ``strict=False``, for degenerate ones).
    ray_distance_mm : (m, N) float64
        Distance of each point from each camera's ray (mm), NaN where the camera does not see
        it: 0 for perfect data; a large one names the camera whose pixel (or calibration) is off.
    views : (m,) int
        How many cameras see each point.
    problems : tuple of str
        With ``strict=False``: one message per point left NaN for a reason other than too few
        views (parallel rays, behind a camera).
    """

    points_mm: FloatArray
    ray_distance_mm: FloatArray
    views: npt.NDArray[np.intp]
    problems: tuple[str, ...] = ()


def pixel_table(pixels: object, m: int | None, n_cams: int, what: str) -> FloatArray:
    """``pixels`` as (m, N, 2) float64; NaN marks "not seen" (a half-NaN pixel is an error)."""
    px = np.asarray(pixels, dtype=np.float64)
    if px.ndim != 3 or px.shape[1:] != (n_cams, 2) or (m is not None and px.shape[0] != m):
        want = f"({'m' if m is None else m}, {n_cams}, 2)"
        raise DegenerateInputError(f"{what}: expected shape {want}, got {px.shape}")
    nan = np.isnan(px)
    half = nan[..., 0] != nan[..., 1]
    inf = np.isinf(px).any(axis=2)
    if half.any() or inf.any():
        i, j = np.argwhere(half | inf)[0]
        raise DegenerateInputError(f"{what}: point {i} in camera {j} is not a finite pixel "
                                   f"(NaN in both coordinates means 'not seen')")
    return px


class MultiView:
    """N calibrated cameras with their poses in the base frame, and their groups (rigs).

    Parameters
    ----------
    cameras : sequence of CameraModel
        Intrinsics and distortion, in image order.
    T_base_cameras : (N, 4, 4) array_like
        Each camera's pose in the base frame (mm) at capture.
    names : sequence of str, optional
        Camera names for messages (default ``cam0``, ``cam1``, ...).
    groups : sequence of (name, camera indices), optional
        Camera groups (rigs) for per-group residuals and the consistency check; default: one
        group per camera, named after it. Every camera in at most one group; cameras in none
        form no group (they still count in the joint fit).
    """

    def __init__(self, cameras: Sequence[CameraModel], T_base_cameras: object,
                 names: Sequence[str] | None = None,
                 groups: Sequence[tuple[str, Sequence[int]]] | None = None) -> None:
        n = len(cameras)
        if n < 1:
            raise DegenerateInputError("MultiView needs at least one camera")
        T = np.asarray(T_base_cameras, dtype=np.float64)
        if T.shape != (n, 4, 4):
            raise DegenerateInputError(f"T_base_cameras: expected shape ({n}, 4, 4), got {T.shape}")
        self.names = tuple(names) if names is not None else tuple(f"cam{j}" for j in range(n))
        if len(self.names) != n:
            raise DegenerateInputError(f"{len(self.names)} names for {n} cameras")
        for j in range(n):
            check_transform(T[j], f"T_base_cameras[{j}] ({self.names[j]})")
        self.cameras = tuple(cameras)
        self.T_base_cameras = T.copy()
        self.T_cameras_base = invert_transforms(T)
        if groups is None:
            groups = [(name, (j,)) for j, name in enumerate(self.names)]
        seen: set[int] = set()
        checked = []
        for name, members in groups:
            idx = tuple(int(j) for j in members)
            if not idx or any(not 0 <= j < n for j in idx) or seen & set(idx):
                raise DegenerateInputError(f"group {name!r}: cameras {list(idx)} are empty, "
                                           f"out of range 0..{n - 1} or already in a group")
            seen |= set(idx)
            checked.append((str(name), idx))
        self.groups: tuple[tuple[str, tuple[int, ...]], ...] = tuple(checked)

    @property
    def centres_mm(self) -> FloatArray:
        """(N, 3) camera centres in the base frame."""
        return self.T_base_cameras[:, :3, 3]

    # ------------------------------------------------------------------ rays and points
    def rays(self, pixels: object) -> FloatArray:
        """(m, N, 3) unit viewing directions in the base frame (NaN where not seen)."""
        px = pixel_table(pixels, None, len(self.cameras), "pixels")
        out = np.full(px.shape[:2] + (3,), np.nan)
        for j, cam in enumerate(self.cameras):
            seen = ~np.isnan(px[:, j, 0])
            if seen.any():
                try:
                    d = cam.rays(px[seen, j])
                except DegenerateInputError as err:
                    raise DegenerateInputError(f"camera {self.names[j]}: {err}") from None
                out[seen, j] = d @ self.T_base_cameras[j, :3, :3].T
        return out

    def triangulate(self, pixels: object, *, strict: bool = True) -> MultiViewTriangulation:
        """Base-frame points nearest (least squares) to all their viewing rays.

        Each point seen by k >= 2 cameras solves the 3x3 system
        ``sum_j (I - d_j d_j^T) X = sum_j (I - d_j d_j^T) o_j`` (all points at once). With two
        rays this is the chapter's eq. (14) (the midpoint of the closest points).

        Parameters
        ----------
        pixels : (m, N, 2) array_like
            Measured pixels, NaN where a camera does not see the point.
        strict : bool
            True: a degenerate point (rays within ``MIN_RAY_ANGLE_RAD`` of parallel, or the
            point behind a camera that sees it) raises; False: it is left NaN and described
            in ``problems``.

        Raises
        ------
        DegenerateInputError
            Bad shape or a half-NaN pixel (naming point and camera); with ``strict``, a
            degenerate point (naming it and, when behind, the camera).
        ConvergenceError
            A pixel cannot be undistorted.
        """
        d = self.rays(pixels)
        m = d.shape[0]
        seen = ~np.isnan(d[..., 0])
        views = seen.sum(axis=1)
        dz = np.where(seen[..., None], d, 0.0)
        P = np.eye(3) * seen[..., None, None] - dz[..., :, None] * dz[..., None, :]
        A = P.sum(axis=1)  # (m, 3, 3)
        b = np.einsum("mjab,jb->ma", P, self.centres_mm)
        # Smallest eigenvalue of A: 1 - cos(angle) for two rays; 0 when all are parallel.
        lam = np.linalg.eigvalsh(A)[:, 0] if m else np.zeros(0)
        ok = (views >= 2) & (lam > 1.0 - math.cos(MIN_RAY_ANGLE_RAD))
        X = np.full((m, 3), np.nan)
        if ok.any():
            X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
        rel = X[:, None, :] - self.centres_mm[None]  # (m, N, 3)
        depth = np.einsum("mjk,mjk->mj", rel, dz)
        dist = np.linalg.norm(rel - depth[..., None] * dz, axis=2)
        dist[~seen] = np.nan
        problems = []
        for i in np.flatnonzero((views >= 2) & ~ok):
            problems.append(f"point {i}: its {views[i]} rays are (nearly) parallel")
        behind = seen & ok[:, None] & ~(depth > 0)
        for i in np.flatnonzero(behind.any(axis=1)):
            j = int(np.argmax(behind[i]))
            problems.append(f"point {i}: lies behind camera {self.names[j]} "
                            f"(depth {depth[i, j]:.4g} mm); wrong correspondence?")
        if problems and strict:
            raise DegenerateInputError(problems[0])
        bad = behind.any(axis=1)
        X[bad] = np.nan
        dist[bad] = np.nan
        return MultiViewTriangulation(points_mm=X, ray_distance_mm=dist, views=views,
                                      problems=tuple(problems))

    def reprojection_errors(self, points_mm: object, pixels: object) -> FloatArray:
        """(m, N) pixel distance between each point's projection and its measured pixel in
        every camera that sees it (NaN elsewhere and for NaN points)."""
        X = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        px = pixel_table(pixels, X.shape[0], len(self.cameras), "pixels")
        out = np.full(px.shape[:2], np.nan)
        for j, cam in enumerate(self.cameras):
            sel = ~np.isnan(px[:, j, 0]) & np.isfinite(X).all(axis=1)
            if sel.any():
                Pc = X[sel] @ self.T_cameras_base[j, :3, :3].T + self.T_cameras_base[j, :3, 3]
                out[sel, j] = np.linalg.norm(cam.project(Pc) - px[sel, j], axis=1)
        return out

    def refine_points(self, points_mm: object, pixels: object) -> tuple[FloatArray, FloatArray]:
        """Points moved to minimise their reprojection error in every camera that sees them.

        Batched Gauss-Newton (3 unknowns per point, analytic projection Jacobians), a step
        accepted per point only where it lowers that point's error; points seen by fewer than
        two cameras, or NaN, are returned unchanged.

        Returns
        -------
        points (m, 3) mm, errors (m, N) px.
        """
        X = np.array(points_mm, dtype=np.float64).reshape(-1, 3)
        px = pixel_table(pixels, X.shape[0], len(self.cameras), "pixels")
        live = np.isfinite(X).all(axis=1) & ((~np.isnan(px[..., 0])).sum(axis=1) >= 2)
        cost = self._point_costs(X, px, live)[0]
        for _ in range(POINT_ITERATIONS):
            _, H, g = self._point_costs(X, px, live, with_jacobian=True)
            step = np.zeros_like(X)
            solvable = live & (np.abs(np.linalg.det(H)) > 0)
            step[solvable] = -np.linalg.solve(H[solvable], g[solvable][..., None])[..., 0]
            trial = X + step
            new_cost = self._point_costs(trial, px, live)[0]
            better = live & (new_cost < cost)
            X[better] = trial[better]
            cost = np.where(better, new_cost, cost)
            if not better.any():
                break
        return X, self.reprojection_errors(X, px)

    def _point_costs(self, X: FloatArray, px: FloatArray, live: npt.NDArray[np.bool_],
                     with_jacobian: bool = False
                     ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per point: summed squared reprojection error (inf if behind a camera that sees it),
        and with ``with_jacobian`` the Gauss-Newton matrix (m, 3, 3) and gradient (m, 3)."""
        m = X.shape[0]
        cost = np.zeros(m)
        H = np.zeros((m, 3, 3))
        g = np.zeros((m, 3))
        for j, cam in enumerate(self.cameras):
            sel = np.flatnonzero(live & ~np.isnan(px[:, j, 0]))
            if not sel.size:
                continue
            R = self.T_cameras_base[j, :3, :3]
            Pc = X[sel] @ R.T + self.T_cameras_base[j, :3, 3]
            front = Pc[:, 2] > MIN_DEPTH_MM
            cost[sel[~front]] = np.inf
            if not front.any():
                continue
            s = sel[front]
            proj, J = project_with_jacobian(cam, Pc[front])
            r = proj - px[s, j]
            cost[s] += (r * r).sum(axis=1)
            if with_jacobian:
                Jb = J @ R  # d px / d X_base
                np.add.at(H, s, Jb.transpose(0, 2, 1) @ Jb)
                np.add.at(g, s, np.einsum("nki,nk->ni", Jb, r))
        return cost, H, g
