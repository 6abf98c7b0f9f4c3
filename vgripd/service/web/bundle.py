"""The support bundle's zip (``GET /api/support-bundle``), built off the event loop.

Beside the parts the view hands in (redacted config, status, history, metrics, log lines) it takes
the last recorded jobs, and reads from the recording folder only what the recorder writes
(``vgripd.service.worker.recorder``): job folders named ``<date>-<time>.<ms>-job<id>``, in each
``left.png``, ``right.png``, ``view<j>.png``, ``pair.json`` and ``result.json``. Nothing else is
read, and no symbolic link is followed: each folder and file is opened relative to its parent with
``O_NOFOLLOW`` and must be a directory or a regular file, so a link planted in the
folder (to a private key, a password file, a FIFO) is left out. The JSON files pass through the
redaction again (a recording made by an older version may hold a camera URL's password); the
recorded ``config.toml`` is left out, the bundle's own is at the top.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import tempfile
import zipfile
from pathlib import Path
from typing import IO

from vgripd.redaction import redact

JOB_FOLDER = re.compile(r"\d{8}-\d{6}\.\d{3}-job\d{6,}")
JOB_FILE = re.compile(r"(left|right|view\d{1,3})\.png|pair\.json|result\.json")
# A recorded image is a few megabytes; anything far larger is not one the recorder wrote.
MAX_FILE_BYTES = 256 << 20
_NOFOLLOW = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)


def _open(name: str, dir_fd: int | None, directory: bool, follow: bool = False) -> int | None:
    """A descriptor of ``name`` (in ``dir_fd``) if it is a directory / regular file and not a
    link (unless ``follow``); None otherwise."""
    flags = (os.O_RDONLY if follow else _NOFOLLOW) | (
        getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(name, flags, dir_fd=dir_fd)
    except OSError:  # ELOOP: a symbolic link; gone; not readable
        return None
    mode = os.fstat(fd).st_mode
    if stat.S_ISDIR(mode) if directory else stat.S_ISREG(mode):
        return fd
    os.close(fd)
    return None


def _read(name: str, dir_fd: int) -> bytes | None:
    fd = _open(name, dir_fd, directory=False)
    if fd is None:
        return None
    with os.fdopen(fd, "rb") as f:
        if os.fstat(f.fileno()).st_size > MAX_FILE_BYTES:
            return None
        return f.read(MAX_FILE_BYTES)


def _job_files(folder_fd: int) -> dict[str, bytes]:
    files: dict[str, bytes] = {}
    for name in sorted(os.listdir(folder_fd)):
        if not JOB_FILE.fullmatch(name):
            continue
        data = _read(name, folder_fd)
        if data is None:
            continue
        if name.endswith(".json"):
            try:
                data = json.dumps(redact(json.loads(data)), indent=2).encode()
            except ValueError:
                continue
        files[name] = data
    return files


def write_bundle(parts: dict[str, str], recorded: Path | None, n_jobs: int) -> IO[bytes]:
    """The support bundle as a zip in an anonymous temporary file (read from the start)."""
    file = tempfile.TemporaryFile()  # noqa: SIM115 (returned open, closed by the caller)
    with zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED) as z:
        for name, text in parts.items():
            z.writestr(name, text)
        if recorded is not None and n_jobs:
            # The configured folder itself may be reached through a link (systemd's
            # DynamicUser state directory is one); what is inside it is not followed.
            root = _open(str(recorded), None, directory=True, follow=True)
            if root is not None:
                try:
                    _add_jobs(z, root, n_jobs)
                finally:
                    os.close(root)
    file.seek(0)
    return file


def _add_jobs(z: zipfile.ZipFile, root: int, n_jobs: int) -> None:
    with contextlib.suppress(OSError):
        names = sorted(n for n in os.listdir(root) if JOB_FOLDER.fullmatch(n))
        for job in names[-n_jobs:]:
            fd = _open(job, root, directory=True)
            if fd is None:
                continue
            try:
                for name, data in _job_files(fd).items():
                    # PNGs are compressed already.
                    kind = zipfile.ZIP_STORED if name.endswith(".png") else zipfile.ZIP_DEFLATED
                    z.writestr(f"jobs/{job}/{name}", data, compress_type=kind)
            finally:
                os.close(fd)
