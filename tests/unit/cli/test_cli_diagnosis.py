"""``vgripd locate`` and ``vgripd replay`` diagnose a failed job as the daemon does: with a
config that cannot find the object (``vision.working_distance_mm`` excludes it), the check's
finding comes first and names the key, where the images alone said "no likely cause"."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import cv2
import pytest

from tests.unit.vision.test_checked import at_distance
from tests.unit.vision.test_diagnosis import grab
from vgripd.__main__ import main
from vgripd.serialize import toml_from_dict

KEY = "vision.working_distance_mm"


def test_locate_and_replay_name_the_key_the_daemon_names(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = at_distance(1000.0, working_distance_mm=[100.0, 400.0])
    pair = asyncio.run(grab(config))
    cfg = tmp_path / "cell.toml"
    cfg.write_text(toml_from_dict(config.model_dump(mode="json", exclude_none=True)))
    job = tmp_path / "job"
    job.mkdir()
    names = ["left.png", "right.png"][:len(pair.views)]
    for name, image in zip(names, pair.views, strict=True):
        assert cv2.imwrite(str(job / name), image)
    (job / "pair.json").write_text("{}")

    assert main(["locate", "-c", str(cfg), "--json", *(str(job / n) for n in names)]) == 1
    located = json.loads(capsys.readouterr().out)
    assert located["status"] == "NOT_FOUND"
    assert located["diagnosis"]["causes"][0]["key"] == KEY, located["diagnosis"]

    main(["replay", "-c", str(cfg), str(job)])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.strip()]
    jobs = [line for line in lines if "status" in line]
    assert jobs, lines
    assert jobs[0]["status"] == "NOT_FOUND"
    assert jobs[0]["diagnosis"]["causes"][0]["key"] == KEY, jobs[0]["diagnosis"]
