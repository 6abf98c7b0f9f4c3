"""The default refinement objective: hand-eye as a maximum-likelihood problem with noise in the
images *and* in the robot poses.

The measurements are the board poses ``B_i`` (from the corners, :func:`.pnp.board_pose`),
each with its covariance ``s^2 (J_i^T J_i)^-1`` (``J_i``: the pixels' Jacobian against a small
motion of the board in the camera frame; ``s^2``: the corner noise pooled over every image's
own pose fit, which no robot error reaches). The reported robot poses get Gaussian noise of
``sigma_deg`` / ``sigma_mm`` per axis in the flange frame, which reaches the predicted board
pose ``Y Q_i C`` through the adjoint of ``Y`` (eye-in-hand) or ``Y Q_i`` (eye-to-hand). The
residual of a sample is the 6-vector between predicted and measured board pose, whitened by the
sum of both covariances. With the robot exact this is, to first order, the pixel objective;
with robot noise it stops the fit from bending X to absorb it. The robot noise is the most
likely one on the grid ``ROBOT_SIGMA_DEG`` x ``ROBOT_SIGMA_MM`` (profile likelihood).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from vgripd.calib.handeye.pnp import corner_jacobians
from vgripd.calib.handeye.refine import STATE_SIDES, Problem, minimise
from vgripd.calib.handeye.samples import FloatArray, Sample
from vgripd.errors import CalibrationError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    adjoint,
    inverse_left_jacobians,
    invert_transform,
    invert_transforms,
    skew,
    vectors_from_transforms,
)

#: Robot pose noise levels (one standard deviation per axis, flange frame) among which the
#: likelihood objective picks the most likely; the smallest mean "exact".
ROBOT_SIGMA_DEG = (1e-4, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0)
ROBOT_SIGMA_MM = (1e-3, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0)


def robot_covariance(problem: Problem, Y: FloatArray, sigma_deg: float, sigma_mm: float,
                     ) -> FloatArray:
    """(n, 6, 6) covariance of each predicted board pose (a small motion in the camera frame)
    from robot pose noise of ``sigma_deg`` / ``sigma_mm`` per axis in the flange frame, for
    ``Y = X^-1``: carried through the adjoint of ``Y`` (eye-in-hand) or ``Y Q_i``
    (eye-to-hand)."""
    p = problem
    A = adjoint(np.broadcast_to(Y, p.Q.shape) if p.mode == "eye-in-hand" else Y @ p.Q)
    robot = np.array([math.radians(sigma_deg)] * 3 + [sigma_mm] * 3) ** 2
    out: FloatArray = (A * robot) @ np.swapaxes(A, 1, 2)
    return out


class Likelihood:
    """Board-pose weights of a set of samples, and fits under a given robot noise."""

    def __init__(self, problem: Problem, cov_board: FloatArray, sigma_px: float):
        self.problem = problem
        self.Binv = invert_transforms(problem.B)
        #: (n, 6, 6) covariance of each board pose from its corners
        self.cov_board = cov_board
        #: corner noise, px per coordinate (pooled over the images' own pose fits)
        self.sigma_px = sigma_px

    @classmethod
    def from_corners(cls, problem: Problem, samples: Sequence[Sample],
                     camera: CameraModel) -> Likelihood:
        """Board-pose covariances from each sample's corners and the pooled corner noise."""
        jacobians, sigma_px = corner_jacobians(samples, problem.B, camera)
        try:
            cov = sigma_px**2 * np.linalg.inv(np.stack([J.T @ J for J in jacobians]))
        except np.linalg.LinAlgError:
            raise CalibrationError("hand-eye: a board pose is not determined by its corners "
                                   "(too few or collinear)") from None
        return cls(problem, cov, sigma_px)

    def without(self, k: int, problem: Problem) -> Likelihood:
        """The same weights without sample k; ``problem`` holds the other samples."""
        return Likelihood(problem, np.delete(self.cov_board, k, axis=0), self.sigma_px)

    def _whitening(self, Y: FloatArray, sigma_deg: float,
                   sigma_mm: float) -> tuple[FloatArray, float]:
        """(n, 6, 6) inverse Cholesky factors of the samples' covariances, and their summed
        log determinant."""
        S = self.cov_board + robot_covariance(self.problem, Y, sigma_deg, sigma_mm)
        L = np.linalg.cholesky(S)
        logdet = 2.0 * float(np.log(np.diagonal(L, axis1=1, axis2=2)).sum())
        return np.linalg.inv(L), logdet

    def fit(self, X: FloatArray, C: FloatArray, sigma_deg: float, sigma_mm: float,
            passes: int = 2) -> tuple[FloatArray, FloatArray, float, bool]:
        """X and the board pose maximising the likelihood for this robot noise, from (X, C);
        the weights follow X (``passes`` times). Returns X, C, -2 log-likelihood (up to a
        constant), converged."""
        Q, Binv = self.problem.Q, self.Binv
        state: Sequence[FloatArray] = (invert_transform(X), C)
        converged, nll = False, math.inf
        for _ in range(passes):
            W, logdet = self._whitening(state[0], sigma_deg, sigma_mm)

            def residual(st: Sequence[FloatArray], W: FloatArray = W) -> FloatArray:
                e = vectors_from_transforms(st[0] @ Q @ st[1] @ Binv)
                out: FloatArray = np.einsum("nij,nj->ni", W, e).ravel()
                return out

            def jacobian(st: Sequence[FloatArray], W: FloatArray = W) -> FloatArray:
                # e_i = log(D_i), D_i = M_i B_i^-1, M_i = Y Q_i C. A motion d of Y (left) moves
                # D_i by d on the left; a motion d of C (right) by adjoint(M_i) d. And
                # log(exp(d) D) = log D + [[Jl^-1(w), 0], [-[t]x, I]] d.
                M = st[0] @ Q @ st[1]
                D = M @ Binv
                e = vectors_from_transforms(D)
                L = np.zeros((len(D), 6, 6))
                L[:, :3, :3] = inverse_left_jacobians(e[:, :3])
                L[:, 3:, :3] = -skew(D[:, :3, 3])
                L[:, 3:, 3:] = np.eye(3)
                WL = W @ L
                out: FloatArray = np.concatenate([WL, WL @ adjoint(M)], axis=2).reshape(-1, 12)
                return out

            state, converged = minimise(residual, jacobian, state, STATE_SIDES)
            r = residual(state)
            nll = float(r @ r) + logdet
        return invert_transform(state[0]), state[1], nll, converged

    def solve(self, X: FloatArray, C: FloatArray,
              ) -> tuple[FloatArray, FloatArray, bool, tuple[float, float]]:
        """The most likely robot noise among ``ROBOT_SIGMA_*`` and the fit under it: X, C,
        converged, (sigma_deg, sigma_mm)."""
        best: tuple[float, float, float] | None = None
        Xw, Cw = X, C
        for sigma_deg in ROBOT_SIGMA_DEG:
            for sigma_mm in ROBOT_SIGMA_MM:
                Xw, Cw, nll, _ = self.fit(Xw, Cw, sigma_deg, sigma_mm, passes=1)
                if best is None or nll < best[0]:
                    best = (nll, sigma_deg, sigma_mm)
        assert best is not None
        X, C, _, converged = self.fit(X, C, best[1], best[2])
        return X, C, converged, (best[1], best[2])
