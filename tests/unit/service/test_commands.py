"""The daemon's vgripd child commands (``vgripd.service.commands``): the exit code and output
come back; a command past its time is killed and named (a reload, a plan or a solve then
ends refused with that reason instead of an internal error)."""

from __future__ import annotations

from pathlib import Path

import pytest

from vgripd.__main__ import EXIT_CONFIG
from vgripd.service.commands import CommandTimeout, run_vgripd


async def test_a_command_gives_its_exit_code_and_output(tmp_path: Path) -> None:
    missing = tmp_path / "missing.toml"
    rc, out, err = await run_vgripd(["check", "-c", str(missing)], 120.0)
    assert rc == EXIT_CONFIG
    assert "missing.toml" in out + err


async def test_a_command_past_its_time_is_stopped_and_named(tmp_path: Path) -> None:
    # no Python interpreter starts within a microsecond: the deadline always passes first
    with pytest.raises(CommandTimeout, match="vgripd check -c"):
        await run_vgripd(["check", "-c", str(tmp_path / "x.toml")], 1e-6)
