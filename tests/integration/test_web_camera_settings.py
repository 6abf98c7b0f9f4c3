"""Exposure and gain from the web view (``POST /api/cameras/{j}/settings``) against the real
daemon: the synthetic camera in the worker process takes them live (the next picture is darker),
the include keeps them for the next start (numbered backup, audit entry); out of the camera's
range, without the token, or during a job, nothing changes."""

from __future__ import annotations

import importlib.util
import json
import tomllib
from pathlib import Path

import aiohttp
import numpy as np
import pytest

from tests.conftest import REPO, need
from tests.integration.test_daemon import Plc
from tests.integration.test_web import _chromium, _until
from tests.integration.test_web_reload import TOKEN, job, post, running_file, write_cell
from vgripd.config import load_config
from vgripd.peer.registers import Reg
from vgripd.types import Status

SAMPLES = REPO / "config" / "samples"


def slow_cell(folder: Path) -> Path:
    """``write_cell``'s cell with a slower render (a job lasts long enough to be seen)."""
    main = write_cell(folder)
    main.write_text(main.read_text().replace("max_tilt_deg = 2.0",
                                             "max_tilt_deg = 2.0\nsupersample = 16"))
    return main


async def test_exposure_and_gain_are_applied_live_and_kept_in_the_include(
        tmp_path: Path) -> None:
    main = slow_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    async with running_file(main) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        url = f"{base}/api/cameras/0/settings"
        assert await job(plc, run, 1) == Status.OK
        before = float(np.mean((await run.daemon.rooms.cameras.camera.grab(10.0)).views[0]))

        # Without the token (or with a wrong one): refused, nothing written.
        code, _ = await post(s, url, {"exposure_us": 5000}, headers={})
        assert code == 403
        code, _ = await post(s, url, {"exposure_us": 5000},
                             headers={"Authorization": "Bearer x"})
        assert code == 403

        # Out of the camera's range: 400 naming the feature and the range; nothing changes.
        code, text = await post(s, url, {"exposure_us": 5})
        assert code == 400
        assert "exposure_us" in text, text
        assert "20 .. 1e+06" in text, text
        code, text = await post(s, url, {"gain_db": 40})
        assert code == 400
        assert "gain_db" in text, text
        assert "0 .. 24" in text, text
        assert not (tmp_path / "cell.toml.1").exists()

        # Half the exposure: read back, the next picture is darker, the include keeps it.
        code, out = await post(s, url, {"exposure_us": 5000})
        assert code == 200, out
        assert out["read_back"]["camera"]["ExposureTime"] == 5000.0
        assert out["saved"]["applied"], out
        assert out["saved"]["diff"] == ["camera.exposure_us: (unset) -> 5000.0"]
        after = float(np.mean((await run.daemon.rooms.cameras.camera.grab(10.0)).views[0]))
        assert after < 0.6 * before, (before, after)
        assert tomllib.loads(cell.read_text())["camera"]["exposure_us"] == 5000.0
        assert "camera" not in tomllib.loads((tmp_path / "cell.toml.1").read_text())
        assert load_config(main).camera.exposure_us == 5000.0  # the next start
        assert run.daemon.reloader is not None
        assert run.daemon.reloader.audit[0].diff == ("camera.exposure_us: (unset) -> 5000.0",)
        async with s.get(f"{base}/api/cameras/settings") as r:
            assert (await r.json())["exposure_us"] == 5000.0
        # A reload of the saved file: the camera already runs with it, no restart named.
        outcome = await run.daemon.reloader.reload("test")
        assert outcome.applied, outcome
        assert "camera.exposure_us" not in outcome.restart, outcome

        # During a job: 409 saying why; the camera and the file stay.
        await plc.trigger(2)
        await run.busy()
        code, text = await post(s, url, {"exposure_us": 8000})
        assert code == 409
        assert "between jobs" in text
        assert (await plc.result(2))[Reg.STATUS] == Status.OK
        assert tomllib.loads(cell.read_text())["camera"]["exposure_us"] == 5000.0
        assert not (tmp_path / "cell.toml.2").exists()


async def test_chromium_sets_the_exposure_from_the_live_camera_page(tmp_path: Path) -> None:
    """In headless Chromium: an out-of-range exposure is refused with the range shown; a good
    one is applied (read back shown), written to the include and listed in the audit."""
    main = write_cell(tmp_path)
    async with running_file(main) as run:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        async with _chromium(tmp_path, base + "/") as evaluate:
            text = "(id) => document.getElementById(id)?.textContent ?? ''"
            assert await _until(evaluate, "document.getElementById('btn-cam-set')?.hidden "
                                          "=== false")

            async def apply(exposure: str) -> str:
                await evaluate(f"""(() => {{
                    document.getElementById('token').value = {json.dumps(TOKEN)};
                    document.getElementById('cam-result').textContent = '';
                    document.getElementById('cam-exposure_us').value = {json.dumps(exposure)};
                    document.getElementById('btn-cam-set').click();
                    return true;
                }})()""")
                result: str = await _until(evaluate, f"({text})('cam-result')")
                return result

            refused = await apply("3")
            assert refused.startswith("REFUSED (400)"), refused
            assert "20 .. 1e+06" in refused, refused
            applied = await apply("12000")
            assert applied.startswith("APPLIED"), applied
            assert "12000" in applied, applied
            assert "saved to cell.toml" in applied, applied
            assert await _until(evaluate, "[...document.querySelectorAll('#audit tbody tr')]"
                                          ".some((r) => r.textContent.includes("
                                          "'camera.exposure_us'))")
        assert tomllib.loads((tmp_path / "cell.toml").read_text())["camera"]["exposure_us"] \
            == 12000.0


def pylon_cell(folder: Path) -> Path:
    """``write_cell`` with two cameras of pylon's emulation (``PYLON_CAMEMU``) fed the demo
    cell's sample images, ``exposure_us`` set in the main file; no calibration (jobs would be
    NOT_CALIBRATED; none is run)."""
    main = write_cell(folder)
    feed = ('{{ TestImageSelector = "Off", ImageFileMode = "On", ImageFilename = "{}" }}')
    camera = "\n".join([
        '[camera]', 'type = "pylon"', "exposure_us = 4000.0",
        "roi = { width = 1280, height = 1024 }",
        *(f'[[camera.cameras]]\nserial = "0815-000{k}"\nfeatures = '
          + feed.format(SAMPLES / f"{side}_00.png") for k, side in enumerate(("left", "right"))),
        ""])
    text = main.read_text()
    start, end = text.index("[camera]"), text.index("[[links]]")
    main.write_text(text[:start] + camera + "\n" + text[end:])
    return main


@pytest.mark.timeout(120, method="thread")  # pylon's waits and SIGALRM: test_cameras_pylon.py
async def test_pylon_emulation_takes_exposure_from_the_page_with_its_range_checked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")
    monkeypatch.setenv("PYLON_CAMEMU", "3")  # the worker process inherits it
    main = pylon_cell(tmp_path)
    async with running_file(main) as run, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        url = f"http://127.0.0.1:{run.daemon.status_server.port}/api/cameras/1/settings"
        code, out = await post(s, url, {"exposure_us": 6000, "gain_db": 2.0})
        assert code == 200, out
        for name in ("left", "right"):
            assert out["read_back"][name]["ExposureTime"] == pytest.approx(6000, rel=0.01)
            assert out["read_back"][name]["Gain"] == pytest.approx(2.0, abs=0.1)
        # The main file sets exposure_us: applied live, not written, the answer says where.
        assert not out["saved"]["applied"]
        assert "camera.exposure_us is set in" in out["saved"]["message"]
        assert "vgripd.toml" in out["saved"]["message"]
        assert "camera" not in tomllib.loads((tmp_path / "cell.toml").read_text())
        assert not (tmp_path / "cell.toml.1").exists()

        code, text = await post(s, url, {"exposure_us": 1e12})
        assert code == 400
        assert "camera left (Basler Emulation" in text, text
        assert "ExposureTime" in text, text
        assert "out of the device's range" in text, text
        async with s.get(url.replace("/1/settings", "/settings")) as r:
            assert (await r.json())["exposure_us"] == 6000.0  # the refused value changed nothing
