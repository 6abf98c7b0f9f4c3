"""The daemon's helper processes, all set up and ended one way.

The children (docs/daemon.md, "Signals and lifetime"):

- the vision worker (``vgripd.service.worker.process``), a long-lived ``multiprocessing``
  spawn of its own; it holds the camera and the recorder, so it gets time to stop in order;
- the web view's JPEG helper (``vgripd.service.web.images``) and the hand-eye walk's board
  finder (``vgripd.service.jobs.walkmode``), one-process ``ProcessPoolExecutor`` pools;
- the UR RTDE link's ur_rtde process (``drivers.links.ur_rtde_worker``), an I/O shell that
  keeps the daemon's priority;
- the vgripd commands the daemon runs in a child (``vgripd.service.host.commands``).

The ``multiprocessing`` children start from one fork server (``context``): it imports numpy,
OpenCV and the children's modules once (``PRELOAD``), and each child is a fork of it, where a
spawned interpreter imported them again at every start (0.5-1 s of CPU, seconds on a busy
core). The fork server's environment and working folder are those of its own start, so a
child takes the daemon's as they are when it is started (``ChildSetup.here``).

Every child calls ``start_child`` first thing (a pool as its initializer), with a
``ChildSetup`` naming what differs between them. What they share: the kernel kills the
child when its parent dies, whatever the cause (``PR_SET_PDEATHSIG``; the fork server ends
with the daemon, ``vgripd.service.host.forkserver``), and one whose parent was gone before it
got there exits at once; SIGINT is ignored (a terminal's Ctrl-C goes to the whole
process group, and the daemon stops its children itself); SIGTERM either ends the child at
once or, for a child that must stop in order, leaves the daemon a grace to do it. A child
doing CPU work drops to ``SCHED_BATCH`` some levels of niceness below the daemon, so the
event loop answering a PLC wins a contested core at once.

Ending a child: ``end_process`` (SIGTERM, a bounded wait, SIGKILL, reaped) for a process,
``end_pool`` for a pool (its processes finish what they hold within a bound, then are ended
the same way; the pool's manager thread is joined). ``wait_exit`` waits for a child's exit
on the event loop, without a thread.

Small and free of heavy imports: the commands' children import it before anything else.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import dataclasses
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import forkserver
from multiprocessing.context import ForkServerContext
from multiprocessing.process import BaseProcess
from typing import Any

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
#: Seconds a killed child gets to be reaped (SIGKILL cannot be caught: microseconds, unless
#: the kernel is stuck in a driver's call).
KILL_REAP_S = 5.0


#: What the fork server imports at its start (``context``): its own set-up first, then the
#: modules of the children it starts (and so numpy, OpenCV, pydantic and the config).
PRELOAD = ("vgripd.service.host.forkserver", "vgripd.service.worker.child",
           "vgripd.service.web.images", "vgripd.calib.boards", "drivers.links.ur_rtde_worker")

_preload_lock = threading.Lock()


def context() -> ForkServerContext:
    """The ``multiprocessing`` context the daemon's children start from: the fork server,
    started at the first child (or ``start_server``) with ``PRELOAD`` imported."""
    with _preload_lock:
        forkserver.set_forkserver_preload(list(PRELOAD))
    return multiprocessing.get_context("forkserver")


_ready_pid: int | None = None  # the fork server known to have imported PRELOAD


def start_server() -> int:
    """Start the fork server unless it runs, and wait until it has imported ``PRELOAD``; its
    pid. A child's start waits as long while the server imports (seconds on a busy machine),
    so the event loop calls this in a thread before it starts a child, which then takes
    milliseconds; once the server is ready this returns at once."""
    global _ready_pid
    pid = server_pid()
    if pid != _ready_pid:
        proc = context().Process(target=int, name="vgripd-forkserver-ready")
        proc.start()
        proc.join()
        _ready_pid = pid
    return pid


def server_pid() -> int:
    """The fork server's pid (started if it was not running): the parent of every child
    started from ``context``."""
    context()
    forkserver.ensure_running()
    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)  # noqa: SLF001
    if not isinstance(pid, int):
        raise RuntimeError("multiprocessing's fork server does not say its pid")
    return pid


@dataclasses.dataclass(frozen=True)
class ChildSetup:
    """What one kind of child sets up on start (``start_child``); picklable, so a started
    child gets it among its arguments."""

    #: The child's parent (the fork server for a child started from ``context``, else the
    #: daemon): the child ends when it does.
    parent_pid: int
    #: Niceness levels below the daemon's (with ``nice_floor``: ``helper_niceness``) and
    #: ``SCHED_BATCH``; None keeps the daemon's priority and policy (a link's I/O).
    nice_below: int | None = None
    nice_floor: int = 0
    #: SIGTERM while the daemon lives: None ends the child at once (the default action);
    #: seconds leave the daemon that long to stop it in order (``end_on_sigterm``).
    term_grace_s: int | None = None
    #: The daemon's log level for the child's own logging (``configure_logging``); None
    #: leaves logging as the interpreter starts it.
    log_level: str | None = None
    #: The environment and working folder the child takes (a fork server's are those of its
    #: own start); None keeps what the child has.
    environ: dict[str, str] | None = None
    cwd: str | None = None
    #: Forked by the fork server (``here``): ``start_child`` lets go of the server's pipe.
    from_server: bool = False

    @classmethod
    def here(cls, **what: Any) -> ChildSetup:
        """The set-up of a child started from ``context`` now: its parent is the fork server,
        and it takes this process's environment and working folder as they are now."""
        return cls(server_pid(), environ=dict(os.environ), cwd=os.getcwd(), from_server=True,
                   **what)


def start_child(setup: ChildSetup) -> None:
    """The set-up every child runs first thing (its initializer)."""
    if setup.from_server:
        let_go_of_server()
    die_with_daemon(setup.parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if setup.term_grace_s is None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    else:
        end_on_sigterm(setup.parent_pid, setup.term_grace_s)
    if setup.environ is not None:
        os.environ.clear()
        os.environ.update(setup.environ)
    if setup.cwd is not None:
        with contextlib.suppress(OSError):  # a folder removed meanwhile: as a spawn would
            os.chdir(setup.cwd)
    if setup.nice_below is not None:
        run_below_daemon(setup.nice_below, setup.nice_floor)
    if setup.log_level is not None:
        from vgripd.service.host.logsetup import configure_logging

        configure_logging(setup.log_level)


def let_go_of_server() -> None:
    """In a child forked by the fork server: close the child's copy of the pipe by which the
    server learns that the daemon is gone. ``multiprocessing`` hands every child one, so that
    the server ends only once all its clients have; but this child ends with the server
    (``die_with_daemon``), so holding it would keep both running after the daemon died."""
    fd = getattr(forkserver._forkserver, "_forkserver_alive_fd", None)  # noqa: SLF001
    if isinstance(fd, int):
        with contextlib.suppress(OSError):
            os.close(fd)
        setattr(forkserver._forkserver, "_forkserver_alive_fd", None)  # noqa: B010, SLF001


def die_with_daemon(parent_pid: int) -> None:
    """Have the kernel SIGKILL this child process when its parent dies (Linux
    ``PR_SET_PDEATHSIG``; elsewhere nothing): the daemon, or the fork server, which ends when
    the daemon does. A parent that died before this call leaves the child re-parented
    already: it exits at once.

    The signal follows the death of the starting *thread*: the fork server has one, and the
    daemon starts its other children from its event loop's thread, which lives as long as the
    daemon serves.
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
    if os.getppid() != parent_pid:
        os._exit(0)


def end_on_sigterm(parent_pid: int, grace_s: int) -> None:
    """SIGTERM handling of a child process: when its parent (and so the daemon) is gone, exit
    now (``finally`` blocks run); while it lives (systemd signalled the whole unit) leave the
    daemon ``grace_s`` to stop this process in order, then the kernel ends it (SIGALRM's
    default action)."""

    def on_term(signum: int, frame: Any) -> None:
        if os.getppid() != parent_pid:
            raise SystemExit(0)
        signal.alarm(grace_s)

    signal.signal(signal.SIGALRM, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, on_term)


def helper_niceness(daemon_nice: int, below: int, floor: int) -> int:
    """The niceness of a helper process of a daemon running at ``daemon_nice``: ``below``
    levels under it, at least ``floor``, at most 19."""
    return min(19, max(daemon_nice + below, floor))


def run_below_daemon(below: int, floor: int) -> None:
    """Make this helper process (CPU work) yield to the daemon's event loop: a real-time
    policy inherited from the daemon (systemd ``CPUSchedulingPolicy=``) is for its event loop
    only, so drop to ``SCHED_BATCH`` (normal time sharing for a CPU-bound task, which never
    preempts a running task when it wakes; ``SCHED_IDLE`` is kept), then lower the priority to
    ``helper_niceness`` of the daemon's (which this process inherited)."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_IDLE:
            os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    inherited = os.getpriority(os.PRIO_PROCESS, 0)
    os.nice(helper_niceness(inherited, below, floor) - inherited)


# --- ending a child ------------------------------------------------------------------------

def end_process(proc: BaseProcess, grace_s: float = 0.0, close: bool = True) -> int | None:
    """End a started child and reap it: SIGTERM and up to ``grace_s`` for it to exit (0: no
    SIGTERM), then SIGKILL; its exit code (None only when even a killed child was not reaped
    within ``KILL_REAP_S``). The process object is closed once reaped, unless ``close`` is
    False (a pool's process: its manager thread still joins it)."""
    if proc.exitcode is None and grace_s > 0:
        with contextlib.suppress(OSError):
            proc.terminate()
        proc.join(grace_s)
    if proc.exitcode is None:
        with contextlib.suppress(OSError):
            proc.kill()
        proc.join(KILL_REAP_S)
    code = proc.exitcode
    if code is not None and close:
        proc.close()
    return code


def end_pool(pool: ProcessPoolExecutor, grace_s: float, cancel_futures: bool = True) -> None:
    """Shut a process pool down, bounded: its processes finish the calls they hold (queued
    ones too unless ``cancel_futures``) within ``grace_s``, are then ended (``end_process``),
    and the pool's manager thread is joined, so neither a process nor the thread outlives
    the call. Blocking: the event loop runs it in a thread."""
    processes: list[BaseProcess] = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=cancel_futures)
    deadline = time.monotonic() + grace_s
    for proc in processes:
        proc.join(max(0.0, deadline - time.monotonic()))
    for proc in processes:
        if proc.exitcode is None:
            log.warning("helper process %s did not finish within %g s: ended", proc.pid,
                        grace_s)
            end_process(proc, 1.0, close=False)
    manager = getattr(pool, "_executor_manager_thread", None)
    if manager is not None:
        # It notices its processes' ends when it next wakes and then cleans up (queues, the
        # feeder thread): seconds on a busy machine, so the rest of the grace, not less than
        # KILL_REAP_S.
        wait_s = max(KILL_REAP_S, deadline - time.monotonic())
        manager.join(wait_s)
        if manager.is_alive():
            log.warning("a helper pool's manager thread still runs %g s after its processes "
                        "were ended", wait_s)


async def wait_exit(proc: BaseProcess, timeout_s: float) -> bool:
    """Wait on the event loop (no thread) until ``proc`` has exited and reap it; False on
    timeout."""
    if proc.exitcode is not None:
        return True
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()
    fd = proc.sentinel

    def resolve() -> None:
        if not done.done():
            done.set_result(None)

    loop.add_reader(fd, resolve)
    try:
        async with asyncio.timeout(timeout_s):
            await done
    except TimeoutError:
        return False
    finally:
        loop.remove_reader(fd)
    # The sentinel closes as the process exits, a moment before it can be reaped: this
    # waitpid returns within microseconds.
    proc.join(1.0)
    return proc.exitcode is not None
