"""`vgripd check` commissions the cell (docs/daemon.md, "vgripd check"): the taught reference is
projected through each camera, the replay folder, the links and the listening ports are checked.
An ERROR exits 78 naming the config key to fix; WARNINGs follow the OK line with exit 0.

Every case is config/example.toml with one change, run from the repository root (its replay
folder config/samples is relative to the working directory).
"""

from __future__ import annotations

import re
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO
from vgripd.__main__ import EXIT_CONFIG, main
from vgripd.geometry.transforms import (
    invert_transform,
    make_transform,
    matrix_from_rotvec,
    rotvec_from_matrix,
)

EXAMPLE = (REPO / "config" / "example.toml").read_text()
HAND_EYE = "T_base_camera = { translation_mm = [525.0, 100.0, 700.0], rotvec_rad = [3.13729, 0.0, 0.16442] }"
REFERENCE = "[reference.T_base_obj]\ntranslation_mm = [600.0, 100.0, 10.0]\nrotvec_rad = [0.0, 0.0, 0.05]"
LINK = re.compile(r'^\[\[links\]\]\ntype = "modbus_server"\n(?:[^\n]+\n)*', re.MULTILINE)


@pytest.fixture(autouse=True)
def _repo_root(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)


def variant(tmp_path: Path, old: str, new: str) -> Path:
    assert EXAMPLE.count(old) == 1, old
    path = tmp_path / "vgripd.toml"
    path.write_text(EXAMPLE.replace(old, new))
    return path


def check(path: Path, capsys: pytest.CaptureFixture[str], *flags: str) -> tuple[int, str, str]:
    rc = main(["check", "-c", str(path), *flags])
    out = capsys.readouterr()
    return rc, out.out, out.err


def inverted(translation: list[float], rotvec: list[float]) -> tuple[list[float], list[float]]:
    T = invert_transform(make_transform(matrix_from_rotvec(np.array(rotvec)),
                                        np.array(translation)))
    return T[:3, 3].round(4).tolist(), rotvec_from_matrix(T[:3, :3]).round(6).tolist()


def test_the_example_config_passes_every_check(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = check(REPO / "config" / "example.toml", capsys)
    assert rc == 0, err
    assert out.startswith("OK ")
    # Ports may be taken by someone else's daemon on this machine: only a warning, never about
    # the scene, the replay folder or the links.
    assert all(".port:" in line for line in out.splitlines()[1:]), out


def test_an_inverted_hand_eye_is_an_error_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t, r = inverted([525.0, 100.0, 700.0], [3.13729, 0.0, 0.16442])
    cfg = variant(tmp_path, HAND_EYE, f"T_base_camera = {{ translation_mm = {t}, rotvec_rad = {r} }}")
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    first = err.splitlines()[0]
    assert first.startswith(f"vgripd: config error: {cfg}: calibration.hand_eye: looks inverted: ")
    assert "6 of 6 marks project outside the left image (1280x1024)" in first
    assert "with the transform inverted all 6 marks would be in front of the cameras, inside " \
           "both images" in first
    assert "reference.T_base_obj: looks inverted" not in err
    assert "only 0 of 6 marks can be found in both images, a pose needs 4" in err


def test_an_inverted_reference_pose_is_an_error_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t, r = inverted([600.0, 100.0, 10.0], [0.0, 0.0, 0.05])
    cfg = variant(tmp_path, REFERENCE,
                  f"[reference.T_base_obj]\ntranslation_mm = {t}\nrotvec_rad = {r}")
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert f"{cfg}: reference.T_base_obj: looks inverted: " in err
    assert "calibration.hand_eye: looks inverted" not in err


def test_a_camera_behind_the_object_is_named(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The camera 700 mm below the plate, still looking down: everything is behind it.
    cfg = variant(tmp_path, HAND_EYE, HAND_EYE.replace("700.0]", "-700.0]"))
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert re.search(r"calibration\.hand_eye: 6 of 6 marks are behind the left camera \(m\d "
                     r"7\d\d mm behind it\)", err), err


def test_marks_outside_the_image(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Taught 180 mm further along base y: half the plate leaves the top of both images.
    cfg = variant(tmp_path, REFERENCE, REFERENCE.replace("100.0, 10.0", "280.0, 10.0"))
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert re.search(r"reference\.T_base_obj: 3 of 6 marks project outside the left image "
                     r"\(1280x1024\): m\d to \(\d+, -\d+\) px", err), err
    assert "vision.min_features: only 3 of 6 marks can be found in both images, a pose needs 4" \
        in err
    # Two marks fewer needed: the same scene works, with a warning.
    cfg = variant(tmp_path, "min_features = 4 ", "min_features = 3 ")
    cfg.write_text(cfg.read_text().replace(REFERENCE, REFERENCE.replace("100.0, 10.0",
                                                                        "280.0, 10.0")))
    rc, out, err = check(cfg, capsys)
    assert rc == 0, err
    assert f"warning: {cfg}: reference.T_base_obj: 3 of 6 marks project outside the left" in out


@pytest.mark.parametrize(("working", "searched"), [("[300.0, 500.0]", "36.1-60.2"),
                                                    ("[800.0, 2000.0]", "9.0-22.6")])
def test_marks_the_finder_does_not_search_for(
        working: str, searched: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    cfg = variant(tmp_path, "working_distance_mm = [300.0, 2000.0]",
                  f"working_distance_mm = {working}")
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert re.search(rf"vision\.working_distance_mm: 6 marks \(m1, m2, m3, m4 and 2 more\) are "
                     rf"2\d\.\d-2\d\.\d px across in the left image, the finder searches "
                     rf"{searched} px", err), err
    assert "from the left camera, outside vision.working_distance_mm" in err


def test_a_missing_replay_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = variant(tmp_path, 'folder = "config/samples"', 'folder = "config/no-such-folder"')
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert f"{cfg}: camera.folder: replay folder config/no-such-folder does not exist" in err


def test_a_replay_folder_without_pairs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    shutil.copy(REPO / "config" / "samples" / "left_00.png", folder)
    cfg = variant(tmp_path, 'folder = "config/samples"', f'folder = "{folder}"')
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert f"{cfg}: camera.left_glob: replay: stereo layout but no image files match " \
           "right_glob" in err


def test_replay_frames_of_another_size(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    for side in ("left", "right"):
        cv2.imwrite(str(folder / f"{side}_00.png"), np.zeros((480, 640), np.uint8))
    cfg = variant(tmp_path, 'folder = "config/samples"', f'folder = "{folder}"')
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert "calibration.left.width: " in err
    assert "is 640x480 but calibration.left is 1280x1024: every job would end with " \
           "CAMERA_ERROR" in err


def test_a_port_in_use_is_a_warning(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        cfg = variant(tmp_path, "port = 1502", f"port = {port}")
        rc, out, err = check(cfg, capsys)
        assert rc == 0, err
        assert out.startswith(f"OK {cfg}")
        assert (f"warning: {cfg}: links[0].port: 127.0.0.1:{port} is in use: is vgripd already "
                "running?") in out
        rc, out, _ = check(cfg, capsys, "--running")
        assert rc == 0
        assert "is in use" not in out
        assert "port checks skipped (--running" in out


def test_two_listeners_on_one_port(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = variant(tmp_path, "port = 1502", "port = 8730")
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert "status.port: 127.0.0.1:8730 is also where links[0] listens" in err


def test_an_address_of_another_machine(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = variant(tmp_path, 'host = "127.0.0.1"            # "0.0.0.0"',
                  'host = "192.0.2.1"            # "0.0.0.0"')
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert "links[0].host: cannot listen on 192.0.2.1:1502" in err


def test_no_links(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    block = LINK.search(EXAMPLE)
    assert block is not None
    cfg = variant(tmp_path, block.group(0), "")
    rc, _, err = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert f"{cfg}: links: no [[links]]: no robot or PLC can trigger a job" in err
    rc, out, _ = check(cfg, capsys, "--no-links-ok")
    assert rc == 0
    assert "note: " in out
