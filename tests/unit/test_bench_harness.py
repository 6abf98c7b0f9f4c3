"""bench/harness.py: the figures every bench prints and the writer of bench/RESULTS.md."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench import harness
from bench.harness import Spread, Stamp, percentile, replace_section, write_section

FINITE = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@given(st.lists(FINITE, min_size=1, max_size=60), st.floats(min_value=0, max_value=100))
def test_percentile_is_numpys(values: list[float], q: float) -> None:
    assert percentile(values, q) == pytest.approx(float(np.percentile(values, q)), abs=1e-6)


def test_percentile_of_nothing_is_nan_and_q_is_checked() -> None:
    assert math.isnan(percentile([], 50))
    with pytest.raises(ValueError, match="q must be within 0..100, got 101"):
        percentile([1.0], 101)


def test_spread_against_numpy() -> None:
    values = list(np.random.default_rng(7).exponential(2.0, 501))
    s = Spread.of(values)
    assert (s.n, s.max) == (501, max(values))
    assert s.median == pytest.approx(np.median(values))
    assert s.p95 == pytest.approx(np.percentile(values, 95))
    assert s.p99 == pytest.approx(np.percentile(values, 99))


def results_file(tmp_path: Path) -> Path:
    path = tmp_path / "RESULTS.md"
    path.write_text(replace_section(replace_section(replace_section(
        "", "Links", "S7 link", "s7 figures\n\n| a | b |\n|---|---|"),
        "Calibration", "Hand-eye", "hand-eye figures"),
        "Links", "OPC UA link", "opcua figures"))
    return path


def sections(text: str) -> list[str]:
    return re.findall(r"^#{2,3} .*$", text, flags=re.M)


def test_results_are_grouped_by_subject_in_the_declared_order(tmp_path: Path) -> None:
    text = results_file(tmp_path).read_text()
    assert text.startswith(harness.TITLE + "\n")
    assert sections(text) == ["## Calibration", "### Hand-eye",
                              "## Links", "### S7 link", "### OPC UA link"]


def test_writer_replaces_exactly_its_own_section(tmp_path: Path) -> None:
    path = results_file(tmp_path)
    before = path.read_text()
    write_section("Links", "S7 link", "new s7 figures", Stamp("bench s7"), path=path)
    after = path.read_text()
    assert sections(after) == sections(before)
    assert "s7 figures\n\n| a | b |" not in after
    assert "new s7 figures" in after
    # every other section keeps its bytes
    for other in ("### OPC UA link\n\nopcua figures\n", "### Hand-eye\n\nhand-eye figures\n"):
        assert other in before
        assert other in after
    assert before.replace("s7 figures\n\n| a | b |\n|---|---|", "") == re.sub(
        r"### S7 link\n\n.*new s7 figures", "### S7 link\n\n", after, flags=re.S)


def test_writer_stamps_commit_machine_and_load(tmp_path: Path) -> None:
    path = results_file(tmp_path)
    text = write_section("Links", "S7 link", "figures", Stamp("python bench/x.py"), path=path)
    stamp = text.splitlines()[2]
    assert stamp.startswith("`python bench/x.py`, commit ")
    assert re.search(r"commit [0-9a-f]{7,}", stamp), stamp
    assert re.search(r"\d+ cores, .+, load average [\d.]+ [\d.]+ [\d.]+ before, "
                     r"[\d.]+ [\d.]+ [\d.]+ after", stamp), stamp


def test_writer_moves_a_section_to_its_subject_and_adds_new_ones_last(tmp_path: Path) -> None:
    path = results_file(tmp_path)
    write_section("Calibration", "OPC UA link", "moved", Stamp("x"), path=path)
    write_section("Links", "RTU link", "rtu", Stamp("x"), path=path)
    assert sections(path.read_text()) == [
        "## Calibration", "### Hand-eye", "### OPC UA link",
        "## Links", "### S7 link", "### RTU link"]


def test_writer_refuses_an_unknown_subject_and_a_heading_with_hashes(tmp_path: Path) -> None:
    path = results_file(tmp_path)
    before = path.read_text()
    with pytest.raises(ValueError, match="unknown subject 'Linkz'"):
        write_section("Linkz", "S7 link", "x", path=path)
    with pytest.raises(ValueError, match="a heading is one line of words"):
        write_section("Links", "## S7 link", "x", path=path)
    assert path.read_text() == before


def test_the_repository_results_parse_into_known_subjects() -> None:
    """bench/RESULTS.md is what the writer writes: rendering it again changes nothing."""
    text = harness.RESULTS.read_text()
    groups = harness.parse_results(text)
    assert [g.subject for g in groups] == [s for s in harness.SUBJECTS
                                           if s in {g.subject for g in groups}]
    assert harness.render_results(groups) == text
