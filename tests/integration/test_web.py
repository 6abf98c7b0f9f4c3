"""The web view against a running daemon (synthetic camera, Modbus/TCP link on 127.0.0.1, a real
pymodbus client as the PLC): the JSON API, server-sent events, images, /metrics parsed with
prometheus_client's own parser, the guarded actions, ``vgripd status``, and the page in a real
headless Chromium. Every wait is on an answer or a daemon state, with a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import itertools
import json
import os
import re
import time
import zipfile
from collections.abc import AsyncIterator, Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.conftest import need_tool
from tests.integration.test_daemon import Plc, Run, make_config, running
from vgripd.__main__ import EXIT_CONFIG
from vgripd.__main__ import main as vgripd_main
from vgripd.cli.status import run as status_run
from vgripd.peer.registers import Reg
from vgripd.types import Status

pytestmark = pytest.mark.slow

TOKEN = "a-test-token-of-32-characters-xx"
WAIT_S = 60.0  # Chromium and the daemon on a busy 2-core machine: a bound, not a target


def _base(run: Run) -> str:
    assert run.daemon.status_server is not None
    return f"http://127.0.0.1:{run.daemon.status_server.port}"


async def _events(resp: aiohttp.ClientResponse) -> AsyncIterator[tuple[str, Any, float]]:
    """Server-sent events as (event, data, monotonic receive time)."""
    event, data = "message", ""
    async for raw in resp.content:
        line = raw.decode().rstrip("\n")
        if line.startswith("event: "):
            event = line[7:]
        elif line.startswith("data: "):
            data += line[6:]
        elif line == "" and data:
            yield event, json.loads(data), time.monotonic()
            event, data = "message", ""


async def _recorded(folder: Path, n: int) -> None:
    """Until the recorder has renamed ``n`` finished job folders into place (its writes are
    not daemon state changes, so this polls the folder, with a timeout)."""
    def count() -> int:
        return len(list(folder.glob("2*-job*")))

    async with asyncio.timeout(WAIT_S):
        while count() < n:  # noqa: ASYNC110 (a folder of a few entries; no event to wait on)
            await asyncio.sleep(0.02)


def _metrics(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in text_string_to_metric_families(text) for s in fam.samples}


async def test_live_view_api_events_images_metrics_and_actions(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("INFO", logger="vgripd")  # as configure_logging does in the service
    config = make_config(
        record={"enabled": True, "folder": str(tmp_path / "rec"), "max_mb": 50},
        status={"port": 0, "token": TOKEN, "allow_trigger": True,
                "allow_support_bundle": True, "bundle_jobs": 2})
    async with running(config) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as http:
        base = _base(run)
        done_at: dict[int, float] = {}
        run.daemon.rooms.jobs.listeners.append(lambda pair, rec: done_at.setdefault(rec.job_id,
                                                                          time.monotonic()))
        async with http.get(f"{base}/api/events") as sse:
            assert sse.headers["Content-Type"].startswith("text/event-stream")
            stream = _events(sse)
            await plc.trigger(1)
            assert (await plc.result(1))[Reg.STATUS] == Status.OK
            async with asyncio.timeout(WAIT_S):
                kinds = []
                async for event, data, t_data in stream:
                    kinds.append(event)
                    if event == "job":
                        job, t_seen = data, t_data
                        break
        assert set(kinds) <= {"status", "job", "links"}  # the PLC connecting: links, status
        assert job["id"] == 1
        assert job["status"] == "OK"
        assert job["images"]
        assert job["stereo"]
        assert t_seen - done_at[1] < 1.0  # within a second of the job
        assert job["target"]["vendor"] == "kuka"
        assert len(job["target"]["values"]) == 6
        assert "epipolar_px" in job["residuals"]
        assert "process" in job["timings_ms"]

        # The status JSON, at the new path and at the old one `vgripd status` used.
        async with http.get(f"{base}/api/status") as resp:
            status = await resp.json()
        async with http.get(f"{base}/status") as resp:
            assert (await resp.json())["last_job"]["id"] == status["last_job"]["id"]
        assert status["last_job"]["status"] == "OK"
        assert status["web"] == {"trigger": True, "support_bundle": True,
                                 "config_edit": False, "history": 100}
        async with http.get(f"{base}/api/jobs") as resp:
            assert [j["id"] for j in await resp.json()] == [1]

        # Images: annotated JPEGs, downscaled, for both cameras; older ones from the recorder.
        sizes = []
        for side in ("left", "right"):
            async with http.get(f"{base}/api/jobs/1/image/{side}.jpg") as resp:
                assert resp.status == 200
                assert resp.content_type == "image/jpeg"
                img = cv2.imdecode(np.frombuffer(await resp.read(), np.uint8), cv2.IMREAD_COLOR)
            assert img is not None
            assert img.shape[1] <= 1024
            sizes.append(img.shape)
        async with http.get(f"{base}/api/jobs/99/image/left.jpg") as resp:
            assert resp.status == 404

        # The register map as the PLC reads it, decoded.
        async with http.get(f"{base}/api/registers") as resp:
            (view,) = await resp.json()
        rows = {r["name"]: r for r in view["rows"]}
        assert rows["STATUS"]["value"] == 1
        assert rows["STATUS"]["meaning"] == "OK"
        assert rows["ACK_SEQ"]["value"] == 1
        assert rows["CHECK_U32"]["value"] == 0x12345678
        assert rows["CHECK_F32"]["value"] == pytest.approx(123.456, rel=1e-6)
        assert rows["VALUES[0]"]["value"] == pytest.approx(job["target"]["values"][0], abs=1e-3)

        # The config, read-only, with the token redacted.
        async with http.get(f"{base}/api/config") as resp:
            cfg = await resp.json()
        assert cfg["status"]["token"] == "<redacted>"
        assert TOKEN not in json.dumps(cfg)

        # Guarded actions: 403 without the token, 200 with it.
        async with http.post(f"{base}/api/trigger") as resp:
            assert resp.status == 403
        async with http.post(f"{base}/api/trigger",
                             headers={"Authorization": "Bearer wrong-token-xxxxxxxxxxx"}) as resp:
            assert resp.status == 403
        auth = {"Authorization": f"Bearer {TOKEN}"}
        async with http.post(f"{base}/api/trigger", headers=auth) as resp:
            assert resp.status == 200
            answer = await resp.json()
        assert answer["job_id"] == 2
        assert answer["status"] == "OK"
        async with http.get(f"{base}/api/support-bundle") as resp:
            assert resp.status == 403
        # Job 2 ran with no page watching: drawn on request from the pair kept; job 1, out of
        # the cache, from the recorder's folder.
        async with http.get(f"{base}/api/jobs/2/image/right.jpg") as resp:
            assert resp.status == 200
        assert run.daemon.status_server is not None
        run.daemon.status_server.images._cache.clear()  # as if job 1 were long gone
        await _recorded(tmp_path / "rec", 1)
        async with http.get(f"{base}/api/jobs/1/image/left.jpg") as resp:
            assert resp.status == 200
            again = cv2.imdecode(np.frombuffer(await resp.read(), np.uint8), cv2.IMREAD_COLOR)
        assert again.shape == sizes[0]
        await _recorded(tmp_path / "rec", 2)
        async with http.get(f"{base}/api/support-bundle", headers=auth) as resp:
            assert resp.status == 200
            assert resp.content_type == "application/zip"
            bundle = zipfile.ZipFile(io.BytesIO(await resp.read()))
        names = bundle.namelist()
        assert {"config.toml", "status.json", "jobs.json", "metrics.txt", "log.txt"} <= set(names)
        assert sum(n.endswith("/left.png") for n in names) == 2
        assert TOKEN not in bundle.read("config.toml").decode()
        assert "job 1: OK" in bundle.read("log.txt").decode()

        # Metrics: jobs by status, the cycle histogram, stages, links.
        async with http.get(f"{base}/metrics") as resp:
            assert resp.status == 200
            m = _metrics(await resp.text())
        assert m[("vgripd_jobs_total", (("status", "OK"),))] == 2
        assert m[("vgripd_jobs_total", (("status", "NOT_FOUND"),))] == 0
        assert m[("vgripd_cycle_seconds_count", ())] == 2
        assert m[("vgripd_stage_seconds_count", (("stage", "acquire"),))] == 2
        assert m[("vgripd_link_up", (("link", "modbus_server"),))] == 1
        assert m[("vgripd_link_up", (("link", "web"),))] == 1
        assert m[("vgripd_link_reconnects_total", (("link", "modbus_server"),))] == 0
        assert m[("vgripd_refusals_total", (("status", "BUSY"),))] == 0
        assert m[("vgripd_epipolar_residual_px_count", ())] == 2
        assert m[("vgripd_recalibrate_warning", ())] == 0

        # `vgripd status` reads the same API (blocking client: from a thread).
        with ThreadPoolExecutor(1) as pool:
            import argparse
            args = argparse.Namespace(url=f"{base}/api/status", config=None, json=False,
                                      timeout=5.0)
            rc = await asyncio.get_running_loop().run_in_executor(pool, status_run, args)
        assert rc == 0


async def test_actions_are_404_while_disabled_and_the_view_is_read_only() -> None:
    async with running(make_config(daemon={"worker": False})) as run, \
            aiohttp.ClientSession() as http:
        base = _base(run)
        assert "web" not in run.daemon.rooms.links.links
        auth = {"Authorization": f"Bearer {TOKEN}"}
        async with http.post(f"{base}/api/trigger", headers=auth) as resp:
            assert resp.status == 404
        async with http.get(f"{base}/api/support-bundle", headers=auth) as resp:
            assert resp.status == 404
        async with http.post(f"{base}/status") as resp:
            assert resp.status == 404
        async with http.get(f"{base}/") as resp:
            assert resp.status == 200
            assert "vgripd" in await resp.text()
        async with http.get(f"{base}/static/app.js") as resp:
            assert resp.status == 200


def test_a_non_local_bind_without_a_token_is_a_config_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[status]\nhost = "0.0.0.0"\nport = 0\n')
    assert vgripd_main(["run", "-c", str(cfg)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "status.host" in err
    assert "status.token" in err
    assert len(err.strip().splitlines()) == 1


async def test_the_page_in_headless_chromium_shows_the_live_job(tmp_path: Path) -> None:
    chromium = need_tool("chromium")
    async with running(make_config()) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        await run.job_done(1)
        proc = await asyncio.create_subprocess_exec(
            chromium, "--headless", "--no-sandbox", "--disable-gpu",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--no-first-run", "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'chr'}",
            "--virtual-time-budget=800", "--dump-dom", _base(run) + "/",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={**os.environ, "HOME": str(tmp_path)})
        try:
            async with asyncio.timeout(90):
                out, err = await proc.communicate()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    dom = out.decode(errors="replace")
    assert "job 1: OK (1)" in dom, err.decode(errors="replace")[-2000:]
    assert 'src="/api/jobs/1/image/left.jpg' in dom
    assert "modbus_server" in dom  # the links table


Evaluate = Callable[[str], Awaitable[Any]]


@contextlib.asynccontextmanager
async def _chromium(tmp_path: Path, url: str) -> AsyncIterator[Evaluate]:
    """Headless Chromium showing ``url``, driven over the DevTools protocol (a websocket): yields
    ``evaluate(js)``, the value of a JavaScript expression in the page (promises awaited)."""
    chromium = need_tool("chromium")
    proc = await asyncio.create_subprocess_exec(
        chromium, "--headless", "--no-sandbox", "--disable-gpu",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--no-first-run", "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'chr'}",
        "--remote-debugging-port=0", url,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "HOME": str(tmp_path)})
    assert proc.stderr is not None
    drain: asyncio.Task[None] | None = None
    try:
        seen = b""
        async with asyncio.timeout(60):
            while not (m := re.search(rb"DevTools listening on ws://([\w.:\[\]]+)/", seen)):
                line = await proc.stderr.readline()
                assert line, "chromium exited: " + seen.decode(errors="replace")[-2000:]
                seen += line

        async def drain_stderr() -> None:  # keep the pipe from filling
            assert proc.stderr is not None
            while await proc.stderr.read(65536):
                pass

        drain = asyncio.create_task(drain_stderr())
        async with aiohttp.ClientSession() as http:
            async with asyncio.timeout(WAIT_S):
                while True:  # the page's target appears once the tab opened
                    async with http.get(f"http://{m.group(1).decode()}/json/list") as resp:
                        pages = [t for t in await resp.json(content_type=None)
                                 if t["type"] == "page" and t["url"].startswith(url)]
                    if pages:
                        break
                    await asyncio.sleep(0.05)
            async with http.ws_connect(pages[0]["webSocketDebuggerUrl"], max_msg_size=0) as ws:
                ids = itertools.count(1)

                async def evaluate(expression: str) -> Any:
                    i = next(ids)
                    await ws.send_json({"id": i, "method": "Runtime.evaluate", "params": {
                        "expression": expression, "returnByValue": True, "awaitPromise": True}})
                    async with asyncio.timeout(WAIT_S):
                        async for msg in ws:
                            data = json.loads(msg.data)
                            if data.get("id") == i:
                                assert "exceptionDetails" not in data["result"], data
                                return data["result"]["result"].get("value")
                    raise AssertionError("the DevTools connection closed")

                yield evaluate
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()
        if drain is not None:
            await drain


async def _until(evaluate: Evaluate, expression: str) -> Any:
    """The first truthy value of ``expression`` in the page (polled, with a timeout)."""
    async with asyncio.timeout(WAIT_S):
        while not (value := await evaluate(expression)):  # noqa: ASYNC110 (the page has no event to push to the test)
            await asyncio.sleep(0.05)
    return value


async def test_chromium_page_updates_live_links_images_and_refuses_actions_without_token(
        tmp_path: Path) -> None:
    config = make_config(status={"port": 0, "token": TOKEN, "allow_trigger": True})
    async with running(config) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as http:
        base = _base(run)
        server = run.daemon.status_server
        assert server is not None
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        await run.job_done(1)
        async with _chromium(tmp_path, base + "/") as evaluate:
            text = "(id) => document.getElementById(id)?.textContent ?? ''"
            assert "job 1: OK" in await _until(
                evaluate, f"({text})('job-status').includes('job 1: OK') && "
                          f"({text})('job-status')")
            # The page's event stream is connected: a job triggered now shows up live.
            # (a connection is no daemon state change to wait on: polled, with a timeout)
            async with asyncio.timeout(WAIT_S):
                while not server.events.clients:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)
            assert await _until(evaluate, "document.body?.dataset.live === 'events'")
            await plc.trigger(2)
            assert (await plc.result(2))[Reg.STATUS] == Status.OK
            status = await _until(evaluate, f"({text})('job-status').includes('job 2') && "
                                            f"({text})('job-status')")
            assert "job 2: OK" in status
            # the status part of the page too, pushed (the page does not poll while it streams)
            assert await _until(evaluate, "lastStatus?.last_job?.id === 2")
            assert await evaluate("document.body.dataset.live") == "events"
            title = await evaluate(f"({text})('job-title')")
            assert title.startswith("2 (seq 2 from modbus_server")
            left = await evaluate("document.getElementById('img-left').src")
            assert left.split("?")[0] == f"{base}/api/jobs/2/image/left.jpg"

            # History: a row per job, each with links to its images, which answer JPEGs.
            rows = await _until(evaluate, """(() => {
                const rows = [...document.querySelectorAll('#jobs tbody tr')];
                return rows.length === 2 && rows.map((r) => [r.cells[0].textContent,
                    r.cells[4].textContent, [...r.querySelectorAll('a')].map((a) => a.href),
                    r.cells[3].textContent]);
            })()""")
            assert [(r[0], r[1], r[3]) for r in rows] == [("2", "OK", "0"), ("1", "OK", "0")]
            recipe = await evaluate(f"({text})('recipe')")
            assert recipe == "recipe 0 default"  # the active one (one recipe: no list)
            for job_id, _, hrefs, _ in rows:
                assert [h.split("?")[0] for h in hrefs] == [
                    f"{base}/api/jobs/{job_id}/image/{side}.jpg" for side in ("left", "right")]
                for href in hrefs:
                    async with http.get(href) as resp:
                        assert resp.status == 200
                        assert resp.content_type == "image/jpeg"
                        img = cv2.imdecode(np.frombuffer(await resp.read(), np.uint8),
                                           cv2.IMREAD_COLOR)
                    assert img is not None

            # Actions: the page offers the test trigger; without the token the server refuses
            # it (403), from the page's button as from a plain request, and no job runs.
            assert await evaluate("document.getElementById('actions-off').hidden")
            assert not await evaluate("document.getElementById('btn-trigger').hidden")
            await evaluate("document.getElementById('btn-trigger').click()")
            refusal = await _until(evaluate, f"({text})('action-result').startsWith('403') && "
                                             f"({text})('action-result')")
            assert "needs the token" in refusal
            async with http.post(f"{base}/api/trigger") as resp:
                assert resp.status == 403
            assert len(run.jobs) == 2
            assert "job 2: OK" in await evaluate(f"({text})('job-status')")


async def test_chromium_page_shows_actions_disabled_on_a_read_only_config(
        tmp_path: Path) -> None:
    async with running(make_config()) as run, aiohttp.ClientSession() as http:
        base = _base(run)
        async with _chromium(tmp_path, base + "/") as evaluate:
            await _until(evaluate, "document.getElementById('run-state')?.textContent"
                                   "?.includes('running')")
            assert not await evaluate("document.getElementById('actions-off').hidden")
            assert await evaluate("document.getElementById('actions-on').hidden")
            assert await evaluate("document.getElementById('btn-trigger').hidden")
            assert "read-only" in await evaluate(
                "document.getElementById('actions-off').textContent")
        async with http.post(f"{base}/api/trigger") as resp:
            assert resp.status == 404  # disabled: not there at all


async def test_chromium_page_shows_every_camera_of_a_multi_camera_cell(tmp_path: Path) -> None:
    """config/samples/two_rigs_frame.toml (four cameras): the page shows one annotated image
    per camera, captioned with its name, and the history links each; every JPEG decodes and
    shows that camera's own image (the marks it sees are drawn where the renderer put them)."""
    from tests.integration.test_daemon_multicam import cell

    config = cell(tmp_path, record=True)
    names = [c.name for c in config.calibration.cameras]
    async with running(config) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as http:
        base = _base(run)
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        pair, _ = await run.job_done(1)
        assert pair is not None
        async with _chromium(tmp_path, base + "/") as evaluate:
            shown = await _until(evaluate, """(() => {
                const figs = [...document.querySelectorAll('#live .images figure')];
                const ok = figs.length === 4 && figs.every((f) => f.querySelector('img').complete
                    && f.querySelector('img').naturalWidth > 0);
                return ok && figs.map((f) => [f.querySelector('img').id,
                    f.querySelector('figcaption').textContent,
                    f.querySelector('img').src.split('?')[0]]);
            })()""")
            assert shown == [[f"img-view{j}", name, f"{base}/api/jobs/1/image/view{j}.jpg"]
                             for j, name in enumerate(names)]
            links = await _until(evaluate, """(() => {
                const row = document.querySelector('#jobs tbody tr');
                return row && [...row.querySelectorAll('a')].map((a) => [a.textContent.trim(),
                    a.href.split('?')[0]]);
            })()""")
            assert links == [[name, f"{base}/api/jobs/1/image/view{j}.jpg"]
                             for j, name in enumerate(names)]
        px = pair.truth["pixels_views"]
        for j in range(4):
            async with http.get(f"{base}/api/jobs/1/image/view{j}.jpg") as resp:
                assert resp.status == 200
                img = cv2.imdecode(np.frombuffer(await resp.read(), np.uint8), cv2.IMREAD_COLOR)
            assert img.shape == (819, 1024, 3)  # 1280x1024 downscaled to the view's width
            # A green circle (a used mark, 6 px radius) around each mark this camera sees;
            # the grey image has none of that colour anywhere.
            bgr = img.astype(int)
            green = (bgr[..., 1] - np.maximum(bgr[..., 0], bgr[..., 2])) > 40
            seen = px[:, j][~np.isnan(px[:, j, 0])] * 1024 / 1280
            assert len(seen) == 8
            for x, y in seen:
                x0, y0 = int(x), int(y)
                assert green[y0 - 7:y0 + 8, x0 - 7:x0 + 8].any(), (j, x, y)
        async with http.get(f"{base}/api/jobs/1/image/view4.jpg") as resp:
            assert resp.status == 404
            assert "the job has 4" in await resp.text()
        # An older job, out of the cache and not the last pair: from the recorder's view*.png.
        server = run.daemon.status_server
        assert server is not None
        await plc.trigger(2)
        assert (await plc.result(2))[Reg.STATUS] == Status.OK
        await run.job_done(2)
        server.images._cache.clear()
        await _recorded(tmp_path / "record", 1)
        async with http.get(f"{base}/api/jobs/1/image/view3.jpg") as resp:
            assert resp.status == 200
            again = cv2.imdecode(np.frombuffer(await resp.read(), np.uint8), cv2.IMREAD_COLOR)
        assert again.shape == (819, 1024, 3)


async def test_a_views_job_shows_every_view_annotated() -> None:
    """One robot-mounted camera, three views of the sample frame (tests/integration/
    test_daemon_views.py's cell): the job lists view1..view3, and each JPEG is that view's
    image with the marks it sees circled at the renderer's pixels, drawn from the flange pose
    each view carried."""
    from tests.integration.test_daemon_views import port, views_config
    from vgripd.sim.plc import MockPlc

    async with running(views_config(3)) as run, aiohttp.ClientSession() as http, \
            MockPlc("127.0.0.1", port(run), timeout_s=WAIT_S) as plc:
        base = _base(run)
        answer = await plc.views_cycle(3)
        assert answer.status is Status.OK
        pair, rec = await run.job_done(1)
        assert pair is not None
        async with http.get(f"{base}/api/jobs/1") as resp:
            job = await resp.json()
        assert job["views"] == [["view0", "view1"], ["view1", "view2"], ["view2", "view3"]]
        # Where each view saw the marks, by OpenCV's projection of the rendered pose through
        # the view's flange pose (marks facing away from the view left out).
        config = run.daemon.config
        cal = config.calibration
        assert cal is not None
        assert cal.hand_eye.T_flange_camera is not None
        from vgripd.vision import scene

        T_fc = scene.matrix_from_pose(cal.hand_eye.T_flange_camera)
        K = np.array([[cal.left.fx, 0, cal.left.cx], [0, cal.left.fy, cal.left.cy], [0, 0, 1]])
        marks = np.array([f.xyz_mm for f in config.object.features])
        normals = np.array([f.normal for f in config.object.features])
        T_obj = pair.truth["T_base_obj"]
        for j in range(3):
            async with http.get(f"{base}/api/jobs/1/image/view{j}.jpg") as resp:
                assert resp.status == 200
                img = cv2.imdecode(np.frombuffer(await resp.read(), np.uint8), cv2.IMREAD_COLOR)
            T_cam_obj = np.linalg.inv(pair.T_base_flange[j] @ T_fc) @ T_obj
            eye = np.linalg.inv(T_cam_obj)[:3, 3]
            facing = ((eye - marks) * normals).sum(axis=1) > 0
            px, _ = cv2.projectPoints(marks[facing], cv2.Rodrigues(T_cam_obj[:3, :3])[0],
                                      T_cam_obj[:3, 3], K, np.array(cal.left.dist))
            px = px.reshape(-1, 2)
            inside = ((px >= 0) & (px < [cal.left.width, cal.left.height])).all(axis=1)
            bgr = img.astype(int)
            green = (bgr[..., 1] - np.maximum(bgr[..., 0], bgr[..., 2])) > 40
            seen = px[inside] * img.shape[1] / pair.views[j].shape[1]
            assert len(seen) >= 4
            for x, y in seen:
                assert green[int(y) - 7:int(y) + 8, int(x) - 7:int(x) + 8].any(), (j, x, y)


async def test_chromium_page_behind_the_token_works_under_the_csp(tmp_path: Path) -> None:
    """A view bound to 0.0.0.0 (reached through 127.0.0.1) with the token: the browser gets the
    login form, logs in once (the cookie), and then the page works as on loopback under the
    Content-Security-Policy: script and stylesheet load, the images (sent with the cookie), the
    live event stream (served as the token holder's), the redacted config, and the test trigger
    with the token typed in."""
    config = make_config(status={"host": "0.0.0.0", "port": 0, "token": TOKEN,
                                 "allow_trigger": True})
    async with running(config) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as http:
        base = _base(run)
        server = run.daemon.status_server
        assert server is not None
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        await run.job_done(1)
        async with http.get(base + "/") as resp:
            assert resp.status == 401
            assert "frame-ancestors 'none'" in resp.headers["Content-Security-Policy"]
        async with _chromium(tmp_path, base + "/") as evaluate:
            text = "(id) => document.getElementById(id)?.textContent ?? ''"
            assert await _until(evaluate, "document.querySelector('form[action=\"/login\"]') "
                                          "!== null")
            assert not await evaluate("document.getElementById('job-status') !== null")
            await evaluate(f"""(() => {{
                document.querySelector('input[name=token]').value = {json.dumps(TOKEN)};
                document.querySelector('form').submit();
                return true;
            }})()""")
            assert "job 1: OK" in await _until(
                evaluate, f"({text})('job-status').includes('job 1: OK') && "
                          f"({text})('job-status')")
            # The stylesheet (style-src 'self') and the images (img-src 'self', the cookie).
            assert await _until(evaluate, "getComputedStyle(document.querySelector('header'))"
                                          ".backgroundColor === 'rgb(34, 34, 51)'")
            assert await _until(evaluate, """(() => {
                const img = document.getElementById('img-left');
                return img && img.complete && img.naturalWidth > 0;
            })()""")
            assert "<redacted>" in await _until(evaluate, f"({text})('config-text')")
            assert TOKEN not in await evaluate(f"({text})('config-text')")
            csp = await evaluate("fetch('/api/status').then((r) => "
                                 "r.headers.get('content-security-policy'))")
            assert "script-src 'self'" in csp
            # The page's stream is the token holder's (its cookie); a job shows up live.
            async with asyncio.timeout(WAIT_S):
                while not [c for c in server.events.clients if c.holder]:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)
            await plc.trigger(2)
            assert (await plc.result(2))[Reg.STATUS] == Status.OK
            assert "job 2: OK" in await _until(
                evaluate, f"({text})('job-status').includes('job 2') && ({text})('job-status')")
            # An action with the token typed in (the header; the cookie alone is refused).
            await evaluate(f"""(() => {{
                document.getElementById('token').value = {json.dumps(TOKEN)};
                document.getElementById('btn-trigger').click();
                return true;
            }})()""")
            result = await _until(evaluate, f"({text})('action-result').startsWith('test job') "
                                            f"&& ({text})('action-result')")
            assert result.startswith("test job 3: OK")
