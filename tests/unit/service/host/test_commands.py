"""The daemon's vgripd child commands (``vgripd.service.host.commands``): the exit code and output
come back; the child is isolated from the daemon's working directory; a command past its time
is stopped (its whole process group) and named, so that a reload, a plan or a solve ends as a
refusal with that reason."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from vgripd.__main__ import EXIT_CONFIG
from vgripd.service.host.commands import CommandTimeout, run_vgripd


def _processes_with(marker: str) -> list[int]:
    found = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                cmdline = Path(entry.path, "cmdline").read_bytes()
            except OSError:
                continue
            if marker.encode() in cmdline:
                found.append(int(entry.name))
    return found


async def test_a_command_gives_its_exit_code_and_output(tmp_path: Path) -> None:
    missing = tmp_path / "missing.toml"
    rc, out, err = await run_vgripd(["check", "-c", str(missing)], 120.0)
    assert rc == EXIT_CONFIG
    assert "missing.toml" in out + err


async def test_the_daemons_working_directory_is_not_on_the_childs_path(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    planted = tmp_path / "planted"
    (tmp_path / "tomllib.py").write_text(
        f"open({str(planted)!r}, 'w').close()\nraise SystemExit(99)\n")
    monkeypatch.chdir(tmp_path)
    rc, out, err = await run_vgripd(["check", "-c", str(tmp_path / "missing.toml")], 120.0)
    assert not planted.exists()
    assert rc == EXIT_CONFIG, out + err


async def test_a_command_past_its_time_is_stopped_and_named(tmp_path: Path) -> None:
    marker = str(tmp_path / "x.toml")
    # an interpreter that imports vgripd takes far longer than 10 ms
    with pytest.raises(CommandTimeout, match=r"vgripd check: not done within 0.01 s: stopped"):
        await run_vgripd(["check", "-c", marker], 0.01)
    deadline = time.monotonic() + 30.0
    while _processes_with(marker) and time.monotonic() < deadline:  # noqa: ASYNC110
        time.sleep(0.05)  # noqa: ASYNC251 (reaped already; this only confirms it)
    assert not _processes_with(marker)
