"""`vgripd replay` through the real CLI on folders laid out the way cells record them.

The example config (the demo cell, a stereo rig) is copied with its ``[camera]`` section
replaced; the images are the bundled sample pairs (config/samples) under other names. Checks
that the config's ``left_glob``/``right_glob`` are what decide the pairs, that non-images are
skipped, that a corrupt image makes the exit code 1 without stopping the other frames, and that
a folder without pairs is refused with one line naming the folder and the patterns.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from vgripd.__main__ import main

REPO = Path(__file__).resolve().parents[3]
EXAMPLE = REPO / "config" / "example.toml"
SAMPLES = REPO / "config" / "samples"
CAMERA_SECTION = re.compile(r"^\[camera\]\n(?:(?!\[).*\n)*", re.MULTILINE)


def config(tmp_path: Path, camera: str) -> Path:
    """The example config with ``camera`` as its [camera] body."""
    text = EXAMPLE.read_text()
    assert CAMERA_SECTION.search(text)
    text = CAMERA_SECTION.sub(lambda _: f"[camera]\n{camera}\n\n", text, count=1)
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


SCENE_GLOBS = 'type = "replay"\nleft_glob = "scene_*_left.*"\nright_glob = "scene_*_right.*"'


def scene_folder(tmp_path: Path, n: int = 5) -> Path:
    """The samples as scene_000_left.png / scene_000_right.png ... plus their truth.json."""
    folder = tmp_path / "scenes"
    folder.mkdir()
    for i in range(n):
        for side in ("left", "right"):
            shutil.copy(SAMPLES / f"{side}_{i:02d}.png", folder / f"scene_{i:03d}_{side}.png")
    shutil.copy(SAMPLES / "truth.json", folder / "truth.json")
    return folder


def truth_xyz(i: int) -> np.ndarray:
    frames = json.loads((SAMPLES / "truth.json").read_text())
    frame = frames[i] if isinstance(frames, list) else frames["frames"][i]
    return np.asarray(frame["T_base_obj"], float)[:3, 3]


def replay(capsys: pytest.CaptureFixture[str], cfg: Path, folder: Path,
           ) -> tuple[int, list[dict], str]:
    rc = main(["replay", "-c", str(cfg), str(folder)])
    captured = capsys.readouterr()
    return rc, [json.loads(line) for line in captured.out.splitlines()], captured.err


def test_the_configs_globs_pair_scene_files_and_truth_json_is_not_an_image(capsys, tmp_path):
    """The issue's folder: scene_000_left.png ..., truth.json. Before: single-camera mode over
    every file, all NOT_FOUND, truth.json read as an image, exit 0."""
    folder = scene_folder(tmp_path)
    (folder / "scene_index_left.txt").write_text("a note the left glob also matches")
    rc, lines, err = replay(capsys, config(tmp_path, SCENE_GLOBS), folder)
    assert rc == 0, err
    jobs, summary = lines[:-1], lines[-1]["summary"]
    assert [j["source"] for j in jobs] == [f"replay:scene_{i:03d}_left.png" for i in range(5)]
    assert summary["frames"] == summary["pairs"] == 5
    assert summary["unreadable"] == 0
    assert summary["skipped"] == ["scene_index_left.txt"]
    assert "skipped 1 non-image file(s)" in err
    assert "scene_index_left.txt" in err
    assert summary["found"] >= 4
    for i, job in enumerate(jobs):  # stereo poses, each of its own pair
        if job["T_base_obj"] is not None:
            xyz = np.asarray(job["T_base_obj"])[:3, 3]
            assert np.linalg.norm(xyz - truth_xyz(i)) < 0.5, i


def test_a_corrupt_image_is_a_camera_error_line_and_exit_1(capsys, tmp_path):
    folder = scene_folder(tmp_path, 3)
    (folder / "scene_001_right.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    rc, lines, err = replay(capsys, config(tmp_path, SCENE_GLOBS), folder)
    assert rc == 1
    jobs, summary = lines[:-1], lines[-1]["summary"]
    assert [j["status"] == "CAMERA_ERROR" for j in jobs] == [False, True, False]
    assert jobs[1]["source"] == "replay:scene_001_left.png"
    assert "scene_001_right.png (corrupt or unsupported)" in jobs[1]["message"]
    assert (summary["frames"], summary["pairs"], summary["unreadable"]) == (3, 2, 1)
    assert "1 of 3 frame(s)" in err


def test_a_stereo_config_with_only_left_images_is_refused(capsys, tmp_path):
    folder = scene_folder(tmp_path, 2)
    for p in folder.glob("*_right.png"):
        p.unlink()
    rc, lines, err = replay(capsys, config(tmp_path, SCENE_GLOBS), folder)
    assert rc == 1
    assert lines == []
    assert err.count("\n") == 1
    assert (f"stereo layout but no image files match right_glob 'scene_*_right.*' in {folder} "
            "(2 match left_glob 'scene_*_left.*'): no pairs to replay") in err


def test_a_stereo_rig_never_falls_back_to_single_images(capsys, tmp_path):
    """A non-replay camera (defaults left* + right*) and a replay camera with one ``glob``:
    the rig is calibrated, so a folder of single images is refused, not run as PnP."""
    folder = scene_folder(tmp_path, 2)
    rc, lines, err = replay(capsys, config(tmp_path, 'type = "synthetic"'), folder)
    assert rc == 1
    assert lines == []
    assert f"no image files match left_glob 'left*' in {folder}" in err
    rc, lines, err = replay(capsys, config(tmp_path, 'type = "replay"\nglob = "*.png"'), folder)
    assert rc == 1
    assert "calibrates a stereo rig but its [camera] replays single images (glob = '*.png')" in err


def test_an_unpaired_file_is_refused_by_name(capsys, tmp_path):
    folder = scene_folder(tmp_path, 3)
    (folder / "scene_001_right.png").unlink()
    rc, lines, err = replay(capsys, config(tmp_path, SCENE_GLOBS), folder)
    assert rc == 1
    assert lines == []
    assert "2 right images (scene_*_right.*)" in err
    assert "no right image for scene_001_left.png" in err


def test_a_recorded_job_folder_is_replayed_as_recorded(capsys, tmp_path):
    """The recorder writes left.png/right.png/pair.json whatever the camera's globs were."""
    job = tmp_path / "job"
    job.mkdir()
    shutil.copy(SAMPLES / "left_03.png", job / "left.png")
    shutil.copy(SAMPLES / "right_03.png", job / "right.png")
    (job / "pair.json").write_text("{}")
    rc, lines, err = replay(capsys, config(tmp_path, SCENE_GLOBS), job)
    assert rc == 0, err
    assert lines[0]["source"] == "replay:left.png"
    assert lines[-1]["summary"]["frames"] == 1
