"""The event streams' caps against the web view's connection slots (``stream_caps``) and a
hub sized by them."""

from __future__ import annotations

from vgripd.service.web.events import (
    MAX_EVENT_CLIENTS,
    MAX_HOLDER_STREAMS,
    EventHub,
    frame,
    stream_caps,
)


def test_streams_always_leave_a_connection_for_requests() -> None:
    for connections in range(2, 4097):
        anonymous, holders = stream_caps(connections)
        assert holders >= 1, connections  # the operator is always served
        assert anonymous + holders <= connections - 1, connections
        assert anonymous <= MAX_EVENT_CLIENTS
        assert holders <= MAX_HOLDER_STREAMS
    assert stream_caps(64) == (MAX_EVENT_CLIENTS, MAX_HOLDER_STREAMS)  # the default cap


def test_a_hub_for_two_connections_streams_to_the_token_holder_only() -> None:
    hub = EventHub(*stream_caps(2))
    assert hub.admit("10.0.0.1", holder=False) is None
    first = hub.admit("10.0.0.1", holder=True)
    second = hub.admit("10.0.0.1", holder=True)
    assert second is not None
    assert second in hub.clients
    assert first not in hub.clients  # made room: one holder stream at a time
    assert len(hub.clients) == 1


def test_an_event_is_one_line_of_json() -> None:
    assert frame("status", {"a": [1, "x\ny"]}) == (
        b'event: status\ndata: {"a": [1, "x\\ny"]}\n\n')
