"""Single-camera calibration from board detections (what Bouguet's toolbox calls "Calibration").

Model: pinhole with two focal lengths, principal point, no skew, Brown distortion
``dist = [k1, k2, p1, p2, k3]`` in OpenCV's order, which is Bouguet's ``kc``. The default is the
toolbox default: k3 fixed at 0 (it is free with ``fix_k3=False``); skew is always 0 (OpenCV's
``calibrateCamera`` has no skew parameter).

Fit: ``cv2.calibrateCameraExtended`` (Zhang's planar initialisation, then Levenberg-Marquardt
on the reprojection error of all points), which also gives one-sigma standard deviations of the
intrinsics and the per-view RMS. Bouguet's printed uncertainties are about three sigma.

Outliers: an image whose per-image RMS is more than ``outlier_factor`` times the median and
above ``outlier_floor_px`` (a misdetected corner, a motion-blurred view) is dropped and the
calibration redone, one image at a time, worst first; it is reported with the numbers. Images
with fewer than ``min_points`` points are dropped before the fit. At least 3 images must remain.

Errors: ``rms_px`` (and per image) is the root mean square of the reprojection error length,
sqrt(mean(dx^2 + dy^2)) px, as OpenCV reports it; Bouguet's ``err`` is the standard deviation of
dx and of dy separately, so for round noise rms_px ~ sqrt(2) * err.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vgripd.calib.boards import Board, Detection
from vgripd.errors import CalibrationError

MIN_IMAGES = 3
FEW_IMAGES = 10  # below this, warn: too few views to pin down distortion and the principal point
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")


@dataclass
class IntrinsicsResult:
    """A calibrated camera and the evidence for it.

    ``camera`` has the keys of ``config.IntrinsicsConfig`` (fx, fy, cx, cy, skew, dist, width,
    height; px); ``std`` the one-sigma standard deviations of the same keys (0 for what was
    fixed). Per used image ``i`` (same order as ``detections``): ``per_image[i]`` = {image,
    rms_px, points}, ``residuals_px[i]`` (N_i, 2) observed - projected px, and the board pose
    ``T_cam_board[i]`` (4x4, mm; also as OpenCV ``rvecs[i]``, ``tvecs[i]``).
    """

    camera: dict[str, Any]
    std: dict[str, Any]
    rms_px: float
    detections: list[Detection]
    per_image: list[dict[str, Any]]
    residuals_px: list[NDArray[np.float64]]
    rvecs: list[NDArray[np.float64]]
    tvecs: list[NDArray[np.float64]]
    T_cam_board: list[NDArray[np.float64]]
    rejected: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def camera_matrix(self) -> NDArray[np.float64]:
        """3x3 OpenCV camera matrix K."""
        c = self.camera
        return np.array([[c["fx"], c["skew"], c["cx"]], [0.0, c["fy"], c["cy"]], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> NDArray[np.float64]:
        """(5,) OpenCV distortion coefficients."""
        return np.asarray(self.camera["dist"], dtype=np.float64)


def calibrate_intrinsics(board: Board, detections: Sequence[Detection],
                         image_size: tuple[int, int], *, fix_k3: bool = True,
                         min_points: int = 8, outlier_factor: float = 3.0,
                         outlier_floor_px: float = 0.5) -> IntrinsicsResult:
    """Calibrate one camera from board detections in images of ``image_size`` (w, h) px.

    See the module docstring for the model, the outlier rule and the error measures. Raises
    CalibrationError when fewer than 3 usable images remain or the fit fails.
    """
    w, h = image_size
    rejected: list[dict[str, str]] = []
    used: list[Detection] = []
    for det in detections:
        if tuple(det.size) != (w, h):
            raise CalibrationError(f"{det.image}: image size {det.size[0]}x{det.size[1]} is not "
                                   f"the calibrated {w}x{h}")
        if len(det.ids) < min_points:
            rejected.append({"image": det.image, "reason": f"only {len(det.ids)} board points "
                                                           f"(need at least {min_points})"})
        else:
            used.append(det)
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    obj = board.object_points()
    while True:
        if len(used) < MIN_IMAGES:
            raise CalibrationError(
                f"need at least {MIN_IMAGES} images with the board {board.spec}, have "
                f"{len(used)}" + (f" ({len(rejected)} rejected)" if rejected else ""))
        fit = _fit(obj, used, (w, h), flags)
        per_view = fit["per_view"]
        median = float(np.median(per_view))
        worst = int(np.argmax(per_view))
        if (len(used) == MIN_IMAGES or per_view[worst] <= outlier_factor * median
                or per_view[worst] <= outlier_floor_px):
            break
        rejected.append({"image": used[worst].image,
                         "reason": f"per-image RMS {per_view[worst]:.2f} px vs median "
                                   f"{median:.2f} px (outlier: > {outlier_factor:g}x median)"})
        del used[worst]
    return _result(board, used, (w, h), fit, rejected, fix_k3)


def _fit(obj: NDArray[np.float64], used: Sequence[Detection], size: tuple[int, int],
         flags: int) -> dict[str, Any]:
    object_points = [obj[d.ids].astype(np.float32) for d in used]
    image_points = [d.px.astype(np.float32).reshape(-1, 1, 2) for d in used]
    try:
        (_rms, K, dist, rvecs, tvecs, std_int, _std_ext,
         per_view) = cv2.calibrateCameraExtended(object_points, image_points, size, np.eye(3),
                                                 np.zeros(5), flags=flags, criteria=CRITERIA)
    except cv2.error as err:
        names = ", ".join(d.image for d in used)
        raise CalibrationError(f"calibration of {names} failed: {err.msg}") from None
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()[:5]
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise CalibrationError("calibration diverged (non-finite parameters); check the board "
                               "spec and the images")
    return {"K": K, "dist": dist, "rvecs": rvecs, "tvecs": tvecs,
            "std": np.asarray(std_int, dtype=np.float64).ravel(),
            "per_view": np.asarray(per_view, dtype=np.float64).ravel()}


def _result(board: Board, used: list[Detection], size: tuple[int, int], fit: dict[str, Any],
            rejected: list[dict[str, str]], fix_k3: bool) -> IntrinsicsResult:
    K, dist, s = fit["K"], fit["dist"], fit["std"]
    w, h = size
    camera = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "skew": 0.0,
              "dist": [float(v) for v in dist], "width": w, "height": h}
    camera = {k: (float(v) if isinstance(v, np.floating) else v) for k, v in camera.items()}
    std_dist = [float(v) for v in s[4:9]]
    if fix_k3:
        std_dist[4] = 0.0
    std = {"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3]),
           "skew": 0.0, "dist": std_dist}
    obj = board.object_points()
    residuals, poses, rvecs, tvecs = [], [], [], []
    for det, rvec, tvec in zip(used, fit["rvecs"], fit["tvecs"], strict=True):
        rv = np.asarray(rvec, dtype=np.float64).ravel()
        tv = np.asarray(tvec, dtype=np.float64).ravel()
        proj, _ = cv2.projectPoints(obj[det.ids], rv, tv, K, dist)
        residuals.append(det.px - proj.reshape(-1, 2))
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rv)[0]
        T[:3, 3] = tv
        poses.append(T)
        rvecs.append(rv)
        tvecs.append(tv)
    per_image = [{"image": d.image, "rms_px": float(np.sqrt(np.mean(np.sum(r**2, axis=1)))),
                  "points": len(d.ids)} for d, r in zip(used, residuals, strict=True)]
    all_res = np.concatenate(residuals)
    rms = float(np.sqrt(np.mean(np.sum(all_res**2, axis=1))))
    result = IntrinsicsResult(camera, std, rms, list(used), per_image, residuals, rvecs, tvecs,
                              poses, rejected)
    result.warnings = _warnings(result)
    return result


def _warnings(r: IntrinsicsResult) -> list[str]:
    out = []
    n = len(r.detections)
    if n < FEW_IMAGES:
        out.append(f"only {n} images used; {FEW_IMAGES}-20 views at varied tilts pin down "
                   "distortion and the principal point better")
    empty = empty_regions(r.detections, (r.camera["width"], r.camera["height"]))
    if empty:
        out.append("no board point in the image's " + ", ".join(empty) + " (3x3 grid): "
                   "distortion there is extrapolated; add views with the board in those parts")
    cam, std = r.camera, r.std
    for key in ("fx", "fy"):
        if std[key] > 0.01 * cam[key]:
            out.append(f"{key} is uncertain: {cam[key]:.2f} +- {std[key]:.2f} px (1 sigma, "
                       "> 1 %); add views with more tilt")
    for key, extent in (("cx", cam["width"]), ("cy", cam["height"])):
        if std[key] > 0.02 * extent:
            out.append(f"{key} is uncertain: {cam[key]:.2f} +- {std[key]:.2f} px (1 sigma, "
                       "> 2 % of the image)")
    for i, name in enumerate(DIST_NAMES[:2]):
        value, sigma = cam["dist"][i], std["dist"][i]
        if sigma > 0.02 and sigma > 0.5 * abs(value):
            out.append(f"{name} is poorly determined: {value:.4f} +- {sigma:.4f} (1 sigma); "
                       "add views with the board near the image corners")
    return out


REGION_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
                ("bottom-left", "bottom", "bottom-right"))


def empty_regions(detections: Sequence[Detection], size: tuple[int, int]) -> list[str]:
    """Names of the cells of a 3x3 split of the image that no board point falls in."""
    w, h = size
    hit = np.zeros((3, 3), dtype=bool)
    for det in detections:
        col = np.clip((det.px[:, 0] * 3 / w).astype(int), 0, 2)
        row = np.clip((det.px[:, 1] * 3 / h).astype(int), 0, 2)
        hit[row, col] = True
    return [REGION_NAMES[r][c] for r in range(3) for c in range(3) if not hit[r, c]]
