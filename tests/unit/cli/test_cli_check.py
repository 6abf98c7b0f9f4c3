"""`vgripd check` / `vgripd run` judge the links against output.vendor when the config is loaded.

Each link class declares what it can carry (``RobotLink.capabilities``); a combination that can
never work is a config error (exit 78) naming both fields, instead of a status 99 or
OUT_OF_LIMITS on every job.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from vgripd.__main__ import EXIT_CONFIG, main
from vgripd.config import config_from_dict, load_config
from vgripd.errors import ConfigError

UR_LINK = '[[links]]\ntype = "ur_rtde"\nhost = "192.168.1.10"\n'
MODBUS_LINK = '[[links]]\ntype = "modbus_server"\nport = 5020\n'


def write(tmp_path: Path, text: str, name: str = "vgripd.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def check(path: Path, capsys: pytest.CaptureFixture[str], command: str = "check") -> tuple[int, str]:
    rc = main([command, "-c", str(path)])
    out = capsys.readouterr()
    return rc, out.out + out.err


@pytest.mark.parametrize("command", ["check", "run"])
def test_ur_link_with_kuka_vendor_is_refused_naming_both_fields(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    cfg = write(tmp_path, UR_LINK + '\n[output]\nvendor = "kuka"\n')
    rc, text = check(cfg, capsys, command)
    assert rc == EXIT_CONFIG, text
    assert f'{cfg}: links[0].type = "ur_rtde" cannot carry output.vendor = "kuka"' in text
    assert 'only the "ur" convention' in text
    assert 'set output.vendor = "ur"' in text


@pytest.mark.parametrize("command", ["check", "run"])
def test_matrix_vendor_on_a_modbus_link_is_refused_naming_both_fields(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    cfg = write(tmp_path, '[output]\nvendor = "matrix"\n\n' + MODBUS_LINK)
    rc, text = check(cfg, capsys, command)
    assert rc == EXIT_CONFIG, text
    assert f'{cfg}: links[0].type = "modbus_server" cannot carry output.vendor = "matrix"' in text
    assert "at most 7 pose values" in text
    assert '"matrix" has 16' in text


def test_the_default_vendor_is_named_as_the_default(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, text = check(write(tmp_path, UR_LINK), capsys)
    assert rc == EXIT_CONFIG
    assert 'cannot carry output.vendor = "kuka" (the default)' in text


def test_every_link_is_judged_and_an_unknown_type_is_named(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = write(tmp_path, MODBUS_LINK + UR_LINK + '[[links]]\ntype = "profinet"\n'
                + '\n[output]\nvendor = "abb"\n')
    rc, text = check(cfg, capsys)
    assert rc == EXIT_CONFIG
    assert 'links[0]' not in text  # a register link carries abb's 7 values
    assert 'links[1].type = "ur_rtde" cannot carry output.vendor = "abb"' in text
    assert 'links[2].type = "profinet": unknown link type' in text


def test_the_refusal_blames_the_file_that_set_the_links(tmp_path: Path) -> None:
    write(tmp_path, UR_LINK, "links.toml")
    cfg = write(tmp_path, 'include = ["links.toml"]\n[output]\nvendor = "fanuc"\n')
    with pytest.raises(ConfigError, match=r"links\.toml: links\[0\]\.type = \"ur_rtde\" cannot "
                                          r"carry output\.vendor = \"fanuc\""):
        load_config(cfg)


def test_an_unknown_vendor_is_refused_at_load(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="output.vendor: .*unknown vendor 'UR'"):
        config_from_dict({"output": {"vendor": "UR"}})


def test_ur_link_with_ur_vendor_passes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = write(tmp_path, UR_LINK + '\n[output]\nvendor = "ur"\n')
    rc, text = check(cfg, capsys)
    assert rc == 0, text
    assert text.startswith(f"OK {cfg}: camera synthetic, links ur_rtde, output ur")


@pytest.mark.parametrize("vendor", ["kuka", "abb", "fanuc", "ur", "staubli", "nachi"])
@pytest.mark.parametrize("link", ["modbus_server", "modbus_client", "modbus_rtu"])
def test_register_links_pass_with_six_and_seven_value_vendors(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], link: str, vendor: str) -> None:
    options = {"modbus_server": "port = 5020", "modbus_client": 'host = "10.0.0.5"',
               "modbus_rtu": 'port = "/dev/ttyUSB0"'}[link]
    cfg = write(tmp_path, f'[[links]]\ntype = "{link}"\n{options}\n\n[output]\nvendor = "{vendor}"\n')
    rc, text = check(cfg, capsys)
    assert rc == 0, text
    assert f"output {vendor}" in text


def test_a_ur_and_a_modbus_link_share_the_ur_vendor(tmp_path: Path) -> None:
    cfg = write(tmp_path, MODBUS_LINK + UR_LINK + '\n[output]\nvendor = "ur"\n')
    assert [s.type for s in load_config(cfg).links] == ["modbus_server", "ur_rtde"]
