"""A simulated robot arm for the walked hand-eye calibration: a flange that moves to a target
inside its reach, settles, and reports the pose it reached with the error a real controller's
pose has (per-axis Gaussian rotation and translation noise, in the flange frame).

Time is counted in control cycles, not slept: ``move`` starts a motion that takes
``settle_cycles`` calls of ``step`` to settle, so a robot program's "wait until settled" is a
loop on a state, and a test never waits on a clock.
"""

from __future__ import annotations

import enum
from typing import Any

import numpy as np

from vgripd.geometry.transforms import transforms_from_vectors


class ArmState(enum.Enum):
    IDLE = "idle"
    MOVING = "moving"
    SETTLED = "settled"


class Unreachable(Exception):
    """The target lies outside the arm's reach."""


class SimulatedArm:
    """Flange poses ``T_base_flange`` (mm); reach: a sphere of ``reach_mm`` about the base
    origin (the flange position), as a first-order stand-in for the work envelope."""

    def __init__(self, T_start: Any, *, reach_mm: float, settle_cycles: int = 3,
                 noise_deg: float = 0.0, noise_mm: float = 0.0,
                 rng: np.random.Generator | None = None) -> None:
        self.T_true = np.asarray(T_start, dtype=float).copy()
        self.reach_mm = reach_mm
        self.settle_cycles = settle_cycles
        self.noise_deg, self.noise_mm = noise_deg, noise_mm
        self.rng = rng or np.random.default_rng(0)
        self.state = ArmState.IDLE
        self._remaining = 0
        self.moves = 0

    def reachable(self, T: Any) -> bool:
        return bool(np.linalg.norm(np.asarray(T, dtype=float)[:3, 3]) <= self.reach_mm)

    def move(self, T: Any) -> None:
        """Start a motion to ``T``; Unreachable (and no motion) outside the reach."""
        if not self.reachable(T):
            raise Unreachable(f"target {np.round(np.asarray(T)[:3, 3], 1).tolist()} mm is "
                              f"beyond the reach of {self.reach_mm:g} mm")
        self.T_true = np.asarray(T, dtype=float).copy()
        self.state = ArmState.MOVING
        self._remaining = self.settle_cycles
        self.moves += 1

    def step(self) -> ArmState:
        """One control cycle."""
        if self.state is ArmState.MOVING:
            self._remaining -= 1
            if self._remaining <= 0:
                self.state = ArmState.SETTLED
        return self.state

    def reported_pose(self) -> np.ndarray:
        """The flange pose the controller reports (true pose plus its error)."""
        if self.state is ArmState.MOVING:
            raise RuntimeError("the arm is still moving: wait until it settles")
        noise = np.concatenate([np.radians(self.rng.normal(scale=self.noise_deg, size=3)),
                                self.rng.normal(scale=self.noise_mm, size=3)])
        return self.T_true @ transforms_from_vectors(noise)
