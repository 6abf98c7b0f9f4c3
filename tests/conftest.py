"""Shared test fixtures.

An autouse fixture fails any test that leaves a thread behind (a leaked supervisor or executor
would keep a real daemon from shutting down).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATASETS = SHARED / "datasets"


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while True:
        leaked = [
            t for t in threading.enumerate()
            if t not in before and t.is_alive() and not t.daemon
        ]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not leaked, f"test leaked threads: {[t.name for t in leaked]}"


@pytest.fixture(scope="session")
def datasets() -> Path:
    """``../shared/datasets`` (CI has it beside the clone); missing is an error, not a skip."""
    assert DATASETS.is_dir(), f"shared datasets not found at {DATASETS}"
    return DATASETS
