"""The diagnosis of a failed job: each classic mistake is told the config key to fix.

The scene is rendered by the synthetic camera with the correct config; the pipeline then runs
with one mistake in its config (as a user would make it), and the top cause must name the key.
"""

from __future__ import annotations

import copy
import json
import logging
import pickle
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pytest

from tests.conftest import REPO
from vgripd.__main__ import main
from vgripd.config import Config, config_from_dict, load_config
from vgripd.geometry.transforms import invert_transform
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.serialize import toml_from_dict
from vgripd.service.worker.recorder import dict_from_result
from vgripd.types import ImagePair, Status
from vgripd.vision import scene
from vgripd.vision.annotate import annotate
from vgripd.vision.diagnosis import Diagnosis
from vgripd.vision.pipeline import Pipeline, diagnose

SAMPLES = REPO / "config" / "samples"
EXAMPLE = REPO / "config" / "example.toml"


def make_config(camera: dict[str, Any] | None = None) -> Config:
    # Default limits (50 mm, 10 deg): a wrong hand-eye must fail them.
    return config_from_dict({"camera": {"type": "synthetic", "seed": 3, **(camera or {})}})


async def grab(config: Config) -> ImagePair:
    cls = load_class(CAMERAS, "camera", config.camera.type)
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    await camera.open()
    try:
        return await camera.grab(30.0)
    finally:
        await camera.close()


def mistaken(config: Config, edit: Callable[[dict[str, Any]], None]) -> Config:
    data = copy.deepcopy(config.model_dump(mode="json", exclude_none=True))
    edit(data)
    return config_from_dict(data)


def wrong_polarity(d: dict[str, Any]) -> None:
    for f in d["object"]["features"]:
        f["polarity"] = "bright"


def working_distance_excludes(d: dict[str, Any]) -> None:
    d["vision"]["working_distance_mm"] = [300.0, 500.0]  # the plate is ~690 mm away


def inverted_stereo(d: dict[str, Any]) -> None:
    T = scene.T_right_left(config_from_dict(d))
    assert T is not None
    d["calibration"]["stereo"]["T_right_left"] = {"matrix": invert_transform(T).tolist()}


def wrong_hand_eye(d: dict[str, Any]) -> None:
    d["calibration"]["hand_eye"]["T_base_camera"]["translation_mm"][0] += 150.0


@pytest.mark.parametrize(
    ("edit", "key", "words"),
    [
        (wrong_polarity, "object.features[*].polarity", "are the marks dark?"),
        (working_distance_excludes, "vision.working_distance_mm", "rejected by size"),
        (inverted_stereo, "calibration.stereo.T_right_left", "looks inverted"),
        (wrong_hand_eye, "calibration.hand_eye.T_base_camera", "hand-eye calibration is wrong"),
    ],
    ids=["polarity", "working_distance", "T_right_left_inverted", "hand_eye"],
)
async def test_each_mistake_names_its_key(edit, key, words):
    good = make_config()
    pair = await grab(good)
    assert Pipeline(good).process(pair, 1).status is Status.OK
    result = Pipeline(mistaken(good, edit)).process(pair, 1)
    assert not result.status.pose_valid
    d = result.diagnosis
    assert isinstance(d, Diagnosis)
    assert d.top is not None, d.lines()
    assert d.top.key == key, d.lines()
    assert words in d.top.reason
    assert key in d.summary()
    # It travels: JSON for locate/recorder, pickle for the worker process.
    data = json.loads(json.dumps(dict_from_result(result)))
    assert data["diagnosis"]["causes"][0]["key"] == key
    assert pickle.loads(pickle.dumps(result)).diagnosis.top == d.top


async def test_stage_counts_of_the_mistakes():
    good = make_config()
    pair = await grab(good)
    d = Pipeline(mistaken(good, wrong_polarity)).process(pair, 1).diagnosis
    assert [s.found for s in d.images] == [0, 0]
    assert [s.opposite_polarity for s in d.images] == [6, 6]
    d = Pipeline(mistaken(good, working_distance_excludes)).process(pair, 1).diagnosis
    assert [s.rejected["size"] for s in d.images] == [6, 6]
    d = Pipeline(mistaken(good, inverted_stereo)).process(pair, 1).diagnosis
    assert [s.found for s in d.images] == [6, 6]
    assert d.paired_left < 3
    assert d.paired_inverted == 6
    d = Pipeline(mistaken(good, wrong_hand_eye)).process(pair, 1).diagnosis
    assert d.best_explained == d.used == 6
    assert d.outside_working_distance == 0


async def test_low_contrast_names_min_contrast():
    config = make_config({"dark_level": 172})  # marks ~18 grey levels under the background
    pair = await grab(config)
    result = Pipeline(config).process(pair, 1)
    assert result.status is Status.NOT_FOUND
    d = result.diagnosis
    assert d.top is not None
    assert d.top.key == "vision.min_contrast", d.lines()
    assert all(s.rejected["contrast"] >= 3 for s in d.images)


async def test_a_correct_config_gives_no_cause():
    config = make_config()
    pair = await grab(config)
    result = Pipeline(config).process(pair, 1)
    assert result.status is Status.OK
    assert result.diagnosis is None  # nothing computed on the success path
    d = diagnose(config, pair)  # the commissioning API always answers
    assert d.status == "OK"
    assert d.causes == ()
    assert [s.found for s in d.images] == [6, 6]
    assert d.used == 6
    assert d.summary().startswith("no likely cause")


async def test_diagnose_api_on_a_mistake_and_a_black_image():
    good = make_config()
    pair = await grab(good)
    d = diagnose(mistaken(good, inverted_stereo), pair)
    assert d.top is not None
    assert d.top.key == "calibration.stereo.T_right_left"
    black = ImagePair(np.zeros_like(pair.left), pair.right, pair.t_mono_ns)
    d = diagnose(good, black)
    assert d.status == "CAMERA_ERROR"
    assert d.top is not None
    assert d.top.key == "camera"


async def test_annotated_failure_draws_every_candidate_with_its_reason():
    good = make_config()
    pair = await grab(good)
    pipeline = Pipeline(mistaken(good, working_distance_excludes))
    result = pipeline.process(pair, 1)
    reasons = {c.reason for s in result.diagnosis.images for c in s.candidates}
    assert reasons == {"size"}
    left, right = annotate(pipeline, pair, result)
    plain = cv2.cvtColor(pair.left, cv2.COLOR_GRAY2BGR)
    # Circles and labels around the dropped blobs: pixels changed near each mark.
    for x, y in pair.truth["pixels_left"]:
        x0, y0 = int(x) - 30, int(y) - 30
        patch = np.abs(left[y0:y0 + 60, x0:x0 + 60].astype(int) - plain[y0:y0 + 60, x0:x0 + 60])
        assert (patch.max(axis=2) > 60).sum() > 30


def _write_config(tmp_path, edit: Callable[[dict[str, Any]], None]) -> str:
    config = load_config(EXAMPLE)
    data = copy.deepcopy(config.model_dump(mode="json", exclude_none=True))
    edit(data)
    path = tmp_path / "mistake.toml"
    path.write_text(toml_from_dict(data))
    return str(path)


def test_locate_json_and_text_show_the_diagnosis(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(REPO)
    path = _write_config(tmp_path, inverted_stereo)
    images = [str(SAMPLES / "left_00.png"), str(SAMPLES / "right_00.png")]
    assert main(["locate", "-c", path, *images, "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "NOT_FOUND"
    diag = out["diagnosis"]
    assert diag["causes"][0]["key"] == "calibration.stereo.T_right_left"
    assert [i["found"] for i in diag["images"]] == [6, 6]
    assert diag["paired_inverted"] == 6
    path = _write_config(tmp_path, wrong_polarity)
    assert main(["locate", "-c", path, *images]) == 1
    text = capsys.readouterr().out
    assert "why:" in text
    assert "likely causes:" in text
    assert "1. object.features[*].polarity:" in text
    # A successful job has no why block and a null diagnosis.
    assert main(["locate", "-c", str(EXAMPLE), *images, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["diagnosis"] is None


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


async def test_daemon_logs_the_top_cause_and_shows_it_in_the_status():
    from tests.integration.test_daemon import Plc, running
    from tests.integration.test_daemon import make_config as daemon_config

    camera = {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0, "dark_level": 172}
    logger = logging.getLogger("vgripd")  # the daemon's logger
    handler, level = _Lines(), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        async with running(daemon_config(camera)) as run, Plc(run.port()) as plc:
            await plc.trigger(1)
            await plc.result(1)
            _, rec = await run.job_done(1)
            assert rec.result.status is Status.NOT_FOUND
            last = run.daemon.snapshot()["last_job"]
            assert last["diagnosis"]["causes"][0]["key"] == "vision.min_contrast"
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    line = next(m for m in handler.lines if m.startswith("job 1: NOT_FOUND in "))
    assert "NOT_FOUND" in line
    assert "likely cause: vision.min_contrast:" in line
    assert "\n" not in line
