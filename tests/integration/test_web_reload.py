"""Reload without a restart: the web view's tuning save and ``POST /api/reload``, and SIGHUP to a
``vgripd run`` process (``systemctl reload``). A synthetic camera renders dark marks (its
config is the one the daemon started with); the pipeline's polarity is edited in the config's
include. The PLC (a real pymodbus client) stays connected through every reload.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.conftest import REPO
from tests.integration.test_daemon import Plc, Run, make_config
from tests.integration.test_daemon_process import _free_port
from tests.integration.test_web import _chromium, _until
from vgripd.config import load_config, read_config_data
from vgripd.peer.registers import Reg
from vgripd.serialize import toml_from_dict
from vgripd.service.daemon import Daemon
from vgripd.service.ops.reload import Reloader
from vgripd.types import Status

pytestmark = pytest.mark.slow

TOKEN = "a-test-token-of-32-characters-xx"
WAIT_S = 120.0  # two suites on two cores: a supersampled render takes a while
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def write_cell(folder: Path, *, polarity: str = "dark", link_port: int = 0,
               status: bool = True) -> Path:
    """``vgripd.toml`` (camera, link, web view) including ``cell.toml`` ([vision], [object])."""
    demo = make_config().model_dump(mode="json", exclude_none=True)
    for feature in demo["object"]["features"]:
        feature["polarity"] = polarity
    (folder / "cell.toml").write_text(toml_from_dict(
        {"vision": {"min_contrast": 25.0}, "object": demo["object"],
         "reference": demo["reference"]}))
    web = (f'[status]\nport = 0\ntoken = "{TOKEN}"\nallow_config_edit = true\n' if status
           else "[status]\nenabled = false\n")
    main = folder / "vgripd.toml"
    main.write_text(f"""include = ["cell.toml"]

[camera]
type = "synthetic"
seed = 11
max_tilt_deg = 2.0

[[links]]
type = "modbus_server"
host = "127.0.0.1"
port = {link_port}

{web}""")
    return main


@contextlib.asynccontextmanager
async def running_file(path: Path) -> AsyncIterator[Run]:
    daemon = Daemon(load_config(path))
    daemon.reloader = Reloader(daemon, path)
    run = Run(daemon)
    await daemon.start()
    try:
        yield run
    finally:
        await daemon.reloader.close()
        await daemon.stop()


async def job(plc: Plc, run: Run, seq: int) -> int:
    await plc.trigger(seq)
    words = await plc.result(seq)
    await run.job_done(seq)
    return words[Reg.STATUS]


async def post(session: aiohttp.ClientSession, url: str, body: Any = None,
               headers: dict[str, str] | None = None) -> tuple[int, Any]:
    async with session.post(url, json=body, headers=AUTH if headers is None else headers) as r:
        return r.status, (await r.json() if r.content_type == "application/json"
                          else await r.text())


async def between_jobs(call: Any, busy: int) -> tuple[int, Any]:
    """``await call()`` -> (status, body) until it is not ``busy`` (409/503: "a job runs, or
    the camera cannot grab: try again"; a grab between jobs slower than the preview's 2 s on a
    busy machine), within WAIT_S."""
    deadline = time.monotonic() + WAIT_S
    while True:
        code, out = await call()
        if code != busy or time.monotonic() > deadline:
            return code, out
        await asyncio.sleep(0.2)


async def preview(session: aiohttp.ClientSession, url: str) -> tuple[int, Any]:
    async with session.get(url) as r:
        return r.status, (dict(r.headers), r.content_type, await r.read())


async def test_a_tuning_save_applies_between_jobs_without_dropping_the_plc(
        tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    async with running_file(main) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        link = next(iter(run.daemon.rooms.links.links.values()))
        assert await job(plc, run, 1) == Status.OK

        # Without the token (or with a wrong one) nothing is written.
        code, _ = await post(s, f"{base}/api/tuning", {"polarity": "bright"}, headers={})
        assert code == 403
        code, _ = await post(s, f"{base}/api/reload", headers={"Authorization": "Bearer x"})
        assert code == 403
        assert not (tmp_path / "cell.toml.1").exists()

        # The wrong polarity, saved: applied at once, the next PLC job finds nothing.
        code, out = await post(s, f"{base}/api/tuning", {"polarity": "bright"})
        assert code == 200, out
        assert out["applied"]
        assert out["restart"] == []
        assert "object.features.0.polarity: 'dark' -> 'bright'" in out["diff"]
        assert (tmp_path / "cell.toml.1").read_text().count('"dark"') == 6  # the backup
        assert tomllib.loads(cell.read_text())["object"]["features"][0]["polarity"] == "bright"
        assert await job(plc, run, 2) == Status.NOT_FOUND

        # Tuned back: the next PLC job is OK, on the same connection, without a restart.
        code, out = await post(s, f"{base}/api/tuning", {"polarity": "dark",
                                                        "vision": {"min_contrast": 20}})
        assert code == 200, out
        assert "vision.min_contrast: 25.0 -> 20.0" in out["diff"]
        assert await job(plc, run, 3) == Status.OK
        assert run.daemon.config.vision.min_contrast == 20.0
        assert (tmp_path / "cell.toml.2").exists()

        # A bad edit: refused by the judge, the file put back, the running config kept.
        before = cell.read_text()
        code, out = await post(s, f"{base}/api/tuning", {"vision": {"min_contrast": -5}})
        assert code == 422, out
        assert not out["applied"]
        assert "vision.min_contrast" in out["message"]
        assert cell.read_text() == before
        assert run.daemon.config.vision.min_contrast == 20.0
        assert await job(plc, run, 4) == Status.OK

        # A trial on a fresh grab (between jobs): nothing applied.
        code, out = await between_jobs(lambda: post(
            s, f"{base}/api/tuning/try", {"polarity": "bright", "grab": True}), 409)
        assert code == 200, out
        assert out["job_id"] is None
        assert out["status"] == "NOT_FOUND"  # the marks are dark
        assert out["causes"][0]["key"] == "object.features[*].polarity"
        assert run.daemon.config.object.features[0].polarity == "dark"

        # A key only a restart can change is named, the rest applies.
        main.write_text(main.read_text().replace("max_tilt_deg = 2.0", "max_tilt_deg = 3.0"))
        code, out = await post(s, f"{base}/api/reload")
        assert code == 200, out
        assert out["restart"] == ["camera.max_tilt_deg"]
        assert "needs a restart" in out["message"]
        assert run.daemon.config.camera.max_tilt_deg == 2.0

        # Calibration health: where each camera is and looks, and the taught reference.
        async with s.get(f"{base}/api/calibration") as r:
            health = await r.json()
        cams = health["geometry"]["cameras"]
        assert [c["name"] for c in cams] == ["left", "right"]
        ref = health["geometry"]["reference"]["position_mm"]
        for c in cams:  # both look at the object (a camera mounted the wrong way would not)
            to_ref = [r - p for r, p in zip(ref, c["position_mm"], strict=True)]
            assert sum(a * b for a, b in zip(to_ref, c["axis"], strict=True)) > 0
        assert health["geometry"]["last"] is not None
        assert health["recalibrate"]["threshold_px"] == 1.0

        # The audit lists every change, newest first, with who and what.
        async with s.get(f"{base}/api/audit") as r:
            audit = await r.json()
        entries = audit["entries"]
        assert [e["applied"] for e in entries] == [True, False, True, True]
        assert all(e["source"] == "web 127.0.0.1" and e["time"] for e in entries)
        assert "object.features.0.polarity: 'dark' -> 'bright'" in entries[-1]["diff"]
        assert link.health().reconnects == 0
        assert run.daemon.rooms.jobs.counters == {"OK": 3, "NOT_FOUND": 1}


async def _line(stream: asyncio.StreamReader, wanted: str, seen: list[str]) -> str:
    async with asyncio.timeout(WAIT_S):
        while True:
            raw = await stream.readline()
            if not raw:
                raise AssertionError(f"{wanted!r} not logged: {seen[-20:]}")
            line = raw.decode()
            seen.append(line)
            if wanted in line:
                return line


async def _process_job(client: Any, seq: int) -> int:
    from pymodbus.client import AsyncModbusTcpClient

    from vgripd.peer.jobcore import Command
    from vgripd.peer.registers import MAP_SIZE

    assert isinstance(client, AsyncModbusTcpClient)
    await client.write_registers(Reg.CMD, [Command.TRIGGER, seq])
    async with asyncio.timeout(WAIT_S):
        while True:
            rr = await client.read_holding_registers(0, count=MAP_SIZE)
            if rr.registers[Reg.ACK_SEQ] == seq:
                return int(rr.registers[Reg.STATUS])
            await asyncio.sleep(0.005)  # the PLC's poll period


@pytest.mark.timeout(240)
async def test_sighup_reloads_the_file_and_a_bad_one_keeps_the_running_config(
        tmp_path: Path) -> None:
    from pymodbus.client import AsyncModbusTcpClient

    port = _free_port()
    main = write_cell(tmp_path, link_port=port, status=False)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(main), cwd=REPO, env=env,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    seen: list[str] = []
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    try:
        await _line(proc.stderr, "ready:", seen)
        assert await client.connect()
        assert await _process_job(client, 1) == Status.OK
        write_cell(tmp_path, polarity="bright", link_port=port, status=False)
        proc.send_signal(signal.SIGHUP)
        line = await _line(proc.stderr, "config reload (SIGHUP)", seen)
        while "judging" in line:
            line = await _line(proc.stderr, "config reload (SIGHUP)", seen)
        assert "applied" in line, line
        assert "'dark' -> 'bright'" in line, line
        assert await _process_job(client, 2) == Status.NOT_FOUND
        # A broken file: refused, logged with the reason; the running config stays.
        (tmp_path / "cell.toml").write_text("[vision]\nmin_contrast = 'high'\n")
        proc.send_signal(signal.SIGHUP)
        line = await _line(proc.stderr, "refused", seen)
        assert "running config stays" in line
        assert await _process_job(client, 3) == Status.NOT_FOUND  # still the reloaded one
        write_cell(tmp_path, polarity="dark", link_port=port, status=False)
        proc.send_signal(signal.SIGHUP)
        await _line(proc.stderr, "applied", seen)
        assert await _process_job(client, 4) == Status.OK
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(WAIT_S):
            await proc.wait()
    finally:
        client.close()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0, "".join(seen[-30:])


def write_replay_cell(folder: Path, polarity: str) -> Path:
    """config/example.toml (replay of config/samples, dark marks) split in two: ``vgripd.toml``
    (camera, link, web view) including ``cell.toml`` (vision, object with ``polarity``,
    reference)."""
    data = read_config_data(REPO / "config" / "example.toml")
    cell = {k: data.pop(k) for k in ("vision", "object", "reference")}
    for feature in cell["object"]["features"]:
        feature["polarity"] = polarity
    data["camera"]["folder"] = str(REPO / "config" / "samples")
    data["links"] = [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}]
    data["status"] = {"port": 0, "token": TOKEN, "allow_config_edit": True}
    data["record"] = {"enabled": False}
    data["include"] = ["cell.toml"]
    (folder / "cell.toml").write_text(toml_from_dict(cell))
    main = folder / "vgripd.toml"
    main.write_text(toml_from_dict(data))
    return main


async def test_chromium_tunes_a_wrong_polarity_until_the_plc_job_is_ok(tmp_path: Path) -> None:
    """The workflow end to end in headless Chromium: the cell's marks are dark, the config says
    bright (NOT_FOUND); the operator picks "dark" on the page and saves with the token; the
    next PLC job, on the same connection, is OK without a restart. A bad edit (a contrast no
    mark reaches on the replay samples) is refused by the judge, and the old config is kept on
    disk and running; both show in the page's audit."""
    main = write_replay_cell(tmp_path, "bright")
    cell = tmp_path / "cell.toml"
    async with running_file(main) as run, Plc(run.port()) as plc:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        assert await job(plc, run, 1) == Status.NOT_FOUND
        async with _chromium(tmp_path, base + "/") as evaluate:
            text = "(id) => document.getElementById(id)?.textContent ?? ''"
            assert await _until(evaluate, "document.getElementById('btn-save')?.hidden === false")
            assert await _until(evaluate, "document.getElementById('t-polarity')?.value "
                                          "=== 'bright'")
            # A trial first: the edited pipeline on job 1's images, nothing applied.
            await evaluate(f"""(() => {{
                document.getElementById('token').value = {json.dumps(TOKEN)};
                document.getElementById('t-polarity').value = 'dark';
                document.getElementById('btn-try').click();
                return true;
            }})()""")
            trial = await _until(evaluate, f"({text})('trial-result').startsWith('TRIAL ') && "
                                           f"({text})('trial-result')")
            assert trial.startswith("TRIAL 1 on job 1: OK"), trial
            assert "used" in trial  # every candidate's fate counted
            assert await _until(evaluate, """(() => {
                const img = document.getElementById('trial-img-0');
                return img && img.complete && img.naturalWidth > 0;
            })()""")
            assert run.daemon.config.object.features[0].polarity == "bright"  # not applied
            await evaluate("document.getElementById('btn-save').click(), true")
            result = await _until(evaluate, f"(({text})('tuning-result').startsWith('APPLIED') "
                                            f"|| ({text})('tuning-result').startsWith('REFUSED'))"
                                            f" && ({text})('tuning-result')")
            assert result.startswith("APPLIED"), result
            assert await job(plc, run, 2) == Status.OK

            before = cell.read_text()
            await evaluate("""(() => {
                document.getElementById('t-min_contrast').value = '250';
                document.getElementById('btn-save').click();
                return true;
            })()""")
            result = await _until(evaluate, f"({text})('tuning-result').startsWith('REFUSED') "
                                            f"&& ({text})('tuning-result')")
            assert "vision.min_contrast" in result
            assert cell.read_text() == before
            assert run.daemon.config.vision.min_contrast != 250
            assert await job(plc, run, 3) == Status.OK
            rows = await _until(evaluate, "document.querySelectorAll('#audit tbody tr').length"
                                          " >= 2 && [...document.querySelectorAll('#audit tbody"
                                          " tr')].map((r) => r.textContent)")
            assert rows[0].count("REFUSED") == 1
            assert "'bright' -> 'dark'" in rows[1]
            # Calibration health: the files and the cell drawn from above and the side.
            assert await _until(evaluate, "document.querySelectorAll('#cell-top .cell-camera')"
                                          ".length === 2")
            assert await evaluate("document.querySelectorAll('#cell-side .cell-reference')"
                                  ".length === 1")
            files = await evaluate("[...document.querySelectorAll('#cal-files tbody tr')]"
                                   ".map((r) => r.textContent)")
            assert any("vgripd.toml" in f and "calibration.hand_eye" in f for f in files)
            assert any("cell.toml" in f and "reference" in f for f in files)
        assert next(iter(run.daemon.rooms.links.links.values())).health().reconnects == 0


async def test_teaching_from_the_page_saves_the_mean_of_the_shots(tmp_path: Path) -> None:
    """Two jobs measured as shots (as ``vgripd teach`` measures), their mean saved as the
    reference into the include that holds it, and applied by the reload; a job already taken
    is refused, and without the token nothing happens."""
    import numpy as np

    from vgripd.calib.teach import mean_transform
    from vgripd.geometry.transforms import pose_error
    from vgripd.vision.scene import T_base_obj_ref

    main = write_cell(tmp_path)
    async with running_file(main) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        old_ref = T_base_obj_ref(run.daemon.config)
        assert await job(plc, run, 1) == Status.OK
        code, _ = await post(s, f"{base}/api/teach/shot", headers={})
        assert code == 403
        code, out = await post(s, f"{base}/api/teach/shot")
        assert code == 200, out
        assert out["shots"] == [1]
        assert out["from_taught_mm"] is not None
        code, _ = await post(s, f"{base}/api/teach/shot")
        assert code == 409  # the same job twice is no second shot
        assert await job(plc, run, 2) == Status.OK
        code, out = await post(s, f"{base}/api/teach/shot")
        assert code == 200, out
        assert out["shots"] == [1, 2]
        assert out["spread_mm"] > 0
        code, out = await post(s, f"{base}/api/teach/save")
        assert code == 200, out
        assert out["applied"]
        assert any(line.startswith("reference.T_base_obj.") for line in out["diff"])
        assert (tmp_path / "cell.toml.1").exists()
        poses = [rec.result.T_base_obj for _, rec in run.jobs[:2]]
        assert all(p is not None for p in poses)
        mean = mean_transform([np.asarray(p) for p in poses])
        new_ref = T_base_obj_ref(run.daemon.config)
        assert pose_error(new_ref, mean)[0] < 1e-3
        assert pose_error(new_ref, old_ref)[0] > 0.01
        async with s.get(f"{base}/api/teach") as r:
            assert (await r.json())["shots"] == []


@pytest.mark.timeout(360)
async def test_live_previews_show_figures_between_jobs_and_never_grab_during_one(
        tmp_path: Path) -> None:
    """The live picture of each camera (over-exposure, focus, marks seen) between jobs; while a
    job runs (a slow synthetic render) a preview request gets the last picture, no grab."""
    from tests.integration.test_daemon import running

    # supersample 8: a render of ~0.1 s on a quiet machine, so the job is long enough to ask for
    # a preview while it runs, and a preview grab still fits the page's 2 s with two suites on
    # two cores (at 16, 0.3 s quiet, a load of 14 made every preview grab miss its 2 s)
    config = make_config(camera={"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0,
                                 "supersample": 8})
    async with running(config) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        turns = run.daemon.status_server.camera
        for j in (0, 1):
            code, (headers, content_type, body) = await between_jobs(
                lambda j=j: preview(s, f"{base}/api/cameras/{j}/preview.jpg"), 503)
            assert code == 200
            assert content_type == "image/jpeg"
            assert body[:2] == b"\xff\xd8"
            assert float(headers["X-Vgripd-Focus"]) > 0
        async with s.get(f"{base}/api/cameras") as r:
            cams = await r.json()
        assert [f["marks"] for f in cams["figures"]] == [6, 6]  # the plate's six marks
        assert all(0 <= f["saturated_share"] < 0.01 for f in cams["figures"])
        grabs = turns.grabs
        assert grabs >= 1
        await plc.trigger(1)
        await run.busy()
        async with s.get(f"{base}/api/cameras/0/preview.jpg") as r:
            assert r.status == 200  # the last picture again
        assert run.daemon.rooms.jobs.state.value != "idle"  # still the same job: the check held
        assert turns.grabs == grabs
        assert (await plc.result(1))[Reg.STATUS] == Status.OK


async def test_chromium_teaches_from_two_shots_and_watches_the_cameras_live(
        tmp_path: Path) -> None:
    """In headless Chromium: the live preview shows both cameras with their figures; two jobs
    added as shots and saved as the reference (applied by the reload, listed in the audit)."""
    from vgripd.vision.scene import T_base_obj_ref

    main = write_cell(tmp_path)
    async with running_file(main) as run, Plc(run.port()) as plc:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        old_ref = T_base_obj_ref(run.daemon.config)
        assert await job(plc, run, 1) == Status.OK
        async with _chromium(tmp_path, base + "/") as evaluate:
            text = "(id) => document.getElementById(id)?.textContent ?? ''"
            assert await _until(evaluate, "document.getElementById('btn-shot')?.hidden === false")
            await evaluate("(() => { const b = document.getElementById('live-on'); "
                           "b.checked = true; b.dispatchEvent(new Event('change')); "
                           "return true; })()")
            figures = await _until(evaluate, f"({text})('live-figures').includes('camera 1') "
                                             f"&& ({text})('live-figures')")
            assert "marks seen 6" in figures, figures
            assert await _until(evaluate, """(() => {
                const img = document.getElementById('live-0');
                return img && img.complete && img.naturalWidth > 0;
            })()""")
            await evaluate("(() => { const b = document.getElementById('live-on'); "
                           "b.checked = false; b.dispatchEvent(new Event('change')); "
                           "return true; })()")
            await evaluate(f"""(() => {{
                document.getElementById('token').value = {json.dumps(TOKEN)};
                document.getElementById('btn-shot').click();
                return true;
            }})()""")
            shot = await _until(evaluate, f"({text})('teach-result').includes('shot(s)') && "
                                          f"({text})('teach-result')")
            assert "1 shot(s) (jobs 1)" in shot, shot
            assert await job(plc, run, 2) == Status.OK
            await evaluate("document.getElementById('btn-shot').click(), true")
            shot = await _until(evaluate, f"({text})('teach-result').includes('2 shot(s)') && "
                                          f"({text})('teach-result')")
            assert "from the taught reference" in shot
            await evaluate("document.getElementById('btn-teach-save').click(), true")
            saved = await _until(evaluate, f"({text})('teach-result').startsWith('SAVED') && "
                                           f"({text})('teach-result')")
            assert saved.startswith("SAVED: applied"), saved
            rows = await _until(evaluate, "[...document.querySelectorAll('#audit tbody tr')]"
                                          ".map((r) => r.textContent).join('|').includes("
                                          "'reference.T_base_obj') && 'ok'")
            assert rows == "ok"
        assert T_base_obj_ref(run.daemon.config)[:3, 3].tolist() != old_ref[:3, 3].tolist()
        assert await job(plc, run, 3) == Status.OK  # the next job against the new reference
