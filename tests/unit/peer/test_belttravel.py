"""Triggering by belt travel (vgripd.peer.belttravel) against belts simulated here with
unwrapped whole counts: images only where the count has advanced the trigger distance since
the last one, none while it stands, skips while a job runs (never taken late), the same
decisions on either side of the counter's wrap, a jump re-based into one image; and the latch
interpolated from the counts read around an exposure (vgripd.peer.beltqueue)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vgripd.geometry.belt import Belt
from vgripd.peer.beltqueue import LatchSource, latch_from_counts
from vgripd.peer.belttravel import Travel, TravelRule, TravelStep

MS = 1_000_000  # ns


def rule(cpm: float, distance_mm: float, bits: int = 32) -> TravelRule:
    return TravelRule(cpm, distance_mm, speed_mm_s=500.0, bits=bits)


def run(r: TravelRule, c0: int, steps: list[int], busy: list[bool] | None = None,
        dt_ns: int = 10 * MS) -> list[TravelStep]:
    """Feed the counts ``c0``, ``c0 + steps[0]``, ... (wrapped to the rule's width), one
    every ``dt_ns``; ``busy[i]``: a job runs at reading i."""
    span = 1 << r.bits
    pos, out = 0, []
    for i, step in enumerate([0, *steps]):
        pos += step
        out.append(r.feed((c0 + pos) % span, i * dt_ns, bool(busy and i < len(busy)
                                                               and busy[i])))
    return out


cpms = st.sampled_from([0.1, 1.0, 7.3, 30.0, 100.0])
distances = st.floats(20.0, 300.0)


@settings(max_examples=150, deadline=None)
@given(cpm=cpms, distance=distances, data=st.data())
def test_images_come_once_per_trigger_distance_and_never_while_the_belt_stands(
        cpm: float, distance: float, data: st.DataObject) -> None:
    d_counts = distance * cpm
    top = max(1, int(d_counts * 0.9))  # each step shorter than the trigger distance
    steps = data.draw(st.lists(st.one_of(st.just(0), st.integers(1, top)), max_size=120))
    r = rule(cpm, distance)
    out = run(r, 12345, steps)
    positions = [sum(steps[:i]) for i in range(len(steps) + 1)]
    images = [positions[i] for i, s in enumerate(out) if s.action is Travel.IMAGE]
    assert out[0].action is Travel.IMAGE  # the first count seen
    assert out[0].first
    for a, b in zip(images, images[1:], strict=False):
        assert d_counts - 1e-6 <= b - a < d_counts + top  # one distance on, never two
    assert positions[-1] - images[-1] < d_counts  # no image left untaken
    for i, step in enumerate(steps, start=1):  # a count that stands still starts nothing
        if step == 0:
            assert out[i].action is Travel.WAIT
    assert not any(s.action is Travel.SKIP or s.skipped for s in out)
    assert (r.stats.images, r.stats.skipped, r.stats.rebased) == (len(images), 0, 0)


@settings(max_examples=150, deadline=None)
@given(cpm=cpms, distance=distances, bits=st.sampled_from([16, 32]), data=st.data())
def test_the_wrap_changes_no_decision(cpm: float, distance: float, bits: int,
                                      data: st.DataObject) -> None:
    """The same belt fed from far below the wrap and from just below it: the same steps."""
    span = 1 << bits
    d_counts = distance * cpm
    if d_counts >= span / 4:
        return  # the config refuses it
    top = max(1, int(min(d_counts * 2.5, span / 8)))
    steps = data.draw(st.lists(st.integers(-2, top), max_size=80))
    busy = data.draw(st.lists(st.booleans(), min_size=len(steps) + 1,
                              max_size=len(steps) + 1))
    before = data.draw(st.integers(1, max(1, sum(max(s, 0) for s in steps))))
    far = run(rule(cpm, distance, bits), 17, steps, busy)
    near = run(rule(cpm, distance, bits), span - before, steps, busy)
    assert [(a.action, a.skipped, a.burst_start, a.jump == "") for a in far] == \
        [(b.action, b.skipped, b.burst_start, b.jump == "") for b in near]


@settings(max_examples=150, deadline=None)
@given(cpm=cpms, distance=distances, data=st.data())
def test_a_trigger_point_passed_while_a_job_runs_is_skipped_and_counted_never_taken_late(
        cpm: float, distance: float, data: st.DataObject) -> None:
    d_counts = distance * cpm
    top = max(1, int(d_counts * 2.5))  # several points between two readings at times
    steps = data.draw(st.lists(st.integers(0, top), min_size=1, max_size=120))
    busy = [False, *data.draw(st.lists(st.booleans(), min_size=len(steps),
                                       max_size=len(steps)))]
    r = rule(cpm, distance)
    out = run(r, 2**32 - 777, steps, busy, dt_ns=1000 * MS)  # 1 s apart: no jump
    positions = [sum(steps[:i]) for i in range(len(steps) + 1)]
    # the independent account: trigger points are due one distance after the last image or
    # the last point skipped; each due point passed while busy is skipped, else imaged now
    due, skipped, images, bursts = float(d_counts), 0, 1, 0
    in_burst = False
    for i in range(1, len(out)):
        got = out[i]
        if busy[i]:
            assert got.action is not Travel.IMAGE
        if positions[i] + 1e-6 < due:
            assert got.action is Travel.WAIT
            continue
        n = math.floor((positions[i] - due) / d_counts + 1e-6) + 1
        if busy[i]:
            assert (got.action, got.skipped) == (Travel.SKIP, n)
            assert got.burst_start == (not in_burst)
            bursts += not in_burst
            in_burst = True
            skipped += n
            due += n * d_counts
        else:
            assert (got.action, got.skipped) == (Travel.IMAGE, n - 1)  # stepped over: skipped
            skipped += n - 1
            images += 1
            in_burst = False
            due = positions[i] + d_counts
    assert (r.stats.images, r.stats.skipped) == (images, skipped)
    assert sum(s.burst_start for s in out if s.action is Travel.SKIP) == bursts


@settings(max_examples=100, deadline=None)
@given(cpm=cpms, distance=distances, jump=st.integers(-2**31 + 1, 2**31 - 1),
       busy=st.booleans(), data=st.data())
def test_a_jump_is_re_based_into_one_image_not_a_burst(cpm: float, distance: float,
                                                       jump: int, busy: bool,
                                                       data: st.DataObject) -> None:
    r = rule(cpm, distance)
    reach_counts = r.reach_mm(10 * MS) * cpm
    if abs(jump) <= reach_counts:
        jump = int(math.copysign(reach_counts + 1 + abs(jump), jump or 1))
        if abs(jump) >= 2**31:
            return
    top = max(1, int(distance * cpm * 0.9))
    after = data.draw(st.lists(st.integers(0, top), max_size=30))
    out = run(r, 5, [int(distance * cpm / 3), jump, *after], [False, False, busy])
    hit = out[2]
    assert hit.jump
    assert hit.first
    assert hit.action is (Travel.SKIP if busy else Travel.IMAGE)
    assert r.stats.rebased == 1
    # from the jump on, the new count is the base: one image per distance again
    positions = [0]
    for s in after:
        positions.append(positions[-1] + s)
    images = [p for p, s in zip(positions[1:], out[3:], strict=True)
              if s.action is Travel.IMAGE]
    assert len(images) <= positions[-1] / (distance * cpm) + 1e-6
    assert not any(s.jump for s in out[3:])


def test_a_slow_reading_link_is_no_jump_but_its_stepped_over_points_are_skipped() -> None:
    r = rule(10.0, 150.0)
    out = run(r, 0, [2000, 10000], dt_ns=4000 * MS)  # 4 s apart: up to 4150 mm is no jump
    assert [s.action for s in out] == [Travel.IMAGE, Travel.IMAGE, Travel.IMAGE]
    assert [s.skipped for s in out] == [0, 0, 5]  # 1000 mm: 6 points passed, 1 imaged
    assert out[2].burst_start
    assert (r.stats.images, r.stats.skipped, r.stats.rebased) == (3, 5, 0)


def test_restart_makes_the_next_count_a_first_one() -> None:
    r = rule(10.0, 150.0)
    run(r, 0, [500])
    r.restart()
    step = r.feed(600, 0, False)
    assert (step.action, step.first, step.jump) == (Travel.IMAGE, True, "")


# --- the latch from the counts read around the exposure ------------------------------------


@settings(max_examples=150, deadline=None)
@given(cpm=cpms, speed=st.floats(0.0, 2000.0), period_ms=st.floats(1.0, 200.0),
       offset=st.floats(0.0, 1.0), bits=st.sampled_from([16, 32]),
       before_wrap_mm=st.floats(-50.0, 50.0))
def test_the_counts_around_the_exposure_give_its_count_across_the_wrap(
        cpm: float, speed: float, period_ms: float, offset: float, bits: int,
        before_wrap_mm: float) -> None:
    """A belt at constant ``speed`` read every ``period_ms``; the exposure between two
    readings near the counter's wrap: its count is the belt's there, within a count."""
    belt = Belt((1.0, 0.0, 0.0), cpm, bits=bits)
    span = 1 << bits
    if speed * period_ms * 1e-3 * 3 * cpm >= span / 4:
        return
    period_ns = int(period_ms * MS)
    t_exp = 3 * period_ns + int(offset * period_ns)
    c_exp = -before_wrap_mm * cpm  # the true count at the exposure, unwrapped

    def at(t: int) -> float:
        return c_exp + speed * cpm * (t - t_exp) * 1e-9

    samples = [(k * period_ns, round(at(k * period_ns)) % span) for k in range(7)]
    latch = latch_from_counts(belt, samples, t_exp, timestamp_error_ms=2.0)
    assert latch is not None
    assert latch.source is LatchSource.TIMESTAMP
    miss = (latch.count - round(c_exp)) % span
    assert min(miss, span - miss) <= 1.5
    assert latch.error_mm == pytest.approx(
        math.hypot(speed * 2e-3, 0.5 / cpm), abs=2.5 / (cpm * period_ms))  # whole counts


def test_a_belt_that_stood_during_the_exposure_is_latched_at_its_count() -> None:
    belt = Belt((1.0, 0.0, 0.0), 10.0)
    samples = [(0, 100), (10 * MS, 500), (20 * MS, 500), (30 * MS, 900)]
    latch = latch_from_counts(belt, samples, 15 * MS, 2.0)
    assert latch is not None
    assert (latch.count, latch.error_mm) == (500, pytest.approx(0.05))


@pytest.mark.parametrize("samples", [
    [],  # nothing read yet
    [(0, 100), (5 * MS, 120)],  # nothing read after the exposure yet
    [(20 * MS, 100)],  # nothing read before it
    [(0, 100), (2_000 * MS, 20000)],  # a gap too long to say where the belt was
])
def test_without_a_reading_on_both_sides_the_timestamp_rule_decides(
        samples: list[tuple[int, int]]) -> None:
    assert latch_from_counts(Belt((1.0, 0.0, 0.0), 10.0), samples, 10 * MS, 2.0) is None
