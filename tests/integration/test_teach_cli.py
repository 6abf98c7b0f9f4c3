"""``vgripd teach`` end to end on the synthetic demo cell, whose camera places the object at a
known pose: the taught reference against that truth, then the pipeline with the written file
included (offset ~ identity at the reference, the applied motion for a moved object), for both
object definitions; the grip output; the refusals (spread, bad shot, existing file).

Tolerances: docs/pipeline.md predicts 1-sigma 0.04 mm / 0.025 deg for one shot; the mean of
several shots is at least as good, and the bounds are 5x that.
"""

from __future__ import annotations

import asyncio
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vgripd.__main__ import main
from vgripd.calib import teach
from vgripd.calib.files import pose_table
from vgripd.config import DEMO_OBJECT, PoseConfig, load_config
from vgripd.geometry.transforms import (
    make_transform,
    matrix_from_rotvec,
    pose_error,
)
from vgripd.geometry.vendors import transform_from_vendor, vendor_from_transform
from vgripd.serialize import toml_from_dict
from vgripd.types import Status
from vgripd.vision.pipeline import Pipeline
from vgripd.vision.scene import matrix_from_pose

MAX_MM = 0.2
MAX_DEG = 0.12
REF_POSE = {"translation_mm": [604.0, 97.0, 12.0], "rotvec_rad": [0.01, -0.02, 0.08]}
# The object moved after teaching: 6 mm / 3 deg about the base z axis through (600, 100, 0).
MOVE = make_transform(matrix_from_rotvec([0.0, 0.0, np.radians(3.0)]), [0.0, 0.0, 0.0])
MOVE = (make_transform(np.eye(3), [606.0, 96.0, 0.0]) @ MOVE
        @ make_transform(np.eye(3), [-600.0, -100.0, 0.0]))


def write_config(folder: Path, pose: dict[str, Any], seed: int = 3, **sections: Any) -> Path:
    path = folder / "cell.toml"
    data = {"camera": {"type": "synthetic", "seed": seed, "pose": pose}, **sections}
    path.write_text(toml_from_dict(data), encoding="utf-8")
    return path


def pose_dict(T: np.ndarray) -> dict[str, Any]:
    return pose_table(T)


def load_config_pose(table: dict[str, Any]) -> PoseConfig:
    return PoseConfig(**table)


def run_teach(config: Path, *extra: str) -> int:
    return main(["teach", "-c", str(config), "--shots", "3", *extra])


def locate(config_path: Path, n: int = 2) -> list[Any]:
    config = load_config(config_path)
    pipeline = Pipeline(config)
    return [(pipeline.process(pair, i), pair) for i, pair in
            enumerate(asyncio.run(teach.acquire(config, n)))]


def demo_object(definition: str) -> dict[str, Any]:
    return {**DEMO_OBJECT.model_dump(mode="json", exclude_none=True), "definition": definition}


def test_teach_cad_reference_then_offsets(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    # The config carries a wrong old reference: teaching measures against the camera anyway.
    old = {"T_base_obj": {"translation_mm": [0.0, 0.0, 0.0]}}
    cfg = write_config(tmp_path, REF_POSE, object=demo_object("cad"), reference=old)
    assert run_teach(cfg, "--json") == 0
    summary = json.loads(capsys.readouterr().out)
    out = tmp_path / "reference.toml"
    assert summary["output"] == str(out)
    assert summary["include"] == "reference.toml"
    written = tomllib.loads(out.read_text())
    T = matrix_from_pose(load_config_pose(written["reference"]["T_base_obj"]))
    err_mm, err_deg = pose_error(T, matrix_from_pose(load_config_pose(REF_POSE)))
    assert err_mm < MAX_MM
    assert err_deg < MAX_DEG
    assert summary["spread"]["mm"] < 0.1
    assert written["about"]["shots"] == 3

    # Same images (same seed), another old reference: bit-for-bit the same measurement.
    (tmp_path / "b").mkdir()
    cfg_b = write_config(tmp_path / "b", REF_POSE, object=demo_object("cad"))
    assert run_teach(cfg_b) == 0
    assert "include = [\"reference.toml\"]" in capsys.readouterr().out
    T_b = matrix_from_pose(load_config_pose(
        tomllib.loads((tmp_path / "b" / "reference.toml").read_text())["reference"]["T_base_obj"]))
    np.testing.assert_allclose(T_b, T, atol=1e-9)

    # Use it: the object at the reference gives ~ identity, a moved one the motion.
    at_ref = write_config(tmp_path, REF_POSE, seed=8, object=demo_object("cad"),
                          include=["reference.toml"])
    for result, _ in locate(at_ref):
        assert result.status is Status.OK, result.message
        assert pose_error(result.offset, np.eye(4)) < (MAX_MM, MAX_DEG)
    moved = MOVE @ matrix_from_pose(load_config_pose(REF_POSE))
    cfg_moved = write_config(tmp_path, pose_dict(moved), seed=9, object=demo_object("cad"),
                             include=["reference.toml"])
    for result, _ in locate(cfg_moved):
        assert result.status is Status.OK, result.message
        assert pose_error(result.offset, MOVE) < (MAX_MM, MAX_DEG)


def test_teach_reference_definition_measures_points(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]):
    obj = demo_object("reference")
    cfg = write_config(tmp_path, REF_POSE, object=obj)
    assert run_teach(cfg, "--json") == 0
    summary = json.loads(capsys.readouterr().out)
    points = tomllib.loads((tmp_path / "reference.toml").read_text())["reference"]["points_mm"]
    T_ref = matrix_from_pose(load_config_pose(REF_POSE))
    for f in obj["features"]:  # truth: the rendered marks in the base frame
        truth = T_ref[:3, :3] @ np.array(f["xyz_mm"]) + T_ref[:3, 3]
        assert np.linalg.norm(np.array(points[f["name"]]) - truth) < MAX_MM, f["name"]
    assert summary["spread"]["points_mm"] < 0.1

    moved = MOVE @ T_ref
    cfg_moved = write_config(tmp_path, pose_dict(moved), seed=9, object=obj,
                             include=["reference.toml"])
    for result, _ in locate(cfg_moved):
        assert result.status is Status.OK, result.message
        assert pose_error(result.offset, MOVE) < (MAX_MM, MAX_DEG)
        assert result.residuals["fit_rms_mm"] < 0.1


def test_grip_is_stored_and_published_as_offset_at_grip(tmp_path: Path):
    grip_kuka = [612.5, 98.1, 55.0, 175.0, -2.0, 179.0]
    cfg = write_config(tmp_path, REF_POSE, object=demo_object("cad"))
    assert run_teach(cfg, "--grip=" + " ".join(map(str, grip_kuka)), "--pose-format", "kuka") == 0
    G = transform_from_vendor("kuka", grip_kuka)
    stored = tomllib.loads((tmp_path / "reference.toml").read_text())["reference"]["grip"]
    np.testing.assert_allclose(matrix_from_pose(load_config_pose(stored)), G, atol=1e-9)

    moved = MOVE @ matrix_from_pose(load_config_pose(REF_POSE))
    cfg_moved = write_config(tmp_path, pose_dict(moved), seed=9, object=demo_object("cad"),
                             include=["reference.toml"], output={"mode": "grip"})
    for result, _ in locate(cfg_moved, 1):
        assert result.status is Status.OK, result.message
        sent = transform_from_vendor("kuka", result.target.values)
        np.testing.assert_allclose(sent, result.offset @ G, atol=1e-6)
        assert pose_error(sent, MOVE @ G) < (MAX_MM + 0.5, MAX_DEG)  # the grip is 45 mm up
        assert vendor_from_transform("kuka", sent) == pytest.approx(result.target.values)


def test_refusals_write_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    cfg = write_config(tmp_path, REF_POSE, object=demo_object("cad"))
    out = tmp_path / "reference.toml"
    assert run_teach(cfg, "--max-spread-mm", "0.0001") == 1
    assert "refused, nothing written: pose spread" in capsys.readouterr().err
    assert not out.exists()

    (tmp_path / "drop").mkdir()
    cfg_drop = write_config(tmp_path / "drop", REF_POSE, object=demo_object("cad"))
    data = tomllib.loads(cfg_drop.read_text())
    data["camera"]["drop_features"] = ["m3"]  # a mark hidden: the shots are incomplete
    cfg_drop.write_text(toml_from_dict(data))
    assert run_teach(cfg_drop) == 1
    err = capsys.readouterr().err
    assert "3 of 3 shot(s) refused" in err
    assert "shot 1: feature(s) m3 not found" in err
    assert not (tmp_path / "drop" / "reference.toml").exists()

    out.write_text("# keep me\n")
    assert run_teach(cfg) == 1
    assert "exists; nothing measured (--force overwrites it)" in capsys.readouterr().err
    assert out.read_text() == "# keep me\n"
    assert run_teach(cfg, "--force") == 0
    assert "T_base_obj" in out.read_text()

    assert run_teach(cfg, "--force", "--grip=1 2 3", "--pose-format", "kuka") == 2
    assert "expected 6 values" in capsys.readouterr().err
