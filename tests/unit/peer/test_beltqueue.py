"""The conveyor's latch and part-queue rules (vgripd.peer.beltqueue) against a belt
simulated here: true parts carried by their own arithmetic, seen by a camera window with
noise, picked by a robot at random counts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vgripd.geometry.belt import Belt
from vgripd.peer.beltqueue import (
    FrameLatches,
    LatchSource,
    PartQueue,
    latch_from_link,
    latch_from_timestamp,
)

FOV = (0.0, 220.0)  # the camera sees this stretch of the belt (mm along it)
WINDOW = (300.0, 700.0)


def truth(alpha: float, s: float, y: float, yaw: float) -> np.ndarray:
    """A part's pose: ``s`` along a belt of heading ``alpha`` through the base origin, ``y``
    across it, turned ``yaw`` about z (independent of the code under test)."""
    d = np.array([math.cos(alpha), math.sin(alpha), 0.0])
    n = np.array([-math.sin(alpha), math.cos(alpha), 0.0])
    T = np.eye(4)
    c, si = math.cos(alpha + yaw), math.sin(alpha + yaw)
    T[:3, :3] = [[c, -si, 0], [si, c, 0], [0, 0, 1]]
    T[:3, 3] = d * s + n * y + [0, 0, 15.0]
    return T


@settings(max_examples=60, deadline=None)
@given(alpha=st.floats(-math.pi, math.pi), scale=st.floats(2.0, 80.0),
       gaps=st.lists(st.floats(25.0, 300.0), min_size=1, max_size=12),
       picks=st.lists(st.integers(0, 3), min_size=40, max_size=40),
       trigger_mm=st.floats(60.0, 200.0), c0=st.integers(0, 2**32 - 1),
       seed=st.integers(0, 2**31))
def test_each_part_is_queued_once_and_served_at_most_once(
        alpha: float, scale: float, gaps: list[float], picks: list[int], trigger_mm: float,
        c0: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    starts = -np.cumsum(gaps)  # along-belt positions at count c0, all upstream of the camera
    ys = rng.uniform(-80, 80, len(starts))
    yaws = rng.uniform(-math.pi, math.pi, len(starts))
    belt = Belt((math.cos(alpha), math.sin(alpha), 0.0), scale)
    queue = PartQueue(belt, WINDOW, sigma_mm=0.3)
    served: list[int] = []
    seen_parts: set[int] = set()

    def where(k: int, travel: float) -> np.ndarray:
        return truth(alpha, starts[k] + travel, ys[k], yaws[k])

    def who(T: np.ndarray, travel: float) -> int:
        return int(np.argmin([np.linalg.norm(where(k, travel)[:3, 3] - T[:3, 3])
                              for k in range(len(starts))]))

    travel = 0.0
    for step in range(40):
        travel = step * trigger_mm
        count = (c0 + round(travel * scale)) % 2**32
        travel = (count - c0) % 2**32 / scale  # the belt where the encoder says
        visible = [k for k in range(len(starts)) if FOV[0] <= starts[k] + travel <= FOV[1]]
        poses = []
        for k in visible:
            T = where(k, travel)
            T[:3, 3] += rng.normal(0, 0.1, 3)
            poses.append(T)
        seen_parts |= set(visible)
        queue.add(latch_from_link(belt, count), poses, job_id=step + 1)
        for _ in range(picks[step]):
            part = queue.next(count)
            if part is None:
                break
            T = part.at(belt, count)
            k = who(T, travel)
            assert np.linalg.norm(T[:3, 3] - where(k, travel)[:3, 3]) < 1.0  # error at pick
            assert starts[k] + travel <= WINDOW[1]  # never one that has left the window
            served.append(k)
    assert len(served) == len(set(served)), f"a part served twice: {served}"
    unique = queue.stats.seen - queue.stats.duplicates
    assert unique == len(seen_parts), "a part queued twice, or two parts taken for one"
    assert queue.stats.served + queue.stats.dropped + len(queue) == unique
    order = [queue.along(p, count) for p in queue.parts]
    assert order == sorted(order, reverse=True), "the queue is not in belt order"


def test_a_part_that_leaves_the_window_is_dropped_and_counted() -> None:
    belt = Belt((1.0, 0.0, 0.0), 10.0)
    queue = PartQueue(belt, WINDOW)
    queue.add(latch_from_link(belt, 0), [truth(0.0, 100.0, 0.0, 0.0)], job_id=1)
    assert queue.next(10 * 700) is None  # at 800 mm: past the downstream end
    assert (queue.stats.dropped, queue.stats.served, len(queue)) == (1, 0, 0)


def test_a_served_part_seen_again_is_not_queued_again() -> None:
    belt = Belt((1.0, 0.0, 0.0), 10.0)
    queue = PartQueue(belt, WINDOW)
    queue.add(latch_from_link(belt, 0), [truth(0.0, 100.0, 0.0, 0.0)], job_id=1)
    assert queue.next(0) is not None
    queue.add(latch_from_link(belt, 500), [truth(0.0, 150.0, 0.0, 0.05)], job_id=2)
    assert (queue.stats.duplicates, len(queue), queue.next(500)) == (1, 0, None)


def test_the_timestamp_latch_states_its_error() -> None:
    """500 mm/s and 2 ms of timestamp uncertainty: 1 mm (and half a count)."""
    belt = Belt((1.0, 0.0, 0.0), 30.0)
    latch = latch_from_timestamp(belt, 1000, t_count_ns=0, t_exposure_ns=20_000_000,
                                 speed_mm_s=500.0, timestamp_error_ms=2.0)
    assert latch.source is LatchSource.TIMESTAMP
    assert latch.count == 1000 + 10 * 30  # 10 mm in 20 ms
    assert latch.error_mm == pytest.approx(math.hypot(1.0, 0.5 / 30))


def test_frame_latches_pair_a_frame_with_its_count() -> None:
    belt = Belt((1.0, 0.0, 0.0), 30.0, bits=16)
    latches = FrameLatches(belt, keep=2)
    assert latches.match(7) is None
    assert "no latched count from the PLC yet" in latches.missing(7)
    latches.report(7, 70000)
    latches.report(8, 100)
    latches.report(9, 200)
    assert latches.match(7) is None  # only the last two kept
    got = latches.match(8)
    assert got is not None
    assert (got.count, got.source) == (100, LatchSource.FRAME_ID)
    assert "latched frames 8..9" in latches.missing(7)
