"""`vgripd check` runs the first replay frames through the pipeline: each of the four mistakes
that once all ended "0 feature(s) matched" is named by its config key, with exit 78."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO
from vgripd.__main__ import EXIT_CONFIG, main

EXAMPLE = (REPO / "config" / "example.toml").read_text()
RIG = "translation_mm = [-149.18, 0.35, 15.68]\nrotvec_rad = [0.0021, 0.20944, -0.0032]"


def _inverted_rig() -> str:
    R, _ = cv2.Rodrigues(np.array([0.0021, 0.20944, -0.0032]))
    t = -R.T @ np.array([-149.18, 0.35, 15.68])
    rv = cv2.Rodrigues(R.T)[0].ravel()
    return (f"translation_mm = [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}]\n"
            f"rotvec_rad = [{rv[0]:.6f}, {rv[1]:.6f}, {rv[2]:.6f}]")


MISTAKES = {
    "polarity": (("diameter_mm = 10.0 },", 'diameter_mm = 10.0, polarity = "bright" },'),
                 ('polarity = "dark"', 'polarity = "bright"')),
    "T_right_left": ((RIG, _inverted_rig()),),
    "working_distance_mm": (("working_distance_mm = [300.0, 2000.0]",
                             "working_distance_mm = [300.0, 500.0]"),),
    "min_contrast": (("min_contrast = 25.0 ", "min_contrast = 250.0"),),
}
KEYS = {
    "polarity": "object.features[*].polarity",
    "T_right_left": "calibration.stereo.T_right_left",
    "working_distance_mm": "vision.working_distance_mm",
    "min_contrast": "vision.min_contrast",
}


@pytest.mark.parametrize("mistake", sorted(MISTAKES))
def test_check_names_the_key_of_a_mistake_the_images_show(
        mistake: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # the example's replay folder is relative: config/samples
    text = EXAMPLE
    for old, new in MISTAKES[mistake]:
        assert old in text, old
        text = text.replace(old, new)
    cfg = tmp_path / f"{mistake}.toml"
    cfg.write_text(text)
    rc = main(["check", "-c", str(cfg), "--running"])
    err = capsys.readouterr().err
    assert rc == EXIT_CONFIG, err
    assert f"{KEYS[mistake]}:" in err, err


def test_example_passes_with_its_sample_frames(capsys: pytest.CaptureFixture[str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    assert main(["check", "-c", str(REPO / "config" / "example.toml"), "--running"]) == 0, \
        capsys.readouterr().err


def test_pallet_sample_passes(capsys: pytest.CaptureFixture[str]) -> None:
    """config/samples/pallet.toml (pick lists, docs/picklists.md) is a valid, commissionable
    cell."""
    assert main(["check", "-c", str(REPO / "config" / "samples" / "pallet.toml"),
                 "--running"]) == 0, capsys.readouterr().err
