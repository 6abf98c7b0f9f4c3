"""The setup page's choices (``vgripd.service.web.setupchoose``) without a daemon: the camera and
link tables built from the page's form (each refusal naming the field), written into the include
``vgripd init`` lays out for them (never the main file; an older layout refused naming where the
section lives), the link types' example settings, the OPC UA contract as the docs name it, and
the camera settings following the camera into its include."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.unit.service.web.test_setup_steps import apply
from vgripd.config import load_config
from vgripd.registry import LINKS
from vgripd.service.host.configtxn import EditRefused
from vgripd.service.web.camsettings import settings_target
from vgripd.service.web.setupchoose import (
    ChoiceError,
    camera_section,
    link_defaults,
    link_kind,
    links_section,
    opcua_nodes,
    section_edit,
)

LINK = {"type": "modbus_server", "host": "127.0.0.1", "port": 1502}


def layout(tmp_path: Path, camera_in_main: bool = False) -> Path:
    """``vgripd init``'s layout (camera and links in includes), or the older one that kept
    them in the main file."""
    names = ["cell.toml", "reference.toml"]
    (tmp_path / "cell.toml").write_text("# empty\n")
    (tmp_path / "reference.toml").write_text("# empty\n")
    main_text = ""
    camera = '[camera]\ntype = "board"\nplate = true\n'
    links = '[[links]]\ntype = "modbus_server"\nhost = "127.0.0.1"\nport = 1502\n'
    if camera_in_main:
        main_text = camera + links
    else:
        (tmp_path / "camera.toml").write_text(camera)
        (tmp_path / "links.toml").write_text(links)
        names += ["camera.toml", "links.toml"]
    main = tmp_path / "vgripd.toml"
    main.write_text(json.dumps({"include": [str(tmp_path / n) for n in names]})[1:-1]
                    .replace('"include":', "include =") + "\n" + main_text)
    return main


def test_a_discovered_pair_becomes_the_camera_table_with_its_names() -> None:
    table = camera_section({"type": "aravis", "cameras": [
        {"name": "left", "serial": "GV01"}, {"name": "right", "ip": "127.0.0.2"}]},
        {"type": "board", "plate": True})
    assert table == {"type": "aravis", "trigger": "software", "cameras": [
        {"name": "left", "serial": "GV01"}, {"name": "right", "ip": "127.0.0.2"}]}
    # the same type keeps the running settings (exposure, ROI): only the devices change
    current = {"type": "pylon", "exposure_us": 5000.0, "trigger": "hardware",
               "cameras": [{"name": "a", "serial": "1"}]}
    table = camera_section({"type": "pylon", "cameras": [{"name": "top", "serial": "2"}]},
                           current)
    assert table["exposure_us"] == 5000.0
    assert table["trigger"] == "hardware"
    assert table["cameras"] == [{"name": "top", "serial": "2"}]
    assert camera_section({"type": "synthetic"}, current) == {"type": "synthetic"}


@pytest.mark.parametrize(("body", "named"), [
    ({"type": "webcam"}, "camera.type: one of pylon, aravis"),
    ({"type": "pylon", "cameras": []}, "camera.cameras: 1 to 8 cameras"),
    ({"type": "pylon", "cameras": [{"name": "1x", "serial": "A"}]}, "camera.cameras[0].name"),
    ({"type": "pylon", "cameras": [{"name": "a", "serial": "A"}, {"name": "a", "serial": "B"}]},
     "camera.cameras[1].name: 'a' names two cameras"),
    ({"type": "aravis", "cameras": [{"name": "a", "serial": "A", "ip": "127.0.0.2"}]},
     "camera.cameras[0]: exactly one of serial, ip, user_name"),
    ({"type": "synthetic", "cameras": [{"name": "a", "serial": "A"}]},
     "camera.cameras: a synthetic camera has no devices"),
    ({"type": "board", "options": {"type": "pylon"}}, "camera options"),
    ([1], "a JSON object"),
])
def test_a_bad_camera_choice_names_its_field(body: object, named: str) -> None:
    with pytest.raises(ChoiceError, match=named.replace("[", r"\[").replace("]", r"\]")):
        camera_section(body, {"type": "board"})


def test_links_are_checked_for_their_type_and_count() -> None:
    assert links_section({"links": [LINK]}) == [LINK]
    with pytest.raises(ChoiceError, match=r"links\[1\]\.type: one of .*got 'profinet'"):
        links_section({"links": [LINK, {"type": "profinet"}]})
    with pytest.raises(ChoiceError, match="1 to 8 links"):
        links_section({"links": []})


def test_the_choices_go_into_their_includes_and_load_back(tmp_path: Path) -> None:
    main = layout(tmp_path)
    camera = camera_section({"type": "synthetic"}, {"type": "board"})
    judged = apply(main, section_edit("camera.", "camera", camera))
    assert tomllib.loads(judged.text(tmp_path / "camera.toml")) == {"camera": camera}
    links = links_section({"links": [{**LINK, "port": 1503},
                                     {"type": "robot_socket", "host": "127.0.0.1",
                                      "port": 7001}]})
    judged = apply(main, section_edit("links", "links", links))
    assert tomllib.loads(judged.text(tmp_path / "links.toml"))["links"] == links
    for path, data in judged.files.items():
        Path(path).write_bytes(data)
    config = load_config(main)
    assert [(link.type, link.options()["port"]) for link in config.links] == [
        ("modbus_server", 1503), ("robot_socket", 7001)]


def test_an_older_layout_is_refused_naming_the_main_file(tmp_path: Path) -> None:
    main = layout(tmp_path, camera_in_main=True)
    with pytest.raises(EditRefused, match=f"{main}: camera is set in the main config file"):
        apply(main, section_edit("camera.", "camera", {"type": "synthetic"}))
    with pytest.raises(EditRefused, match=f"{main}: links is set in the main config file"):
        apply(main, section_edit("links", "links", [LINK]))


def test_camera_settings_follow_the_camera_into_its_include(tmp_path: Path) -> None:
    assert settings_target(layout(tmp_path)) == tmp_path / "camera.toml"
    older = tmp_path / "older"
    older.mkdir()
    main = layout(older, camera_in_main=True)
    (older / "cell.toml").write_text("[object]\nfeatures = []\n")  # the tuning save's file
    assert settings_target(main) == older / "cell.toml"


def test_every_link_type_is_offered_with_its_example_settings() -> None:
    defaults = link_defaults()
    assert set(defaults) == set(LINKS)
    assert defaults["s7"]["example"] == "s7.toml"
    assert defaults["opcua"]["type"] == "opcua"
    assert "port" in defaults["ur_rtde"] or "host" in defaults["ur_rtde"]
    assert [link_kind(t) for t in ("s7", "opcua", "robot_socket")] == [
        "registers", "nodes", "robot"]


def test_the_opcua_contract_lists_the_nodes_the_docs_name() -> None:
    pytest.importorskip("asyncua", reason="pip install 'vgripd[opcua]'")
    nodes = opcua_nodes()
    docs = (REPO / "docs" / "opcua.md").read_text()
    variables = [v["node"].removeprefix("VisionSystem.Plc.") for v in nodes["variables"]]
    assert variables[-2:] == ["ResultId", "Sequence"]  # written last
    for name in variables:
        assert f"`{name}`" in docs, name
    for method in nodes["methods"]:
        assert f"`Plc.{method['node'].removeprefix('VisionSystem.Plc.')}(" in docs, method
    assert nodes["namespace"] == "urn:vgripd:vision-system"


def test_cameras_json_lists_what_the_stacks_find() -> None:
    out = subprocess.run([sys.executable, "-m", "vgripd", "cameras", "--json"],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    found = json.loads(out)
    assert set(found) == {"devices", "unavailable"}
    for device in found["devices"]:
        assert device["stack"] in ("pylon", "aravis")
        assert device["serial"]
