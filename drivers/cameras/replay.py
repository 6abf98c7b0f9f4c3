"""Replay recorded images from disk, in order: for tests, demos and offline re-runs of a cell.

Options (``[camera]`` with ``type = "replay"``)::

    folder = "recordings/2024-05-02"   # optional; patterns are relative to it (else to the cwd)
    left_glob = "left_*.png"           # stereo: the two patterns, paired by sorted position
    right_glob = "right_*.png"
    # glob = "cam_*.png"               # or single-camera: one pattern instead of the two
    # globs = ["n_left_*.png", "n_right_*.png", "s_left_*.png", "s_right_*.png"]
                                       # or a multi-camera cell: one pattern per camera, in
                                       # the order of calibration.cameras
    loop = false                       # start again after the last frame
    flange_poses = "flange.txt"        # optional, robot-mounted cameras (format below)
    grayscale = true                   # read 8-bit grey (else as stored: grey or BGR)

Only image files count (by suffix: .png, .jpg, .tif, .bmp, .pgm, ...): a ``truth.json`` or a
``notes.txt`` that a pattern also matches is skipped. Files are ordered by natural sort (``img_2``
before ``img_10``).

Pairing (:func:`vgripd.imagefiles.list_frames`, which ``vgripd replay`` uses too): the parts of
a file name that the wildcards of its pattern stand for are its key (``scene_007`` for
``scene_007_left.png`` under ``*_left.png``; ``07`` for ``right_07.png`` under ``right_*.png``).
When the left and the right keys have anything in common, the i-th pair is the left and the
right file with the same key, and a file without a partner is an error naming it, so one missing
file cannot shift every later pair by one. When they have nothing in common (``cam0/t1001.png``
with ``cam1/t2001.png``), files pair by sorted position and the counts must agree. A stereo
layout with no left or no right image is an error; all of this is checked at ``open()``, with
the folder and the patterns in the message.

Flange pose file: one pose per frame, one per line, in frame order; empty lines and lines
starting with ``#`` are skipped; numbers separated by spaces or commas. A line is either
6 numbers ``x y z rx ry rz`` (translation in mm, rotation vector in rad: the flange pose
``T_base_flange`` in the robot base frame) or 16 numbers (the 4x4 matrix, row by row).
The pose of frame i becomes ``ImagePair.T_base_flange``.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
from pydantic import ValidationError, model_validator

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import MAX_CAMERAS, Config, PoseConfig
from vgripd.errors import CameraError, VgripError
from vgripd.imagefiles import list_frames, list_views
from vgripd.types import FloatArray, ImagePair
from vgripd.vision.scene import matrix_from_pose


class ReplayOptions(DriverOptions):
    folder: str | None = None
    glob: str | None = None
    globs: tuple[str, ...] | None = None
    left_glob: str | None = None
    right_glob: str | None = None
    loop: bool = False
    flange_poses: str | None = None
    grayscale: bool = True

    @model_validator(mode="after")
    def _one_layout(self) -> ReplayOptions:
        stereo = self.left_glob is not None or self.right_glob is not None
        layouts = stereo + (self.glob is not None) + (self.globs is not None)
        if layouts != 1:
            raise ValueError("give one of glob (single camera), left_glob and right_glob "
                             "(stereo) or globs (one per camera of a multi-camera cell)")
        if self.globs is not None and not 2 <= len(self.globs) <= MAX_CAMERAS:
            raise ValueError(f"globs: one pattern per camera, 2 to {MAX_CAMERAS}, "
                             f"got {len(self.globs)}")
        if stereo and (self.left_glob is None or self.right_glob is None):
            raise ValueError("stereo replay needs both left_glob and right_glob")
        return self


def read_flange_poses(path: Path) -> list[FloatArray]:
    """Parse a flange pose file (format in the module docstring) into (4, 4) transforms."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise CameraError(f"replay: cannot read flange pose file {path}: {err.strerror}") from None
    poses = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
            if len(values) == 6:
                fields: dict[str, object] = {"translation_mm": values[:3], "rotvec_rad": values[3:]}
            elif len(values) == 16:
                fields = {"matrix": np.reshape(values, (4, 4)).tolist()}
            else:
                raise ValueError(f"expected 6 or 16 numbers, got {len(values)}")
            poses.append(matrix_from_pose(PoseConfig.model_validate(fields)))
        except ValidationError as err:
            msg = "; ".join(e["msg"] for e in err.errors())
            raise CameraError(f"replay: {path} line {lineno}: {msg}") from None
        except (ValueError, VgripError) as err:
            raise CameraError(f"replay: {path} line {lineno}: {err}") from None
    return poses


class ReplayCamera(CameraDriver):
    """Images from files, one frame (pair) per ``grab``."""

    Options = ReplayOptions
    type_name = "replay"
    no_focus = "it replays recorded images: no lens to focus"
    options: ReplayOptions

    def __init__(self, options: ReplayOptions, config: Config) -> None:
        super().__init__(options, config)
        self._left: list[Path] = []
        self._right: list[Path] | None = None
        self._views: list[list[Path]] | None = None  # multi-camera: per camera, frame order
        self._flange: list[FloatArray] | None = None
        self._next = 0

    def describe(self) -> str:
        o = self.options
        patterns = (o.glob if o.glob is not None else " + ".join(o.globs) if o.globs
                    else f"{o.left_glob} + {o.right_glob}")
        return f"{o.folder or '.'}/{patterns}"

    def _open_blocking(self) -> None:
        o = self.options
        if o.globs is not None:
            self._views = list_views(Path(o.folder or "."), o.globs)
            self._left = self._views[0]
        else:
            frames = list_frames(Path(o.folder or "."), glob=o.glob, left_glob=o.left_glob,
                                 right_glob=o.right_glob)
            self._left, self._right = frames.left, frames.right
        n_cams = len(o.globs or ())
        cal = self.config.calibration
        cameras = cal.cameras if cal is not None else None
        if n_cams and cameras is not None and len(cameras) != n_cams:
            raise CameraError(f"replay: {n_cams} globs for the {len(cameras)} cameras of "
                              "calibration.cameras (one pattern per camera, in their order)")
        if o.flange_poses is not None:
            path = Path(o.folder or ".") / o.flange_poses
            self._flange = read_flange_poses(path)
            if len(self._flange) != len(self._left):
                raise CameraError(
                    f"replay: {path} has {len(self._flange)} poses for {len(self._left)} frames"
                )
        self._next = 0

    def _read(self, path: Path) -> np.ndarray:
        if not path.is_file():
            raise CameraError(f"replay: image file {path} is missing")
        flags = cv2.IMREAD_GRAYSCALE if self.options.grayscale else cv2.IMREAD_UNCHANGED
        image = cv2.imread(str(path), flags)
        if image is None or image.size == 0:
            raise CameraError(f"replay: cannot decode image file {path} (corrupt or unsupported)")
        return image

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        n = len(self._left)
        if self._next >= n:
            if not self.options.loop:
                raise CameraError(f"replay: no more images ({n} frames from {self.describe()})")
            self._next = 0
        i = self._next
        self._next += 1
        flange = self._flange[i] if self._flange is not None else None
        if self._views is not None:
            paths = [view[i] for view in self._views]
            images = self._per_camera(self._read, paths)
            return ImagePair.of_views(
                images, time.monotonic_ns(), source=f"replay:{paths[0].name}",
                meta={"frame": i, "paths": [str(p) for p in paths]}, T_base_flange=flange)
        left = self._read(self._left[i])
        right = self._read(self._right[i]) if self._right is not None else None
        t_mono_ns = time.monotonic_ns()
        meta: dict[str, object] = {"frame": i, "left_path": str(self._left[i])}
        if self._right is not None:
            meta["right_path"] = str(self._right[i])
        return ImagePair(
            left=left,
            right=right,
            t_mono_ns=t_mono_ns,
            source=f"replay:{self._left[i].name}",
            meta=meta,
            T_base_flange=self._flange[i] if self._flange is not None else None,
        )
