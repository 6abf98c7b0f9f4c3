"""``vgripd init``: the main file plus the writable cell includes, judged by ``vgripd check``,
and each include is the file the web view writes for its kind of edit."""

from __future__ import annotations

import contextlib
import io
import re
import stat
import tomllib
from pathlib import Path

import pytest

from tests.conftest import REPO, need_camera_sdk
from vgripd.__main__ import EXIT_USAGE, main
from vgripd.config import load_config
from vgripd.service.web.commission import holding_include, tuning_target

EXAMPLES_DIR = REPO / "config" / "examples"
EXAMPLES = sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml"))


def _run(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = main(list(argv))
    return rc, out.getvalue()


def _init(tmp_path: Path, *extra: str) -> tuple[Path, Path]:
    config, state = tmp_path / "etc" / "vgripd.toml", tmp_path / "state"
    rc, text = _run("init", "-c", str(config), "--state-dir", str(state), *extra)
    assert rc == 0, text
    return config, state


@pytest.mark.parametrize("example", [None, *EXAMPLES])
def test_init_writes_a_config_check_accepts(example: str | None, tmp_path: Path) -> None:
    if example:
        need_camera_sdk(EXAMPLES_DIR / f"{example}.toml")
    config, state = _init(tmp_path, *(["--example", example] if example else []))
    rc, text = _run("check", "--no-camera", "-c", str(config))
    assert rc == 0, text
    # fingerprints recorded: the files belong together. (A port another program holds right
    # now, e.g. a second suite's robot socket on 50100, is the machine's state, not the files'.)
    warnings = [line for line in text.splitlines()
                if "warning" in line and not re.search(r"\.port: \S+ is in use", line)]
    assert not warnings, text
    assert {p.name for p in state.iterdir()} >= {"rig.toml", "cell.toml", "reference.toml"}


def test_each_edit_of_the_page_lands_in_its_own_include(tmp_path: Path) -> None:
    config, state = _init(tmp_path)
    assert tuning_target(config) == state / "cell.toml"
    assert holding_include(config, "reference.", "teach") == state / "reference.toml"
    assert holding_include(config, "calibration.hand_eye.", "accept") == state / "handeye.toml"
    # the main file holds no cell section the page would have to move
    text = config.read_text()
    for section in ("[object]", "[vision]", "[reference", "[calibration", "[camera",
                    "[[links"):
        assert section not in text
    # the setup page's cameras and link steps write the camera and the links there
    assert tomllib.loads((state / "camera.toml").read_text())["camera"]["type"] == "synthetic"
    assert tomllib.loads((state / "links.toml").read_text())["links"][0]["port"] == 1502


def test_allow_edit_writes_a_private_token(tmp_path: Path) -> None:
    config, state = _init(tmp_path, "--allow-edit")
    access = state / "access.toml"
    assert stat.S_IMODE(access.stat().st_mode) == 0o600
    loaded = load_config(config)
    assert loaded.status.allow_config_edit
    assert loaded.status.token
    assert len(loaded.status.token) >= 16
    assert loaded.status.token not in config.read_text()


def test_existing_files_are_kept_unless_forced(tmp_path: Path) -> None:
    config, state = _init(tmp_path)
    (state / "cell.toml").write_text("# mine\n")
    rc, text = _run("init", "-c", str(config), "--state-dir", str(state))
    assert rc == EXIT_USAGE
    assert "exist: nothing written" in text
    assert str(config) in text
    assert (state / "cell.toml").read_text() == "# mine\n"
    _init(tmp_path, "--force")
    assert (state / "cell.toml").read_text() != "# mine\n"


def test_an_unknown_example_names_the_known_ones(tmp_path: Path) -> None:
    rc, text = _run("init", "-c", str(tmp_path / "c.toml"), "--state-dir", str(tmp_path),
                    "--example", "nope")
    assert rc == 78
    assert "--example nope" in text
    assert "robot-socket-kuka" in text
    assert not (tmp_path / "c.toml").exists()


def test_a_recalibrated_rig_refuses_the_old_hand_eye_except_to_the_commands_that_redo_it(
        tmp_path: Path) -> None:
    """The walked hand-eye's plan and walk take the old hand-eye as a rough start and teaching
    takes the old reference (a warning each); every other load refuses them, and teaching
    still refuses a hand-eye of another rig."""
    from vgripd.errors import ConfigError

    main_file = tmp_path / "vgripd.toml"
    assert main(["init", "-c", str(main_file), "--state-dir", str(tmp_path / "state")]) == 0
    rig = tmp_path / "state" / "rig.toml"
    rig.write_text(rig.read_text().replace("fx = 1805.2", "fx = 1806.0"))
    with pytest.raises(ConfigError, match="hand-eye was made with camera model"):
        load_config(main_file)
    with pytest.raises(ConfigError, match="hand-eye was made with camera model"):
        load_config(main_file, redo="reference")
    config = load_config(main_file, redo="hand_eye")
    assert [w.split(":")[0] for w in config.load_warnings] == [
        str(tmp_path / "state" / "handeye.toml"), str(tmp_path / "state" / "reference.toml")]
