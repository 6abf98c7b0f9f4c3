"""N-camera calibration: every camera's pose relative to a reference camera, from board images
taken at the same instants ("image sets"), then a joint bundle adjustment.

Why not chain ``calibrate stereo`` results: each pair's fit sees only its own views, so a chain
c1 -> c2 -> c3 -> c4 adds up every link's error, and a camera seen together with several others
gets one answer per partner that disagree. Here every board corner seen by any camera constrains
one common solution.

Steps (frames: ``T_a_b`` is the pose of b in a, mm; the reference camera's frame is ``ref``):

1. Board pose per camera and image set (``cv2.solvePnP`` with that camera's intrinsics).
2. View graph: two cameras are joined when they saw the board in the same image set; each such
   set gives one estimate of their relative pose ``T_b_a = T_b_board @ inv(T_a_board)``; the
   pair's consensus is the medoid rotation and the median translation (robust to a bad set).
3. Spanning tree over the graph, widest links first (most shared sets; Prim's algorithm from
   the reference camera), so a camera that shares no set with the reference is reached through
   others (chaining). Cameras the tree cannot reach are refused, naming them and the group they
   form.
4. Start values: each camera's pose by composing the tree's links; each image set's board pose
   in ``ref`` from the camera that saw it best (lowest PnP error).
5. Joint refinement (Levenberg-Marquardt, :func:`levenberg_marquardt`) over all cameras'
   board-corner reprojection errors (px); parameters: the camera poses ``T_cam_ref``
   (reference held at the identity), the board poses ``T_ref_board`` of every set and, per
   camera, the intrinsics chosen free (``free``; none by default). Every residual depends on
   one camera and one board pose only, so the analytic Jacobian is a sparse matrix (2 rows
   per corner, at most 12 + 9 non-zeros each): forming it and ``J^T J`` costs time linear in
   the observations.
6. Outliers: an observation (one camera, one set) whose RMS is above ``outlier_factor`` x the
   median and above ``outlier_floor_px`` is dropped (worst first, one at a time) and the fit
   redone: an image taken at another instant, a board that moved, a bad detection.

Residuals reported: per camera the RMS reprojection error; per pair the spread of the pair's
own per-set estimates (step 2) around the final relative pose, in degrees and mm -- a camera
that moved between sets or an image from another instant shows up here; per image set the RMS
over all cameras that saw it.

The projection model is OpenCV's pinhole + Brown (k1 k2 p1 p2 k3), the distortion from
:mod:`vgripd.geometry.distortion` with one set of coefficients per observation, so all
observations project in one vectorised call; tests check it against ``cv2.projectPoints`` and
the whole fit against ``cv2.stereoCalibrate``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.sparse import coo_matrix, csr_matrix

from vgripd.errors import CalibrationError
from vgripd.geometry.distortion import (
    Brown,
    coefficient_jacobian,
    distort,
    distort_with_jacobian,
)
from vgripd.geometry.transforms import (
    invert_transform,
    left_jacobians,
    make_transform,
    matrices_from_rotvecs,
    rotation_angle,
    rotvec_from_matrix,
    skew,
)

FloatArray = NDArray[np.float64]
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
MAX_CAMERAS = 8
MIN_POINTS = 6
FEW_SETS = 3  # a camera in fewer image sets than this is warned about
# A pair's per-set estimates spreading more than this (RMS) around the joint solution is warned
# about (a camera that moved, images of different instants). Single-view board poses are loose
# in depth, so the translation limit is relative to the board's distance.
PAIR_WARN_DEG = 0.5
PAIR_WARN_DISTANCE = 0.01
MAX_ITERATIONS = 100
OUTLIER_WARN_SHARE = 0.05  # more outlier images than this share (and > 2): warn


@dataclass
class Observation:
    """The board seen by one camera in one image set.

    ``obj`` (N, 3) board points (mm, board frame), ``px`` (N, 2) their pixels (OpenCV
    convention), ``image`` the file name for messages.
    """

    camera: int
    set_key: str
    obj: FloatArray
    px: FloatArray
    image: str


@dataclass
class MultiResult:
    """Calibrated cameras and the evidence.

    ``T_ref_camera[i]`` (4x4, mm): camera i in the reference camera's frame. ``intrinsics[i]``
    IntrinsicsConfig keys (refined where ``free`` said so). ``cameras``: per camera {name,
    rms_px, sets, points, position_std_mm (3,), rotation_std_deg} (one sigma, in the
    reference frame). ``pairs``: per connected pair {a, b, shared_sets, rms_px,
    rotation_deg {rms, max}, translation_mm {rms, max}}. ``graph``: {edges: [(a, b, shared)],
    tree: [(parent, child)]}. ``sets``: per image set {set, cameras, rms_px}. ``T_ref_board``:
    set key -> 4x4. ``residuals``: per kept observation (N, 2) observed - projected, px.
    """

    names: list[str]
    reference: str
    T_ref_camera: list[FloatArray]
    intrinsics: list[dict[str, Any]]
    cameras: list[dict[str, Any]]
    pairs: list[dict[str, Any]]
    graph: dict[str, Any]
    sets: list[dict[str, Any]]
    T_ref_board: dict[str, FloatArray]
    observations: list[Observation]
    residuals: list[FloatArray]
    rms_px: float
    rejected: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def vector_from_pose(T: FloatArray) -> FloatArray:
    return np.r_[rotvec_from_matrix(T[:3, :3]), T[:3, 3]]


def project(points_cam: FloatArray, k: FloatArray, skew: FloatArray | float = 0.0) -> FloatArray:
    """Pixels (M, 2) of camera-frame points (M, 3), mm, through per-point intrinsics ``k``
    (M, 9) in the order of ``INTRINSIC_KEYS`` (OpenCV's model; ``skew`` px, default 0)."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = k.T
    xd, yd = distort(points_cam[:, :2].T / points_cam[:, 2], Brown.per_point(k1, k2, p1, p2, k3))
    return np.column_stack([fx * xd + skew * yd + cx, fy * yd + cy])


def intrinsic_vector(cam: dict[str, Any]) -> FloatArray:
    """IntrinsicsConfig keys -> (9,) in the order of ``INTRINSIC_KEYS``."""
    return np.r_[cam["fx"], cam["fy"], cam["cx"], cam["cy"], np.asarray(cam["dist"], float)]


def _opencv(cam: dict[str, Any]) -> tuple[FloatArray, FloatArray]:
    K = np.array([[cam["fx"], cam.get("skew", 0.0), cam["cx"]], [0.0, cam["fy"], cam["cy"]],
                  [0.0, 0.0, 1.0]])
    return K, np.asarray(cam["dist"], dtype=np.float64)


def _pnp(obs: Observation, cam: dict[str, Any]) -> tuple[FloatArray, float]:
    """Board pose in the camera (4x4) and the PnP RMS (px) of one observation."""
    K, dist = _opencv(cam)
    ok, rvec, tvec = cv2.solvePnP(obs.obj, obs.px, K, dist)
    if not ok:
        raise CalibrationError(f"{obs.image}: no board pose (solvePnP failed)")
    proj = cv2.projectPoints(obs.obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum((obs.px - proj) ** 2, axis=1))))
    return make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()), rms


def _consensus(rel: list[FloatArray]) -> FloatArray:
    """Robust mean of relative poses: the medoid rotation, the median translation."""
    spread = [sum(rotation_angle(a[:3, :3] @ b[:3, :3].T) for b in rel) for a in rel]
    out = rel[int(np.argmin(spread))].copy()
    out[:3, 3] = np.median([r[:3, 3] for r in rel], axis=0)
    return out


def _spread(estimates: list[FloatArray], T: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation (deg) and translation (mm) of each estimate off ``T``."""
    deg = np.array([np.degrees(rotation_angle(e[:3, :3] @ T[:3, :3].T)) for e in estimates])
    mm = np.array([float(np.linalg.norm(e[:3, 3] - T[:3, 3])) for e in estimates])
    return deg, mm


class _Problem:
    """The observations as flat arrays for the vectorised residual."""

    def __init__(self, obs: list[Observation], n_cams: int, set_keys: list[str],
                 free: list[tuple[str, ...]], ref: int) -> None:
        self.obs, self.n_cams, self.set_keys, self.ref = obs, n_cams, set_keys, ref
        index = {k: i for i, k in enumerate(set_keys)}
        self.X = np.concatenate([o.obj for o in obs])
        self.px = np.concatenate([o.px for o in obs])
        self.cam = np.concatenate([np.full(len(o.obj), o.camera) for o in obs])
        self.view = np.concatenate([np.full(len(o.obj), index[o.set_key]) for o in obs])
        self.sizes = [len(o.obj) for o in obs]
        # parameter layout: camera poses (non-reference), board poses, free intrinsics
        self.cam_col = {}
        col = 0
        for c in range(n_cams):
            if c != ref:
                self.cam_col[c] = col
                col += 6
        self.board_col0 = col
        col += 6 * len(set_keys)
        self.free_idx = [[INTRINSIC_KEYS.index(k) for k in f] for f in free]
        self.intr_col = []
        for f in self.free_idx:
            self.intr_col.append(col)
            col += len(f)
        self.n_params = col

    def pack(self, T_cam_ref: list[FloatArray], T_ref_board: list[FloatArray],
             intr: FloatArray) -> FloatArray:
        x = np.zeros(self.n_params)
        for c, col in self.cam_col.items():
            x[col:col + 6] = vector_from_pose(T_cam_ref[c])
        for v, T in enumerate(T_ref_board):
            x[self.board_col0 + 6 * v:self.board_col0 + 6 * v + 6] = vector_from_pose(T)
        for c, idx in enumerate(self.free_idx):
            x[self.intr_col[c]:self.intr_col[c] + len(idx)] = intr[c, idx]
        return x

    def unpack(self, x: FloatArray, intr0: FloatArray,
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Camera rotations (C, 3, 3), translations (C, 3), board ones (V, 3, 3), (V, 3), and
        the intrinsics (C, 9)."""
        cam_v = np.zeros((self.n_cams, 6))
        for c, col in self.cam_col.items():
            cam_v[c] = x[col:col + 6]
        board_v = x[self.board_col0:self.board_col0 + 6 * len(self.set_keys)].reshape(-1, 6)
        intr = intr0.copy()
        for c, idx in enumerate(self.free_idx):
            intr[c, idx] = x[self.intr_col[c]:self.intr_col[c] + len(idx)]
        return (matrices_from_rotvecs(cam_v[:, :3]), cam_v[:, 3:], matrices_from_rotvecs(
            board_v[:, :3]), board_v[:, 3:], intr)

    def _chain(self, x: FloatArray, intr0: FloatArray) -> tuple[FloatArray, ...]:
        Rc, tc, Rb, tb, intr = self.unpack(x, intr0)
        RbX = np.einsum("nij,nj->ni", Rb[self.view], self.X)
        Xr = RbX + tb[self.view]
        RcXr = np.einsum("nij,nj->ni", Rc[self.cam], Xr)
        return Rc, RbX, RcXr, RcXr + tc[self.cam], intr

    def residuals(self, x: FloatArray, intr0: FloatArray, skews: FloatArray) -> FloatArray:
        """Projected - observed, (2M,) px, u and v interleaved."""
        *_, Xc, intr = self._chain(x, intr0)
        out: FloatArray = (project(Xc, intr[self.cam], skews[self.cam]) - self.px).ravel()
        return out

    def jacobian(self, x: FloatArray, intr0: FloatArray, skews: FloatArray) -> csr_matrix:
        """The residuals' Jacobian, analytic and sparse (finite differences stall short of
        the optimum at these scales: mm translations beside 1e-6 rad rotations).

        With ``Xr = Rb X + tb`` and ``Xc = Rc Xr + tc``, a rotation vector's derivative is
        ``d(R p)/dv = -[R p]x J_l(v)`` (J_l: SO(3)'s left Jacobian); the projection's chain
        rule is written out below for OpenCV's distortion model.
        """
        Rc, RbX, RcXr, Xc, intr = self._chain(x, intr0)
        n_cams_v = np.zeros((self.n_cams, 3))
        for c, col in self.cam_col.items():
            n_cams_v[c] = x[col:col + 3]
        board_v = x[self.board_col0:self.board_col0 + 6 * len(self.set_keys)].reshape(-1, 6)
        k = intr[self.cam]
        fx, fy, _cx, _cy, k1, k2, p1, p2, k3 = k.T
        sk = skews[self.cam]
        X, Y, Z = Xc.T
        N = Xc[:, :2].T / Z  # normalized (xn, yn), (2, M)
        (xd, yd), (dxd_dx, dyd_dy), dxd_dy = distort_with_jacobian(
            N, Brown.per_point(k1, k2, p1, p2, k3))
        dyd_dx = dxd_dy  # the distortion's derivative is symmetric
        # d(u, v)/d(xn, yn), (M, 2, 2)
        A = np.empty((len(X), 2, 2))
        A[:, 0, 0] = fx * dxd_dx + sk * dyd_dx
        A[:, 0, 1] = fx * dxd_dy + sk * dyd_dy
        A[:, 1, 0] = fy * dyd_dx
        A[:, 1, 1] = fy * dyd_dy
        # d(xn, yn)/d Xc, (M, 2, 3)
        B = np.zeros((len(X), 2, 3))
        B[:, 0, 0] = 1.0 / Z
        B[:, 1, 1] = 1.0 / Z
        B[:, 0, 2] = -X / Z**2
        B[:, 1, 2] = -Y / Z**2
        P = A @ B  # d(u, v)/d Xc
        IntArray = NDArray[np.int64]
        # (M, 2, k) derivative blocks, their first columns (M,), their points (M,)
        blocks: list[tuple[FloatArray, IntArray, IntArray]] = []

        def add(J: FloatArray, cols: Any, on: Any = None) -> None:
            rows = np.arange(len(X)) if on is None else on
            blocks.append((J, np.asarray(cols, np.int64), np.asarray(rows, np.int64)))

        Jl_c = left_jacobians(n_cams_v)[self.cam]
        Jl_b = left_jacobians(board_v[:, :3])[self.view]
        d_vc = -P @ skew(RcXr) @ Jl_c
        d_vb = -(P @ Rc[self.cam]) @ skew(RbX) @ Jl_b
        d_tb = P @ Rc[self.cam]
        non_ref = self.cam != self.ref
        cam_cols = np.array([self.cam_col.get(c, 0) for c in self.cam])
        add(np.concatenate([d_vc, P], axis=2)[non_ref], cam_cols[non_ref],
            np.flatnonzero(non_ref))
        add(np.concatenate([d_vb, d_tb], axis=2), self.board_col0 + 6 * self.view)
        # intrinsics, (M, 2, 9) in INTRINSIC_KEYS order
        Ji = np.zeros((len(X), 2, 9))
        Ji[:, 0, 0] = xd
        Ji[:, 1, 1] = yd
        Ji[:, 0, 2] = 1.0
        Ji[:, 1, 3] = 1.0
        G = coefficient_jacobian(N)  # d(xd, yd)/d(k1, k2, p1, p2, k3), (2, 5, M)
        Ji[:, 0, 4:] = (fx * G[0] + sk * G[1]).T
        Ji[:, 1, 4:] = (fy * G[1]).T
        for c, idx in enumerate(self.free_idx):
            on = np.flatnonzero(self.cam == c)
            if idx and len(on):
                add(Ji[on][:, :, idx], np.full(len(on), self.intr_col[c]), on)
        rows, cols, vals = [], [], []
        for J, c0, on in blocks:
            width = J.shape[2]
            r_idx = (2 * on[:, None, None] + np.arange(2)[None, :, None]) * np.ones((1, 1, width))
            c_idx = c0[:, None, None] + np.arange(width)[None, None, :] * np.ones((1, 2, 1))
            rows.append(r_idx.ravel())
            cols.append(c_idx.ravel())
            vals.append(J.ravel())
        return coo_matrix((np.concatenate(vals), (np.concatenate(rows).astype(np.int64),
                                                  np.concatenate(cols).astype(np.int64))),
                          shape=(2 * len(X), self.n_params)).tocsr()


def calibrate_cameras(names: Sequence[str], intrinsics: Sequence[dict[str, Any]],
                      observations: Sequence[Observation], *, reference: str | None = None,
                      free: Sequence[Sequence[str]] | None = None, outlier_factor: float = 3.0,
                      outlier_floor_px: float = 0.5,
                      intrinsics_prior: Sequence[dict[str, Any] | None] | None = None,
                      ) -> MultiResult:
    """Calibrate N cameras' poses (and optionally intrinsics) from board observations.

    Parameters
    ----------
    names : camera names (2..8, unique).
    intrinsics : per camera IntrinsicsConfig keys (fx fy cx cy skew dist width height), the
        start values (fixed unless ``free`` says).
    observations : the board per camera and image set (see :class:`Observation`).
    reference : the camera whose frame is ``ref`` (default the first).
    free : per camera the intrinsics refined in the joint fit (names from
        ``INTRINSIC_KEYS``); default none.
    outlier_factor, outlier_floor_px : the observation outlier rule (module docstring).
    intrinsics_prior : per camera None or what is known of its intrinsics' error:
        ``values`` (9, ``INTRINSIC_KEYS`` order; the best estimate, e.g. the richest model's
        of ``calibrate_intrinsics``) and ``covariance`` (9x9). The intrinsics the joint fit
        holds (not in ``free``) are not exact: their error ``start - values`` (known, the
        model choice's shift) plus one of that covariance moves the camera poses, and the
        pose sigmas include it (:func:`_camera_std`); without, they hold only for exact
        intrinsics (then as ``std_model``).

    Raises CalibrationError naming the camera, image or pair at fault.
    """
    names = [str(n) for n in names]
    n_cams = len(names)
    if not 2 <= n_cams <= MAX_CAMERAS:
        raise CalibrationError(f"{n_cams} cameras: need 2 to {MAX_CAMERAS}")
    if len(set(names)) != n_cams:
        raise CalibrationError(f"camera names are not unique: {names}")
    if len(intrinsics) != n_cams:
        raise CalibrationError(f"{len(intrinsics)} intrinsics for {n_cams} cameras")
    ref_name = names[0] if reference is None else reference
    if ref_name not in names:
        raise CalibrationError(f"reference camera {ref_name!r} is not one of {names}")
    ref = names.index(ref_name)
    free_sets = [tuple(f) for f in free] if free is not None else [()] * n_cams
    for c, f in enumerate(free_sets):
        bad = [k for k in f if k not in INTRINSIC_KEYS]
        if bad:
            raise CalibrationError(f"camera {names[c]}: unknown intrinsic(s) {bad}; "
                                   f"choose from {INTRINSIC_KEYS}")
    obs = []
    for o in observations:
        if not 0 <= o.camera < n_cams:
            raise CalibrationError(f"{o.image}: camera index {o.camera} out of range")
        if len(o.obj) < MIN_POINTS:
            raise CalibrationError(f"{o.image}: only {len(o.obj)} board points (need "
                                   f"{MIN_POINTS})")
        obs.append(Observation(o.camera, str(o.set_key), np.asarray(o.obj, np.float64),
                               np.asarray(o.px, np.float64), o.image))
    cams = [dict(c) for c in intrinsics]
    pnp: dict[tuple[int, str], tuple[FloatArray, float]] = {
        (o.camera, o.set_key): _pnp(o, cams[o.camera]) for o in obs}
    rejected: list[dict[str, str]] = []
    x: FloatArray | None = None
    while True:
        try:
            T_cam_ref, edges, tree = _initial_cameras(names, obs, pnp, ref)
        except CalibrationError as err:
            if not rejected:
                raise
            left_out = ", ".join(f"{x['image']} ({x['reason']})" for x in rejected)
            raise CalibrationError(f"{err} [after leaving out outlier image(s): {left_out}]"
                                   ) from None
        set_keys = sorted({o.set_key for o in obs}, key=_set_order)
        problem = _Problem(obs, n_cams, set_keys, list(free_sets), ref)
        intr0 = np.array([intrinsic_vector(c) for c in cams])
        skews = np.array([float(c.get("skew", 0.0)) for c in cams])
        if x is None or len(x) != problem.n_params:
            boards = _initial_boards(obs, pnp, T_cam_ref, set_keys)
            x = problem.pack(T_cam_ref, boards, intr0)
        x, fun = levenberg_marquardt(partial(problem.residuals, intr0=intr0, skews=skews),
                                     partial(problem.jacobian, intr0=intr0, skews=skews), x,
                                     blocks=(problem.board_col0, len(set_keys)))
        res = fun.reshape(-1, 2)
        per_obs = np.split(res, np.cumsum(problem.sizes)[:-1])
        rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in per_obs])
        median = float(np.median(rms))
        worst = int(np.argmax(rms))
        if rms[worst] <= outlier_factor * median or rms[worst] <= outlier_floor_px:
            break
        o = obs[worst]
        rejected.append({"camera": names[o.camera], "set": o.set_key, "image": o.image,
                         "reason": f"RMS {rms[worst]:.2f} px vs median {median:.2f} px "
                                   f"(outlier: > {outlier_factor:g}x median)"})
        del obs[worst]
        del pnp[(o.camera, o.set_key)]
        x = None  # the layout may change (a set or a camera gone): start again from PnP
    result = _result(names, ref, cams, problem, x, intr0, per_obs, obs, pnp, edges, tree,
                     rejected)
    priors = list(intrinsics_prior) if intrinsics_prior is not None else [None] * n_cams
    if len(priors) != n_cams:
        raise CalibrationError(f"{len(priors)} intrinsics priors for {n_cams} cameras")
    for row, std in zip(result.cameras, _camera_std(problem, x, intr0, skews, fun, priors),
                        strict=True):
        row.update(std)
    return result


def _camera_std(problem: _Problem, x: FloatArray, intr0: FloatArray, skews: FloatArray,
                fun: FloatArray, priors: Sequence[dict[str, Any] | None] = (),
                ) -> list[dict[str, Any]]:
    """One-sigma uncertainty of every camera's pose in the reference camera:
    ``position_std_mm`` (x, y, z of the camera centre in the reference frame) and
    ``rotation_std_deg`` (the root of the rotation vector's variances).

    From the fit's covariance ``s^2 (J^T J)^-1`` (``s^2 = SSR / (m - p)``), which treats the
    held intrinsics as exact (kept as ``std_model``), plus what the held intrinsics' error
    does to the poses (``priors``, see ``calibrate_cameras``): with ``G = d(pose)/d(k)``
    (the fit's response to the held intrinsics k, ``-(J_x^T J_x)^-1 J_x^T J_k``), the pose
    covariance gains ``G C Gᵀ`` (C the intrinsics' covariance) and the known shift ``G
    (start - values)`` adds in quadrature, as ``intrinsics.with_model_bias`` does for a
    single camera. The reference camera: zeros."""
    m, p = len(fun), problem.n_params
    zero = {"position_std_mm": [0.0, 0.0, 0.0], "rotation_std_deg": 0.0}
    if m <= p:
        raise CalibrationError(f"{m} residuals for {p} parameters: too few board points")
    J = problem.jacobian(x, intr0, skews)
    normal = _Normal((J.T @ J).tocsr(), J.T @ fun, (problem.board_col0, len(problem.set_keys)))
    try:
        inv = normal.camera_inverse()
    except np.linalg.LinAlgError:
        raise CalibrationError("the views do not determine the camera poses (singular normal "
                               "matrix)") from None
    s2 = float(fun @ fun) / (m - p)
    G, C, shift = _intrinsics_response(problem, x, intr0, skews, normal, inv, priors)
    out = []
    for c in range(problem.n_cams):
        if c not in problem.cam_col:
            out.append({**zero, "std_model": dict(zero)})
            continue
        col = problem.cam_col[c]
        idx = np.searchsorted(normal.c, np.arange(col, col + 6))
        cov = s2 * inv[np.ix_(idx, idx)]
        v = x[col:col + 6]

        def centre(u: FloatArray) -> FloatArray:
            centre_ref: FloatArray = -matrices_from_rotvecs(u[:3]).T @ u[3:]
            return centre_ref

        # d(centre)/d(rotvec, t) by central differences (6 evaluations of a 3x3 product)
        D = np.column_stack([(centre(v + h) - centre(v - h)) / 2e-7
                             for h in np.eye(6) * 1e-7])
        own = {"position_std_mm": [float(q) for q in np.sqrt(np.diag(D @ cov @ D.T))],
               "rotation_std_deg": float(np.degrees(np.sqrt(np.trace(cov[:3, :3]))))}
        if G is None:
            out.append({**own, "std_model": own})
            continue
        Gc = G[idx]
        wide = cov + Gc @ C @ Gc.T
        d = Gc @ shift  # the pose's shift from the held intrinsics' known error
        pos = np.sqrt(np.diag(D @ wide @ D.T) + (D @ d) ** 2)
        rot = np.sqrt(np.trace(wide[:3, :3]) + float(d[:3] @ d[:3]))
        out.append({"position_std_mm": [float(q) for q in pos],
                    "rotation_std_deg": float(np.degrees(rot)), "std_model": own})
    return out


def _intrinsics_response(problem: _Problem, x: FloatArray, intr0: FloatArray,
                         skews: FloatArray, normal: _Normal, inv: FloatArray,
                         priors: Sequence[dict[str, Any] | None],
                         ) -> tuple[FloatArray | None, FloatArray, FloatArray]:
    """``(G, C, shift)``: ``G`` (len(normal.c), q) how the fit's non-board parameters move
    per unit of the q held intrinsics that have a prior, ``C`` (q, q) their covariance
    (cameras independent), ``shift`` (q,) start - prior values. G is None without priors."""
    extra = [[k for k in INTRINSIC_KEYS if k not in free] if prior is not None else []
             for free, prior in zip(
                 [[INTRINSIC_KEYS[i] for i in f] for f in problem.free_idx],
                 list(priors) or [None] * problem.n_cams, strict=True)]
    if not any(extra):
        return None, np.zeros((0, 0)), np.zeros(0)
    free2 = [tuple(INTRINSIC_KEYS[i] for i in f) + tuple(e)
             for f, e in zip(problem.free_idx, extra, strict=True)]
    p2 = _Problem(problem.obs, problem.n_cams, problem.set_keys, free2, problem.ref)
    x2 = np.zeros(p2.n_params)
    x2[:p2.intr_col[0]] = x[:problem.board_col0 + 6 * len(problem.set_keys)]
    x_cols: list[int] = list(range(p2.intr_col[0]))
    k_cols: list[int] = []
    blocks, shifts = [], []
    for c, (f, e) in enumerate(zip(problem.free_idx, extra, strict=True)):
        c0 = p2.intr_col[c]
        x2[c0:c0 + len(f)] = x[problem.intr_col[c]:problem.intr_col[c] + len(f)]
        x_cols += range(c0, c0 + len(f))
        if not e:
            continue
        ei = [INTRINSIC_KEYS.index(k) for k in e]
        x2[c0 + len(f):c0 + len(f) + len(e)] = intr0[c, ei]
        k_cols += range(c0 + len(f), c0 + len(f) + len(e))
        prior = priors[c]
        assert prior is not None
        cov = np.asarray(prior["covariance"], np.float64)
        blocks.append(cov[np.ix_(ei, ei)])
        shifts.append(intr0[c, ei] - np.asarray(prior["values"], np.float64)[ei])
    J2 = p2.jacobian(x2, intr0, skews)
    B = (J2[:, x_cols].T @ J2[:, k_cols]).toarray()  # (p, q) = J_x^T J_k
    q = B.shape[1]
    V_inv = np.linalg.inv(normal.V)
    VB = np.einsum("nij,njq->niq", V_inv, B[normal.b].reshape(normal.n, 6, q)).reshape(-1, q)
    G = -inv @ (B[normal.c] - normal.W @ VB)
    C = np.zeros((q, q))
    i = 0
    for blk in blocks:
        C[i:i + len(blk), i:i + len(blk)] = blk
        i += len(blk)
    return G, C, np.concatenate(shifts)


def levenberg_marquardt(fun: Callable[[FloatArray], FloatArray],
                        jac: Callable[[FloatArray], csr_matrix], x0: FloatArray,
                        blocks: tuple[int, int] = (0, 0),
                        tol: float = 1e-12) -> tuple[FloatArray, FloatArray]:
    """Minimise ``|fun(x)|^2`` from ``x0``: Levenberg-Marquardt on the normal equations.

    Why not ``scipy.optimize.least_squares``: with a sparse Jacobian it solves each step with
    LSMR, whose iterations grow with the conditioning of a bundle adjustment (at tolerances
    tight enough to converge: 1 to 15 s for 8 cameras, 170 images on this machine); at its
    default tolerances the inexact steps crawl.

    Here ``J^T J`` is formed from the sparse Jacobian and each step solved exactly.
    ``blocks = (start, n)``: parameters ``start .. start + 6n`` are ``n`` board poses that no
    residual shares, so their part of ``J^T J`` is block diagonal (6x6 blocks); they are
    eliminated first (Schur complement, the classic bundle adjustment step) and the rest --
    the cameras, a few dozen parameters -- solved by Cholesky. Every part costs time linear in
    the observations and sets. Marquardt's damping scales with the diagonal (invariant to mm
    vs rad vs px). Stops when the cost falls by less than ``tol`` relative or the step is
    below ``tol`` relative to ``x``. Returns the solution and its residuals; CalibrationError
    if non-finite.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    r = fun(x)
    cost = float(r @ r)
    lam = 1e-4
    for _ in range(MAX_ITERATIONS):
        J = jac(x)
        normal = _Normal((J.T @ J).tocsr(), J.T @ r, blocks)
        while True:
            step = normal.solve(lam)
            if step is not None:
                x_new = x + step
                r_new = fun(x_new)
                cost_new = float(r_new @ r_new)
                if np.isfinite(cost_new) and cost_new <= cost:
                    break
            lam *= 10.0
            if lam > 1e12:  # no step lowers the cost: at the minimum (to rounding)
                return x, r
        done = (cost - cost_new <= tol * cost
                or np.linalg.norm(step) <= tol * (np.linalg.norm(x) + tol))
        x, r, cost = x_new, r_new, cost_new
        lam = max(lam / 10.0, 1e-12)
        if done:
            break
    if not np.all(np.isfinite(x)):
        raise CalibrationError("the joint fit diverged (non-finite parameters)")
    return x, r


class _Normal:
    """The normal equations ``A step = -g`` split into the 6x6 board blocks ``V`` and the rest
    ``U`` (with their coupling ``W``), for damped solves by the Schur complement."""

    def __init__(self, A: csr_matrix, g: FloatArray, blocks: tuple[int, int]) -> None:
        start, n = blocks
        p = A.shape[0]
        self.b = np.arange(start, start + 6 * n)
        self.c = np.setdiff1d(np.arange(p), self.b)
        self.n = n
        A_cc = A[self.c][:, self.c]
        self.U = A_cc.toarray()
        self.W = A[self.c][:, self.b].toarray()  # (pc, 6n): linear in the sets
        V = A[self.b][:, self.b].tocoo()
        self.V = np.zeros((n, 6, 6))
        self.V[V.row // 6, V.row % 6, V.col % 6] = V.data
        self.g_c, self.g_b = g[self.c], g[self.b]
        self.d_c = np.where(np.diag(self.U) > 0, np.diag(self.U), 1.0)
        dv = np.einsum("nii->ni", self.V)
        self.d_b = np.where(dv > 0, dv, 1.0)
        self.p = p

    def camera_inverse(self) -> FloatArray:
        """``(J^T J)^-1`` restricted to the non-board parameters (in the order of ``c``):
        the inverse of the undamped Schur complement."""
        V_inv = np.linalg.inv(self.V)
        WV = np.einsum("pnj,njk->pnk", self.W.reshape(len(self.c), self.n, 6),
                       V_inv).reshape(len(self.c), -1)
        out: FloatArray = np.linalg.inv(self.U - WV @ self.W.T)
        return out

    def solve(self, lam: float) -> FloatArray | None:
        """The damped step, or None when the damped matrix is not positive definite."""
        try:
            V = self.V + lam * np.einsum("ni,ij->nij", self.d_b, np.eye(6))
            V_inv = np.linalg.inv(V)
            gb = self.g_b.reshape(-1, 6)
            if len(self.c):
                WV = np.einsum("pnj,njk->pnk", self.W.reshape(len(self.c), self.n, 6),
                               V_inv).reshape(len(self.c), -1)
                S = self.U + lam * np.diag(self.d_c) - WV @ self.W.T
                d_c = -cho_solve(cho_factor(S), self.g_c - WV @ self.g_b)
            else:
                d_c = np.zeros(0)
            rhs = -(gb + (self.W.T @ d_c).reshape(-1, 6))
            d_b = np.einsum("nij,nj->ni", V_inv, rhs).ravel()
        except (LinAlgError, np.linalg.LinAlgError):
            return None
        step = np.zeros(self.p)
        step[self.c] = d_c
        step[self.b] = d_b
        if not np.all(np.isfinite(step)):
            return None
        return step


def _set_order(key: str) -> tuple[int, str]:
    return (int(key), "") if key.isdigit() else (1 << 62, key)


def _initial_cameras(names: list[str], obs: list[Observation],
                     pnp: dict[tuple[int, str], tuple[FloatArray, float]], ref: int,
                     ) -> tuple[list[FloatArray], dict[tuple[int, int], list[FloatArray]],
                                list[tuple[int, int]]]:
    """Camera poses ``T_cam_ref`` composed along the widest spanning tree of the view graph;
    also the per-set pair estimates (``edges[(a, b)]``: estimates of ``T_b_a``) and the tree."""
    n = len(names)
    by_set: dict[str, list[int]] = {}
    for o in obs:
        by_set.setdefault(o.set_key, []).append(o.camera)
    edges: dict[tuple[int, int], list[FloatArray]] = {}
    for key, cams in by_set.items():
        for i, a in enumerate(sorted(cams)):
            for b in sorted(cams)[i + 1:]:
                rel = pnp[(b, key)][0] @ invert_transform(pnp[(a, key)][0])
                edges.setdefault((a, b), []).append(rel)
    seen_cams = {o.camera for o in obs}
    unseen = [names[c] for c in range(n) if c not in seen_cams]
    if unseen:
        raise CalibrationError(f"camera(s) {', '.join(unseen)}: the board was not found in "
                               "any of their images")
    T_cam_ref: list[FloatArray | None] = [None] * n
    T_cam_ref[ref] = np.eye(4)
    tree: list[tuple[int, int]] = []
    while True:  # Prim: add the widest edge from the tree to a camera outside it
        best: tuple[int, int, int] | None = None
        for (a, b), est in edges.items():
            for parent, child in ((a, b), (b, a)):
                if T_cam_ref[parent] is not None and T_cam_ref[child] is None and (
                        best is None or len(est) > best[0]):
                    best = (len(est), parent, child)
        if best is None:
            break
        _, parent, child = best
        pair = (min(parent, child), max(parent, child))
        T_b_a = _consensus(edges[pair])
        T_child_parent = T_b_a if parent == pair[0] else invert_transform(T_b_a)
        T_parent_ref = T_cam_ref[parent]
        assert T_parent_ref is not None
        T_cam_ref[child] = T_child_parent @ T_parent_ref
        tree.append((parent, child))
    missing = [c for c in range(n) if T_cam_ref[c] is None]
    if missing:
        groups = _components(missing, edges)
        told = "; ".join("{" + ", ".join(names[c] for c in g) + "}" for g in groups)
        reached = ", ".join(names[c] for c in range(n) if T_cam_ref[c] is not None)
        raise CalibrationError(
            f"cannot connect camera(s) {', '.join(names[c] for c in missing)} to the reference "
            f"{names[ref]}: they share no image set (board seen at the same instant) with "
            f"{reached}, directly or through other cameras (unconnected groups: {told}); take "
            "image sets where the board is seen by a camera of each group")
    return [T for T in T_cam_ref if T is not None], edges, tree


def _components(cams: list[int], edges: dict[tuple[int, int], list[FloatArray]],
                ) -> list[list[int]]:
    left = set(cams)
    groups = []
    while left:
        stack, group = [min(left)], set()
        while stack:
            c = stack.pop()
            if c in group:
                continue
            group.add(c)
            stack += [b if a == c else a for a, b in edges if c in (a, b) and
                      (b if a == c else a) in left]
        left -= group
        groups.append(sorted(group))
    return groups


def _initial_boards(obs: list[Observation], pnp: dict[tuple[int, str], tuple[FloatArray, float]],
                    T_cam_ref: list[FloatArray], set_keys: list[str]) -> list[FloatArray]:
    """Each set's board pose in ``ref`` from the camera with the lowest PnP error in it."""
    best: dict[str, tuple[float, FloatArray]] = {}
    for o in obs:
        T_cam_board, rms = pnp[(o.camera, o.set_key)]
        if o.set_key not in best or rms < best[o.set_key][0]:
            best[o.set_key] = (rms, invert_transform(T_cam_ref[o.camera]) @ T_cam_board)
    return [best[k][1] for k in set_keys]


def _result(names: list[str], ref: int, cams: list[dict[str, Any]], problem: _Problem,
            x: FloatArray, intr0: FloatArray, per_obs: list[FloatArray],
            obs: list[Observation], pnp: dict[tuple[int, str], tuple[FloatArray, float]],
            edges: dict[tuple[int, int], list[FloatArray]], tree: list[tuple[int, int]],
            rejected: list[dict[str, str]]) -> MultiResult:
    Rc, tc, Rb, tb, intr = problem.unpack(x, intr0)
    T_cam_ref = [make_transform(R, t) for R, t in zip(Rc, tc, strict=True)]
    n = len(names)
    intrinsics = []
    for c in range(n):
        cam = dict(cams[c])
        k = intr[c]
        cam.update(fx=float(k[0]), fy=float(k[1]), cx=float(k[2]), cy=float(k[3]),
                   dist=[float(v) for v in k[4:9]])
        intrinsics.append(cam)
    residuals = [-r for r in per_obs]  # observed - projected
    sq = [np.sum(r**2, axis=1) for r in residuals]
    cameras = []
    for c in range(n):
        mine = [s for s, o in zip(sq, obs, strict=True) if o.camera == c]
        cameras.append({"name": names[c], "sets": len(mine),
                        "points": int(sum(len(s) for s in mine)),
                        "rms_px": float(np.sqrt(np.mean(np.concatenate(mine))))})
    pairs = []
    for (a, b), est in sorted(edges.items()):
        T_b_a = T_cam_ref[b] @ invert_transform(T_cam_ref[a])
        deg, mm = _spread(est, T_b_a)
        shared = {o.set_key for o in obs if o.camera == a} & {o.set_key for o in obs
                                                             if o.camera == b}
        both = [s for s, o in zip(sq, obs, strict=True)
                if o.camera in (a, b) and o.set_key in shared]
        distance = float(np.median([np.linalg.norm(pnp[(a, k)][0][:3, 3]) for k in shared]))
        pairs.append({"a": names[a], "b": names[b], "shared_sets": len(est),
                      "board_distance_mm": distance,
                      "rms_px": float(np.sqrt(np.mean(np.concatenate(both)))),
                      "rotation_deg": {"rms": float(np.sqrt(np.mean(deg**2))),
                                       "max": float(deg.max())},
                      "translation_mm": {"rms": float(np.sqrt(np.mean(mm**2))),
                                         "max": float(mm.max())}})
    sets = []
    for key in problem.set_keys:
        mine = [(s, o) for s, o in zip(sq, obs, strict=True) if o.set_key == key]
        sets.append({"set": key, "cameras": [names[o.camera] for _, o in mine],
                     "rms_px": float(np.sqrt(np.mean(np.concatenate([s for s, _ in mine]))))})
    T_ref_camera = [invert_transform(T) for T in T_cam_ref]
    boards = {k: make_transform(R, t) for k, R, t in zip(problem.set_keys, Rb, tb, strict=True)}
    result = MultiResult(
        names=names, reference=names[ref], T_ref_camera=T_ref_camera, intrinsics=intrinsics,
        cameras=cameras, pairs=pairs,
        graph={"edges": [(names[a], names[b], len(e)) for (a, b), e in sorted(edges.items())],
               "tree": [(names[p], names[c]) for p, c in tree]},
        sets=sets, T_ref_board=boards, observations=obs, residuals=residuals,
        rms_px=float(np.sqrt(np.mean(np.concatenate(sq)))), rejected=rejected)
    result.warnings = _warnings(result)
    return result


def _warnings(r: MultiResult) -> list[str]:
    out = []
    for cam in r.cameras:
        if cam["sets"] < FEW_SETS:
            out.append(f"camera {cam['name']} saw the board in only {cam['sets']} image "
                       f"set(s); its pose rests on few views")
    for p in r.pairs:
        if (p["rotation_deg"]["rms"] > PAIR_WARN_DEG
                or p["translation_mm"]["rms"] > PAIR_WARN_DISTANCE * p["board_distance_mm"]):
            out.append(f"pair {p['a']} / {p['b']}: its own per-set estimates spread "
                       f"{p['rotation_deg']['rms']:.2f} deg, {p['translation_mm']['rms']:.1f} "
                       "mm (RMS) around the joint solution: did a camera move, or are some "
                       "images not from the same instant?")
    n_out = sum(1 for x in r.rejected if "outlier" in x["reason"])
    if n_out > max(2, OUTLIER_WARN_SHARE * (n_out + len(r.observations))):
        out.append(f"{n_out} images were left out as outliers, more than a few: usually a "
                   "camera that moved during the session or images not from the same instants; "
                   "the result rests on the rest, check it")
    return out


def place(result: MultiResult, T_base_ref: FloatArray) -> list[FloatArray]:
    """Every camera's pose in the base frame, given the reference camera's frame there:
    ``T_base_camera = T_base_ref @ T_ref_camera``."""
    return [T_base_ref @ T for T in result.T_ref_camera]


def base_from_board(result: MultiResult, set_key: str, T_base_board: FloatArray) -> FloatArray:
    """``T_base_ref`` from the board's pose in the base frame in one image set."""
    if set_key not in result.T_ref_board:
        kept = ", ".join(result.T_ref_board)
        raise CalibrationError(f"image set {set_key!r} is not in the fit (sets: {kept})")
    out: FloatArray = T_base_board @ invert_transform(result.T_ref_board[set_key])
    return out


def base_from_camera(result: MultiResult, camera: str, T_base_camera: FloatArray) -> FloatArray:
    """``T_base_ref`` from one camera's known pose (a hand-eye result); for a robot-mounted
    camera pass ``T_flange_camera`` and read "base" as "flange"."""
    if camera not in result.names:
        raise CalibrationError(f"camera {camera!r} is not one of {result.names}")
    out: FloatArray = T_base_camera @ invert_transform(
        result.T_ref_camera[result.names.index(camera)])
    return out
