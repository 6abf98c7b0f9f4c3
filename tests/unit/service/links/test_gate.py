"""The connection manager's policy (``Slots``), allow lists, the file budget and the config
checks of ``allow``, fed with event sequences: no sockets, no clock."""

from __future__ import annotations

import logging

import pytest
from hypothesis import given
from hypothesis import strategies as st

from vgripd.config import DriverSection, StatusConfig
from vgripd.errors import ConfigError
from vgripd.registry import LINKS, load_class, validate_options
from vgripd.service.links.gate import Gate, Slots, allowed, parse_allow, plan_budget


def test_newcomers_evict_the_oldest_never_valid_first() -> None:
    slots = Slots(3)
    assert slots.admit("plc", 0.0).accepted
    slots.activity("plc", 0.5, valid=True)
    assert slots.admit("a", 1.0).accepted
    assert slots.admit("b", 2.0).accepted
    d = slots.admit("c", 3.0)  # full: "a" is the oldest that never sent a valid request
    assert d.accepted
    assert d.victims == ["a"]
    d = slots.admit("d", 4.0)
    assert d.victims == ["b"]
    assert slots.connections() == ["plc", "c", "d"]


def test_a_surface_full_of_talkers_refuses_the_newcomer() -> None:
    """The old rule (longest idle goes) evicted the PLC that polled 1 s ago for a newcomer."""
    slots = Slots(2)
    for name, t in (("plc", 0.0), ("robot", 1.0)):
        assert slots.admit(name, t).accepted
        slots.activity(name, t, valid=True)
    d = slots.admit("x", 100.0)
    assert not d.accepted
    assert d.victims == []
    assert slots.connections() == ["plc", "robot"]


def test_invalid_requests_do_not_make_a_talker() -> None:
    slots = Slots(1)
    slots.admit("junk", 0.0)
    slots.activity("junk", 1.0, valid=False)  # e.g. a Modbus exception answer
    assert slots.admit("plc", 2.0).victims == ["junk"]


def test_busy_connections_are_never_evicted_or_expired() -> None:
    slots = Slots(1, reclaim_idle=True)
    slots.admit("browser", 0.0)
    slots.set_busy("browser", True, 0.0)  # a live event stream
    assert not slots.admit("x", 1.0).accepted
    assert slots.expired(1e6, idle_timeout_s=1.0, pending_timeout_s=1.0) == []


def test_reclaim_idle_evicts_the_longest_idle_talker_when_no_pending_is_left() -> None:
    slots = Slots(2, reclaim_idle=True)
    slots.admit("a", 0.0)
    slots.activity("a", 5.0, valid=True)
    slots.admit("b", 1.0)
    slots.activity("b", 2.0, valid=True)
    d = slots.admit("c", 6.0)
    assert d.victims == ["b"]
    assert slots.was_valid("b")


def test_timeouts() -> None:
    slots = Slots(4)
    slots.admit("pending", 0.0)
    slots.admit("talker", 0.0)
    slots.activity("talker", 8.0, valid=True)
    assert slots.expired(9.0, idle_timeout_s=0.0, pending_timeout_s=5.0) == [
        ("pending", "pending", 9.0)]
    assert slots.expired(9.0, idle_timeout_s=0.0, pending_timeout_s=0.0) == []
    assert [c for c, *_ in slots.expired(20.0, idle_timeout_s=10.0, pending_timeout_s=0.0)] == [
        "pending", "talker"]


@given(st.lists(st.tuples(st.sampled_from(["connect", "valid", "close"]),
                          st.integers(0, 30)), max_size=300),
       st.integers(1, 6))
def test_never_more_than_cap_and_talkers_survive_any_flood(
        events: list[tuple[str, int]], cap: int) -> None:
    """Property: whatever the order of connects, valid requests and closes, the slots never
    exceed the cap, and a connection that has completed a valid request is never a victim."""
    slots = Slots(cap)
    talkers: set[int] = set()
    t = 0.0
    for kind, who in events:
        t += 1.0
        if kind == "connect" and who not in slots:
            d = slots.admit(who, t)
            assert not talkers & set(d.victims)
        elif kind == "valid" and who in slots:
            slots.activity(who, t, valid=True)
            talkers.add(who)
        elif kind == "close":
            slots.forget(who)
            talkers.discard(who)
        assert len(slots) <= cap
        assert talkers <= set(slots.connections())


def test_allow_lists() -> None:
    nets = parse_allow(["10.0.0.5", "10.0.1.0/24", "fd00::/8"])
    assert allowed(nets, "10.0.0.5")
    assert allowed(nets, "10.0.1.77")
    assert allowed(nets, "::ffff:10.0.1.3")  # IPv4 seen on an IPv6 socket
    assert allowed(nets, "fd00::1")
    assert not allowed(nets, "10.0.0.6")
    assert not allowed(nets, "10.0.2.1")
    assert not allowed(nets, "?")
    assert allowed(None, "192.0.2.1")


@pytest.mark.parametrize(("link_type", "options"), [
    ("modbus_server", {}), ("robot_socket", {}),
    ("opcua", {"security": ["None"], "allow_anonymous": True})])
def test_a_bad_allow_entry_is_a_config_error_naming_the_field(
        link_type: str, options: dict[str, object]) -> None:
    cls = load_class(LINKS, "link", link_type)
    section = DriverSection.model_validate(
        {"type": link_type, **options, "allow": ["10.0.0.5", "10.0.1.0/33"]})
    with pytest.raises(ConfigError, match=r"links\.2: allow\.1: .*'10\.0\.1\.0/33' is not an IP"):
        validate_options(cls, section, "links.2")
    section = DriverSection.model_validate({"type": link_type, **options, "allow": []})
    with pytest.raises(ConfigError, match=r"links\.2: allow"):
        validate_options(cls, section, "links.2")


def test_web_view_options() -> None:
    assert StatusConfig().max_connections == 64
    assert StatusConfig().header_timeout_s == 10.0
    with pytest.raises(ValueError, match=r"allow\.0"):
        StatusConfig(allow=["localhost"])


def test_budget_keeps_the_configured_caps_when_they_fit() -> None:
    b = plan_budget(1024, 40, 256, [("web view", 64), ("plc", 16), ("robot", 4)])
    assert dict(b.caps) == {"web view": 64, "plc": 16, "robot": 4}
    assert not b.scaled
    assert b.spare >= 0
    assert "limit 1024" in b.describe()
    assert "256 kept" in b.describe()


def test_budget_scales_caps_down_to_fit_and_never_eats_the_reserve() -> None:
    for limit in (128, 256, 300, 512):
        b = plan_budget(limit, 40, 256, [("web view", 64), ("plc", 16), ("opc", 256)])
        assert b.scaled
        assert all(c >= 1 for c in b.caps.values())
        reserve = min(256, (limit - 40) // 2)
        assert b.reserve == reserve
        used = sum(b.caps.values()) + sum(b.backlogs.values())
        assert used <= limit - 40 - reserve or all(c == 1 for c in b.caps.values())


def test_gate_logs_one_line_per_client_and_kind(caplog: pytest.LogCaptureFixture) -> None:
    class Conn:
        def __init__(self, host: str, port: int) -> None:
            self.host, self.client = host, f"{host}:{port}"
            self.shut_reason = ""

        def shut(self, reason: str) -> None:
            self.shut_reason = reason

    now = [0.0]
    gate = Gate("plc", 2, allow=["127.0.0.1"], logger=logging.getLogger("t"),
                clock=lambda: now[0])
    caplog.set_level(logging.INFO, logger="t")
    conns = [Conn("127.0.0.1", p) for p in range(50)]
    for c in conns:
        now[0] += 0.01
        assert gate.admit(c)
    assert all(c.shut_reason.startswith("evicted for") for c in conns[:48])
    assert gate.faults["evicted"] == 48
    for p in range(20):
        assert not gate.admit(Conn("127.0.0.2", p))
    assert gate.faults["not_allowed"] == 20
    text = [r.getMessage() for r in caplog.records]
    assert len([m for m in text if "evicted" in m]) == 1
    assert len([m for m in text if "not in allow" in m]) == 1
