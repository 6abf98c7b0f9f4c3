"""``vgripd calibrate conveyor``: positions of an independent belt (direction and scale known
here) fitted back, the result file loaded as a config include, bad input named."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from vgripd.__main__ import main
from vgripd.config import load_config


def belt_points(path: Path, direction: np.ndarray, scale: float, seed: int = 3) -> None:
    rng = np.random.default_rng(seed)
    p0 = np.array([250.0, 40.0, 20.0])
    lines = ["# count, x, y, z"]
    for travel in (0.0, 150.0, 310.0, 455.0, 600.0):
        count = (2**32 - 2000 + round(travel * scale)) % 2**32  # across the counter's wrap
        p = p0 + direction * travel + rng.normal(0, 0.05, 3) * [1, 1, 0]
        lines.append(f"{count}, {p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}")
    path.write_text("\n".join(lines) + "\n")


def test_points_give_the_belt_and_a_loadable_include(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    d = np.array([math.cos(0.3), math.sin(0.3), 0.0])
    belt_points(tmp_path / "obs.csv", d, 30.0)
    out = tmp_path / "conveyor.toml"
    rc = main(["calibrate", "conveyor", "--points", str(tmp_path / "obs.csv"), "-o", str(out),
               "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    got = summary["conveyor"]
    assert math.degrees(math.acos(np.dot(got["direction"], d))) < 0.05
    assert got["counts_per_mm"] == pytest.approx(30.0, rel=1e-3)
    assert summary["about"]["observations"] == 5
    assert tomllib.loads(out.read_text())["conveyor"]["counts_per_mm"] == got["counts_per_mm"]
    cfg = tmp_path / "vgripd.toml"
    cfg.write_text('include = ["conveyor.toml"]\n[conveyor]\nwindow_mm = [0.0, 900.0]\n'
                   'trigger_distance_mm = 100.0\nspeed_mm_s = 300.0\n')
    loaded = load_config(cfg).conveyor
    assert loaded is not None
    assert loaded.counts_per_mm == got["counts_per_mm"]


def test_an_imported_robot_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """UR's track_conveyor_linear(p[0, 2, 0, ...], 30000) in ticks per metre: 30 per mm."""
    out = tmp_path / "c.toml"
    assert main(["calibrate", "conveyor", "--import-direction", "0", "2", "0",
                 "--counts-per-mm", "30", "-o", str(out)]) == 0
    section = tomllib.loads(out.read_text())["conveyor"]
    assert section["direction"] == [0.0, 1.0, 0.0]
    assert section["counts_per_mm"] == 30.0


def test_a_bad_line_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "obs.csv"
    bad.write_text("100, 0, 0, 0\n200, 1.0, nope, 0\n")
    assert main(["calibrate", "conveyor", "--points", str(bad), "-o",
                 str(tmp_path / "c.toml")]) != 0
    assert f"{bad}:2: 'count, x, y, z' expected" in capsys.readouterr().err


def test_one_count_is_not_a_belt(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    one = tmp_path / "obs.csv"
    one.write_text("100, 0, 0, 0\n100, 5, 0, 0\n")
    assert main(["calibrate", "conveyor", "--points", str(one), "-o",
                 str(tmp_path / "c.toml")]) != 0
    assert "move the belt between the images" in capsys.readouterr().err


def test_observed_images_locate_the_object(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Two sample pairs as two belt positions: the fitted line runs between the rendered
    truths (config/samples/truth.json, written by the sample renderer), 1 mm per 10 counts."""
    from tests.conftest import REPO

    monkeypatch.chdir(REPO)
    frames = json.loads((REPO / "config/samples/truth.json").read_text())["frames"][:2]
    p = [np.array(f["T_base_obj"])[:3, 3] for f in frames]
    counts = [1000, 1000 + round(10 * float(np.linalg.norm(p[1] - p[0])))]
    observe = [f"--observe={c}=config/samples/{f['left']},config/samples/{f['right']}"
               for c, f in zip(counts, frames, strict=True)]
    assert main(["calibrate", "conveyor", "-c", "config/example.toml", *observe,
                 "-o", str(tmp_path / "c.toml"), "--json"]) == 0
    about = json.loads(capsys.readouterr().out)["about"]
    assert about["observations"] == 2
    got = tomllib.loads((tmp_path / "c.toml").read_text())["conveyor"]
    assert got["counts_per_mm"] == pytest.approx(10.0, rel=0.01)
    assert got["origin_mm"] == pytest.approx(list((p[0] + p[1]) / 2), abs=0.5)
