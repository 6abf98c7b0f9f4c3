"""A cell to learn on: a calibration board moved by a virtual operator, seen by known cameras.

``vgripd capture`` and the calibration commands can then be tried, and their results checked,
without hardware: the cameras the images are rendered through (the *truth*) are known, so a
calibration from these images can be compared with them.

Options (``[camera]`` with ``type = "board"``)::

    board = "chessboard:9x6:30"  # the board held up (chessboards only), vgripd.calib.boards spec
    truth = "rig.toml"           # optional: a file with the [calibration] (left, right, stereo)
                                 # the images are rendered through, relative to the working
                                 # directory; default: the demo cell's two cameras
    hold_frames = 3              # grabs the operator holds each place still
    move_frames = 1              # grabs while moving to the next place (half way: a board on
                                 # the move, which vgripd capture must not keep)
    max_tilt_deg = 40.0          # the board's tilt (normal vs the left camera's axis), at most
    fill = 0.35                  # the board's width as a share of the image width, about
    noise_std = 1.0              # Gaussian sensor noise (grey levels)
    blur_px = 0.7                # Gaussian blur sigma (px)
    seed = 1                     # same seed, same places
    plate = false                # true: the demo plate (six dark 10 mm marks) lies on the
                                 # table at the demo cell's taught place, where the truth
                                 # cameras' hand-eye puts it; the operator holds the board
                                 # only where it covers no mark, so a job finds the plate
    robot_state = "robot.json"   # optional: the robot twin's state file (vgripd.sim.robot_twin
                                 # --state), relative to the working directory
    board_offset_mm = [2.0, -3.0, 12.0]  # the board's centre in the flange frame (robot-held)
    board_turn_deg = 1.5         # and its turn about the flange's z axis
    plate_pose = { translation_mm = [...], rotvec_rad = [...] }  # where the plate lies
                                 # (T_base_obj; default the demo cell's reference)

With ``robot_state`` the cell goes on after the cameras' calibration: while that file does not
exist (the robot twin has not run) the operator holds the board as above; while it says the
board is on the flange (``"board": true``, the twin's hand-eye walk) the board is drawn where
the twin's arm really is (``T_base_flange``, mm; not the pose it reports, which carries the
controller's error), mounted at ``board_offset_mm``/``board_turn_deg`` with its face away from
the flange, seen through the truth cameras placed in the base by the truth's hand-eye; once it
says ``"board": false`` (the walk is over and the board taken off) the config's ``[object]``
lies on the table at ``plate_pose``, drawn by the synthetic renderer through the same truth
cameras (its circle marks; the truth never comes from the config's own calibration, so a
calibration made from these images is judged against the cell, not against itself).
The operator works like a careful person: place ``i`` aims at cell ``i mod 9`` of a 3x3 grid
over the left image and tilts the board in turn flat, left, right, top, bottom side nearer (each
up to ``max_tilt_deg``), with a random roll, and only holds places where every camera sees the
whole board. The images: each pixel's ray (through the camera's distortion) meets the board
plane and takes the printed board's grey there (a texture at 4 px per mm, sampled bilinearly),
then blur and noise. ``ImagePair.truth``: ``board`` (the spec), ``T_cam_board`` (left camera,
4x4, mm), ``T_right_left`` (4x4 or None), ``still`` (False while moving), ``place``; with the
board on the flange also ``T_base_flange`` and ``T_base_camera``; after the walk, the synthetic
camera's truth (``T_base_obj`` ...); with ``plate`` also ``T_base_obj`` (the plate in the base
frame), ``T_base_camera`` (the left truth camera's hand-eye) and ``board_shown``.

With ``plate`` the plate is rendered once at open by the synthetic camera's renderer (the same
area-exact discs) through the truth cameras, at the demo reference pose, and the operator's
board is drawn over it: the setup page's road without hardware (calibrate with the board,
define the object from the plate's marks, teach, pick; docs/setup.md).
"""

from __future__ import annotations

import json
import time
import tomllib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.calib.boards import Board
from vgripd.config import Config, PoseConfig, config_from_dict
from vgripd.errors import CameraError, VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
from vgripd.types import FloatArray, ImagePair
from vgripd.vision import scene

#: Grey levels of the paper and the printed squares.
PAPER, INK = 235, 20
#: White paper around the outer squares (mm).
MARGIN_MM = 20.0
#: Tries to find a place every camera sees whole before giving up.
MAX_TRIES = 400
#: The tilt directions the operator works through (the side nearer the left camera).
SIDES = ("flat", "left", "right", "top", "bottom")


class BoardOptions(DriverOptions):
    board: str = "chessboard:9x6:30"
    truth: str | None = None
    hold_frames: int = Field(3, ge=1, le=1000)
    move_frames: int = Field(1, ge=0, le=100)
    max_tilt_deg: float = Field(40.0, ge=0.0, le=60.0)
    fill: float = Field(0.35, gt=0.05, le=0.9)
    noise_std: float = Field(1.0, ge=0.0, le=50.0)
    blur_px: float = Field(0.7, ge=0.0, le=10.0)
    seed: int = 1
    robot_state: str | None = None
    board_offset_mm: tuple[float, float, float] = (2.0, -3.0, 12.0)
    board_turn_deg: float = Field(1.5, ge=-180.0, le=180.0)
    plate_pose: PoseConfig | None = None
    plate: bool = False


def _even_stripes(x: FloatArray, pitch: float, n: int) -> FloatArray:
    """The length of the board's even squares (index ``a`` even, ``a = floor(x / pitch)``,
    ``a`` from -1 to ``n - 1``) along one axis from the board's edge to ``x`` (mm)."""
    y = np.clip(x + pitch, 0.0, (n + 1) * pitch)  # from the outer edge, index a + 1
    return pitch * np.floor(y / (2 * pitch)) + np.clip(np.mod(y, 2 * pitch) - pitch, 0.0, pitch)


def texture(board: Board, ppm: float) -> tuple[np.ndarray, FloatArray]:
    """The printed chessboard as an 8-bit image at ``ppm`` px per mm, and the map from board mm
    to texture px (3x3, pixel centres). Each texture pixel is the exact area average of the
    squares it covers (a chessboard is the product of its rows and columns: a pixel's black
    share is ``ex * ey + ox * oy`` with the shares of even and odd squares along x and y), so
    sampling it near its own scale renders edges to a fraction of a pixel. The square left of
    and above corner 0 is black (``vgripd.calib.boards``)."""
    p = board.pitch_mm
    off = (MARGIN_MM + p) * ppm  # texture px of the board's x = 0 (corner 0), pixel edge
    w = int(np.ceil(((board.cols + 1) * p + 2 * MARGIN_MM) * ppm))
    h = int(np.ceil(((board.rows + 1) * p + 2 * MARGIN_MM) * ppm))

    def shares(size: int, n: int) -> tuple[FloatArray, FloatArray]:
        edges: FloatArray = (np.arange(size + 1, dtype=np.float64) - off) / ppm  # mm
        even = np.diff(_even_stripes(edges, p, n)) * ppm
        inside = np.diff(np.clip(edges + p, 0.0, (n + 1) * p)) * ppm
        return even, inside - even

    ex, ox = shares(w, board.cols)
    ey, oy = shares(h, board.rows)
    black = np.outer(ey, ex) + np.outer(oy, ox)
    img = np.round(PAPER - (PAPER - INK) * black).astype(np.uint8)
    A = np.array([[ppm, 0.0, off - 0.5], [0.0, ppm, off - 0.5], [0, 0, 1]])
    return img, A


def ray_map(model: CameraModel) -> FloatArray:
    """(H * W, 3) normalised viewing rays ``(x, y, 1)`` of every pixel, row by row
    (OpenCV's iterative undistortion, to 1e-10)."""
    w, h = model.width, model.height
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    K, dist = model.to_opencv()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    xn = cv2.undistortPoints(pix, K, dist, None, None, None, crit).reshape(-1, 2)
    return np.column_stack([xn, np.ones(len(xn))])


class BoardCamera(CameraDriver):
    """Renders the board places of a virtual operator through the truth cameras."""

    Options = BoardOptions
    type_name = "board"
    no_focus = ("the learning cell renders its images: no lens to focus (blur_px sets their "
                "sharpness)")

    def __init__(self, options: BoardOptions, config: Config) -> None:
        super().__init__(options, config)
        try:
            self.board = Board.parse(options.board)
        except VgripError as err:
            raise CameraError(f"board: camera.board: {err}") from None
        if self.board.kind != "chessboard":
            raise CameraError(f"board: camera.board {options.board!r}: the learning cell "
                              "draws chessboards only")
        self._frame = 0
        self._places: list[FloatArray] = []
        self._plate: list[np.ndarray] | None = None
        self._plate_px: list[FloatArray] = []

    def describe(self) -> str:
        return f"the learning cell's {self.board.spec} board"

    def _truth_config(self) -> Config:
        if self.options.truth is None:
            return Config()
        path = Path(self.options.truth)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise CameraError(f"board: camera.truth {path}: {err}") from None
        if "calibration" not in data:
            raise CameraError(f"board: camera.truth {path}: no [calibration]")
        calibration = dict(data["calibration"])
        if "hand_eye" not in calibration:  # where the cameras are in the cell: not needed here
            demo = Config().model_dump(mode="json", exclude_none=True)["calibration"]
            calibration["hand_eye"] = demo["hand_eye"]
        return config_from_dict({"calibration": calibration}, str(path))

    def _open_blocking(self) -> None:
        try:
            truth = self._truth_config()
            left, right = scene.camera_models(truth)
            self._T_right_left = scene.T_right_left(truth)
            self._T_base_camera = (scene.T_base_camera(truth)
                                   if truth.calibration is not None
                                   and truth.calibration.hand_eye.mounting == "fixed" else None)
        except VgripError as err:
            raise CameraError(f"board: cannot set up the cameras: {err}") from None
        self._truth = truth
        self._plate_cam: Any = None  # the object on the table after the robot twin's walk
        self._models: list[CameraModel] = [left] + ([right] if right is not None else [])
        self._T_cam_left = [np.eye(4)] + ([self._T_right_left]
                                          if self._T_right_left is not None else [])
        # the texture at about the image's scale (bilinear sampling then acts as area sampling)
        size_mm = np.ptp(self.board.object_points()[:, 0]) + 2 * self.board.pitch_mm
        ppm = float(np.clip(self.options.fill * left.width / size_mm, 0.25, 16.0))
        self._texture, self._A = texture(self.board, ppm)
        # each camera's pixel rays (normalised coordinates), once: the frames only move the
        # board
        self._rays = [ray_map(m) for m in self._models]
        self._rng = np.random.default_rng(self.options.seed)
        self._frame = 0
        self._places = []
        self._plate = None
        self._plate_px = []
        if self.options.plate:
            try:
                self._open_plate(truth)
            except VgripError as err:
                raise CameraError(f"board: cannot render the plate: {err}") from None

    def _open_plate(self, truth: Config) -> None:
        """The demo plate rendered once through every truth camera (no noise or blur here:
        the frame's own are added over board and plate alike)."""
        from drivers.cameras.synthetic import SyntheticCamera, SyntheticOptions

        ref = truth.reference.T_base_obj
        assert ref is not None  # the demo reference
        options = SyntheticOptions(pose=ref, noise_std=0.0, blur_px=0.0)
        renderer = SyntheticCamera(options, truth)
        renderer._open_blocking()
        pair = renderer._grab_blocking(1.0)
        self._plate = [np.asarray(v, np.uint8) for v in pair.views]
        self._plate_px = [np.asarray(pair.truth["pixels_left"], np.float64)] + (
            [np.asarray(pair.truth["pixels_right"], np.float64)]
            if pair.truth.get("pixels_right") is not None else [])
        self._T_base_obj = np.asarray(pair.truth["T_base_obj"], np.float64)
        self._T_base_camera = scene.T_base_camera(truth)

    # ---------------------------------------------------------------- the operator
    def _sees_whole(self, T_left_board: FloatArray) -> bool:
        obj = self.board.object_points()
        p = self.board.pitch_mm
        corners = np.array([[-p, -p, 0], [self.board.cols * p, -p, 0],
                            [-p, self.board.rows * p, 0],
                            [self.board.cols * p, self.board.rows * p, 0]], float)
        pts = np.vstack([obj, corners])
        for model, T in zip(self._models, self._T_cam_left, strict=True):
            cam = (T @ T_left_board @ np.c_[pts, np.ones(len(pts))].T)[:3].T
            if np.any(cam[:, 2] < 50.0):
                return False
            px = model.project(cam)
            margin = 0.03 * model.width
            if np.any(px[:, 0] < margin) or np.any(px[:, 0] > model.width - margin) or \
                    np.any(px[:, 1] < margin) or np.any(px[:, 1] > model.height - margin):
                return False
        return not self._covers_plate(T_left_board)

    def _covers_plate(self, T_left_board: FloatArray) -> bool:
        """Whether the board (with its paper margin and a mark's width more) would hide a mark
        of the plate in some camera."""
        if not self._plate_px:
            return False
        p, m = self.board.pitch_mm, MARGIN_MM + 15.0
        outline = np.array([[-p - m, -p - m, 0], [self.board.cols * p + m, -p - m, 0],
                            [self.board.cols * p + m, self.board.rows * p + m, 0],
                            [-p - m, self.board.rows * p + m, 0]], float)
        for model, T, marks in zip(self._models, self._T_cam_left, self._plate_px,
                                   strict=False):
            cam = (T @ T_left_board @ np.c_[outline, np.ones(4)].T)[:3].T
            poly = model.project(cam).astype(np.float32).reshape(-1, 1, 2)
            if any(cv2.pointPolygonTest(poly, (float(u), float(v)), False) >= 0
                   for u, v in marks if np.isfinite(u)):
                return True
        return False

    def _place(self, index: int) -> FloatArray:
        """Place ``index``: its board pose in the left camera (4x4, mm)."""
        left = self._models[0]
        size_mm = np.ptp(self.board.object_points()[:, :2], axis=0) + 2 * self.board.pitch_mm
        distance = start = left.fx * size_mm[0] / (self.options.fill * left.width)
        cell = index % 9
        side = SIDES[index % len(SIDES)]
        tilt = np.radians(self.options.max_tilt_deg)
        for _ in range(MAX_TRIES):
            u = (cell % 3 + self._rng.uniform(0.15, 0.85)) / 3.0 * left.width
            v = (cell // 3 + self._rng.uniform(0.15, 0.85)) / 3.0 * left.height
            ray = left.rays(np.array([[u, v]]))[0]
            centre = ray / ray[2] * distance * self._rng.uniform(0.9, 1.15)
            angle = tilt * self._rng.uniform(0.6, 1.0)
            # the side named comes nearer: turn about the image's y (left/right) or x axis
            # (+ about y takes the right side nearer, + about x the top side)
            turn = {"flat": np.zeros(3), "left": [0.0, -angle, 0.0],
                    "right": [0.0, angle, 0.0], "top": [angle, 0.0, 0.0],
                    "bottom": [-angle, 0.0, 0.0]}[side]
            roll = self._rng.uniform(-0.35, 0.35)
            R = matrix_from_rotvec(np.asarray(turn, float)) @ matrix_from_rotvec(
                np.array([0.0, 0.0, roll]))
            t = centre - R @ self.board.object_points().mean(axis=0)
            T = make_transform(R, t)
            if self._sees_whole(T):
                return T
            cell = int(self._rng.integers(9))  # that cell cannot hold the board whole
            distance = min(distance * 1.01, 1.5 * start)
        raise CameraError(f"board: no place where every camera sees the whole {self.board.spec} "
                          f"board (camera.fill = {self.options.fill:g} too large, or the "
                          "cameras share too little view)")

    def _pose_at(self, frame: int) -> tuple[FloatArray, bool, int]:
        """The board pose at grab ``frame``, whether it is held still, and the place."""
        period = self.options.hold_frames + self.options.move_frames
        place, k = divmod(frame, period)
        while len(self._places) < place + 2:
            self._places.append(self._place(len(self._places)))
        if k < self.options.hold_frames:
            return self._places[place], True, place
        a, b = self._places[place], self._places[place + 1]
        s = (k - self.options.hold_frames + 1) / (self.options.move_frames + 1)
        R = cv2.Rodrigues(cv2.Rodrigues(a[:3, :3])[0] * (1 - s)
                          + cv2.Rodrigues(b[:3, :3])[0] * s)[0]
        return make_transform(R, a[:3, 3] * (1 - s) + b[:3, 3] * s), False, place

    # ---------------------------------------------------------------- rendering
    def _render(self, camera: int, T_cam_board: FloatArray | None) -> np.ndarray:
        """Camera ``camera``'s image of the board at ``T_cam_board`` (None: no board in
        view, the plate alone)."""
        model = self._models[camera]
        if T_cam_board is None:
            assert self._plate is not None
            return self._finish(self._plate[camera].astype(np.float32))
        # normalised (x, y, 1) -> board plane: the inverse of Hn = [r1 r2 t], then texture px
        Hn = np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]])
        M = self._A @ np.linalg.inv(Hn)
        h = self._rays[camera] @ M.T
        with np.errstate(divide="ignore", invalid="ignore"):
            tex = h[:, :2] / h[:, 2:3]
        # a pixel whose ray meets the plane behind the camera sees no board
        tex[~(h[:, 2] * np.linalg.det(Hn) > 0)] = -1e6
        mx = tex[:, 0].reshape(model.height, model.width).astype(np.float32)
        my = tex[:, 1].reshape(model.height, model.width).astype(np.float32)
        out: Any = cv2.remap(self._texture, mx, my, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=110)
        out = out.astype(np.float32)
        if self._plate is not None:  # the board over the plate: the table where it is not
            inside = cv2.remap(np.ones(self._texture.shape, np.float32), mx, my,
                               cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            out = inside * out + (1.0 - inside) * self._plate[camera].astype(np.float32)
        return self._finish(out)

    def _finish(self, out: Any) -> np.ndarray:
        """Blur and sensor noise over the rendered grey levels (float32), as 8 bits."""
        if self.options.blur_px > 0:
            out = cv2.GaussianBlur(out, (0, 0), self.options.blur_px)
        if self.options.noise_std > 0:
            out = out + self._rng.standard_normal(out.shape, np.float32) * np.float32(
                self.options.noise_std)
        return np.clip(np.round(out), 0, 255).astype(np.uint8)

    # ---------------------------------------------------------------- the robot twin
    def _robot(self) -> dict[str, Any] | None:
        """The robot twin's state, or None while it has not run (no file)."""
        if self.options.robot_state is None:
            return None
        path = Path(self.options.robot_state)
        try:
            state = json.loads(path.read_text(encoding="utf-8"))
            return {"board": bool(state["board"]),
                    "T_base_flange": np.array(state["T_base_flange"], float).reshape(4, 4)}
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise CameraError(f"board: camera.robot_state {path}: {err}") from None

    def T_flange_board(self) -> FloatArray:
        """Where the board sits on the flange: face away from it (turned pi about x), its
        centre at ``board_offset_mm``, turned ``board_turn_deg`` about the flange's z."""
        centre = self.board.object_points().mean(axis=0)
        turn = matrix_from_rotvec(np.array([0.0, 0.0, np.radians(self.options.board_turn_deg)]))
        flip = matrix_from_rotvec(np.array([np.pi, 0.0, 0.0]))
        return (make_transform(turn, np.asarray(self.options.board_offset_mm, float))
                @ make_transform(flip, np.zeros(3)) @ make_transform(np.eye(3), -centre))

    def _grab_held(self, T_base_flange: FloatArray) -> ImagePair:
        if self._T_base_camera is None:
            raise CameraError("board: camera.robot_state needs cameras fixed in the cell (the "
                              "truth's calibration.hand_eye.mounting = \"fixed\")")
        T = np.linalg.inv(self._T_base_camera) @ T_base_flange @ self.T_flange_board()
        self._frame += 1
        images = [self._render(c, T_cam @ T) for c, T_cam in enumerate(self._T_cam_left)]
        truth: dict[str, Any] = {"board": self.board.spec, "T_cam_board": T,
                                 "T_right_left": self._T_right_left, "still": True,
                                 "place": -1, "T_base_flange": T_base_flange,
                                 "T_base_camera": self._T_base_camera}
        return ImagePair(left=images[0], right=images[1] if len(images) > 1 else None,
                         t_mono_ns=time.monotonic_ns(), source=f"board:{self._frame - 1}",
                         meta={"frame": self._frame - 1}, truth=truth)

    def _grab_plate(self, timeout_s: float) -> ImagePair:
        """The config's object on the table, drawn through the truth cameras."""
        if self._plate_cam is None:
            from drivers.cameras.synthetic import SyntheticCamera, SyntheticOptions

            pose = self.options.plate_pose or Config().reference.T_base_obj
            assert pose is not None
            calibration = self._truth.model_dump(mode="json", exclude_none=True)["calibration"]
            try:
                world = config_from_dict({
                    "camera": {"type": "synthetic"}, "calibration": calibration,
                    "object": self.config.object.model_dump(mode="json", exclude_none=True),
                    "reference": {"T_base_obj": pose.model_dump(mode="json",
                                                                exclude_none=True)}})
                options = SyntheticOptions(pose=pose, seed=self.options.seed,
                                           noise_std=self.options.noise_std,
                                           blur_px=self.options.blur_px)
                plate = SyntheticCamera(options, world)
                plate._open_blocking()
            except VgripError as err:
                raise CameraError(f"board: the plate on the table: {err}") from None
            self._plate_cam = plate
        pair: ImagePair = self._plate_cam._grab_blocking(timeout_s)
        return pair

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        robot = self._robot()
        if robot is not None:
            if robot["board"]:
                return self._grab_held(robot["T_base_flange"])
            return self._grab_plate(timeout_s)
        T, still, place = self._pose_at(self._frame)
        self._frame += 1
        # With the plate, the operator carries the board between places around the plate, not
        # over it: a move that would hide a mark shows the table without the board.
        shown = not (self._plate is not None and not still and self._covers_plate(T))
        images = [self._render(c, T_cam @ T if shown else None)
                  for c, T_cam in enumerate(self._T_cam_left)]
        truth: dict[str, Any] = {"board": self.board.spec, "T_cam_board": T.copy(),
                                 "T_right_left": self._T_right_left, "still": still,
                                 "place": place}
        if self._plate is not None:
            assert self._T_base_camera is not None  # set with the plate (_open_plate)
            truth.update(T_base_obj=self._T_base_obj.copy(),
                         T_base_camera=self._T_base_camera.copy(), board_shown=shown)
        return ImagePair(left=images[0], right=images[1] if len(images) > 1 else None,
                         t_mono_ns=time.monotonic_ns(), source=f"board:{self._frame - 1}",
                         meta={"frame": self._frame - 1}, truth=truth)
