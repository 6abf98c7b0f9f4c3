"""`vgripd demo` end to end as a user runs it: daemon, synthetic camera, mock PLC over TCP."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from tests.conftest import REPO


def test_demo_runs_cycles_with_a_busy_refusal_a_gated_fault_and_small_pose_errors() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "vgripd", "demo", "--cycles", "4", "--port", "0",
         "--vendor", "abb"],
        capture_output=True, text=True, cwd=REPO, timeout=300, check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)})
    out = proc.stdout
    assert proc.returncode == 0, out + proc.stderr
    assert "q1" in out  # ABB quaternion fields in the header
    rows = [line.split() for line in out.splitlines() if re.match(r"\s+\d+\s+[A-Z_]+\s", line)]
    assert [r[1] for r in rows] == ["OK", "OK", "OK", "BUSY", "OK", "OUT_OF_LIMITS"]
    assert [int(r[0]) for r in rows] == [1, 2, 3, 4, 5, 1]  # the fault runs on a new daemon
    assert "(no pose: offset translation" in out
    for r in rows:
        if r[1] == "OK":
            # x y z q1..q4, cycle ms, err mm, err deg
            assert len(r) == 2 + 7 + 3
            q = [float(v) for v in r[5:9]]
            assert abs(sum(v * v for v in q) - 1.0) < 1e-3
            assert float(r[-2]) < 0.5
            assert float(r[-1]) < 0.1
    assert "counts: BUSY 1, OK 4, OUT_OF_LIMITS 1" in out
    m = re.search(r"pose error vs synthetic truth: max ([\d.]+) mm", out)
    assert m is not None
    assert float(m.group(1)) < 0.5
