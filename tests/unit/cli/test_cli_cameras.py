"""`vgripd cameras` and `vgripd cameras grab` as processes, on pylon's camera emulation and
Aravis' fake GigE camera."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO, need
from tests.drivers.cameras.test_cameras_aravis import FakeCamera, one_fake
from vgripd.cli.cameras import parse_sets, parse_value
from vgripd.errors import ConfigError

LEFT = REPO / "config" / "samples" / "left_00.png"
FEED = ["--set", "TestImageSelector=Off", "--set", "ImageFileMode=On",
        "--set", f"ImageFilename={LEFT}", "--set", "Width=1280", "--set", "Height=1024"]


def vgripd(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYLON_CAMEMU": "2"}
    return subprocess.run([sys.executable, "-W", "ignore", "-m", "vgripd", *args],
                          capture_output=True, text=True, cwd=REPO, env=env, timeout=120,
                          check=False)


@pytest.fixture
def pylon() -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")


@pytest.fixture
def fake() -> Iterator[FakeCamera]:
    with one_fake() as camera:
        yield camera


def test_set_values_take_the_devices_types() -> None:
    assert parse_value("true") is True
    assert parse_value("12") == 12
    assert parse_value("2.5") == 2.5
    assert parse_value("/x/y.png") == "/x/y.png"
    assert parse_sets(["Gain=3", "PixelFormat=Mono12"]) == {"Gain": 3, "PixelFormat": "Mono12"}
    with pytest.raises(ConfigError, match="--set 'Gain': expected FEATURE=VALUE"):
        parse_sets(["Gain"])


def test_the_list_names_each_stacks_cameras(pylon: None, fake: FakeCamera) -> None:
    proc = vgripd("cameras")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert "pylon\tserial 0815-0000\tBasler Emulation\t-\t-" in lines
    assert "pylon\tserial 0815-0001\tBasler Emulation\t-\t-" in lines
    assert "aravis\tserial GV01\tAravis Fake\t127.0.0.1\tAravis-Fake-GV01" in lines


def test_grab_writes_the_frame_the_camera_delivers(pylon: None, tmp_path: Path) -> None:
    out = tmp_path / "aim.png"
    proc = vgripd("cameras", "grab", "0815-0001", "-o", str(out), *FEED, "--count", "3")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"wrote {out}: 1280x1024 from pylon camera 0815-0001 Mono8, ")
    assert "frames/s over 3" in proc.stdout
    np.testing.assert_array_equal(cv2.imread(str(out), cv2.IMREAD_GRAYSCALE),
                                  cv2.imread(str(LEFT), cv2.IMREAD_GRAYSCALE))


def test_grab_refuses_a_setting_out_of_the_devices_range(pylon: None, tmp_path: Path) -> None:
    proc = vgripd("cameras", "grab", "0815-0000", "-o", str(tmp_path / "x.png"),
                  "--set", "Gain=99")
    assert proc.returncode == 1
    assert ("camera 0815-0000 (Basler Emulation, serial 0815-0000): Gain = 99 is out of the "
            "device's range 0 .. 48") in proc.stderr
    assert not (tmp_path / "x.png").exists()


def test_grab_uses_a_configs_camera_by_its_name(pylon: None, tmp_path: Path) -> None:
    cfg = tmp_path / "cell.toml"
    cfg.write_text(f"""[camera]
type = "pylon"
roi = {{ width = 1280, height = 1024 }}
pixel_format = "Mono12"
trigger = "hardware"
[[camera.cameras]]
name = "top"
serial = "0815-0001"
features = {{ TestImageSelector = "Off", ImageFileMode = "On", ImageFilename = "{LEFT}" }}
""")
    out = tmp_path / "top.png"
    proc = vgripd("cameras", "grab", "top", "-c", str(cfg), "-o", str(out))
    assert proc.returncode == 0, proc.stderr  # a software trigger although the cell's is hardware
    assert proc.stdout.startswith(f"wrote {out}: 1280x1024 from pylon camera top Mono12")
    np.testing.assert_array_equal(cv2.imread(str(out), cv2.IMREAD_GRAYSCALE),
                                  cv2.imread(str(LEFT), cv2.IMREAD_GRAYSCALE))


def test_grab_of_a_camera_nobody_has(fake: FakeCamera, tmp_path: Path) -> None:
    proc = vgripd("cameras", "grab", "GV07", "--stack", "aravis", "-o", str(tmp_path / "x.png"))
    assert proc.returncode == 1
    assert "no camera 'GV07' (found: aravis: Aravis Fake, serial GV01, 127.0.0.1)" in proc.stderr


def test_grab_from_the_fake_gige_camera_by_ip(fake: FakeCamera, tmp_path: Path) -> None:
    out = tmp_path / "gige.png"
    proc = vgripd("cameras", "grab", "127.0.0.1", "--stack", "aravis", "-o", str(out),
                  "--set", "PixelFormat=BayerGR8")
    assert proc.returncode == 0, proc.stderr
    assert "512x512 from aravis camera 127.0.0.1 BayerGR8" in proc.stdout
    assert cv2.imread(str(out), cv2.IMREAD_UNCHANGED).shape == (512, 512)


def test_grab_of_a_name_the_replay_config_does_not_have_says_its_camera_type(
        pylon: None, tmp_path: Path) -> None:
    proc = vgripd("cameras", "grab", "left", "--stack", "pylon", "-c", "config/example.toml",
                  "-o", str(tmp_path / "x.png"))
    assert proc.returncode == 1
    assert "no camera 'left' (found: pylon: " in proc.stderr
    assert "config/example.toml: camera.type = 'replay', not a pylon or aravis camera" in proc.stderr


def test_grab_of_a_name_the_config_does_not_have_lists_the_configs_names(
        pylon: None, tmp_path: Path) -> None:
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[camera]\ntype = "pylon"\n[[camera.cameras]]\nname = "top"\n'
                   'serial = "0815-0001"\n')
    proc = vgripd("cameras", "grab", "side", "--stack", "pylon", "-c", str(cfg),
                  "-o", str(tmp_path / "x.png"))
    assert proc.returncode == 1
    assert f"{cfg} names the cameras top" in proc.stderr


def test_the_missing_aravis_message_names_the_whole_install() -> None:
    """What docs/cameras.md installs for the aravis driver, the driver's error names too."""
    import re

    from drivers.cameras.aravis import MISSING

    docs = (REPO / "docs" / "cameras.md").read_text()
    block = docs[docs.index("apt-get install", docs.index("## Industrial cameras")):]
    packages = re.findall(r"[\w.+-]+", block.split("#", 1)[0].split("install", 1)[1])
    packages = [p for p in packages if p != "aravis-tools"]  # optional on a cell (the docs)
    assert "gir1.2-aravis-0.8" in packages
    missing = [p for p in packages if p not in MISSING]
    assert not missing, missing
    assert "vgripd[aravis]" in MISSING
