"""docs/getting-started.md as a reader runs it: every ```sh block in order, in one bash
session (``set -e``), in an empty folder, with this package's venv first on the PATH (the
install block, marked as not run, is what made that venv). The end: the robot twin's locate
answers OK; and the calibrations the guide made are checked against the learning cell's truth
(the demo cell's cameras and hand-eye, the plate where the camera driver lays it), which the
commands never saw."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, lo
from vgripd.config import Config
from vgripd.geometry.transforms import pose_error
from vgripd.vision.scene import matrix_from_pose

pytestmark = [pytest.mark.timeout(900), pytest.mark.slow(minutes=2)]
NOT_RUN = "<!-- not run by the docs test"


def blocks(text: str) -> list[str]:
    """The ```sh blocks run by the test, in order (a block right after the NOT_RUN comment is
    left out)."""
    out = []
    for m in re.finditer(r"(?P<before>[^\n]*)\n```sh\n(?P<body>.*?)```", text, re.S):
        if not m.group("before").startswith(NOT_RUN):
            out.append(m.group("body"))
    return out


def on_own_address(script: str, address: str) -> str:
    """The guide's commands with one change: the cell's robot socket and web view on this test
    process's own loopback address instead of 127.0.0.1 (two suites on one machine would meet
    on port 50100 and 8730): the main file gets it right after ``vgripd init``, the robot
    twin is told with ``--host``. (The links may sit in an include beside the main file: every
TOML under the cell's folder is moved.)"""
    init = re.search(r"^vgripd init .*-c (\S+).*$", script, re.M)
    assert init is not None, "the guide has no vgripd init line"
    main = init.group(1)
    folder = main.rsplit("/", 1)[0] if "/" in main else "."
    move = (f"find {folder} -name '*.toml' -exec "
            f"sed -i 's/host = \"127.0.0.1\"/host = \"{address}\"/' {{}} +\n"
            f"printf '\\n[status]\\nhost = \"{address}\"\\n' >> {main}")
    script = script[:init.end()] + "\n" + move + script[init.end():]
    twins = script.count("python -m vgripd.sim.robot_twin ")
    assert twins >= 2
    return script.replace("python -m vgripd.sim.robot_twin walk ",
                          f"python -m vgripd.sim.robot_twin walk --host {address} ").replace(
        "python -m vgripd.sim.robot_twin locate ",
        f"python -m vgripd.sim.robot_twin locate --host {address} ")


def run_guide(script: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """The script in its own session, its output in files; when bash ends (or its time is up)
    whatever it left in the background (``vgripd run &``, a walk still waiting for its robot
    after a failed step) is ended with it, so a failing step reports at once."""
    out_file, err_file = cwd / "guide.out", cwd / "guide.err"
    with out_file.open("w") as out, err_file.open("w") as err, \
            subprocess.Popen(["bash", "-c", script], cwd=cwd, env=env, stdout=out, stderr=err,
                             start_new_session=True) as proc:
        try:
            proc.wait(timeout=840)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode,
                                       out_file.read_text(errors="replace"),
                                       err_file.read_text(errors="replace"))


def test_only_the_install_block_is_left_out() -> None:
    text = (REPO / "docs" / "getting-started.md").read_text(encoding="utf-8")
    assert text.count(NOT_RUN) == 1
    assert len(blocks(text)) == text.count("```sh") - 1


def test_the_guide_runs_to_a_first_ok_pick_on_the_learning_cell(tmp_path: Path) -> None:
    text = (REPO / "docs" / "getting-started.md").read_text(encoding="utf-8")
    script = on_own_address("set -e\n" + "\n".join(blocks(text)), lo("127.0.0.1"))
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": bin_dir + os.pathsep + os.environ.get("PATH", ""),
           "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    proc = run_guide(script, tmp_path, env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-6000:]
    assert "refused, exit 78" in out  # the old hand-eye after the new rig
    assert "walk complete: the board is taken off the flange" in out
    locates = re.findall(r"^locate: (\S+) job (\d+) (.*)$", proc.stdout, re.M)
    assert [(s, j) for s, j, _ in locates] == [("OK", "1"), ("OK", "2")], out[-4000:]

    demo = Config()
    assert demo.calibration is not None
    # the hand-eye the walk found, against where the cell's left camera really is
    he = tomllib.loads((tmp_path / "cell/state/handeye.toml").read_text())
    found = matrix_from_pose(Config.model_validate(
        {"calibration": {**demo.calibration.model_dump(mode="json", exclude_none=True),
                         "hand_eye": he["calibration"]["hand_eye"]}}).calibration.hand_eye
        .T_base_camera)
    dt, dr = pose_error(matrix_from_pose(demo.calibration.hand_eye.T_base_camera), found)
    assert dt < 0.5
    assert dr < 0.05
    # the taught plate, against where the camera driver lays it (the demo reference)
    ref = tomllib.loads((tmp_path / "cell/state/reference.toml").read_text())
    taught = np.array(ref["about"]["T_base_obj"])
    assert demo.reference.T_base_obj is not None
    dt, dr = pose_error(matrix_from_pose(demo.reference.T_base_obj), taught)
    assert dt < 0.5
    assert dr < 0.05
    # the offsets of the two picks: the plate has not moved since it was taught
    for _, _, values in locates:
        numbers = [float(v.split("=")[1]) for v in values.split()]
        assert max(abs(v) for v in numbers[:3]) < 0.5
