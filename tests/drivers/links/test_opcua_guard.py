"""The opcua link's login throttle and rejected-certificate store, without a server: the clock
is passed in, the store is a temporary folder. The server-side behaviour against a raw client
is tests/drivers/links/test_opcua.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.links.opcua_guard import RejectedStore
from vgripd.service.links.throttle import LoginThrottle


def test_failures_are_spaced_then_the_address_is_locked_out() -> None:
    t = LoginThrottle(max_failures=5, rate_per_s=10.0, lockout_s=60.0)
    answers = [t.failed("10.0.0.9", 100.0) for _ in range(5)]
    # five failures at once: answered 0.1 s apart, the fifth locks the address out
    assert [round(d, 6) for d, _ in answers] == [0.0, 0.1, 0.2, 0.3, 0.4]
    assert [locked for _, locked in answers] == [False] * 4 + [True]
    assert t.locked("10.0.0.9", 100.5) == pytest.approx(59.9)
    assert t.locked("10.0.0.10", 100.5) == 0.0  # per address
    assert t.locked("10.0.0.9", 160.5) == 0.0  # over
    assert t.failed("10.0.0.9", 161.0) == (0.0, False)  # counting starts again


def test_a_success_resets_the_count_and_old_failures_are_forgotten() -> None:
    t = LoginThrottle(max_failures=3, rate_per_s=10.0, lockout_s=60.0)
    t.failed("a", 0.0)
    t.failed("a", 1.0)
    t.succeeded("a")
    assert not t.failed("a", 2.0)[1]
    assert not t.failed("a", 3.0)[1]
    assert not t.failed("a", 100.0)[1]  # the two before are older than lockout_s
    assert not t.failed("a", 101.0)[1]
    assert t.failed("a", 102.0)[1]


def test_the_throttle_remembers_a_bounded_number_of_addresses() -> None:
    t = LoginThrottle(max_failures=3, rate_per_s=10.0, lockout_s=60.0, max_tracked=100)
    for n in range(3):
        t.failed("locked", float(n))
    for n in range(1000):
        t.failed(f"10.1.{n // 250}.{n % 250}", 10.0)
    assert len(t) <= 100
    assert t.locked("10.0.0.1", 11.0) == 0.0


def test_rejected_store_keeps_the_newest_one_file_per_thumbprint(tmp_path: Path) -> None:
    store = RejectedStore(tmp_path / "rejected", max_files=3, max_bytes=10_000)
    for n in range(5):
        assert store.keep(bytes([n]) * 100, f"t{n}") == tmp_path / "rejected" / f"t{n}.der"
    assert store.keep(b"\x02" * 100, "t2") is not None  # refused again: newest now
    assert store.keep(b"\x05" * 100, "t5") is not None
    assert sorted(p.name for p in (tmp_path / "rejected").iterdir()) == [
        "t2.der", "t4.der", "t5.der"]


def test_rejected_store_bytes_cap_and_no_store(tmp_path: Path) -> None:
    store = RejectedStore(tmp_path / "r", max_files=100, max_bytes=1000)
    for n in range(4):
        store.keep(b"x" * 400, f"b{n}")
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["b2.der", "b3.der"]
    assert store.keep(b"x" * 1001, "huge") is None
    assert RejectedStore(tmp_path / "none", max_files=0).keep(b"x", "t") is None
    assert not (tmp_path / "none").exists()


def test_rejected_store_that_cannot_be_written_keeps_nothing(tmp_path: Path) -> None:
    blocker = tmp_path / "pki"
    blocker.write_text("a file where the folder should be")
    assert RejectedStore(blocker / "rejected", max_files=3).keep(b"x", "t") is None
