"""Single-camera calibration from board detections (what Bouguet's toolbox calls "Calibration").

Model: pinhole with two focal lengths, principal point, no skew, Brown distortion
``dist = [k1, k2, p1, p2, k3]`` in OpenCV's order, which is Bouguet's ``kc``; skew is always 0
(OpenCV's ``calibrateCamera`` has no skew parameter). k1 and k2 are always estimated; whether
the tangential pair p1, p2 and the 6th-order k3 are estimated or held at 0 is chosen from the
data (:class:`DistortionModel`), unless the caller fixes it (``fix_k3``, ``fix_tangential``).

Model choice: every candidate model (with and without p1 p2, with and without k3) is fitted to
the same views and scored by the Bayesian information criterion of the reprojection residuals,
``BIC = m ln(SSR / m) + p ln(m)`` (m residuals = 2 per point, p parameters: intrinsics and board
poses). The lowest BIC wins, except that the reference model (Bouguet's default, k1 k2 p1 p2
with k3 = 0, or the nearest to it that the options allow) is kept unless another beats it by
more than ``BIC_MARGIN`` = 2 (Kass and Raftery's threshold for "positive" evidence): a term
the data cannot tell from 0 is left out. Fixing k3 when the lens has one biases k2 by many of
its (then too small) standard deviations; freeing it when the lens has none makes k2 and k3
trade off (correlation ~0.98) and the distortion extrapolates badly beyond the views. Every
candidate's RMS, BIC and k2/k3 are kept in ``IntrinsicsResult.model`` for the report. When the
views cannot show k3 (a narrow lens, boards that never reach the corners), no criterion can
find it: k3 = 0 is chosen; the candidates table shows k2 with k3 free next to it.

Reported sigmas (``std``): the chosen model's point estimate, with a sigma that covers its
error whatever the left-out terms are (``with_model_bias``: the richest model's sigma with
the shift to its estimate in quadrature) and whichever candidate the data did not rule out
(``widen``: BIC within ``PLAUSIBLE_BIC`` = 10 of the chosen one). ``std_model`` keeps the
chosen model's own sigma (valid only if the left-out terms are exactly 0).

Fit: ``cv2.calibrateCameraExtended`` (Zhang's planar initialisation, then Levenberg-Marquardt
on the reprojection error of all points), which also gives one-sigma standard deviations of the
intrinsics and the per-view RMS. Bouguet's printed uncertainties are about three sigma.

Outliers: an image whose per-image RMS is more than ``outlier_factor`` times the median and
above ``outlier_floor_px`` (a misdetected corner, a motion-blurred view) is dropped and the
calibration redone, one image at a time, worst first; it is reported with the numbers. This
runs with the richest candidate model, so that a lens term left out cannot make the views that
reach the image corners look like outliers. Images with fewer than ``min_points`` points are
dropped before the fit. At least 3 images must remain.

Errors: ``rms_px`` (and per image) is the root mean square of the reprojection error length,
sqrt(mean(dx^2 + dy^2)) px, as OpenCV reports it; Bouguet's ``err`` is the standard deviation of
dx and of dy separately, so for round noise rms_px ~ sqrt(2) * err.
"""

from __future__ import annotations

import math
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
BIC_MARGIN = 2.0  # another model must beat the reference model's BIC by more than this
# A candidate whose BIC is within this of the chosen model's is not ruled out by the data
# (Kass and Raftery: above 10 the evidence is "very strong"); the reported sigmas cover the
# shift to its estimates too (``widen``).
PLAUSIBLE_BIC = 10.0


@dataclass(frozen=True)
class DistortionModel:
    """Which Brown terms are estimated: k1, k2 always, p1 p2 when ``tangential``, k3 when
    ``k3``; the others are held at 0."""

    tangential: bool
    k3: bool

    @property
    def mask(self) -> tuple[bool, ...]:
        """Per ``DIST_NAMES`` entry: estimated?"""
        return (True, True, self.tangential, self.tangential, self.k3)

    @property
    def free(self) -> tuple[str, ...]:
        """Names of the estimated distortion terms, in OpenCV order."""
        return tuple(n for n, f in zip(DIST_NAMES, self.mask, strict=True) if f)

    @property
    def name(self) -> str:
        return " ".join(self.free)

    @property
    def flags(self) -> int:
        """The OpenCV calibration flags that hold the other terms at 0."""
        return ((0 if self.k3 else cv2.CALIB_FIX_K3)
                | (0 if self.tangential else cv2.CALIB_ZERO_TANGENT_DIST))


BOUGUET_MODEL = DistortionModel(tangential=True, k3=False)


def candidate_models(fix_k3: bool | None, fix_tangential: bool | None,
                     ) -> tuple[list[DistortionModel], DistortionModel]:
    """The models to choose from (simplest first) and the reference model, for the options:
    ``fix_*`` True holds the term at 0, False estimates it, None lets the data choose."""
    k3s = [False, True] if fix_k3 is None else [not fix_k3]
    tangentials = [False, True] if fix_tangential is None else [not fix_tangential]
    models = [DistortionModel(t, k) for k in k3s for t in tangentials]
    reference = DistortionModel(tangential=True if fix_tangential is None else not fix_tangential,
                                k3=False if fix_k3 is None else not fix_k3)
    return models, reference


def bic(ssr: float, m: int, p: int) -> float:
    """Bayesian information criterion of a least-squares fit with Gaussian noise of unknown
    variance: m residuals with sum of squares ``ssr``, p parameters."""
    return m * math.log(max(ssr, 1e-300) / m) + p * math.log(m)


def _evidence(delta: float) -> str:
    """Kass and Raftery's words for a BIC difference."""
    return ("weak" if delta < 2 else "positive" if delta < 6 else "strong" if delta < 10
            else "very strong")


@dataclass
class ModelChoice:
    """Which distortion model was used and why.

    ``chosen_by`` is "BIC" or "options" (one candidate only); ``reason`` one line; per
    candidate (simplest first): model, rms_px, dist and dist_std (one sigma, 0 where held),
    bic, delta_bic (to the chosen one). ``notes``: what the choice means for the numbers (k2
    when k3 was left out by the choice).
    """

    model: DistortionModel
    chosen_by: str
    reason: str
    candidates: list[dict[str, Any]]
    notes: list[str] = field(default_factory=list)
    #: chosen - richest model's estimate per parameter (``with_model_bias``); None when the
    #: richest model was chosen. The reported std already includes it.
    model_bias: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the chosen model's name, how, why, the candidates and the notes."""
        out: dict[str, Any] = {"model": self.model.name, "chosen_by": self.chosen_by,
                               "reason": self.reason, "notes": self.notes,
                               "candidates": self.candidates}
        if self.model_bias is not None:
            out["model_bias"] = self.model_bias
        return out

    def table(self, cameras: Sequence[tuple[str, str]] = (("", "dist"),)) -> list[str]:
        """Human lines: one per candidate, the chosen one marked with ``*``; k2 and k3 of each
        (label, key) in ``cameras`` (the candidates' ``key``/``key_std`` entries)."""
        width = max(len(c["model"]) for c in self.candidates)
        head = "".join(f"  {label + name:>20s}" for label, _ in cameras for name in ("k2", "k3"))
        lines = ["  candidates; k2 and k3 +- each model's own 1 sigma (valid only if the terms "
                 "it leaves out are 0):",
                 f"  {'model':{width}s}  RMS px    dBIC{head}"]
        for c in self.candidates:
            mark = "*" if c["model"] == self.model.name else " "
            cells = ""
            for _, key in cameras:
                value, sigma = c[key], c[key + "_std"]
                k3 = (f"{value[4]:.5f} +- {sigma[4]:.5f}" if "k3" in c["model"].split()
                      else "0 (held)")
                k2 = f"{value[1]:.5f} +- {sigma[1]:.5f}"
                cells += f"  {k2:>20s}  {k3:>20s}"
            lines.append(f"{mark} {c['model']:{width}s}  {c['rms_px']:6.4f}  "
                         f"{c['delta_bic']:6.1f}{cells}")
        return lines


def k3_note(choice: ModelChoice, camera: str = "", key: str = "dist") -> list[str]:
    """When the choice left k3 out although a candidate had it: what k2 is with and without it
    (``camera`` prefixes the line; ``key`` names the candidates' dist entries)."""
    rows = {c["model"]: c for c in choice.candidates}
    with_k3 = DistortionModel(choice.model.tangential, k3=True)
    if choice.model.k3 or with_k3.name not in rows:
        return []
    a, b = rows[choice.model.name], rows[with_k3.name]
    va, sa, vb, sb = a[key], a[key + "_std"], b[key], b[key + "_std"]
    return [f"{camera}k3 left out by the choice: k2 = {va[1]:.5f} +- {sa[1]:.5f} holds if "
            f"k3 = 0; with k3 free, k3 = {vb[4]:.5f} +- {sb[4]:.5f} and k2 = {vb[1]:.5f} +- "
            f"{sb[1]:.5f} (k2 and k3 trade off; both fit the views, see the RMS column)"]


def choose_model(scores: dict[DistortionModel, float], reference: DistortionModel,
                 rows: dict[DistortionModel, dict[str, Any]]) -> ModelChoice:
    """Pick from ``scores`` (BIC per candidate) by the rule of the module docstring; ``rows``
    are the candidates' table entries (rms_px, dist, dist_std), completed here."""
    order = sorted(scores, key=lambda mdl: (len(mdl.free), mdl.k3))
    best = min(order, key=lambda mdl: scores[mdl])
    if len(order) == 1:
        chosen, how, reason = best, "options", "the only model the options allow"
    elif best == reference or reference not in scores:
        chosen, how = best, "BIC"
        second = min((mdl for mdl in order if mdl != best), key=lambda mdl: scores[mdl])
        delta = scores[second] - scores[best]
        reason = (f"lowest BIC; the next, {second.name}, is {delta:.1f} higher "
                  f"({_evidence(delta)} evidence)")
    else:
        delta = scores[reference] - scores[best]
        how = "BIC"
        if delta > BIC_MARGIN:
            chosen = best
            reason = (f"lowest BIC, {delta:.1f} below the reference model {reference.name} "
                      f"({_evidence(delta)} evidence)")
        else:
            chosen = reference
            reason = (f"reference model kept: {best.name} has a BIC only {delta:.1f} lower "
                      f"(not more than {BIC_MARGIN:g}: not worth its extra terms)")
    candidates = [{"model": mdl.name, **rows[mdl], "bic": scores[mdl],
                   "delta_bic": scores[mdl] - scores[chosen]} for mdl in order]
    return ModelChoice(chosen, how, reason, candidates)


@dataclass
class IntrinsicsResult:
    """A calibrated camera and the evidence for it.

    ``camera`` has the keys of ``config.IntrinsicsConfig`` (fx, fy, cx, cy, skew, dist, width,
    height; px); ``std`` the one-sigma standard deviations of the same keys (0 for what was
    fixed). Per used image ``i`` (same order as ``detections``): ``per_image[i]`` = {image,
    rms_px, points}, ``residuals_px[i]`` (N_i, 2) observed - projected px, and the board pose
    ``T_cam_board[i]`` (4x4, mm; also as OpenCV ``rvecs[i]``, ``tvecs[i]``). ``model``: the
    distortion model used and the candidates it was chosen from.
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
    model: ModelChoice
    rejected: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: The chosen model's own standard deviations (what OpenCV and Bouguet's toolbox report);
    #: ``std`` adds the model's possible bias (``with_model_bias``) and covers the error.
    std_model: dict[str, Any] | None = None
    #: The richest candidate model's estimate and covariance, for propagating the intrinsics'
    #: uncertainty (``calibrate cameras``): ``model`` (its name), ``values`` (9: fx fy cx cy
    #: k1 k2 p1 p2 k3) and ``covariance`` (9x9, same order; rows of held terms 0), from the
    #: Jacobian at the residual RMS (``richest_covariance``).
    richest: dict[str, Any] | None = None

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
                         image_size: tuple[int, int], *, fix_k3: bool | None = None,
                         fix_tangential: bool | None = None, min_points: int = 8,
                         outlier_factor: float = 3.0,
                         outlier_floor_px: float = 0.5) -> IntrinsicsResult:
    """Calibrate one camera from board detections in images of ``image_size`` (w, h) px.

    ``fix_k3`` / ``fix_tangential``: True holds k3 / p1 p2 at 0, False estimates them, None
    (default) chooses from the data. See the module docstring for the model choice, the
    outlier rule and the error measures. Raises CalibrationError when fewer than 3 usable
    images remain or the fit fails.
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
    models, reference = candidate_models(fix_k3, fix_tangential)
    richest = models[-1]
    obj = board.object_points()
    while True:
        if len(used) < MIN_IMAGES:
            raise CalibrationError(
                f"need at least {MIN_IMAGES} images with the board {board.spec}, have "
                f"{len(used)}" + (f" ({len(rejected)} rejected)" if rejected else ""))
        fit = _fit(obj, used, (w, h), richest.flags)
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
    fits = {mdl: fit if mdl == richest else _fit(obj, used, (w, h), mdl.flags) for mdl in models}
    m = 2 * sum(len(d.ids) for d in used)
    scores, rows = {}, {}
    for mdl, f in fits.items():
        scores[mdl] = bic(f["ssr"], m, 4 + len(mdl.free) + 6 * len(used))
        rows[mdl] = {"rms_px": f["rms"], "dist": [float(v) for v in f["dist"]],
                     "dist_std": _dist_std(f["std"], mdl)}
    choice = choose_model(scores, reference, rows)
    choice.notes = k3_note(choice)
    others = [fits[mdl] | {"model": mdl} for mdl in models
              if mdl not in (choice.model, richest)
              and scores[mdl] - scores[choice.model] < PLAUSIBLE_BIC]
    result = _result(board, used, (w, h), fits[choice.model], rejected, choice,
                     fits[richest] if choice.model != richest else None, others)
    rich = fits[richest]
    result.richest = {
        "model": richest.name,
        "values": [float(v) for v in (rich["K"][0, 0], rich["K"][1, 1], rich["K"][0, 2],
                                      rich["K"][1, 2], *rich["dist"])],
        "covariance": richest_covariance(obj, used, rich, richest)}
    return result


def richest_covariance(obj: NDArray[np.float64], used: Sequence[Detection], fit: dict[str, Any],
                       model: DistortionModel) -> NDArray[np.float64]:
    """9x9 covariance of (fx fy cx cy k1 k2 p1 p2 k3) of ``fit`` (a ``_fit`` of ``model``),
    the board poses marginalised: ``s^2 (J^T J)^-1`` with ``s^2 = SSR / (m - p)``, J from
    ``cv2.projectPoints``. calibrateCameraExtended gives only the diagonal's roots; the
    correlations (fx with fy, cx with p1) matter when the intrinsics' uncertainty is carried
    into another fit. Held terms: rows and columns 0."""
    keep = np.array([True] * 4 + list(model.mask))
    n_k = int(keep.sum())
    n = len(used)
    A_kk = np.zeros((n_k, n_k))
    A_kv = np.zeros((n_k, 6 * n))
    V = np.zeros((n, 6, 6))
    for i, det in enumerate(used):
        _, jac = cv2.projectPoints(obj[det.ids], np.asarray(fit["rvecs"][i], np.float64),
                                   np.asarray(fit["tvecs"][i], np.float64), fit["K"],
                                   fit["dist"])
        J_v, J_k = jac[:, :6], jac[:, 6:15][:, keep]
        A_kk += J_k.T @ J_k
        A_kv[:, 6 * i:6 * i + 6] = J_k.T @ J_v
        V[i] = J_v.T @ J_v
    W = A_kv.reshape(n_k, n, 6)
    S = A_kk - np.einsum("knj,njl,mnl->km", W, np.linalg.inv(V), W)
    m = 2 * sum(len(d.ids) for d in used)
    p = n_k + 6 * n
    cov = np.zeros((9, 9))
    try:
        cov[np.ix_(keep, keep)] = fit["ssr"] / (m - p) * np.linalg.inv(S)
    except np.linalg.LinAlgError:
        raise CalibrationError("the views do not determine the intrinsics (singular normal "
                               "matrix); add views at varied tilts") from None
    return cov


def with_model_bias(std: dict[str, Any], camera: dict[str, Any], rich: dict[str, Any],
                    model: DistortionModel) -> tuple[dict[str, Any], dict[str, Any]]:
    """The standard deviations of a model that left terms out, made to cover its error.

    The error of the chosen estimate splits into ``(chosen - richest) + (richest - truth)``,
    the richest model (every term the options allow free) fitted to the same views: the first
    part is known (the shift), the second has the richest model's sigma, not the chosen
    model's own (which holds only if the left-out terms are truly 0: the data did not rule
    them out, only found them not worth their price in the BIC). Hence per estimated
    parameter ``sqrt(max(std, std_richest)^2 + (chosen - richest)^2)``; at 2 sigma that covers
    the error in at least 95.4 % of sets for any shift (least at shift 0). The chosen model's
    point estimate is kept (it is the better one where the left-out term is small).
    bench/bench_calib_coverage.py: on a 2.2 m profile whose p1, p2 = 0.0002 were dropped the
    principal point was 3-5 sigma off with the chosen model's own sigma; with a dropped k3,
    k2 up to 21 sigma.

    ``rich`` holds the richest fit's ``K`` (3x3), ``dist`` (5,) and ``std`` (fx fy cx cy k1
    k2 p1 p2 k3 sigmas, 0 where held). A term held at 0 keeps std 0 (it is not estimated);
    what it may be, given the data, is in the returned bias as ``held`` (name -> [richest
    value, its std]). Returns (widened std, the shifts ``chosen - richest``)."""
    K, dist, s = rich["K"], rich["dist"], rich["std"]
    rich_values = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    out = dict(std)
    bias: dict[str, Any] = {}
    for i, (k, v) in enumerate(rich_values.items()):
        shift = float(camera[k] - v)
        bias[k] = shift
        out[k] = float(math.hypot(max(std[k], float(s[i])), shift))
    widened, shifts = [], []
    held: dict[str, list[float]] = {}
    for i, (chosen, free) in enumerate(zip(camera["dist"], model.mask, strict=True)):
        shift = float(chosen - dist[i])
        shifts.append(shift)
        if free:
            widened.append(float(math.hypot(max(std["dist"][i], float(s[4 + i])), shift)))
        else:
            widened.append(0.0)
            held[DIST_NAMES[i]] = [float(dist[i]), float(s[4 + i])]
    out["dist"] = widened
    bias["dist"] = shifts
    bias["held"] = held
    return out, bias


def widen(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Per parameter the larger of two std dicts (fx fy cx cy skew, dist list).

    Used for the candidates the data did not rule out (BIC within ``PLAUSIBLE_BIC`` of the
    chosen one): the model choice keeps a term because its estimate came out large enough,
    or drops it because it came out small, so the chosen model's estimate is conditioned on
    that and may sit off by its shift to a plausible neighbour (measured: p1 p2 kept in the
    sets where the choice kept them were outside 2 sigma in half of them). The reported
    sigma is each parameter's largest ``with_model_bias`` over the richest model and those
    candidates."""
    out = {k: max(a[k], b[k]) for k in ("fx", "fy", "cx", "cy", "skew")}
    out["dist"] = [max(x, y) for x, y in zip(a["dist"], b["dist"], strict=True)]
    return out


def _dist_std(std: NDArray[np.float64], model: DistortionModel) -> list[float]:
    """One-sigma std of dist from calibrateCameraExtended's intrinsic std (0 where held)."""
    return [float(v) if free else 0.0 for v, free in zip(std[4:9], model.mask, strict=True)]


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
    n_points = sum(len(d.ids) for d in used)
    return {"K": K, "dist": dist, "rvecs": rvecs, "tvecs": tvecs, "rms": float(_rms),
            "ssr": float(_rms) ** 2 * n_points,
            "std": np.asarray(std_int, dtype=np.float64).ravel(),
            "per_view": np.asarray(per_view, dtype=np.float64).ravel()}


def _result(board: Board, used: list[Detection], size: tuple[int, int], fit: dict[str, Any],
            rejected: list[dict[str, str]], choice: ModelChoice,
            rich: dict[str, Any] | None = None,
            others: Sequence[dict[str, Any]] = ()) -> IntrinsicsResult:
    K, dist, s = fit["K"], fit["dist"], fit["std"]
    w, h = size
    camera = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "skew": 0.0,
              "dist": [float(v) for v in dist], "width": w, "height": h}
    camera = {k: (float(v) if isinstance(v, np.floating) else v) for k, v in camera.items()}
    std_dist = _dist_std(s, choice.model)
    std = {"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3]),
           "skew": 0.0, "dist": std_dist}
    std_model = std
    if rich is not None:
        std, choice.model_bias = with_model_bias(std, camera, rich, choice.model)
    for other in others:
        std = widen(std, with_model_bias(std_model, camera, other, choice.model)[0])
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
                              poses, choice, rejected, std_model=std_model)
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
