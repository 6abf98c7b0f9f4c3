"""The daemon's conveyor lines across a reload (``belt_lines``, docs/conveyor.md): a recipe
whose ``[conveyor]`` (the cell's) and ``[output]`` (its own) are unchanged keeps its line and
queued parts, a changed or added one starts empty and says so (with the parts dropped), a
removed one is gone."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest

from vgripd.config import Config, config_from_dict
from vgripd.peer.beltqueue import latch_from_link
from vgripd.service.jobs.beltlines import belt_lines

BELT: dict[str, Any] = {"counts_per_mm": 30.0, "direction": [1.0, 0.0, 0.0],
                        "origin_mm": [0.0, 0.0, 0.0], "window_mm": [300.0, 800.0],
                        "trigger_distance_mm": 150.0, "speed_mm_s": 500.0}


def cell(recipes: dict[int, dict[str, Any]], belt: dict[str, Any] | None = BELT) -> Config:
    data: dict[str, Any] = {"recipes": {str(n): {"name": f"r{n}", **r}
                                        for n, r in recipes.items()}}
    if belt is not None:
        data["conveyor"] = belt
    return config_from_dict(data)


def queue_a_part(lines: dict[int, Any], recipe: int) -> None:
    line = lines[recipe]
    T = np.eye(4)
    T[:3, 3] = (400.0, 0.0, 0.0)
    line.queue.add(latch_from_link(line.belt, 0), [T], job_id=1)
    assert len(line.queue) == 1


def test_a_config_without_a_belt_has_no_lines() -> None:
    assert belt_lines(config_from_dict({})) == {}


def test_every_recipe_gets_its_own_line_in_its_own_convention() -> None:
    lines = belt_lines(cell({1: {}, 2: {"output": {"vendor": "abb"}}}))
    assert sorted(lines) == [0, 1, 2]
    assert lines[0] is not lines[1]
    assert (lines[1].vendor, lines[2].vendor) == (lines[0].vendor, "abb")


def test_a_reload_keeps_unchanged_lines_and_empties_changed_ones(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "vgripd.conveyor")
    old = cell({1: {}, 2: {}})
    running = belt_lines(old)
    queue_a_part(running, 1)
    queue_a_part(running, 2)
    new = cell({1: {}, 2: {"output": {"vendor": "abb"}}, 3: {}})
    lines = belt_lines(new, running, old)
    assert lines[1] is running[1]
    assert len(lines[1].queue) == 1
    assert lines[2] is not running[2]
    assert len(lines[2].queue) == 0
    assert 3 in lines
    text = caplog.text
    assert "conveyor of recipe 2 (r2): changed by the reload" in text
    assert "(1 queued parts dropped)" in text
    assert "conveyor of recipe 3 (r3): added by the reload" in text
    assert "recipe 1" not in text


def test_a_changed_belt_is_a_changed_line_for_every_recipe() -> None:
    old = cell({1: {}})
    running = belt_lines(old)
    lines = belt_lines(cell({1: {}}, {**BELT, "speed_mm_s": 250.0}), running, old)
    assert lines[0] is not running[0]
    assert lines[1] is not running[1]
    assert lines[1].speed_mm_s == 250.0


def test_a_removed_belt_is_gone_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "vgripd.conveyor")
    old = cell({1: {}})
    running = belt_lines(old)
    new = cell({1: {}}, belt=None)
    assert belt_lines(new, running, old) == {}
    assert "conveyor of recipe 0: removed by the reload" in caplog.text
    assert "conveyor of recipe 1: removed by the reload" in caplog.text
