"""Stereo triangulation and epipolar geometry of a calibrated camera pair.

Frames: ``left`` and ``right`` are the two camera frames (x right, y down, z forward, mm).
The rig stores ``T_right_left``, the pose of the left camera in the right camera:
``X_R = R X_L + t`` for a 3D point, which is Bouguet's (and OpenCV ``stereoCalibrate``'s)
``om``/``T`` convention. Triangulated points are returned in the left camera frame.

Pixels are measured (distorted) coordinates with OpenCV's origin (centre of the top-left pixel
is 0, 0). "Ideal pixels" are what a distortion-free camera with the same K would see:
``K @ [x_n, y_n, 1]`` of the undistorted normalised coordinates. Epipolar lines live in ideal
pixels because with lens distortion the epipolar "line" in the raw image is a curve.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NoReturn

import numpy as np

from vgripd.errors import DegenerateInputError
from vgripd.geometry.camera_model import CameraModel, PairInverse, undistort_pair
from vgripd.geometry.transforms import check_transform, skew
from vgripd.types import FloatArray

__all__ = ["StereoRig", "Triangulation"]


@dataclass(frozen=True, eq=False)
class Triangulation:
    """Result of :meth:`StereoRig.triangulate`.

    Attributes
    ----------
    points_mm : (n, 3) float64
        Midpoints of the closest points of the two viewing rays, left camera frame (mm).
    gap_mm : (n,) float64
        Distance between the two rays at their closest approach (mm): 0 for a perfect
        correspondence and calibration; grows with matching errors and calibration drift.
    """

    points_mm: FloatArray
    gap_mm: FloatArray


def _undistort(camera: CameraModel, px: object, name: str) -> FloatArray:
    """``camera.undistort`` (it checks shape and NaN by point index), errors prefixed by name."""
    try:
        return camera.undistort(px)
    except DegenerateInputError as err:
        raise DegenerateInputError(f"{name}: {err}") from None


def _same_count(nl: FloatArray, nr: FloatArray) -> None:
    if nl.shape != nr.shape:
        raise DegenerateInputError(
            f"px_left has {nl.shape[0]} points but px_right has {nr.shape[0]}"
        )


def _triangulation_maps(
    R_lr: FloatArray, c: FloatArray, min_angle_rad: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Linear maps that let :meth:`StereoRig.triangulate` work in a few array products.

    With h = (x_L, y_L, 1, x_R, y_R, 1), d = h[:3], e = R_lr h[3:] and the right centre c
    (left frame, mm):

    * forms (36, 5): ``outer(h, h).ravel() @ forms = (a, b, cc, p, q)`` with a = d.d,
      b = d.e, cc = e.e, p = d.c, q = e.c (q = (R_lr^T c).h[3:]);
    * solve (25, 4): ``outer(Q, Q).ravel() @ solve`` of those five gives
      ``(det, det - s^2 a cc, cc p - b q, b p - a q)`` with det = a cc - b^2 and s the sine of
      the smallest ray angle: the 2x2 normal equations by Cramer's rule, the depths being
      z1 = (cc p - b q) / det and z2 = (b p - a q) / det;
    * gap (6, 3), gap0 (3,): ``(z1 h[:3], z2 h[3:]) @ gap + gap0 = g``, the gap vector
      z1 d - (z2 e + c) between the closest points of the two rays; their midpoint is
      z1 d - g / 2.

    All entries are 0, +-1 or the rig's constants, so the products add the same terms as the
    written-out formulas.
    """
    forms = np.zeros((6, 6, 5))
    for i in range(3):
        forms[i, i, 0] = forms[3 + i, 3 + i, 2] = 1.0
        forms[i, 3:, 1] = R_lr[i]
        forms[i, 2, 3] = c[i]
    forms[3:, 5, 4] = R_lr.T @ c
    solve = np.zeros((5, 5, 4))  # indices a 0, b 1, cc 2, p 3, q 4
    solve[0, 2, 0] = 1.0
    solve[1, 1, 0:2] = -1.0
    solve[0, 2, 1] = 1.0 - min_angle_rad**2
    solve[2, 3, 2] = solve[1, 3, 3] = 1.0
    solve[1, 4, 2] = solve[0, 4, 3] = -1.0
    gap = np.concatenate([np.eye(3), -R_lr.T])
    return forms.reshape(36, 5), solve.reshape(25, 4), gap, -c


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Two calibrated cameras and the pose between them.

    Parameters
    ----------
    left, right : CameraModel
        Intrinsics and distortion of each camera.
    T_right_left : (4, 4) array_like
        Pose of the left camera frame in the right camera frame (mm): ``X_R = R X_L + t``.
    min_ray_angle_rad : float
        Rays meeting at a smaller angle are refused as parallel: depth along them is not
        determined (a point 1e6 baselines away, or a wrong correspondence).
    """

    left: CameraModel
    right: CameraModel
    T_right_left: FloatArray
    min_ray_angle_rad: float = 1e-6
    #: (3, 3) fundamental matrix in ideal pixels: ``u_R^T F u_L = 0``.
    F: FloatArray = field(init=False, repr=False)
    _R_lr: FloatArray = field(init=False, repr=False)  # right-camera axes in the left frame
    _c_right: FloatArray = field(init=False, repr=False)  # right-camera centre, left frame (mm)
    # Tabulated maps of triangulate (see _triangulation_maps).
    _forms: FloatArray = field(init=False, repr=False)
    _solve: FloatArray = field(init=False, repr=False)
    _gap: FloatArray = field(init=False, repr=False)
    _gap0: FloatArray = field(init=False, repr=False)
    # n -> constants of undistort_pair for n points per image (few distinct n in practice).
    _pair_cache: dict[int, PairInverse] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        T = check_transform(self.T_right_left, "T_right_left").copy()
        R, t = T[:3, :3], T[:3, 3]
        if np.linalg.norm(t) == 0.0:
            raise DegenerateInputError("T_right_left: zero baseline, nothing to triangulate")
        if not 0.0 <= self.min_ray_angle_rad < 0.5 * np.pi:
            raise DegenerateInputError(
                f"min_ray_angle_rad must be in [0, pi/2), got {self.min_ray_angle_rad}"
            )
        T.flags.writeable = False
        essential = skew(t) @ R
        F = np.linalg.inv(self.right.K).T @ essential @ np.linalg.inv(self.left.K)
        F /= np.linalg.norm(F)
        F.flags.writeable = False
        set_ = object.__setattr__
        set_(self, "T_right_left", T)
        set_(self, "F", F)
        set_(self, "_R_lr", np.ascontiguousarray(R.T))
        set_(self, "_c_right", -R.T @ t)
        maps = _triangulation_maps(self._R_lr, self._c_right, self.min_ray_angle_rad)
        for name, value in zip(("_forms", "_solve", "_gap", "_gap0"), maps, strict=True):
            set_(self, name, value)
        set_(self, "_pair_cache", {})

    def triangulate(self, px_left: object, px_right: object) -> Triangulation:
        """3D points from corresponding pixels, by linear least squares on the chapter's eq. (14).

        Eq. (14), ``M1^-1 r1 z1 = R M2^-1 r2 z2 + K``, with ``d = M1^-1 r1`` (left ray, z = 1),
        ``e = R M2^-1 r2`` (right ray in the left frame, its right-frame z = 1) and ``c = K``
        (right camera centre in the left frame), is three equations in the two depths z1
        (left camera) and z2 (right camera). Their normal equations are 2x2 and solved in
        closed form for all points at once. The returned point is the midpoint of the two
        closest ray points ``z1 d`` and ``z2 e + c``; their distance is the gap. The pixels
        are undistorted first (Newton inversion of the camera's Brown model).

        Parameters
        ----------
        px_left, px_right : (n, 2) array_like
            Measured (distorted) pixels of the same n points in the left and right image.

        Raises
        ------
        DegenerateInputError
            Shape mismatch, NaN (naming the point), rays (nearly) parallel, or a point whose
            least-squares depth puts it behind either camera (naming the point).
        ConvergenceError
            A pixel cannot be undistorted (beyond the fold of the distortion model).
        """
        P = self._undistort_both(px_left, px_right)
        n = P.shape[1] // 2
        # h = (x_L, y_L, 1, x_R, y_R, 1) per point: the left ray d (z = 1) and the right ray
        # in its own frame. With u = (z1, -z2), eq. (14) reads u1 d + u2 e = c; its normal
        # equations [[a, b], [b, cc]] u = (p, q) have a = |d|^2, b = d.e, cc = |e|^2, p = d.c,
        # q = e.c, all quadratic forms in h, and the solution's numerators and determinant
        # are quadratic forms in those: two outer products and two tabulated maps (see
        # _triangulation_maps) replace some 20 small numpy calls per point set.
        H = np.empty((n, 2, 3))
        H[:, :, :2] = P.reshape(2, 2, n).transpose(2, 1, 0)
        H[:, :, 2] = 1.0
        h = H.reshape(n, 6)
        Q = (h[:, :, None] * h[:, None, :]).reshape(n, 36) @ self._forms  # a, b, cc, p, q
        Z = (Q[:, :, None] * Q[:, None, :]).reshape(n, 25) @ self._solve
        # Z[:, 1] = det - sin^2(min angle) a cc > 0: the rays are not (nearly) parallel; then
        # det > 0 and the depths z = Z[:, 2:] / det are positive iff their numerators are.
        if not np.minimum.reduce(Z[:, 1:], axis=None, initial=np.inf) > 0:
            self._raise_degenerate(Q, Z)
        z = Z[:, 2:] / Z[:, :1]  # (n, 2): depth z1 in the left camera, z2 = -u2 in the right
        # The closest point on the left ray is z1 d = zh[:, :3]; the gap vector (it minus the
        # closest point z2 e + c on the right ray) is linear in zh: one more tabulated map.
        zh = (z[:, :, None] * H).reshape(n, 6)
        g = zh @ self._gap + self._gap0
        return Triangulation(points_mm=zh[:, :3] - 0.5 * g, gap_mm=np.sqrt(np.add.reduce(g * g, 1)))

    @staticmethod
    def _raise_degenerate(Q: FloatArray, Z: FloatArray) -> NoReturn:
        """The error of :meth:`triangulate` for its forms Q and Z: parallel rays (the first
        such point) before rays meeting behind a camera (the first such point)."""
        det = Z[:, 0]  # = |d|^2 |e|^2 sin^2(angle between the rays)
        parallel = ~(Z[:, 1] > 0)
        if parallel.any():
            i = int(np.argmax(parallel))
            raise DegenerateInputError(
                f"point {i}: left and right rays are (nearly) parallel "
                f"(angle {np.arcsin(np.sqrt(max(det[i], 0.0) / (Q[i, 0] * Q[i, 2]))):.3g} rad)"
            )
        z = Z[:, 2:] / det[:, None]
        i = int(np.argmax(~(z > 0).all(axis=1)))
        raise DegenerateInputError(
            f"point {i}: rays meet behind a camera (depth left {z[i, 0]:.4g} mm, "
            f"right {z[i, 1]:.4g} mm); wrong correspondence?"
        )

    def _undistort_both(self, px_left: object, px_right: object) -> FloatArray:
        """Normalized coordinates of both images, stacked: P (2, 2n), rows x, y, the left
        image's n points first.

        The usual case takes :func:`~vgripd.geometry.camera_model.undistort_pair` (one Newton run
        for
        both images); anything else, and every error, goes through each camera's ``undistort``
        so that the errors name the image and point as they always have.
        """
        pl = np.asarray(px_left, dtype=np.float64)
        pr = np.asarray(px_right, dtype=np.float64)
        if pl.ndim == 2 and pl.shape[1] == 2 and pl.shape == pr.shape and pl.shape[0]:
            n = pl.shape[0]
            pc = self._pair_cache.get(n)
            if pc is None:
                if len(self._pair_cache) > 8:
                    self._pair_cache.clear()
                pc = self._pair_cache[n] = self.left._pair_constants(self.right, n)
            fast = undistort_pair(pc, pl, pr)
            if fast is not None:
                return fast[0]
        nl = _undistort(self.left, pl, "px_left")
        nr = _undistort(self.right, pr, "px_right")
        _same_count(nl, nr)
        return np.concatenate((nl, nr)).T

    @staticmethod
    def _ideal_homogeneous(norm: FloatArray, camera: CameraModel) -> FloatArray:
        """Homogeneous ideal pixels (n, 3) from normalised coordinates: re-project with K only."""
        return np.c_[norm, np.ones(len(norm))] @ camera.K.T

    def epipolar_lines_right(self, px_left: object) -> FloatArray:
        """Epipolar lines in the right image of measured left pixels.

        Returns
        -------
        (n, 3) float64
            Lines ``(a, b, c)`` in right *ideal* pixels with ``a^2 + b^2 = 1``, so that
            ``a u + b v + c`` is the signed distance (px) of ideal pixel (u, v) from the line.
            To test measured right pixels, convert them with :meth:`ideal_pixels` first.
        """
        u_l = self._ideal_homogeneous(_undistort(self.left, px_left, "px_left"), self.left)
        lines = u_l @ self.F.T
        return lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]

    def ideal_pixels(self, camera: CameraModel, px: object) -> FloatArray:
        """Measured pixels (n, 2) of ``camera`` -> ideal (distortion-free) pixels (n, 2)."""
        return self._ideal_homogeneous(_undistort(camera, px, "px"), camera)[:, :2]

    def epipolar_residuals_px(self, px_left: object, px_right: object) -> FloatArray:
        """Distance of each point to the epipolar line of its partner, both images.

        Both pixel sets are undistorted and re-projected into ideal pixels; the fundamental
        matrix of the calibration then gives the lines. Use it to watch calibration drift
        (the chapter: frequent large residuals call for recalibration) and to reject wrong
        correspondences before triangulating.

        Returns
        -------
        (n, 2) float64
            Column 0: distance (ideal px) of the left point from the epipolar line of the
            right point in the left image; column 1: of the right point from the line of the
            left point in the right image.
        """
        nl = _undistort(self.left, px_left, "px_left")
        nr = _undistort(self.right, px_right, "px_right")
        _same_count(nl, nr)
        u_l = self._ideal_homogeneous(nl, self.left)
        u_r = self._ideal_homogeneous(nr, self.right)
        lines_r = u_l @ self.F.T  # in the right image
        lines_l = u_r @ self.F  # in the left image
        algebraic = np.abs(np.einsum("ij,ij->i", u_r, lines_r))
        return np.stack(
            [
                algebraic / np.hypot(lines_l[:, 0], lines_l[:, 1]),
                algebraic / np.hypot(lines_r[:, 0], lines_r[:, 1]),
            ],
            axis=1,
        )
