"""Each command imports only what it needs: ``vgripd --help`` and ``vgripd convert`` do not
load the daemon, aiohttp, OpenCV or pydantic (the start-up figures are in bench/RESULTS.md,
bench/bench_cli_start.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ["aiohttp", "cv2", "pydantic", "scipy", "vgripd.service", "vgripd.config", "vgripd.cli.run"]

PROBE = """
import contextlib, io, json, sys
from vgripd.__main__ import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        rc = main(sys.argv[1:])
    except SystemExit as stop:
        rc = stop.code
print(json.dumps({"rc": rc, "out": out.getvalue(), "modules": sorted(sys.modules)}))
"""


def _run(*argv: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True,
                          timeout=120, check=True)
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.parametrize("argv", [
    ("--help",),
    ("convert", "--from", "kuka", "--to", "abb", "100", "-20", "300", "-90", "45", "-10"),
    ("convert", "--help"),
])
def test_quick_commands_leave_the_heavy_modules_alone(argv: tuple[str, ...]) -> None:
    got = _run(*argv)
    assert got["rc"] == 0
    loaded = [name for name in HEAVY if name in got["modules"]]
    assert loaded == [], f"vgripd {' '.join(argv)} imported {loaded}"


def test_help_still_lists_every_command() -> None:
    from vgripd.__main__ import COMMANDS
    got = _run("--help")
    for name, (_, help_text) in COMMANDS.items():
        assert name in got["out"]
        assert help_text in got["out"]


def test_a_command_still_gets_its_own_arguments() -> None:
    got = _run("convert", "--from", "kuka", "--to", "abb", "100", "-20", "300", "-90", "45",
               "-10")
    assert got["out"].split()[:3] == ["100", "-20", "300"]
    assert "vgripd.geometry.vendors" in got["modules"]
