"""The fork server's own set-up: ``children.PRELOAD`` names it first, so the fork server
imports it at its start. Import it nowhere else.

The fork server is the parent of the daemon's ``multiprocessing`` children, and they are
killed when it ends (``PR_SET_PDEATHSIG``). systemd stops the unit by sending SIGTERM to every
process in it (``KillMode=control-group``): ended by it, the fork server would take the worker
with it before the daemon had stopped the worker in order (camera closed, recording flushed).
So it ignores SIGTERM; it ends when the daemon does (``multiprocessing`` ends it once the
daemon's end closes their pipe), and SIGINT it ignores already. Its children set their own
SIGTERM handling first thing (``children.start_child``).
"""

import signal

signal.signal(signal.SIGTERM, signal.SIG_IGN)
