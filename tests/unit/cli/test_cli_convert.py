"""``vgripd convert``: in process through ``vgripd.__main__.main`` and as a real subprocess."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vgripd.__main__ import main

REPO = Path(__file__).resolve().parents[3]


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(["convert", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def numbers(line: str) -> np.ndarray:
    return np.array([float(x) for x in line.split()])


def test_kuka_to_ur_and_abb_by_hand(capsys: pytest.CaptureFixture[str]) -> None:
    # Rz(90): UR rotation vector (0, 0, pi/2), metres; ABB q = (cos 45, 0, 0, sin 45).
    rc, out, err = run_cli(capsys, "--from", "kuka", "--to", "ur", "100", "-20", "300", "90", "0", "0")
    assert (rc, err) == (0, "")
    assert len(out.splitlines()) == 1
    assert np.allclose(numbers(out), [0.1, -0.02, 0.3, 0, 0, math.pi / 2], atol=1e-9)
    rc, out, _ = run_cli(capsys, "--from", "kuka", "--to", "abb", "100", "-20", "300", "90", "0", "0")
    assert rc == 0
    assert np.allclose(numbers(out), [100, -20, 300, math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-9)


def test_negative_numbers_need_no_double_dash(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run_cli(capsys, "--from", "kuka", "--to", "fanuc", "100", "-20", "300", "-90", "45", "-10")
    assert (rc, err) == (0, "")
    # FANUC (W, P, R) = KUKA (C, B, A).
    assert np.allclose(numbers(out), [100, -20, 300, -10, 45, -90], atol=1e-9)
    rc, out, err = run_cli(capsys, "--from", "kuka", "--to", "kuka", "-1e-3", "-.5", "-2E+2", "-0.25", "0", "0")
    assert (rc, err) == (0, "")
    assert np.allclose(numbers(out), [-1e-3, -0.5, -200, -0.25, 0, 0], atol=1e-12)


def test_output_round_trips_through_printed_digits(capsys: pytest.CaptureFixture[str]) -> None:
    pose = ["512.125", "-33.5", "1210", "37.25", "-61.5", "122.75"]
    _, abb, _ = run_cli(capsys, "--from", "kuka", "--to", "abb", *pose)
    _, back, _ = run_cli(capsys, "--from", "abb", "--to", "kuka", *abb.split())
    assert np.abs(numbers(back) - numbers(" ".join(pose))).max() < 1e-6


def test_json_output(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, _ = run_cli(capsys, "--from", "kuka", "--to", "ur", "--json", "100", "0", "0", "0", "0", "0")
    assert rc == 0
    assert json.loads(out) == {"vendor": "ur", "fields": ["x", "y", "z", "rx", "ry", "rz"],
                               "values": [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]}


@pytest.mark.parametrize(("argv", "message"), [
    (["--from", "kukka", "--to", "ur", "1", "2", "3", "4", "5", "6"], "unknown vendor convention 'kukka'"),
    (["--from", "kuka", "--to", "urr", "1", "2", "3", "4", "5", "6"], "unknown vendor convention 'urr'"),
    (["--from", "kuka", "--to", "ur", "1", "2", "3", "4", "5"], "expected 6 values (X Y Z A B C), got 5"),
    (["--from", "kuka", "--to", "ur", "1", "2", "3", "4", "5", "six"], "C = 'six' is not a number"),
    (["--from", "abb", "--to", "kuka", "0", "0", "0", "0.5", "0.5", "0.5", "0.6"], "not unit length"),
    (["--from", "kuka", "--to", "ur", "1", "2", "3", "nan", "5", "6"], "A = 'nan' is not finite"),
])
def test_bad_input_is_one_line_on_stderr_and_exit_2(capsys: pytest.CaptureFixture[str], argv: list[str],
                                                    message: str) -> None:
    rc, out, err = run_cli(capsys, *argv)
    assert rc == 2
    assert out == ""
    assert len(err.strip().splitlines()) == 1
    assert message in err


def test_batch_from_stdin(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    text = "# KUKA poses\n100 -20 300 90 0 0\n\n  1, 2, 3, 0, 90, 0\n"
    monkeypatch.setattr(sys, "stdin", io.StringIO(text))
    rc, out, err = run_cli(capsys, "--from", "kuka", "--to", "ur")
    assert (rc, err) == (0, "")
    lines = out.splitlines()
    assert len(lines) == 2
    assert np.allclose(numbers(lines[0]), [0.1, -0.02, 0.3, 0, 0, math.pi / 2], atol=1e-9)
    assert np.allclose(numbers(lines[1]), [0.001, 0.002, 0.003, 0, math.pi / 2, 0], atol=1e-9)


def test_batch_error_names_the_line(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "stdin", io.StringIO("1 2 3 0 0 0\n# comment\n1 2 3 0 0\n"))
    rc, out, err = run_cli(capsys, "--from", "kuka", "--to", "abb")
    assert rc == 2
    assert len(out.splitlines()) == 1
    assert "stdin line 3" in err
    assert "expected 6 values" in err


def test_subprocess_args_stdin_and_errors() -> None:
    cmd = [sys.executable, "-m", "vgripd", "convert"]
    done = subprocess.run([*cmd, "--from", "kuka", "--to", "abb", "100", "-20", "300", "-90", "45", "-10"],
                          cwd=REPO, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    q = numbers(done.stdout)[3:]
    assert abs(np.linalg.norm(q) - 1) < 1e-8
    assert q[0] >= 0
    done = subprocess.run([*cmd, "--from", "ur", "--to", "kuka", "--json"], input="0.1 0 0 0 0 3.14159265358979\n",
                          cwd=REPO, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    obj = json.loads(done.stdout)
    assert obj["fields"] == ["X", "Y", "Z", "A", "B", "C"]
    assert np.allclose(np.abs(obj["values"]), [100, 0, 0, 180, 0, 0], atol=1e-6)
    done = subprocess.run([*cmd, "--from", "nope", "--to", "kuka", "1"], cwd=REPO, capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert "unknown vendor convention 'nope'" in done.stderr
