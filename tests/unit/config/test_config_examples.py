"""config/examples/: a config for every camera type and link, each accepted by ``vgripd check``
(the camera examples also on the devices they name: pylon's camera emulation and Aravis' fake
GigE cameras), and the README's ``robot-program`` and ``s7-udt`` lines run as written."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import re
import shlex
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO, need, need_camera_sdk
from vgripd.__main__ import main
from vgripd.peer.socket_frames import BRANDS

EXAMPLES = REPO / "config" / "examples"
FILES = sorted(EXAMPLES.glob("*.toml"))
#: The links and cameras an integrator starts from; each has an example.
LINKS = {"modbus_server", "modbus_rtu", "ur_rtde", "s7", "opcua", "robot_socket"}
CAMERAS = {"pylon", "aravis", "synthetic"}


def _check(path: Path, *extra: str) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["check", "-c", str(path), *extra])
    return rc, out.getvalue() + err.getvalue()


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_every_example_passes_check(path: Path) -> None:
    # The devices of the camera examples are judged below, on their emulations.
    need_camera_sdk(path)
    rc, text = _check(path, "--no-camera")
    assert rc == 0, text
    assert text.startswith(f"OK {path}"), text


def test_every_camera_type_and_link_has_an_example() -> None:
    data = {p.name: tomllib.loads(p.read_text()) for p in FILES}
    links = {link["type"] for d in data.values() for link in d.get("links", [])}
    assert links >= LINKS, LINKS - links
    assert {d["camera"]["type"] for d in data.values()} >= CAMERAS
    assert any(len(d.get("calibration", {}).get("cameras", [])) > 2 for d in data.values())
    for brand in BRANDS:  # one robot socket example per brand of `vgripd robot-program`
        d = data.get(f"robot-socket-{brand}.toml")
        assert d is not None, f"no config/examples/robot-socket-{brand}.toml"
        assert d["output"]["vendor"] == BRANDS[brand].convention
        assert [link["type"] for link in d["links"]] == ["robot_socket"]


def test_the_examples_readme_lists_every_example() -> None:
    text = (EXAMPLES / "README.md").read_text()
    for path in FILES:
        stem = path.stem.removeprefix("robot-socket-")
        assert path.name in text or f"-{stem}" in text, path.name


@pytest.mark.parametrize("brand", sorted(BRANDS))
def test_robot_program_from_each_brands_example(brand: str, tmp_path: Path) -> None:
    out = tmp_path / brand
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["robot-program", "--brand", brand, "-c",
                   str(EXAMPLES / f"robot-socket-{brand}.toml"), "-o", str(out),
                   "--host", "192.168.1.20"])
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(BRANDS[brand].files)
    assert all("@@" not in p.read_text() for p in out.iterdir())


def _readme_lines(command: str) -> list[str]:
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, re.S)
    return [line for block in blocks for line in block.splitlines()
            if line.startswith(f".venv/bin/vgripd {command} ")]


@pytest.mark.parametrize("command", ["robot-program", "s7-udt"])
def test_readme_lines_run_as_written(command: str, tmp_path: Path) -> None:
    lines = _readme_lines(command)
    assert lines, f"README shows no `.venv/bin/vgripd {command}` line"
    for line in lines:
        argv = shlex.split(line)[1:]
        # an output folder under /tmp goes to this test's own folder instead
        argv = [str(tmp_path / Path(a).name) if a.startswith("/tmp/") else a for a in argv]
        proc = subprocess.run([sys.executable, "-m", "vgripd", *argv], cwd=REPO,
                              capture_output=True, text=True, timeout=120, check=False)
        assert proc.returncode == 0, f"{line}\n{proc.stderr}"
        assert proc.stdout.strip(), line


def test_pylon_example_on_pylons_camera_emulation() -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")
    path = EXAMPLES / "pylon-stereo.toml"
    env = {**os.environ, "PYLON_CAMEMU": "2"}
    proc = subprocess.run([sys.executable, "-m", "vgripd", "check", "-c", str(path)],
                          env=env, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"OK {path}: camera pylon"), proc.stdout


@pytest.fixture
def fake_gige() -> Iterator[None]:
    from tests.drivers.cameras.test_cameras_aravis import two_fake_cameras

    with two_fake_cameras():
        yield


def test_aravis_example_on_aravis_fake_cameras(fake_gige: None) -> None:
    path = EXAMPLES / "aravis.toml"
    proc = subprocess.run([sys.executable, "-m", "vgripd", "check", "-c", str(path)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"OK {path}: camera aravis"), proc.stdout
