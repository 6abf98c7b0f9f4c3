"""A vgripd command run in a child process by the daemon (the reload's ``vgripd check``, the
web view's ``calibrate handeye plan``, the walk's solve), so that the event loop keeps serving
the PLC while it runs. Bounded in time: on the timeout (or a cancel) the child is killed and
reaped before the error goes on.
"""

from __future__ import annotations

import asyncio
import os
import sys


async def run_vgripd(args: list[str], timeout_s: float) -> tuple[int, str, str]:
    """``python -m vgripd ARGS`` with no input: (exit code, stdout, stderr) as text;
    ``TimeoutError`` after ``timeout_s`` (the child killed)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", *args, stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=dict(os.environ))
    try:
        async with asyncio.timeout(timeout_s):
            out, err = await proc.communicate()
    except BaseException:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        raise
    return int(proc.returncode or 0), out.decode(errors="replace"), err.decode(errors="replace")
