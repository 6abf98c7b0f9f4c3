"""The layout judgement of a new object's marks (``vgripd.vision.survey.judge_layout``): too
few, too close, and symmetric layouts (a relabelling that keeps every pairwise distance) are
errors; the demo plate's layout (all distances distinct) passes."""

from __future__ import annotations

import numpy as np
import pytest

from vgripd.config import Config
from vgripd.vision import scene
from vgripd.vision.survey import judge_layout


def _levels(points: list[list[float]], diameter: float = 10.0) -> list[str]:
    names = [f"m{i + 1}" for i in range(len(points))]
    return [f.level for f in judge_layout(names, np.array(points, float),
                                          [diameter] * len(points))]


def test_the_demo_plate_passes() -> None:
    pts = scene.object_points(Config())
    assert judge_layout([f"m{i}" for i in range(len(pts))], pts, [10.0] * len(pts)) == []


def test_too_few_marks_are_refused_and_three_warned() -> None:
    assert _levels([[0, 0, 0], [40, 0, 0]]) == ["ERROR"]
    assert _levels([[0, 0, 0], [40, 0, 0], [0, 70, 0]]) == ["WARNING"]


def test_marks_closer_than_two_diameters_are_refused() -> None:
    findings = judge_layout(["a", "b", "c", "d"], np.array(
        [[0, 0, 0], [15, 0, 0], [0, 70, 0], [90, 45, 0]], float), [10.0] * 4)
    assert [f.level for f in findings] == ["ERROR"]
    assert "a and b are 15.0 mm apart" in findings[0].message


@pytest.mark.parametrize("points", [
    [[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0]],                # a square
    [[0, 0, 0], [80, 0, 0], [80, 40, 0], [0, 40, 0]],                # a rectangle
    [[0, 0, 0], [60, 0, 0], [30, 70, 0], [30, 25, 0]],               # a mirror axis
    [[0, 0, 0], [30, 0, 0], [60, 0, 0], [90, 0, 0], [30, 50, 0], [60, 50, 0], [45, 80, 0],
     [45, 20, 0]],                                                   # 8 marks, a mirror axis
])
def test_symmetric_layouts_are_refused(points: list[list[float]]) -> None:
    findings = judge_layout([f"m{i}" for i in range(len(points))], np.array(points, float),
                            [10.0] * len(points))
    assert any(f.level == "ERROR" and "symmetric layout" in f.message for f in findings)


def test_breaking_the_symmetry_by_a_few_millimetres_passes() -> None:
    assert _levels([[0, 0, 0], [50, 0, 0], [53, 57, 0], [0, 50, 0]]) == []
