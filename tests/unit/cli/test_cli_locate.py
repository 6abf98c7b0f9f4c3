"""`vgripd locate` and `vgripd replay` on the bundled sample pairs, and every config in config/."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO
from vgripd.__main__ import EXIT_CONFIG, main
from vgripd.config import load_config
from vgripd.geometry.transforms import pose_error

SAMPLES = REPO / "config" / "samples"
EXAMPLE = REPO / "config" / "example.toml"
CONFIGS = sorted((REPO / "config").glob("*.toml"))


def truth(frame: int) -> np.ndarray:
    data = json.loads((SAMPLES / "truth.json").read_text())
    return np.array(data["frames"][frame]["T_base_obj"])


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_config_loads_and_locates_a_sample(path, capsys, monkeypatch):
    monkeypatch.chdir(REPO)  # configs name files relative to the repository root
    load_config(path)
    assert main(["check", "-c", str(path)]) == 0  # driver and link options too
    assert capsys.readouterr().out.startswith("OK ")
    rc = main(["locate", "-c", str(path), str(SAMPLES / "left_00.png"),
               str(SAMPLES / "right_00.png"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0, out["message"]
    assert out["status"] == "OK"
    T = np.array(out["T_base_obj"])
    T_true = truth(0)
    mm, deg = pose_error(T, T_true)
    assert mm < 0.2
    assert deg < 0.15


def test_locate_human_readable(capsys):
    rc = main(["locate", "-c", str(EXAMPLE), str(SAMPLES / "left_02.png"),
               str(SAMPLES / "right_02.png")])
    out = capsys.readouterr().out
    assert rc == 0
    for text in ("status:    OK (1)", "T_base_obj (mm):", "offset (mm):", "robot (kuka): X=",
                 "residuals: fit_rms_mm=", "timings:"):
        assert text in out


def test_locate_without_pose_exits_1(capsys, tmp_path):
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((1024, 1280), np.uint8))
    rc = main(["locate", "-c", str(EXAMPLE), str(black), str(SAMPLES / "right_00.png"),
               "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 1
    assert out["status"] == "CAMERA_ERROR"
    assert out["target"] is None


def test_locate_bad_files_are_one_line_errors(capsys, tmp_path):
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG not really")
    for args in ([str(tmp_path / "missing.png")], [str(corrupt)]):
        rc = main(["locate", "-c", str(EXAMPLE), *args])
        err = capsys.readouterr().err
        assert rc == 2
        assert err.count("\n") == 1
        assert Path(args[0]).name in err
    bad = tmp_path / "bad.toml"
    bad.write_text("[vision]\nmin_featurs = 3\n")
    assert main(["locate", "-c", str(bad), str(corrupt)]) == EXIT_CONFIG
    assert "vision.min_featurs" in capsys.readouterr().err


def test_replay_folder_with_annotation(capsys, tmp_path):
    out_dir = tmp_path / "annotated"
    rc = main(["replay", "-c", str(EXAMPLE), str(SAMPLES), "--annotate", str(out_dir)])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 0
    jobs, summary = lines[:-1], lines[-1]["summary"]
    assert len(jobs) == 5
    assert summary["pairs"] == 5
    found = sum(1 for j in jobs if j["status"] in ("OK", "OK_RECALIBRATE"))
    assert summary["found"] == found
    assert summary["found_rate"] == pytest.approx(found / 5)
    assert set(summary["total_ms"]) == {"p50", "p95", "p99"}
    for i, job in enumerate(jobs):
        assert job["source"].endswith(f"left_{i:02d}.png")
        if job["T_base_obj"] is not None:  # the pose is reported even when a gate refused it
            T_true = truth(i)
            assert np.linalg.norm(np.array(job["T_base_obj"])[:3, 3] - T_true[:3, 3]) < 0.2
    images = sorted(p.name for p in out_dir.iterdir())
    assert images == sorted(f"left_{i:02d}_{s}.png" for i in range(5) for s in ("left", "right"))
    annotated = cv2.imread(str(out_dir / "left_00_left.png"))
    plain = cv2.imread(str(SAMPLES / "left_00.png"))
    assert annotated.shape == (*plain.shape[:2], 3)
    # Green labels where the model features are: the drawing changed the image.
    assert (annotated[:, :, 1].astype(int) - annotated[:, :, 0] > 100).sum() > 100


def test_locate_prints_the_pick_list_of_a_pallet(tmp_path, capsys, monkeypatch):
    """config/samples/pallet.toml on a rendered pallet pair: the JSON carries every instance
    (status, pick id, score, pose), the text a line per instance."""
    import asyncio

    from vgripd.registry import CAMERAS, load_class, validate_options

    monkeypatch.chdir(REPO)
    cfg_path = SAMPLES / "pallet.toml"
    config = load_config(cfg_path)

    async def grab():
        cls = load_class(CAMERAS, "camera", "synthetic")
        camera = cls(validate_options(cls, config.camera, "camera"), config)
        await camera.open()
        try:
            return await camera.grab(30.0)
        finally:
            await camera.close()

    pair = asyncio.run(grab())
    left, right = tmp_path / "left.png", tmp_path / "right.png"
    cv2.imwrite(str(left), pair.left)
    cv2.imwrite(str(right), pair.right)
    assert main(["locate", "-c", str(cfg_path), str(left), str(right), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["instances"]) == 6
    assert {i["status"] for i in out["instances"]} == {"OK"}
    assert {i["pick_id"] for i in out["instances"]} == {1}
    assert out["target"] == out["instances"][0]["target"]
    truths = pair.truth["instances_T_base_obj"]
    for inst in out["instances"]:
        T = np.array(inst["T_base_obj"])
        mm = min(pose_error(T, t)[0] for t in truths)
        assert mm < 0.5
    assert main(["locate", "-c", str(cfg_path), str(left), str(right)]) == 0
    text = capsys.readouterr().out
    assert "pick list: 6 pickable of 6" in text
