"""vgripd.calib.teach: averaging (against scipy's rotation mean), spread, shot refusal, the measuring
config, and the config's ``reference.points_mm`` / ``grip`` / ``output.mode`` checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgripd.calib import teach
from vgripd.config import config_from_dict
from vgripd.errors import CalibrationError, ConfigError, NotCalibratedError
from vgripd.geometry.transforms import make_transform
from vgripd.types import JobResult, Status
from vgripd.vision.pipeline import Pipeline

NAMES = ("a", "b", "c")


def test_mean_transform_matches_scipy_rotation_mean() -> None:
    rng = np.random.default_rng(7)
    base = Rotation.from_rotvec([0.3, -2.9, 0.4])  # near pi: quaternion signs flip between shots
    rots = [base * Rotation.from_rotvec(rng.normal(0, 0.02, 3)) for _ in range(9)]
    ts = rng.normal([600, 100, 10], 0.1, (9, 3))
    Ts = [make_transform(r.as_matrix(), t) for r, t in zip(rots, ts, strict=True)]
    T = teach.mean_transform(Ts)
    oracle = Rotation.concatenate(rots).mean().as_matrix()
    np.testing.assert_allclose(T[:3, :3], oracle, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], ts.mean(axis=0), atol=1e-12)


def _shot(i: int, T: np.ndarray, offset_mm: float) -> teach.Shot:
    pts = {n: np.array([10.0 * k, 0.0, offset_mm]) for k, n in enumerate(NAMES)}
    return teach.Shot(i, T, pts, {"fit_rms_mm": 0.01})


def test_average_reports_each_shot_deviation_and_the_spread() -> None:
    turn = make_transform(Rotation.from_rotvec([0, 0, math.radians(0.3)]).as_matrix(), [0, 0, 0])
    shift = make_transform(np.eye(3), [0.0, 0.6, 0.0])
    shots = [_shot(1, np.eye(4), 0.0), _shot(2, turn, 0.0), _shot(3, shift, 0.3)]
    taught = teach.average(shots)
    np.testing.assert_allclose(taught.points_base["b"], [10.0, 0.0, 0.1])
    assert taught.point_deviations_mm == pytest.approx((0.1, 0.1, 0.2))
    assert taught.spread_mm == pytest.approx(0.4, abs=1e-6)  # shot 3: 0.6 - 0.2 from the mean
    assert taught.spread_deg == pytest.approx(0.2, abs=1e-6)  # shot 2: 0.3 - 0.1
    assert taught.problems(0.5, 0.25) == []
    assert len(taught.problems(0.3, 0.1)) == 2
    assert taught.problems(0.5, 0.25, check_points=False) == []
    assert "feature point spread 0.200 mm" in taught.problems(0.15, 1.0, check_points=True)[-1]


def test_a_shot_must_be_ok_and_complete() -> None:
    points = {n: np.zeros(3) for n in NAMES}
    ok = JobResult(1, Status.OK, T_base_obj=np.eye(4), offset=np.eye(4))
    assert teach.shot_from_result(1, ok, points, NAMES).index == 1
    drift = JobResult(2, Status.OK_RECALIBRATE, "median epipolar residual 2.2 px",
                      T_base_obj=np.eye(4), offset=np.eye(4))
    with pytest.raises(CalibrationError, match="shot 2: status OK_RECALIBRATE: median epipolar"):
        teach.shot_from_result(2, drift, points, NAMES)
    with pytest.raises(CalibrationError, match=r"shot 3: feature\(s\) b not found"):
        teach.shot_from_result(3, ok, {"a": np.zeros(3), "c": np.zeros(3)}, NAMES)


def test_measuring_config_lifts_offset_limits_and_needs_no_reference() -> None:
    untaught = config_from_dict({
        "object": config_from_dict({}).model_dump()["object"],
        "output": {"mode": "grip"},
    })
    with pytest.raises(NotCalibratedError, match="reference.T_base_obj"):
        Pipeline(untaught)
    measuring = teach.measuring_config(untaught)
    pipeline = Pipeline(measuring)  # builds: placeholder reference, plain offset output
    np.testing.assert_array_equal(pipeline.T_base_obj_ref, np.eye(4))
    assert measuring.limits.max_translation_mm == math.inf
    assert measuring.limits.workspace_min_mm == untaught.limits.workspace_min_mm


def _reference_object(**reference: object) -> dict[str, object]:
    obj = config_from_dict({}).model_dump()["object"]
    return {"object": {**obj, "definition": "reference"}, "reference": reference}


def test_points_mm_must_name_every_feature_and_only_for_the_reference_definition() -> None:
    pts = {f"m{i}": [float(i), 0.0, 0.0] for i in range(1, 7)}
    config = config_from_dict(_reference_object(points_mm=pts))
    assert config.reference.points_mm is not None
    with pytest.raises(ConfigError, match=r"missing \['m6'\], unknown \['x'\]"):
        config_from_dict(_reference_object(points_mm={**{k: v for k, v in pts.items()
                                                          if k != "m6"}, "x": [0, 0, 0]}))
    with pytest.raises(ConfigError, match="points_mm is only for"):
        config_from_dict({"reference": {"T_base_obj": {"translation_mm": [0, 0, 0]},
                                        "points_mm": pts}})


def test_pipeline_fits_the_taught_points() -> None:
    rng = np.random.default_rng(3)
    pts = {f"m{i}": rng.normal(0, 50, 3).tolist() for i in range(1, 7)}
    pipeline = Pipeline(config_from_dict(_reference_object(points_mm=pts)))
    np.testing.assert_array_equal(pipeline.model, [pts[f"m{i}"] for i in range(1, 7)])
    np.testing.assert_array_equal(pipeline.T_base_obj_ref, np.eye(4))


def test_grip_output_needs_a_taught_grip() -> None:
    with pytest.raises(NotCalibratedError, match="reference.grip"):
        Pipeline(config_from_dict({"output": {"mode": "grip"}}))


def test_recalibrate_fields_are_consistent() -> None:
    with pytest.raises(ConfigError, match="recalibrate_min_jobs"):
        config_from_dict({"daemon": {"recalibrate_window": 5, "recalibrate_min_jobs": 6}})
    with pytest.raises(ConfigError, match="recalibrate_share"):
        config_from_dict({"daemon": {"recalibrate_share": 1.0}})
