"""A config written by ``vgripd init --allow-edit`` runs as is, and the web view's tuning save
lands in the state directory's ``cell.toml``: nothing moved by hand, the main file untouched."""

from __future__ import annotations

import contextlib
import io
import tomllib
from pathlib import Path

import aiohttp

from tests.integration.test_daemon import Plc
from tests.integration.test_web_reload import job, post, running_file
from vgripd.__main__ import main
from vgripd.types import Status


async def test_the_page_saves_into_the_include_init_wrote(tmp_path: Path) -> None:
    source = tmp_path / "source.toml"
    source.write_text('[camera]\ntype = "synthetic"\nseed = 11\nmax_tilt_deg = 2.0\n\n'
                      '[[links]]\ntype = "modbus_server"\nhost = "127.0.0.1"\nport = 0\n\n'
                      '[status]\nport = 0\n')
    config, state = tmp_path / "etc" / "vgripd.toml", tmp_path / "state"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["init", "--from", str(source), "-c", str(config), "--state-dir",
                     str(state), "--allow-edit"]) == 0
    token = tomllib.loads((state / "access.toml").read_text())["status"]["token"]
    before = config.read_bytes()
    auth = {"Authorization": f"Bearer {token}"}
    async with running_file(config) as run, Plc(run.port()) as plc, \
            aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        assert await job(plc, run, 1) == Status.OK
        code, out = await post(s, f"{base}/api/tuning", {"vision": {"min_contrast": 21.0}},
                               headers=auth)
        assert code == 200, out
        assert run.daemon.config.vision.min_contrast == 21.0
        assert await job(plc, run, 2) == Status.OK
    assert tomllib.loads((state / "cell.toml").read_text())["vision"]["min_contrast"] == 21.0
    assert config.read_bytes() == before
