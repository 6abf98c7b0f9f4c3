"""`vgripd demo --link KIND` as a user runs it: the daemon on that link, the link's simulator as
the peer (the robot socket program twin, the mock UR controller with the real ur_rtde client,
snap7's server with a PLC program, asyncua's client). Checked from the printed lines: every
cycle OK, the pose within 0.5 mm / 0.1 deg of the synthetic truth, and the values the peer read
with its own decoding the ones the daemon published."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys

import pytest

from tests.conftest import REPO, lo, need

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]
CYCLES = 3


def demo(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vgripd", "demo", "--cycles", str(CYCLES), "--web-port", "0",
         *args],
        capture_output=True, text=True, cwd=REPO, timeout=280, check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)})


def check_ok_cycles(out: str, fields: int) -> None:
    rows = [line.split() for line in out.splitlines() if re.match(r"\s+\d+\s+[A-Z_]+\s", line)]
    assert [r[1] for r in rows] == ["OK"] * CYCLES, out
    for r in rows:
        assert len(r) == 2 + fields + 3, r  # values, cycle ms, err mm, err deg
        assert float(r[-2]) < 0.5, r
        assert float(r[-1]) < 0.1, r
    m = re.search(r"the peer read the published pose: largest difference (\S+)", out)
    assert m is not None, out
    assert float(m.group(1)) < 1e-3
    assert f"counts: OK {CYCLES}" in out


@pytest.mark.parametrize(("vendor", "fields"), [("kuka", 6), ("abb", 7), ("yaskawa", 6)])
def test_robot_socket_program_twin_locates(vendor: str, fields: int) -> None:
    proc = demo("--link", "robot_socket", "--vendor", vendor)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"the Python twin of the {vendor.upper()} program" in proc.stdout
    check_ok_cycles(proc.stdout, fields)


def test_ur_rtde_mock_controller_runs_the_script_locate() -> None:
    need(importlib.util.find_spec("rtde_control") is not None,
         "needs ur_rtde: pip install -e '.[test]'")
    proc = demo("--link", "ur_rtde", "--peer-host", lo("127.0.30.1"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "x m" in proc.stdout  # the UR convention, whatever --vendor says
    check_ok_cycles(proc.stdout, 6)


def test_s7_plc_program_on_snap7s_server() -> None:
    need(importlib.util.find_spec("snap7") is not None,
         "needs python-snap7: pip install -e '.[test]'")
    proc = demo("--link", "s7")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "S7 client of DB10" in proc.stdout
    check_ok_cycles(proc.stdout, 6)


def test_opcua_client_starts_single_jobs() -> None:
    need(importlib.util.find_spec("asyncua") is not None,
         "needs asyncua: pip install -e '.[test]'")
    proc = demo("--link", "opcua", "--vendor", "fanuc")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "StartSingleJob" in proc.stdout
    check_ok_cycles(proc.stdout, 6)


def test_a_vendor_without_a_robot_program_is_refused_naming_the_brands() -> None:
    proc = demo("--link", "robot_socket", "--vendor", "nachi")
    assert proc.returncode == 2
    assert "abb, fanuc, kuka, staubli, ur, yaskawa" in proc.stdout
