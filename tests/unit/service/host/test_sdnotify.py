"""sd_notify against a real unix datagram socket bound by the test (as systemd would)."""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from vgripd.service.host.sdnotify import Notifier, socket_address_from_env, watchdog_interval_s


@pytest.fixture
def receiver(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(5.0)
    yield path, sock
    sock.close()


def test_messages_arrive_on_a_path_socket(receiver: tuple[str, socket.socket]) -> None:
    path, sock = receiver
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("serving 1 link")
    assert sock.recv(4096) == b"READY=1\nSTATUS=serving 1 link"
    assert n.watchdog()
    assert sock.recv(4096) == b"WATCHDOG=1"
    # A newline inside a status must not become a second assignment.
    assert n.status("job 3\nOK")
    assert sock.recv(4096) == b"STATUS=job 3 OK"
    assert n.stopping()
    assert sock.recv(4096) == b"STOPPING=1"
    n.close()


def test_abstract_namespace_socket() -> None:
    name = f"vgripd-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(5.0)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert sock.recv(4096) == b"READY=1"
        n.close()
    finally:
        sock.close()


def test_without_notify_socket_everything_is_a_no_op() -> None:
    n = Notifier({})
    assert not n.enabled
    assert not n.ready()
    assert not n.watchdog()


def test_a_missing_socket_is_reported_not_raised(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert not n.ready()
    assert not n.watchdog()
    assert sum("sd_notify" in r.getMessage() for r in caplog.records) == 1
    n.close()


def test_address_and_watchdog_parsing() -> None:
    assert socket_address_from_env("@x") == b"\0x"
    assert socket_address_from_env("/run/systemd/notify") == "/run/systemd/notify"
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 10.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "abc"}) is None
    assert watchdog_interval_s({}) is None
    mine = str(os.getpid())
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": mine}) == 2.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}) is None
