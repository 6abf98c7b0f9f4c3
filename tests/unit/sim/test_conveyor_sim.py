"""The conveyor cell's own pieces (vgripd/sim/conveyor.py): the motion blur kernel moves an
image's centroid by half the travel during the exposure and spreads it along that travel only;
the belt's counts wrap and its truth moves along the direction."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vgripd.config import ConveyorConfig
from vgripd.sim.conveyor import SimBelt, SimPart, line_kernel


@pytest.mark.parametrize("shift", [(3.0, 0.0), (0.4, 0.0), (2.5, -1.5), (0.0, 0.0)])
def test_the_blur_moves_a_spot_by_half_the_travel_along_it(shift: tuple[float, float]) -> None:
    image = np.zeros((41, 41))
    image[20, 20] = 1.0
    out = cv2.filter2D(image, -1, line_kernel(np.array(shift)),
                       borderType=cv2.BORDER_CONSTANT)
    assert out.sum() == pytest.approx(1.0)
    ys, xs = np.mgrid[:41, :41]
    centroid = np.array([(xs * out).sum(), (ys * out).sum()])
    # the spot sweeps from where it was to where it went: its mean is half way
    assert centroid == pytest.approx(np.array([20.0, 20.0]) + np.array(shift) / 2, abs=0.02)
    # and it spreads along the travel, not across it
    d = np.array(shift) / (np.linalg.norm(shift) or 1.0)
    across = (xs - centroid[0]) * -d[1] + (ys - centroid[1]) * d[0]
    assert (across ** 2 * out).sum() < 0.25


def test_the_belt_counts_wrap_and_carry_the_parts_along_its_direction() -> None:
    s2 = np.sqrt(0.5)
    conveyor = ConveyorConfig(counts_per_mm=4.0, encoder_bits=16, direction=(s2, s2, 0.0),
                              origin_mm=(10.0, 20.0, 5.0), window_mm=(100.0, 500.0),
                              trigger_distance_mm=50.0, speed_mm_s=300.0)
    belt = SimBelt(conveyor, [SimPart(30.0, 2.0, 90.0)], count0=65000)
    assert belt.count_at(200.0) == (65000 + 800) % 65536
    assert belt.travel_of(belt.count_at(200.0)) == pytest.approx(200.0)
    assert belt.travel_of(belt.count_at(-100.0)) == pytest.approx(-100.0)
    T0, T1 = belt.truth(0, 0.0), belt.truth(0, 200.0)
    assert T1[:3, 3] - T0[:3, 3] == pytest.approx([200 * s2, 200 * s2, 0.0])
    # at travel 0: 30 along, 2 to the left of the direction, on the belt's surface
    assert T0[:3, 3] == pytest.approx([10 + 30 * s2 - 2 * s2, 20 + 30 * s2 + 2 * s2, 5.0])
    # turned 90 deg from the belt's direction about its normal
    assert T0[:3, 0] == pytest.approx([-s2, s2, 0.0])
