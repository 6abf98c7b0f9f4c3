"""The one helper-process mechanism (``vgripd.service.host.children``): a child set up by
``start_child`` dies with its daemon, even one killed by SIGKILL, also through the fork server,
whose children take the daemon's environment and working folder of the moment; it ignores
SIGINT and runs
below the daemon when asked; ``end_process`` ends and reaps a child that ignores SIGTERM;
``end_pool`` ends a pool whose call outlives the bound, its manager thread included."""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest

from tests.conftest import REPO
from vgripd.service.host.children import (
    ChildSetup,
    end_pool,
    end_process,
    helper_niceness,
    start_child,
)

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="PR_SET_PDEATHSIG and /proc are Linux's")

DEADLINE_S = 60.0


def _gone(pid: int) -> bool:
    """The process no longer runs: reaped, or a zombie waiting for its new parent."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat.rsplit(")", 1)[1].split()[0] == "Z"


def _wait_for(what: str, ok: object) -> None:
    deadline = time.monotonic() + DEADLINE_S
    while not ok() and time.monotonic() < deadline:  # type: ignore[operator]
        time.sleep(0.05)
    assert ok(), f"not within {DEADLINE_S:g} s: {what}"  # type: ignore[operator]


# The daemon stand-in: starts a child that runs start_child, tells its pid, then waits.
_PARENT = """
import os, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], str(os.getpid()), sys.argv[2]])
print(child.pid, flush=True)
time.sleep(600)
"""
_CHILD = """
import sys, time
from vgripd.service.host.children import ChildSetup, start_child
start_child(ChildSetup(int(sys.argv[1])))
open(sys.argv[2], "w").close()
time.sleep(600)
"""


def test_a_child_dies_when_its_daemon_is_killed(tmp_path: Path) -> None:
    ready = tmp_path / "ready"
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, _CHILD, str(ready)],
                              cwd=REPO, stdout=subprocess.PIPE, text=True)
    child_pid = 0
    try:
        assert parent.stdout is not None
        child_pid = int(parent.stdout.readline())
        _wait_for("the child set itself up", ready.exists)
        assert not _gone(child_pid)
        parent.kill()
        parent.wait(DEADLINE_S)
        _wait_for(f"child {child_pid} ended with its daemon", lambda: _gone(child_pid))
    finally:
        if parent.returncode is None:
            parent.kill()
            parent.wait(DEADLINE_S)
        if child_pid and not _gone(child_pid):
            os.kill(child_pid, signal.SIGKILL)
        if parent.stdout is not None:
            parent.stdout.close()


# The daemon stand-in with a fork server: it starts the server, then changes its environment
# and working folder, starts a child from the server, tells both pids, then waits.
_FORKSERVER_PARENT = """
import os, sys, time
from vgripd.service.host import children
server = children.start_server()
os.environ["VGRIPD_TEST_LATE"] = "set after the fork server started"
os.chdir(sys.argv[2])
setup = children.ChildSetup.here(term_grace_s=60)
proc = children.context().Process(target=exec,
                                  args=(sys.argv[1], {"setup": setup, "out": sys.argv[3]}))
proc.start()
print(proc.pid, server, flush=True)
time.sleep(600)
"""
_FORKSERVER_CHILD = """
import os, time
from vgripd.service.host.children import start_child
start_child(setup)
with open(out + ".tmp", "w") as f:
    f.write(os.environ.get("VGRIPD_TEST_LATE", "-") + "\\n" + os.getcwd())
os.rename(out + ".tmp", out)
time.sleep(600)
"""


def _parent_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def test_a_fork_server_child_takes_the_daemons_state_and_ends_with_it(tmp_path: Path) -> None:
    """A child forked by the fork server takes the environment and working folder the daemon
    has when it starts the child (not those of the server's start); the server outlives the
    SIGTERM systemd sends the whole unit, so the worker is not killed under the daemon that
    stops it in order; and both end when the daemon is SIGKILLed."""
    work = tmp_path / "work"
    work.mkdir()
    out = tmp_path / "child.txt"
    parent = subprocess.Popen(
        [sys.executable, "-c", _FORKSERVER_PARENT, _FORKSERVER_CHILD, str(work), str(out)],
        cwd=REPO, stdout=subprocess.PIPE, text=True)
    child_pid = server_pid = 0
    try:
        assert parent.stdout is not None
        child_pid, server_pid = map(int, parent.stdout.readline().split())
        _wait_for("the child set itself up", out.exists)
        assert out.read_text().splitlines() == ["set after the fork server started", str(work)]
        assert _parent_of(child_pid) == server_pid
        assert _parent_of(server_pid) == parent.pid
        os.kill(server_pid, signal.SIGTERM)  # systemd's stop signals every process of the unit
        time.sleep(0.5)
        assert not _gone(server_pid)
        assert not _gone(child_pid)
        parent.kill()
        parent.wait(DEADLINE_S)
        _wait_for(f"fork server {server_pid} ended with its daemon", lambda: _gone(server_pid))
        _wait_for(f"child {child_pid} ended with its daemon", lambda: _gone(child_pid))
    finally:
        if parent.returncode is None:
            parent.kill()
            parent.wait(DEADLINE_S)
        for pid in (child_pid, server_pid):
            if pid and not _gone(pid):
                os.kill(pid, signal.SIGKILL)
        if parent.stdout is not None:
            parent.stdout.close()


def test_end_process_reaps_a_child_that_ignores_sigterm(tmp_path: Path) -> None:
    ready = tmp_path / "ready"
    code = ("import signal, time\n"
            "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
            f"open({str(ready)!r}, 'w').close()\n"
            "time.sleep(600)\n")
    proc = multiprocessing.get_context("spawn").Process(target=exec, args=(code,))
    proc.start()
    pid = proc.pid
    assert pid is not None
    try:
        _wait_for("the child ignores SIGTERM", ready.exists)
        assert end_process(proc, grace_s=0.5) == -signal.SIGKILL
        assert not Path(f"/proc/{pid}").exists()  # reaped, no zombie left
    finally:
        if not _gone(pid):
            os.kill(pid, signal.SIGKILL)


# The pool's manager thread joins its processes after end_pool ended them: a process object
# closed under it raised in that thread ("process object is closed").
@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_pool_child_is_set_up_and_its_pool_ended_within_the_bound() -> None:
    setup = ChildSetup(os.getpid(), nice_below=3, nice_floor=3)
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                               initializer=start_child, initargs=(setup,))
    try:
        pid = pool.submit(os.getpid).result(DEADLINE_S)
        assert pool.submit(signal.getsignal, signal.SIGINT).result(DEADLINE_S) == signal.SIG_IGN
        assert pool.submit(os.nice, 0).result(DEADLINE_S) == helper_niceness(os.nice(0), 3, 3)
        assert pool.submit(os.sched_getscheduler, 0).result(DEADLINE_S) in (
            os.SCHED_BATCH, os.SCHED_IDLE)
        stuck = pool.submit(time.sleep, 600)
        _wait_for("the call runs", stuck.running)
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    end_pool(pool, grace_s=0.5)
    assert _gone(pid)
    with pytest.raises(BrokenProcessPool):
        stuck.result(DEADLINE_S)
    manager = getattr(pool, "_executor_manager_thread", None)
    assert manager is None or not manager.is_alive()
