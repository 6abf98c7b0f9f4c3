"""The setup page's server-side steps (``vgripd.service.web.setupsteps``) without a daemon:
``vgripd check``'s output sorted to the steps, where each step writes (the include that holds
the keys, else the layout's file, never the main file), the edits' bytes loaded back as the
daemon loads a config, and the progress file read back whatever it holds."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from vgripd.config import DEMO_CALIBRATION, load_config
from vgripd.configsnapshot import Snapshot
from vgripd.errors import ConfigError
from vgripd.serialize import toml_from_dict
from vgripd.service.host.configtxn import EditRefused
from vgripd.service.web.setupsteps import (
    calibration_edit,
    dump_progress,
    flange_text,
    hand_eye_values,
    include_for,
    load_progress,
    object_edit,
    parse_check,
    step_of,
)

NAMES = ("rig.toml", "handeye.toml", "cell.toml", "reference.toml")
RIG = toml_from_dict({"about": {"rms_px": 0.05}, "calibration": {
    k: v for k, v in DEMO_CALIBRATION.model_dump(mode="json", exclude_none=True).items()
    if k in ("left", "right", "stereo")}})
HAND_EYE = {"mounting": "fixed", "T_base_camera": {"translation_mm": [525.0, 100.0, 700.0],
                                                   "rotvec_rad": [3.13729, 0.0, 0.16442]}}


def cell(tmp_path: Path, main_extra: str = "") -> Path:
    """The layout demo --setup writes: a main file and four empty includes."""
    for name in NAMES:
        (tmp_path / name).write_text("# empty\n")
    main = tmp_path / "vgripd.toml"
    main.write_text(f"include = {[str(tmp_path / n) for n in NAMES]!r}\n".replace("'", '"')
                    + '[camera]\ntype = "board"\nplate = true\n' + main_extra
                    + '[[links]]\ntype = "modbus_server"\nhost = "127.0.0.1"\nport = 1502\n')
    return main


def apply(main: Path, edit) -> Snapshot:  # noqa: ANN001
    before = Snapshot.read(main)
    changes = edit(before)
    assert str(main) not in {str(p) for p in changes}  # the main file is never written
    return before.replaced(changes)


def test_check_lines_go_to_their_steps() -> None:
    err = ("vgripd: config error: /c.toml: not calibrated: camera models: no [calibration] "
           "section\n/c.toml: links.0.port: 502 is privileged")
    ok, findings = parse_check(78, "", err, "/c.toml")
    assert not ok
    assert [(f.level, f.step) for f in findings] == [("ERROR", "calibration"),
                                                      ("ERROR", "link")]
    assert findings[0].message.startswith("not calibrated: camera models")
    out = ("OK /c.toml: camera board, links modbus_server\n"
           "warning: /c.toml: reference.toml: not taught, its jobs end NOT_CALIBRATED\n"
           "warning: /c.toml: calibration.hand_eye: no camera-model fingerprint")
    ok, findings = parse_check(0, out, "", "/c.toml")
    assert ok
    assert [(f.level, f.step) for f in findings] == [("WARNING", "object"),
                                                      ("WARNING", "handeye")]
    assert step_of("camera.exposure_us: out of range") == "cameras"
    assert step_of("something else entirely") == "pick"
    assert parse_check(1, "", "", "/c.toml")[1][0].message == "vgripd check exited with 1"


def test_calibration_and_hand_eye_are_written_together_into_their_includes(
        tmp_path: Path) -> None:
    main = cell(tmp_path)
    # the rig alone cannot load (no hand-eye): the page keeps it until the hand-eye step
    judged = apply(main, calibration_edit(RIG, HAND_EYE))
    rig = tomllib.loads(judged.text(tmp_path / "rig.toml"))
    he = tomllib.loads(judged.text(tmp_path / "handeye.toml"))
    assert set(rig["calibration"]) == {"left", "right", "stereo"}
    assert he["calibration"]["hand_eye"] == HAND_EYE
    assert he["about"]["camera_model"]  # the fingerprint of the camera model it belongs to
    config = load_config(judged.main, judged.files)
    assert config.calibration is not None
    assert config.calibration.left.fx == DEMO_CALIBRATION.left.fx
    assert config.load_warnings == []
    # A recalibration alone leaves a hand-eye made with another camera model (the config
    # refuses that pair, naming the order), so the page writes the rig with the hand-eye
    # confirmed again: the fingerprint then follows the new model.
    for path, data in judged.files.items():
        Path(path).write_bytes(data)
    new_rig = RIG.replace("1805.2", "1806.0")
    alone = apply(main, calibration_edit(new_rig, None))
    with pytest.raises(ConfigError, match="calibrate the hand-eye again"):
        load_config(alone.main, alone.files)
    again = apply(main, calibration_edit(new_rig, HAND_EYE))
    assert load_config(again.main, again.files).calibration.left.fx == 1806.0  # type: ignore[union-attr]
    assert tomllib.loads(again.text(tmp_path / "handeye.toml"))["about"] != he["about"]


def test_a_key_in_the_main_file_is_never_rewritten(tmp_path: Path) -> None:
    main = cell(tmp_path, '[object]\nname = "x"\nfeatures = [' + ", ".join(
        f'{{name = "m{i}", kind = "circle", diameter_mm = 10.0, xyz_mm = [{i * 30}, {i * i}, 0]}}'
        for i in range(4)) + "]\n")
    with pytest.raises(EditRefused, match="main config file"):
        include_for(Snapshot.read(main), "object.")


def test_without_the_layouts_include_the_write_is_refused_naming_it(tmp_path: Path) -> None:
    main = cell(tmp_path)
    text = main.read_text()
    main.write_text(text.replace(f'"{tmp_path / "cell.toml"}", ', ""))
    with pytest.raises(EditRefused, match="none is named cell.toml"):
        include_for(Snapshot.read(main), "object.")


def test_the_object_is_a_reference_object_of_the_chosen_marks(tmp_path: Path) -> None:
    main = cell(tmp_path)
    (tmp_path / "reference.toml").write_text(
        '[reference]\nT_base_obj = {translation_mm = [1, 2, 3]}\n'
        'grip = {translation_mm = [600, 100, 60], rotvec_rad = [3.14159, 0, 0]}\n')
    marks = [{"name": f"m{i}", "diameter_mm": 9.96, "xyz_mm": xyz} for i, xyz in enumerate(
        [[582.0, 144.2, 10.7], [536.9, 124.9, 10.6], [657.3, 117.9, 22.8], [569.1, 82.5, 10.8]])]
    judged = apply(main, object_edit("part", marks))
    config = load_config(judged.main, judged.files)
    assert config.object.definition == "reference"
    assert [f.name for f in config.object.features] == ["m0", "m1", "m2", "m3"]
    assert config.object.features[2].xyz_mm == (657.3, 117.9, 22.8)
    assert config.object.features[0].diameter_mm == 10.0  # rounded to 0.1 mm
    assert config.reference.T_base_obj is None  # a reference object's frame is the base's
    assert config.reference.grip is not None  # the taught grip stays


def test_hand_eye_values_name_the_field() -> None:
    assert hand_eye_values({"translation_mm": [1, 2, 3], "rotvec_rad": [0, 0, 0.5]}) == {
        "mounting": "fixed", "T_base_camera": {"translation_mm": [1.0, 2.0, 3.0],
                                               "rotvec_rad": [0.0, 0.0, 0.5]}}
    with pytest.raises(ValueError, match="T_base_camera.rotvec_rad"):
        hand_eye_values({"translation_mm": [1, 2, 3], "rotvec_rad": [0, 0]})
    with pytest.raises(ValueError, match="translation_mm"):
        hand_eye_values({"translation_mm": [1, True, 3], "rotvec_rad": [0, 0, 0]})


def test_progress_reads_back_and_survives_garbage(tmp_path: Path) -> None:
    path = tmp_path / "progress.json"
    assert load_progress(path) == {"done": {}}
    path.write_bytes(dump_progress({"done": {"cameras": 1.0}, "board": "chessboard:9x6:30"}))
    assert load_progress(path)["done"] == {"cameras": 1.0}
    path.write_text("{not json")
    assert load_progress(path) == {"done": {}}
    path.write_text('{"done": []}')
    assert load_progress(path) == {"done": {}}


def test_flange_text_reads_as_the_flange_file_line() -> None:
    import numpy as np
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = [412.34, -198.7, 502.1]
    assert flange_text(T.tolist()) == "412.3 -198.7 502.1 mm, 0.1000 -0.2000 0.3000 rad"
    assert flange_text(None) == ""
