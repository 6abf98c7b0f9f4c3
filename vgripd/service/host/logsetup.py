"""Logging setup of the service, shared by the daemon's process (``vgripd run``, ``vgripd
demo``) and the worker process it starts, so both write the same lines."""

from __future__ import annotations

import logging
import os
import sys


def configure_logging(level: str = "INFO") -> None:
    """One compact line per event on stderr; no timestamps under systemd (journald adds them)."""
    fmt = "%(levelname)s %(name)s: %(message)s"
    if "JOURNAL_STREAM" not in os.environ:
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(stream=sys.stderr, level=level, format=fmt, force=True)
    logging.getLogger("pymodbus").setLevel(max(logging.WARNING, logging.getLevelName(level)))
