"""What a hand-eye calibration works on: the samples, the two mountings, and the board pose
the samples agree on for a given X (used by the solvers, the refinement and the report)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from vgripd.errors import CalibrationError
from vgripd.geometry.transforms import (
    invert_transforms,
    make_transform,
    pose_errors,
    project_rotation,
)

FloatArray = npt.NDArray[np.float64]

MODES = ("eye-in-hand", "eye-to-hand")


@dataclass
class Sample:
    """One robot pose and what the camera saw there.

    Attributes
    ----------
    T_base_flange : (4, 4) flange pose in the robot base frame, mm (from the controller).
    T_cam_board : (4, 4) board pose in the camera frame, mm; None until measured from ``px``.
    image : name of the image (for messages), or "".
    obj : (N, 3) board points in the board frame, mm (None when only the pose is known).
    px : (N, 2) their detected pixels (OpenCV convention).
    number : the sample's number in messages and residuals (its place in the samples file when
        some are left out); None: its position in the list given.
    """

    T_base_flange: FloatArray
    T_cam_board: FloatArray | None = None
    image: str = ""
    obj: FloatArray | None = None
    px: FloatArray | None = None
    number: int | None = None

    @property
    def has_pixels(self) -> bool:
        return self.obj is not None and self.px is not None


def check_mode(mode: str) -> None:
    if mode not in MODES:
        raise CalibrationError(f"hand-eye mode {mode!r}: expected one of {', '.join(MODES)}")


def number(samples: Sequence[Sample], i: int) -> int:
    """Sample i's number in messages."""
    n = samples[i].number
    return i if n is None else n


def label(samples: Sequence[Sample], i: int) -> str:
    """"sample N (image)" for messages."""
    image = samples[i].image
    return f"sample {number(samples, i)}" + (f" ({image})" if image else "")


def anchor_poses(samples: Sequence[Sample], mode: str) -> FloatArray:
    """The ``P_i`` (n, 4, 4) of ``T_anchor_board = P_i @ X @ T_cam_board_i``: the robot poses
    ``T_base_flange`` (eye-in-hand) or their inverses ``T_flange_base`` (eye-to-hand)."""
    P = np.stack([np.asarray(s.T_base_flange, dtype=np.float64) for s in samples])
    return invert_transforms(P) if mode == "eye-to-hand" else P


def board_poses(samples: Sequence[Sample]) -> FloatArray:
    """The measured ``T_cam_board`` of every sample, (n, 4, 4)."""
    B = [s.T_cam_board for s in samples]
    if any(b is None for b in B):
        raise CalibrationError("hand-eye: a sample has no board pose (measure it first)")
    return np.stack([np.asarray(b) for b in B])


def consensus_board(P: FloatArray, B: FloatArray, X: FloatArray) -> FloatArray:
    """The board pose in the anchor frame that the samples agree on for a given X: the chordal
    mean of the rotations and the mean of the translations of ``P_i @ X @ B_i``."""
    C = P @ X @ B
    return make_transform(project_rotation(C[:, :3, :3].sum(axis=0)), C[:, :3, 3].mean(axis=0))


def inconsistency(P: FloatArray, B: FloatArray, X: FloatArray,
                  C: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per sample: how far its implied board pose ``P_i @ X @ B_i`` lies from ``C``, as
    (rotation deg, translation mm)."""
    mm, deg = pose_errors(P @ X @ B, C)
    return deg, mm
