"""The daemon's start-up heap frozen out of the cyclic collector's way (the poll's p99)."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from vgripd.cli import run as run_cli
from vgripd.service.host.heap import GEN0_THRESHOLD

REPO = Path(__file__).resolve().parents[3]


def test_freeze_moves_the_start_up_heap_out_of_the_collections() -> None:
    # In a process of its own: freezing this test session's heap would change later tests.
    code = ("import gc, vgripd.service.daemon; from vgripd.service.host.heap import "
            "freeze_start_up_heap; n = freeze_start_up_heap(); "
            "print(n, gc.get_freeze_count(), gc.get_threshold()[0])")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout.split()
    frozen, count, gen0 = map(int, out)
    assert frozen == count
    assert frozen > 10_000  # vgripd and its libraries: what a full collection used to walk
    assert gen0 == GEN0_THRESHOLD


def test_vgripd_run_freezes_at_ready_and_in_process_daemons_do_not(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = tmp_path / "vgripd.toml"
    config.write_text('[camera]\ntype = "synthetic"\n\n[daemon]\nworker = false\n')
    seen: list[Any] = []

    def fake_run(coro: Any) -> None:  # the daemon `vgripd run` would serve, not served
        seen.append(coro.cr_frame.f_locals["daemon"])
        coro.close()

    monkeypatch.setattr(run_cli.asyncio, "run", fake_run)
    assert run_cli.run(argparse.Namespace(config=str(config))) == 0
    assert seen[0].freeze_heap_at_ready is True
    assert type(seen[0])(seen[0].config).freeze_heap_at_ready is False
