"""The belt geometry (vgripd.geometry.belt) against oracles written here: positions of a board
carried by a belt of known direction and scale, a pinhole camera looking straight down."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vgripd.errors import DegenerateInputError
from vgripd.geometry.belt import Belt, blur_px, count_delta, fit_belt


def test_count_delta_takes_the_short_way_round_the_wrap() -> None:
    assert count_delta(10, 25) == 15
    assert count_delta(25, 10) == -15
    assert count_delta(0xFFFF_FFF0, 0x10) == 0x20  # forward over the 32-bit wrap
    assert count_delta(0x10, 0xFFFF_FFF0) == -0x20
    assert count_delta(65530, 4, bits=16) == 10


@given(c0=st.integers(0, 2**32 - 1), step=st.integers(-2**30, 2**30))
def test_count_delta_inverts_a_wrapped_step(c0: int, step: int) -> None:
    assert count_delta(c0, (c0 + step) % 2**32) == step


def test_moved_carries_the_pose_along_the_direction_only() -> None:
    d = np.array([0.6, 0.8, 0.0])
    belt = Belt(tuple(d), counts_per_mm=20.0)  # type: ignore[arg-type]
    T = np.eye(4)
    T[:3, 3] = [100.0, -50.0, 12.0]
    moved = belt.moved(T, 1000, 1000 + 20 * 250)  # 250 mm
    np.testing.assert_allclose(moved[:3, 3], [100 + 150, -50 + 200, 12.0])
    np.testing.assert_allclose(moved[:3, :3], np.eye(3))
    assert belt.along_mm(moved[:3, 3]) - belt.along_mm(T[:3, 3]) == pytest.approx(250.0)


def test_a_direction_that_is_not_unit_is_refused() -> None:
    with pytest.raises(DegenerateInputError, match="direction .* not a unit vector"):
        Belt((1.0, 1.0, 0.0), counts_per_mm=10.0)


@settings(max_examples=40, deadline=None)
@given(angle=st.floats(-math.pi, math.pi), scale=st.floats(0.5, 200.0),
       n=st.integers(3, 12), seed=st.integers(0, 2**31))
def test_fit_recovers_direction_and_scale_within_its_sigmas(angle: float, scale: float, n: int,
                                                            seed: int) -> None:
    """Board positions of an independent belt (known direction, counts per mm, 0.05 mm
    noise), seen at random counts over about a metre: the fit lands within 5 sigma."""
    rng = np.random.default_rng(seed)
    d = np.array([math.cos(angle), math.sin(angle), 0.0])
    p0 = np.array([400.0, -120.0, 35.0])
    c0 = int(rng.integers(0, 2**32))
    travel = np.sort(rng.uniform(0.0, 1000.0, n))
    travel[-1] = travel[0] + 600.0  # the board moves at least 600 mm
    counts = [(c0 + round(t * scale)) % 2**32 for t in travel]
    exact = np.array([p0 + d * (count_delta(c0, c) / scale) for c in counts])
    points = exact + rng.normal(0.0, 0.05, exact.shape)
    fit = fit_belt(counts, points, point_sigma_mm=0.01)
    angle_err = math.degrees(math.acos(min(1.0, float(np.dot(fit.direction, d)))))
    assert angle_err <= 5 * fit.sigma_direction_deg + 1e-9
    assert abs(fit.counts_per_mm - scale) <= 5 * fit.sigma_counts_per_mm + 1e-9
    assert fit.rms_mm < 0.3


def test_fit_from_two_counts_takes_the_stated_sigma() -> None:
    fit = fit_belt([100, 100 + 30 * 500], [[0, 0, 0], [500, 0, 0]], point_sigma_mm=0.2)
    assert fit.counts_per_mm == pytest.approx(30.0)
    assert fit.direction == pytest.approx((1.0, 0.0, 0.0))
    # sigma of b: 0.2 / sqrt(sum (c - mean)^2) = 0.2 / (15000 / sqrt(2)) mm per count
    sigma_b = 0.2 / (15000 / math.sqrt(2))
    assert fit.sigma_counts_per_mm == pytest.approx(sigma_b * 30.0 ** 2)


def test_fit_refuses_a_board_at_one_count() -> None:
    with pytest.raises(DegenerateInputError, match="one count"):
        fit_belt([5, 5], [[0, 0, 0], [1, 0, 0]])
    with pytest.raises(DegenerateInputError, match="two or more"):
        fit_belt([5], [[0, 0, 0]])


def test_blur_of_a_camera_looking_straight_down() -> None:
    """f = 2000 px at 1000 mm: 1 mm of travel is 2 px."""
    K = np.array([[2000.0, 0, 640], [0, 2000.0, 512], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # z down
    T[:3, 3] = [500.0, 0.0, 1000.0]
    assert blur_px(K, T, [500.0, 0.0, 0.0], [1.0, 0.0, 0.0], 1.0) == pytest.approx(2.0)
    assert blur_px(K, T, [500.0, 0.0, 2000.0], [1.0, 0.0, 0.0], 1.0) == math.inf
