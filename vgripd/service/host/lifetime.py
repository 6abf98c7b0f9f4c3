"""Child processes end with their daemon (the worker, the web view's image helper, the UR RTDE
link's process): on the daemon's SIGTERM, on systemd stopping the whole unit, and when the
daemon is killed (SIGKILL, a crash), which no code of the daemon sees.

Small and free of heavy imports: every spawned child calls it first thing.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
from typing import Any

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_daemon(daemon_pid: int) -> None:
    """Have the kernel SIGKILL this child process when the daemon that spawned it dies (Linux
    ``PR_SET_PDEATHSIG``; elsewhere nothing). A daemon that died before this call leaves the
    child re-parented already: it exits at once.

    The signal follows the death of the spawning *thread*: the daemon spawns its children from
    its event loop's thread, which lives as long as the daemon serves.
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
    if os.getppid() != daemon_pid:
        os._exit(0)


def end_on_sigterm(daemon_pid: int, grace_s: int) -> None:
    """SIGTERM handling of a child process: when the daemon is gone, exit now (``finally``
    blocks run); while it lives (systemd signalled the whole unit) leave it ``grace_s`` to stop
    this process in order, then the kernel ends it (SIGALRM's default action)."""

    def on_term(signum: int, frame: Any) -> None:
        if os.getppid() != daemon_pid:
            raise SystemExit(0)
        signal.alarm(grace_s)

    signal.signal(signal.SIGALRM, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, on_term)
