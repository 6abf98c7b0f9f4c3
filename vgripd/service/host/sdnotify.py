"""systemd notification protocol (``sd_notify``) without a dependency.

systemd passes a unix datagram socket in ``NOTIFY_SOCKET`` (a path, or ``@name`` for the Linux
abstract namespace) to services with ``Type=notify``; the service sends newline-separated
``KEY=value`` assignments to it: ``READY=1`` once it serves, ``STATUS=...`` for ``systemctl
status``, ``WATCHDOG=1`` at least every ``WatchdogSec`` (passed as ``WATCHDOG_USEC``), and
``STOPPING=1`` on shutdown. Without ``NOTIFY_SOCKET`` every call is a no-op.

Sending never blocks the event loop: the socket is non-blocking and a full receive queue drops
the message (logged once), as systemd's own ``sd_notify`` would fail it.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


def socket_address_from_env(value: str) -> str | bytes:
    """The ``sendto`` address for a ``NOTIFY_SOCKET`` value (``@`` is the abstract namespace)."""
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


def watchdog_interval_s(env: Mapping[str, str] | None = None) -> float | None:
    """The watchdog timeout in seconds if systemd asked this process for pings, else None.

    ``WATCHDOG_PID``, when set, names the process meant; any other process must not ping.
    """
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC", "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    pid = env.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    return int(usec) / 1e6


class Notifier:
    """Sends notifications to ``NOTIFY_SOCKET`` (read once, at construction)."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        value = env.get("NOTIFY_SOCKET", "")
        self._address: str | bytes | None = socket_address_from_env(value) if value else None
        self._sock: socket.socket | None = None
        self._failed_once = False

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def send(self, *assignments: str) -> bool:
        """Send ``KEY=value`` lines as one datagram; True if it was handed to the socket."""
        if self._address is None:
            return False
        # A status line with a newline would be read as a second assignment.
        payload = "\n".join(a.replace("\n", " ") for a in assignments).encode()
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.setblocking(False)
            self._sock.sendto(payload, self._address)
        except OSError as err:
            if not self._failed_once:
                log.warning("sd_notify to %r failed: %s (further failures not logged)",
                            self._address, err)
                self._failed_once = True
            return False
        return True

    def ready(self, status: str = "") -> bool:
        return self.send("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def stopping(self, status: str = "") -> bool:
        return self.send("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
