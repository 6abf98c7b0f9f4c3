"""Samples with known truth, for the tests and the benchmark."""

from __future__ import annotations

import math

import numpy as np

from vgripd.calib.handeye.samples import FloatArray, Sample, check_mode
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    invert_transform,
    make_transform,
    matrix_from_rotvec,
    transforms_from_vectors,
)


def synthetic_samples(
    mode: str,
    X: FloatArray,
    T_anchor_board: FloatArray,
    camera: CameraModel,
    object_points: FloatArray,
    n: int = 15,
    *,
    rng: np.random.Generator,
    noise_px: float = 0.0,
    robot_noise_deg: float = 0.0,
    robot_noise_mm: float = 0.0,
    tilt_deg: float = 30.0,
    distance_mm: tuple[float, float] = (400.0, 700.0),
) -> list[Sample]:
    """``n`` samples of a camera with hand-eye transform ``X`` seeing a board at
    ``T_anchor_board``.

    Each view puts the board centre on the optical axis at a random distance, tilted by up to
    ``tilt_deg`` about random axes in the board plane and rolled freely; the robot pose that
    produces it follows from X and the board pose. Pixels get Gaussian noise ``noise_px`` (per
    coordinate); the robot poses reported get rotation noise ``robot_noise_deg`` (per axis) and
    translation noise ``robot_noise_mm`` (per axis) after the pixels were made.
    """
    check_mode(mode)
    centre = object_points.mean(axis=0)
    out = []
    for i in range(n):
        roll = rng.uniform(-math.pi, math.pi)
        tilt_axis = rng.normal(size=2)
        tilt = math.radians(rng.uniform(-tilt_deg, tilt_deg))
        R = matrix_from_rotvec([0.0, 0.0, roll]) @ matrix_from_rotvec(
            np.array([*tilt_axis / np.linalg.norm(tilt_axis), 0.0]) * tilt)
        depth = rng.uniform(*distance_mm)
        B = make_transform(R, np.array([0.0, 0.0, depth]) - R @ centre)  # T_cam_board
        P = T_anchor_board @ invert_transform(B) @ invert_transform(X)
        T_base_flange = P if mode == "eye-in-hand" else invert_transform(P)
        px = camera.project(object_points @ B[:3, :3].T + B[:3, 3])
        px = px + rng.normal(scale=noise_px, size=px.shape) if noise_px else px
        if robot_noise_deg or robot_noise_mm:
            noise = np.concatenate([np.radians(rng.normal(scale=robot_noise_deg, size=3)),
                                    rng.normal(scale=robot_noise_mm, size=3)])
            T_base_flange = T_base_flange @ transforms_from_vectors(noise)
        out.append(Sample(T_base_flange, None, f"synthetic-{i:02d}", object_points.copy(), px))
    return out
