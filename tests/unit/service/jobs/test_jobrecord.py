"""The epipolar monitor behind the RECALIBRATE warning (``EpipolarMonitor``): judged only
once enough stereo jobs are in, up while the share above the level exceeds the limit, a
change reported once, and the window forgetting old jobs. The daemon's side of it (status,
metrics, the log line) is tests/integration/test_daemon_recalibrate.py."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from vgripd.service.jobs.jobrecord import EpipolarMonitor


def monitor() -> EpipolarMonitor:
    return EpipolarMonitor(window=10, share=0.5, min_jobs=4, threshold_px=1.0)


def test_no_warning_before_min_jobs_even_when_every_job_is_above() -> None:
    m = monitor()
    assert [m.add(5.0, t) for t in range(3)] == [False, False, False]
    assert not m.warning
    assert m.add(5.0, 3) is True  # the fourth job judges: every one above
    assert m.warning
    assert m.since_mono_ns == 3


def test_the_warning_changes_once_each_way_and_says_since_when() -> None:
    m = monitor()
    changes = [t for t, px in enumerate([2.0] * 6 + [0.1] * 10) if m.add(px, t)]
    # up at the 4th job; down once the window of 10 holds 5 or fewer above (share not > 0.5)
    assert changes == [3, 10]
    assert not m.warning
    snap = m.snapshot(20)
    assert (snap["jobs"], snap["above"], snap["since_s"]) == (10, 0, None)


def test_a_residual_at_the_level_is_not_above_it() -> None:
    m = monitor()
    for t in range(6):
        m.add(1.0, t)
    assert m.share() == 0.0
    assert not m.warning


def test_describe_names_the_settings_an_operator_can_change() -> None:
    m = monitor()
    for t in range(5):
        m.add(3.0 if t % 2 else 0.2, t)
    text = m.describe()
    assert "2 of the last 5 stereo jobs" in text
    assert "vision.epipolar_warn_px = 1.0 px" in text
    assert "daemon.recalibrate_share = 0.5" in text


@given(st.lists(st.floats(0.0, 5.0, allow_nan=False), max_size=40))
def test_the_warning_always_equals_the_rule_on_the_window(residuals: list[float]) -> None:
    m = monitor()
    for t, px in enumerate(residuals):
        m.add(px, t)
        window = residuals[max(0, t + 1 - 10):t + 1]
        above = sum(r > 1.0 for r in window)
        assert m.warning == (len(window) >= 4 and above / len(window) > 0.5)
        assert m.snapshot(t)["above"] == above
