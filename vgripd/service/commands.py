"""A vgripd command run in a child process by the daemon (the reload's ``vgripd check``, the
web view's ``calibrate handeye plan``, the walk's solve), so that the event loop keeps serving
the PLC while it runs. Bounded in time: on the timeout (or a cancel) the child is killed and
reaped before the error goes on.
"""

from __future__ import annotations

import asyncio
import os
import sys

from vgripd.errors import VgripError


class CommandTimeout(VgripError):
    """The command did not finish in its time (it was stopped)."""


async def run_vgripd(args: list[str], timeout_s: float) -> tuple[int, str, str]:
    """``python -m vgripd ARGS`` with no input: (exit code, stdout, stderr) as text;
    ``CommandTimeout`` after ``timeout_s`` (the child killed)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", *args, stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=dict(os.environ))
    try:
        async with asyncio.timeout(timeout_s):
            out, err = await proc.communicate()
    except BaseException as exc:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        if isinstance(exc, TimeoutError):
            raise CommandTimeout(f"vgripd {' '.join(args[:3])}: no answer in {timeout_s:g} s, "
                                 "stopped") from None
        raise
    return int(proc.returncode or 0), out.decode(errors="replace"), err.decode(errors="replace")
