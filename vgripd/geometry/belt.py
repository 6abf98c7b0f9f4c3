"""A straight conveyor belt in the robot base frame: its frame, counts to millimetres, the
motion of a part between two encoder counts, and the belt's calibration from observations.

The belt frame ``T_base_belt``: origin ``origin_mm`` (a point on the belt surface, in the base
frame), x = ``direction`` (unit, the way the parts travel), z = ``normal`` (the belt plane's
normal, up), y = z x x. A part on the belt keeps its pose in the belt frame while the frame
moves: between encoder counts ``c0`` and ``c1`` every point travels ``travel_mm(c0, c1)`` along
``direction``. Encoder counts are unsigned ``bits``-wide numbers that wrap; the difference of
two counts is the shortest signed one (a belt never moves half the counter's range between two
images).

``fit_belt``: a board (or a taught object) on the belt seen at two or more counts. Its
positions p_i at counts c_i lie on the line p = a + b c; b is millimetres per count along the
direction, so ``direction = b / |b|`` and ``counts_per_mm = 1 / |b|``. The sigmas are the
linear regression's (from the residuals when there are more than two observations, else from
the stated point sigma), propagated to the scale and to the direction's angle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vgripd.errors import DegenerateInputError
from vgripd.geometry.transforms import invert_transform
from vgripd.types import FloatArray

#: Largest deviation of |direction| from 1 accepted as a unit vector.
UNIT_TOL = 1e-3


def count_delta(c0: int, c1: int, bits: int = 32) -> int:
    """``c1 - c0`` of two ``bits``-wide encoder counts, the shortest way round the wrap."""
    span = 1 << bits
    d = (c1 - c0) % span
    return d - span if d >= span // 2 else d


@dataclass(frozen=True)
class Belt:
    """A straight belt: ``direction`` and ``normal`` unit vectors (base frame), a point
    ``origin_mm`` on it, ``counts_per_mm`` of its encoder, counts ``bits`` wide."""

    direction: tuple[float, float, float]
    counts_per_mm: float
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    bits: int = 32

    def __post_init__(self) -> None:
        for name in ("direction", "normal"):
            n = float(np.linalg.norm(getattr(self, name)))
            if abs(n - 1.0) > UNIT_TOL:
                raise DegenerateInputError(f"belt {name} {list(getattr(self, name))}: not a "
                                           f"unit vector (length {n:.6g})")
        if not self.counts_per_mm > 0:
            raise DegenerateInputError(f"belt counts_per_mm {self.counts_per_mm}: must be > 0")

    @property
    def d(self) -> FloatArray:
        v = np.asarray(self.direction, dtype=np.float64)
        return v / np.linalg.norm(v)

    def T_base_belt(self) -> FloatArray:
        """The belt frame in the base frame (x along the belt, z its normal)."""
        z = np.asarray(self.normal, dtype=np.float64)
        z = z / np.linalg.norm(z)
        x = self.d - z * float(self.d @ z)  # tolerate a hair out of plane: the plane wins
        x = x / np.linalg.norm(x)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2] = x, np.cross(z, x), z
        T[:3, 3] = self.origin_mm
        return T

    def travel_mm(self, c0: int, c1: int) -> float:
        """How far the belt moves from count ``c0`` to ``c1`` (mm, negative backwards)."""
        return count_delta(c0, c1, self.bits) / self.counts_per_mm

    def along_mm(self, p_base: Sequence[float] | FloatArray) -> float:
        """Where point ``p_base`` lies along the belt: its distance from ``origin_mm`` (mm)."""
        return float((np.asarray(p_base, dtype=np.float64)[:3] - self.origin_mm) @ self.d)

    def moved(self, T_base_obj: FloatArray, c0: int, c1: int) -> FloatArray:
        """Pose ``T_base_obj`` seen at count ``c0``, carried by the belt to count ``c1``."""
        T = np.array(T_base_obj, dtype=np.float64)
        T[:3, 3] += self.d * self.travel_mm(c0, c1)
        return T

    def in_belt(self, T_base_obj: FloatArray) -> FloatArray:
        """``T_belt_obj``: a part's pose in the belt frame (at the count it was seen)."""
        return invert_transform(self.T_base_belt()) @ np.asarray(T_base_obj, dtype=np.float64)


def blur_px(K: FloatArray, T_base_cam: FloatArray, point_mm: Sequence[float],
            direction: Sequence[float], travel_mm: float) -> float:
    """Pixels a point at ``point_mm`` (base frame) smears in the image while it travels
    ``travel_mm`` along ``direction``: the distance between its two pinhole projections
    (camera matrix ``K``, camera pose ``T_base_cam``). ``inf`` when it is not in front."""
    T_cam_base = np.linalg.inv(np.asarray(T_base_cam, dtype=np.float64))
    pts = []
    for p in (np.asarray(point_mm, dtype=np.float64),
              np.asarray(point_mm, dtype=np.float64)
              + np.asarray(direction, dtype=np.float64) * travel_mm):
        q = T_cam_base[:3, :3] @ p + T_cam_base[:3, 3]
        if q[2] <= 0:
            return math.inf
        uv = np.asarray(K, dtype=np.float64) @ (q / q[2])
        pts.append(uv[:2])
    return float(np.linalg.norm(pts[1] - pts[0]))


@dataclass(frozen=True)
class BeltFit:
    """``fit_belt``'s answer: direction (unit), counts per mm, a point on the line (the fitted
    position at the mean count), their one-sigma uncertainties, and the fit's residual RMS."""

    direction: tuple[float, float, float]
    counts_per_mm: float
    origin_mm: tuple[float, float, float]
    sigma_counts_per_mm: float
    sigma_direction_deg: float
    rms_mm: float
    observations: int

    def belt(self, normal: Sequence[float] = (0.0, 0.0, 1.0), bits: int = 32) -> Belt:
        n = np.asarray(normal, dtype=np.float64)
        return Belt(self.direction, self.counts_per_mm, self.origin_mm,
                    tuple(float(v) for v in n / np.linalg.norm(n)), bits)  # type: ignore[arg-type]


def fit_belt(counts: Sequence[int], points_mm: Sequence[Sequence[float]],
             point_sigma_mm: float = 0.1, bits: int = 32) -> BeltFit:
    """The belt line through ``points_mm`` (base frame) seen at encoder ``counts``.

    Counts are unwrapped against the first one (``count_delta``). ``DegenerateInputError`` for
    fewer than two observations, all at one count, or a board that did not move.
    ``point_sigma_mm``: the sigma of one measured position, used when two observations leave
    no residual to estimate it from (and as a floor otherwise).
    """
    if len(counts) != len(points_mm):
        raise DegenerateInputError(f"{len(counts)} counts but {len(points_mm)} positions")
    if len(counts) < 2:
        raise DegenerateInputError("the belt needs the board seen at two or more counts, "
                                   f"got {len(counts)}")
    c = np.array([count_delta(counts[0], k, bits) for k in counts], dtype=np.float64)
    P = np.asarray(points_mm, dtype=np.float64)[:, :3]
    cm = c.mean()
    sxx = float(((c - cm) ** 2).sum())
    if sxx == 0:
        raise DegenerateInputError(f"all {len(c)} observations at one count {counts[0]}: move "
                                   "the belt between the images")
    b = ((c - cm)[:, None] * (P - P.mean(axis=0))).sum(axis=0) / sxx  # mm per count
    a = P.mean(axis=0)  # the line's point at the mean count
    nb = float(np.linalg.norm(b))
    if nb == 0 or nb * math.sqrt(sxx) < 1e-9:
        raise DegenerateInputError("the board did not move between the counts: is the encoder "
                                   "count the belt's?")
    resid = P - (a + (c - cm)[:, None] * b)
    n = len(c)
    rms = float(np.sqrt((resid ** 2).sum(axis=1).mean()))
    sigma = point_sigma_mm
    if n > 2:  # per-axis sigma from the residuals (n - 2 degrees of freedom per axis)
        sigma = max(sigma, math.sqrt(float((resid ** 2).sum()) / (3 * (n - 2))))
    sigma_b = sigma / math.sqrt(sxx)  # each component of b
    d = b / nb
    return BeltFit(
        direction=tuple(float(v) for v in d),  # type: ignore[arg-type]
        counts_per_mm=1.0 / nb,
        origin_mm=tuple(float(v) for v in a),  # type: ignore[arg-type]
        sigma_counts_per_mm=sigma_b / nb ** 2,
        sigma_direction_deg=math.degrees(sigma_b / nb),
        rms_mm=rms,
        observations=n,
    )
