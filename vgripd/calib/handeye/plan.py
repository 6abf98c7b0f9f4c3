"""Plans for a walked hand-eye calibration: flange poses around a start pose that the robot
program visits, chosen so that the AX = XB problem is well conditioned.

Geometry assumed at the start pose ``T0`` (``T_base_flange``): the board's centre lies on the
camera's optical axis at ``distance_mm`` and the board faces the camera squarely. The camera's
pose on the flange (eye-in-hand) or in the base (eye-to-hand) need only be roughly known: the
config's present hand-eye when it has one of that mounting, else the camera looking along the
flange's z axis (eye-in-hand) or the board on the flange at ``board_offset_mm`` facing away from
it (eye-to-hand). It serves only to keep the board inside the image.

Every candidate pose turns the flange about the board's centre (``pivot``, in the flange frame),
so that the board stays near the image centre: a tilt about an axis across the line of sight
plus a roll about it, the whole rotation at most ``tilt_deg`` from the start, the flange at most
``travel_mm`` from its start position (where the orbit about the board would move it further,
the pivot is moved towards the flange). A candidate is kept when the projected board lies inside
the image with a margin, faces the camera, and its corners are at least ``MIN_SPACING_PX``
apart (what the detector handles). From the kept candidates the poses are chosen greedily,
each one the candidate that most raises the smallest singular value of the stacked
``(R_Aij - I)`` over all pairs (i, j) of chosen poses (``A_ij`` the relative flange motion):
the translation of X is ``sum (R_Aij - I) t_X = ...``, so that singular value is what
determines it, and it is zero when every rotation is about one axis.

Condition figure (:class:`PlanCondition`): ``condition`` = largest / smallest singular value of
that stack (1 is ideal, large = nearly parallel axes), and ``effective_deg`` = the rotation
angle that a set of as many pairs all rotating about perpendicular axes would need for the same
smallest singular value (``2 asin(s_min / (2 sqrt(pairs)))``: small = rotations too small). A
plan is refused when ``effective_deg < MIN_EFFECTIVE_DEG`` or ``condition > MAX_CONDITION``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.handeye.samples import FloatArray, check_mode
from vgripd.errors import CalibrationError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import invert_transform, make_transform, matrix_from_rotvec

PLAN_FORMAT = "vgripd-handeye-plan/1"
MIN_POSES, MAX_POSES = 12, 30
MIN_SPACING_PX = 8.0  # corner spacing the chessboard detector still finds reliably
MARGIN_FRACTION = 0.04  # of the image size, kept free around the board
MAX_VIEW_ANGLE_DEG = 60.0  # board normal against the line of sight
#: Refusal limits of the condition figure (bench/bench_handeye_plan.py: planned sets reach
#: condition 1.02 and 33 deg effective in a 250 mm / 30 deg box; hand-made sets of random
#: rotations up to 10 deg condition 1.3-2.5 and 2.5-5.5 deg effective; rotations about one axis
#: only: condition infinite).
MIN_EFFECTIVE_DEG = 6.0
MAX_CONDITION = 8.0


@dataclass
class PlanCondition:
    """How well a set of flange poses determines X (module docstring)."""

    condition: float
    effective_deg: float
    pairs: int
    singular_values: tuple[float, float, float]

    def problems(self) -> list[str]:
        """Why the set is refused (empty: accepted)."""
        out = []
        if self.effective_deg < MIN_EFFECTIVE_DEG:
            out.append(f"the rotations are too small: effective {self.effective_deg:.1f} deg "
                       f"between poses, at least {MIN_EFFECTIVE_DEG:g} needed (allow a larger "
                       f"tilt, or more travel so that the flange can orbit the board)")
        if not self.condition <= MAX_CONDITION:
            out.append(f"the rotation axes are nearly parallel: condition {self.condition:.3g} "
                       f"(at most {MAX_CONDITION:g}): the translation of X along the common "
                       f"axis is barely determined (rotate about different axes: tilt both "
                       f"ways and roll)")
        return out


def plan_condition(poses: Sequence[FloatArray]) -> PlanCondition:
    """The condition figure of a set of ``T_base_flange`` (or of any poses: the figure is the
    same for their inverses' relative motions up to a rotation of the frame)."""
    R = np.stack([np.asarray(T, dtype=float)[:3, :3] for T in poses])
    gram = np.zeros((3, 3))
    pairs = 0
    for i in range(len(R)):
        for j in range(i + 1, len(R)):
            D = R[j].T @ R[i] - np.eye(3)
            gram += D.T @ D
            pairs += 1
    s = np.sqrt(np.clip(np.linalg.eigvalsh(gram)[::-1], 0.0, None))
    smin = float(s[2])
    cond = float(s[0] / smin) if smin > 1e-12 else math.inf
    half = 0.0 if pairs == 0 else min(1.0, smin / (2 * math.sqrt(pairs)))
    eff = math.degrees(2 * math.asin(half))
    return PlanCondition(cond, eff, pairs, (float(s[0]), float(s[1]), float(s[2])))


@dataclass
class PlannedView:
    """What the camera should see at one pose (from the rough geometry)."""

    board_px: tuple[float, float, float, float]  # bounding box x0, y0, x1, y1
    spacing_px: float  # smallest corner spacing
    view_angle_deg: float
    outline_px: tuple[tuple[float, float], ...] = ()  # the grid's 4 outer corners, in order


@dataclass
class HandEyePlan:
    mode: str
    T_start: FloatArray
    poses: list[FloatArray]
    views: list[PlannedView]
    condition: PlanCondition
    settings: dict[str, float] = field(default_factory=dict)


def _view(camera: CameraModel, B: FloatArray, obj: FloatArray, cols: int) -> PlannedView | None:
    """The projected board at camera-board pose B, or None when it is not usable."""
    pts = obj @ B[:3, :3].T + B[:3, 3]
    if np.any(pts[:, 2] <= 1.0):
        return None
    to_centre = B[:3, 3] / np.linalg.norm(B[:3, 3])
    angle = math.degrees(math.acos(min(1.0, abs(float(B[:3, 2] @ to_centre)))))
    if angle > MAX_VIEW_ANGLE_DEG or B[:3, 2] @ to_centre <= 0:
        return None
    px = camera.project(pts)
    mx, my = MARGIN_FRACTION * camera.width, MARGIN_FRACTION * camera.height
    x0, y0 = px.min(axis=0)
    x1, y1 = px.max(axis=0)
    if x0 < mx or y0 < my or x1 > camera.width - mx or y1 > camera.height - my:
        return None
    grid = px.reshape(-1, cols, 2)
    spacing = min(float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
                  float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()))
    if spacing < MIN_SPACING_PX:
        return None
    outline = tuple((float(p[0]), float(p[1])) for p in
                    (grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]))
    return PlannedView((float(x0), float(y0), float(x1), float(y1)), spacing, angle, outline)


def draw_plan(path: str, plan: HandEyePlan, camera: CameraModel, title: str = "") -> None:
    """A PNG of what the camera should see: each pose's board outline in the image (numbered,
    the start pose thick), with the condition figure. For the dry run: a pose whose board
    would leave the image was already dropped; the drawing shows the spread of the views."""
    import cv2

    scale = min(1.0, 1000.0 / camera.width)
    w, h = int(camera.width * scale), int(camera.height * scale)
    img = np.full((h + 40, w, 3), 255, np.uint8)
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), (0, 0, 0), 1)
    colours = [(200, 80, 0), (0, 140, 0), (0, 0, 200), (160, 0, 160), (0, 140, 160)]
    for k, v in enumerate(plan.views):
        pts = (np.array(v.outline_px) * scale).round().astype(np.int32)
        colour = colours[k % len(colours)]
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], True, colour, 3 if k == 0 else 1,
                      cv2.LINE_AA)
        cv2.putText(img, str(k), tuple(int(x) for x in pts[0]), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    c = plan.condition
    text = (f"{title}  {len(plan.poses)} poses, condition {c.condition:.3g}, effective "
            f"{c.effective_deg:.1f} deg").strip()
    cv2.putText(img, text, (8, h + 26), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1,
                cv2.LINE_AA)
    if not cv2.imwrite(path, img):
        raise CalibrationError(f"{path}: cannot write the drawing")


def plan_hand_eye(mode: str, T_start: FloatArray, camera: CameraModel, object_points: FloatArray,
                  cols: int, *, distance_mm: float, travel_mm: float, tilt_deg: float,
                  n: int = 15, X_guess: FloatArray | None = None,
                  board_offset_mm: Sequence[float] = (0.0, 0.0, 0.0)) -> HandEyePlan:
    """``n`` flange poses (``T_base_flange``, mm) around ``T_start`` (module docstring).

    ``X_guess``: the rough hand-eye (``T_flange_camera`` or ``T_base_camera``), None for the
    default. Raises CalibrationError naming the setting when no good plan fits the box.
    """
    check_mode(mode)
    if not MIN_POSES <= n <= MAX_POSES:
        raise CalibrationError(f"--poses {n}: a plan has {MIN_POSES} to {MAX_POSES} poses")
    if camera.width <= 0 or camera.height <= 0:
        raise CalibrationError("the camera model has no image size (width, height)")
    for name, value in (("distance", distance_mm), ("travel", travel_mm), ("tilt", tilt_deg)):
        if not (math.isfinite(value) and value > 0):
            raise CalibrationError(f"--{name}: must be > 0, got {value}")
    T0 = np.asarray(T_start, dtype=float)
    centre = object_points.mean(axis=0)
    B0 = make_transform(np.eye(3), np.array([0.0, 0.0, distance_mm]) - centre)  # T_cam_board
    if mode == "eye-in-hand":
        X = np.eye(4) if X_guess is None else np.asarray(X_guess, dtype=float)
        T_base_board = T0 @ X @ B0
        pivot = (X @ np.array([0.0, 0.0, distance_mm, 1.0]))[:3]
        sight = X[:3, 2]  # the camera's line of sight in the flange frame

        def board_in_camera(T: FloatArray) -> FloatArray:
            return invert_transform(X) @ invert_transform(T) @ T_base_board
    else:
        flip = make_transform(matrix_from_rotvec([math.pi, 0.0, 0.0]), np.zeros(3))
        T_flange_board = make_transform(np.eye(3), np.asarray(board_offset_mm, float)) @ flip
        T_flange_board = T_flange_board @ make_transform(np.eye(3), -centre)
        C = (T0 @ T_flange_board @ invert_transform(B0) if X_guess is None
             else np.asarray(X_guess, dtype=float))
        pivot = (T_flange_board @ np.array([*centre, 1.0]))[:3]
        sight = (invert_transform(T0) @ C)[:3, 2]

        def board_in_camera(T: FloatArray) -> FloatArray:
            return invert_transform(C) @ T @ T_flange_board
    if board_in_camera(T0)[2, 3] <= 0:
        raise CalibrationError("the board lies behind the camera at the start pose: check the "
                               "mode and the rough hand-eye of the config")
    a = np.cross(sight, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 0.1:
        a = np.cross(sight, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(sight, a)
    tilt = math.radians(tilt_deg)
    candidates: list[tuple[FloatArray, PlannedView]] = []
    for k in range(24):
        phi = 2 * math.pi * k / 24
        axis = math.cos(phi) * a + math.sin(phi) * b
        for t_frac, r_frac in ((1.0, 0.0), (0.75, 0.6), (0.75, -0.6), (0.5, 0.85),
                               (0.5, -0.85), (0.4, 0.0)):
            R = matrix_from_rotvec(sight * r_frac * tilt) @ matrix_from_rotvec(axis * t_frac * tilt)
            angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2)))
            if angle > tilt * 1.0001:
                continue
            for scale in (1.0, 0.75, 0.5, 0.25, 0.0):  # the pivot towards the flange
                p = pivot * scale
                move = make_transform(R, p - R @ p)  # rotation about p, flange frame
                T = T0 @ move
                if np.linalg.norm(T[:3, 3] - T0[:3, 3]) > travel_mm:
                    continue
                view = _view(camera, board_in_camera(T), object_points, cols)
                if view is not None:
                    candidates.append((T, view))
                    break
    start_view = _view(camera, board_in_camera(T0), object_points, cols)
    if start_view is None:
        raise CalibrationError(
            "the board is not usable at the start pose (outside the image, too small for the "
            f"detector: corners under {MIN_SPACING_PX:g} px apart, or seen too obliquely): "
            "check --distance and the start pose")
    chosen: list[tuple[FloatArray, PlannedView]] = [(T0, start_view)]
    gram = np.zeros((3, 3))
    pool = list(candidates)
    while len(chosen) < n and pool:
        best, best_gram, best_score = -1, gram, -1.0
        for c, (T, _) in enumerate(pool):
            g = gram.copy()
            for Tc, _v in chosen:
                D = Tc[:3, :3].T @ T[:3, :3] - np.eye(3)
                g += D.T @ D
            ev = np.linalg.eigvalsh(g)
            score = ev[0] + 1e-3 * ev.sum()
            if score > best_score:
                best, best_gram, best_score = c, g, score
        chosen.append(pool.pop(best))
        gram = best_gram
    if len(chosen) < n:
        raise CalibrationError(
            f"only {len(chosen)} poses keep the board usable inside the box (travel "
            f"{travel_mm:g} mm, tilt {tilt_deg:g} deg); {n} asked: allow more travel or tilt, or "
            "ask for fewer poses")
    poses = [T for T, _ in chosen]
    return HandEyePlan(mode, T0, poses, [v for _, v in chosen], plan_condition(poses),
                       {"distance_mm": distance_mm, "travel_mm": travel_mm,
                        "tilt_deg": tilt_deg})


def plan_data(plan: HandEyePlan, board: str, pose_format: str,
              about: dict[str, Any]) -> dict[str, Any]:
    """The plan file's tables: ``[plan]`` (mode, board, settings, condition) and one
    ``[[poses]]`` per target (``matrix_mm`` and the numbers in ``pose_format``)."""
    from vgripd.geometry.vendors import vendor_from_transform

    c = plan.condition
    return {
        "plan": {"format": PLAN_FORMAT, "mode": plan.mode, "board": board,
                 "pose_format": pose_format, **plan.settings,
                 "T_start_mm": np.asarray(plan.T_start).tolist(),
                 "condition": {"condition": c.condition, "effective_deg": c.effective_deg,
                               "pairs": c.pairs, "singular_values": list(c.singular_values)},
                 **about},
        "poses": [{"index": k, "matrix_mm": np.asarray(T).tolist(),
                   pose_format: list(vendor_from_transform(pose_format, T)),
                   "board_px": list(v.board_px), "spacing_px": v.spacing_px}
                  for k, (T, v) in enumerate(zip(plan.poses, plan.views, strict=True))],
    }


@dataclass
class LoadedPlan:
    path: str
    mode: str
    board: str
    pose_format: str
    poses: list[FloatArray]
    condition: PlanCondition
    table: dict[str, Any]


def load_plan(path: str) -> LoadedPlan:
    """Read a plan file; CalibrationError names the file and the entry."""
    import tomllib

    from vgripd.geometry.transforms import check_transform

    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise CalibrationError(f"{path}: cannot read the plan: {err}") from None
    head = data.get("plan", {})
    if head.get("format") != PLAN_FORMAT:
        raise CalibrationError(f"{path}: not a hand-eye plan ([plan] format must be "
                               f"{PLAN_FORMAT!r})")
    poses = []
    for k, entry in enumerate(data.get("poses", [])):
        try:
            poses.append(check_transform(entry["matrix_mm"], f"poses[{k}].matrix_mm"))
        except (KeyError, ValueError, DegenerateInputError) as err:
            raise CalibrationError(f"{path}: poses[{k}]: {err}") from None
    check_mode(str(head.get("mode")))
    c = head.get("condition", {})
    cond = PlanCondition(float(c.get("condition", math.inf)), float(c.get("effective_deg", 0)),
                         int(c.get("pairs", 0)), tuple(c.get("singular_values", (0, 0, 0))))
    return LoadedPlan(path, str(head["mode"]), str(head.get("board", "")),
                      str(head.get("pose_format", "matrix")), poses, cond, head)


#: The most corners a planned board may have (a plan projects every corner of every candidate).
MAX_BOARD_CORNERS = 10_000


def board_size_problem(cols: int, rows: int, pitch_mm: float, distance_mm: float, width: int,
                       height: int, fx: float, fy: float) -> str | None:
    """Why a board of ``cols`` x ``rows`` at ``pitch_mm`` cannot be planned at ``distance_mm``
    from a camera of ``width`` x ``height`` px and focal lengths ``fx``, ``fy`` px, facing it
    squarely (the start pose; tilting only shrinks the spacing); None when it may. Cheap: run
    before the planner, which would project every corner of hundreds of candidates."""
    if cols * rows > MAX_BOARD_CORNERS:
        return (f"board {cols}x{rows}: {cols * rows} corners, a plan takes at most "
                f"{MAX_BOARD_CORNERS}")
    if not (math.isfinite(distance_mm) and distance_mm > 0):
        return None  # the planner names it
    spacing_px = min(fx, fy) * pitch_mm / distance_mm
    if spacing_px < MIN_SPACING_PX:
        return (f"board pitch {pitch_mm:g} mm at --distance {distance_mm:g} mm is "
                f"{spacing_px:.1f} px in the image: the detector needs at least "
                f"{MIN_SPACING_PX:g} px (a closer distance or a coarser board)")
    w_px = fx * (cols - 1) * pitch_mm / distance_mm
    h_px = fy * (rows - 1) * pitch_mm / distance_mm
    free = 1.0 - 2 * MARGIN_FRACTION
    if w_px > free * width or h_px > free * height:
        return (f"board {cols}x{rows} at pitch {pitch_mm:g} mm is {w_px:.0f} x {h_px:.0f} px at "
                f"--distance {distance_mm:g} mm: it does not fit the {width} x {height} px image "
                "(a farther distance or a smaller board)")
    return None


#: The longest plan name the page takes (characters; a file name holds at most 255 bytes).
MAX_PLAN_NAME = 200


def plan_inside(config_path: Path, plan: str | Path) -> Path:
    """``plan`` (relative to the config's folder) as a path inside that folder;
    ``CalibrationError`` for one outside it (the page names files, it does not browse), and
    for a name no file can have (a control character, longer than ``MAX_PLAN_NAME``)."""
    text = str(plan)
    if len(text) > MAX_PLAN_NAME:
        raise CalibrationError(f"plan {text[:40]!r}...: {len(text)} characters, at most "
                               f"{MAX_PLAN_NAME}")
    if any(ord(c) < 32 or ord(c) == 127 for c in text):
        raise CalibrationError(f"plan {text!r}: a control character (such as NUL) in the name")
    folder = config_path.resolve().parent
    try:
        path = (folder / plan).resolve()
    except (OSError, ValueError) as err:
        raise CalibrationError(f"plan {text!r}: {err}") from None
    if not path.is_relative_to(folder) or path.suffix != ".toml":
        raise CalibrationError(f"plan {str(plan)!r}: a .toml file inside {folder}")
    return path
