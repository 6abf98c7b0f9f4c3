"""A vgripd command run in a child process by the daemon (the reload's ``vgripd check``, the
web view's ``calibrate handeye plan``, the walk's solve), so that the event loop keeps serving
the PLC while it runs.

Every child is started the same way:

- ``python -I``: isolated, so neither the working directory nor ``PYTHON*`` variables come
  first on ``sys.path`` (a ``tomllib.py`` lying there is not imported); the folder that holds
  the daemon's own ``vgripd`` package is appended, so the child runs the same code;
- in the daemon's own working directory, so that a relative path in the config (a replay
  folder, an include given relative to it) means in the child what it means in the daemon
  (``-I`` keeps that folder off ``sys.path``), and in its own session (its process group is
  killed as one);
- first thing in the child (``child_main``): ``PR_SET_PDEATHSIG`` (the kernel kills it when
  the daemon dies, even by SIGKILL), ``SCHED_BATCH`` and a niceness ``CHILD_NICE_BELOW`` levels
  below the daemon's (at least ``CHILD_NICE_FLOOR``: below the worker and the image helper),
  and a CPU-time limit (``RLIMIT_CPU``) of ``CPU_PER_WALL`` times its time.

Bounded in time: past ``timeout_s`` (or on a cancel) the child's process group is killed and
reaped; past its time the command ends as ``CommandTimeout`` (a ``VgripError`` naming the
command and its limit), which the reload, the plan and the solve answer as a refusal.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import sys
from pathlib import Path

from vgripd.errors import VgripError

#: The child's niceness: this many levels below the daemon's, and at least the floor.
CHILD_NICE_BELOW = 12
CHILD_NICE_FLOOR = 12
#: CPU seconds a child may use per second of its time (the solver's BLAS may use two cores).
CPU_PER_WALL = 2.0
#: Seconds to reap a killed child's process group before its pipes are closed regardless.
REAP_S = 5.0
#: The folder holding the ``vgripd`` package the daemon runs.
PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])
_BOOT = ("import sys; sys.path.append(sys.argv[1]); "
         "from vgripd.service.host.commands import child_main; child_main(sys.argv[2:])")


class CommandTimeout(VgripError):
    """A child command did not finish in its time (it was stopped)."""


def _describe(args: list[str]) -> str:
    """``vgripd calibrate handeye plan``: the command's words before its first option."""
    words = []
    for word in args[:3]:
        if word.startswith("-"):
            break
        words.append(word)
    return "vgripd " + " ".join(words)


def child_main(argv: list[str]) -> None:
    """In the child: ``DAEMON_PID CPU_S VGRIPD_ARGS...``; set up its lifetime and priority,
    then run ``python -m vgripd VGRIPD_ARGS``."""
    import resource
    import runpy

    from vgripd.service.host.children import ChildSetup, start_child

    daemon_pid, cpu_s, args = int(argv[0]), int(argv[1]), argv[2:]
    start_child(ChildSetup(daemon_pid, nice_below=CHILD_NICE_BELOW,
                           nice_floor=CHILD_NICE_FLOOR))
    _soft, hard = resource.getrlimit(resource.RLIMIT_CPU)
    limit = cpu_s if hard == resource.RLIM_INFINITY else min(cpu_s, hard)
    resource.setrlimit(resource.RLIMIT_CPU, (limit, hard))
    sys.argv = ["vgripd", *args]
    runpy.run_module("vgripd", run_name="__main__", alter_sys=True)


def command_line(args: list[str], timeout_s: float) -> list[str]:
    """The child's command line for ``vgripd ARGS`` with ``timeout_s``."""
    cpu_s = max(1, math.ceil(timeout_s * CPU_PER_WALL))
    return [sys.executable, "-I", "-c", _BOOT, PACKAGE_ROOT, str(os.getpid()), str(cpu_s),
            *args]


def _kill_group(proc: asyncio.subprocess.Process) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)


async def run_vgripd(args: list[str], timeout_s: float) -> tuple[int, str, str]:
    """``vgripd ARGS`` in a child with no input: (exit code, stdout, stderr) as text;
    ``CommandTimeout`` after ``timeout_s`` (the child's process group killed). A child ended
    by its CPU limit exits with -SIGXCPU/-SIGKILL, its stderr saying so."""
    proc = await asyncio.create_subprocess_exec(
        *command_line(args, timeout_s), stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=dict(os.environ),
        start_new_session=True)
    timed_out = False
    try:
        try:
            async with asyncio.timeout(timeout_s):
                out, err = await proc.communicate()
        except TimeoutError:
            timed_out = True
    finally:
        if proc.returncode is None or timed_out:
            _kill_group(proc)
            # wait() also waits for the pipes: a grandchild outside the group may hold them
            try:
                async with asyncio.timeout(REAP_S):
                    await proc.wait()
            except TimeoutError:
                transport = getattr(proc, "_transport", None)
                if transport is not None:
                    transport.close()
    if timed_out:
        raise CommandTimeout(f"{_describe(args)}: not done within {timeout_s:g} s: stopped")
    rc = int(proc.returncode or 0)
    text = err.decode(errors="replace")
    if rc in (-signal.SIGXCPU, -signal.SIGKILL) and not text.strip():
        text = (f"{_describe(args)}: ended by signal {-rc} (its CPU limit of "
                f"{math.ceil(timeout_s * CPU_PER_WALL)} s, or killed)")
    return rc, out.decode(errors="replace"), text
