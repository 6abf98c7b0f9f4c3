"""The web view's parts without a daemon: the [status] config rules, redaction, the decoded
register map, the metrics registry, the event hub's bound, the trigger link and the image
rendering (in this process)."""

from __future__ import annotations

import asyncio
import os
import signal
import threading
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from vgripd.config import config_from_dict
from vgripd.errors import ConfigError
from vgripd.peer.registers import RegisterBank, ValueCodec
from vgripd.redaction import redact
from vgripd.service.links.protocol import LinkHealth, LinkState, Trigger
from vgripd.service.links.webtrigger import WebTriggerLink
from vgripd.service.web.events import MAX_EVENTS_QUEUED, EventHub
from vgripd.service.web.images import render
from vgripd.service.web.metrics import Metrics
from vgripd.service.web.registers import register_views
from vgripd.types import ImagePair, JobResult, Status

TOKEN = "0123456789abcdef"


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.20", "::", "cellpc.local"])
def test_a_non_loopback_bind_needs_a_token(host: str) -> None:
    with pytest.raises(ConfigError, match=r"status\.host .* status\.token"):
        config_from_dict({"status": {"host": host}})
    assert config_from_dict({"status": {"host": host, "token": TOKEN}}).status.host == host


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.53", "::1", "localhost"])
def test_loopback_binds_need_no_token(host: str) -> None:
    assert config_from_dict({"status": {"host": host}}).status.token is None


def test_actions_need_a_token_and_a_short_token_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"status\.allow_trigger = true needs status\.token"):
        config_from_dict({"status": {"allow_trigger": True}})
    with pytest.raises(ConfigError, match=r"status\.token"):
        config_from_dict({"status": {"token": "short"}})
    st = config_from_dict({"status": {"allow_support_bundle": True, "token": TOKEN}}).status
    assert st.allow_support_bundle
    assert not st.allow_trigger


def test_redact_hides_every_secret_key_at_any_depth() -> None:
    data = {"status": {"token": TOKEN, "port": 1}, "links": [{"password": "x", "host": "h"}],
            "a": {"api_key": "k", "secret_file": None}}
    out = redact(data)
    assert out == {"status": {"token": "<redacted>", "port": 1},
                   "links": [{"password": "<redacted>", "host": "h"}],
                   "a": {"api_key": "<redacted>", "secret_file": None}}


def test_redact_keeps_a_diagnosis_key_and_hides_secrets_by_their_names() -> None:
    """A field named ``key`` names a config key (a diagnosis' cause), never a secret; secrets
    are found by their own names and inside URLs."""
    diagnosis = {"causes": [{"key": "vision.working_distance_mm", "reason": "2 size rejected"}]}
    data = {"last_job": {"diagnosis": diagnosis},
            "about": {"camera": "rtsp://user:pass@cam/s", "api_key": "k1", "apikey": "k2",
                      "private_key": "k3", "access-key": "k4", "passphrase": "p",
                      "client_secret": "s", "key": "vision.min_contrast"}}
    out = redact(data)
    assert out["last_job"]["diagnosis"] == diagnosis
    about = out["about"]
    assert about["key"] == "vision.min_contrast"
    assert about["camera"] == "rtsp://<redacted>@cam/s"
    for name in ("api_key", "apikey", "private_key", "access-key", "passphrase",
                 "client_secret"):
        assert about[name] == "<redacted>", name


def test_register_map_is_decoded_with_names_in_either_word_order() -> None:
    for order in ("ABCD", "CDAB"):
        bank = RegisterBank(ValueCodec(order, "float32"))
        assert bank.write(0, [1, 5]) is not None  # CMD TRIGGER, REQ_SEQ 5
        bank.captured(5, 42)
        result = JobResult(job_id=42, status=Status.NOT_FOUND, message="none")
        bank.publish(5, result, time.monotonic_ns())
        (view,) = register_views({"plc": SimpleNamespace(bank=bank), "other": object()})
        rows = {r["name"]: r for r in view["rows"]}
        assert view["link"] == "plc"
        assert view["word_order"] == order
        assert rows["CHECK_U32"]["value"] == 0x12345678
        assert rows["CHECK_F32"]["value"] == pytest.approx(123.456, rel=1e-6)
        assert rows["ACK_SEQ"]["value"] == 5
        assert (rows["STATUS"]["value"], rows["STATUS"]["meaning"]) == (10, "NOT_FOUND")
        assert rows["JOB_ID"]["value"] == 42
        assert rows["STATE"]["meaning"] == "DONE"
        assert rows["WARNINGS"]["meaning"] == "none"
        assert [r["address"] for r in view["rows"]] == sorted(r["address"] for r in view["rows"])


class _Link:
    def __init__(self, state: LinkState, reconnects: int) -> None:
        self._h = LinkHealth(state=state, reconnects=reconnects)

    def health(self) -> LinkHealth:
        return self._h


def _fake_daemon() -> Any:
    epipolar = SimpleNamespace(warning=False, share=lambda: 0.25)
    links = {"plc": _Link(LinkState.UP, 2), "robot": _Link(LinkState.CONNECTING, 0)}
    rooms = SimpleNamespace(
        links=SimpleNamespace(links=links),
        jobs=SimpleNamespace(undelivered=Counter(), epipolar=epipolar, recorder=None,
                             record_dropped=0))
    return SimpleNamespace(
        rooms=rooms,
        answered=lambda: (Counter({"OK": 3, "BUSY": 1}), Counter({"BUSY": 1})),
        healthy=lambda: True, snapshot=lambda: {"camera": {"open": True}},
        recipe_snapshot=lambda: {"active": 2, "recipes": [
            {"number": 0, "name": "default"}, {"number": 2, "name": "plate-b"}]})


def _samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in text_string_to_metric_families(text) for s in fam.samples}


def test_metrics_count_jobs_by_status_and_read_links_at_scrape_time() -> None:
    metrics = Metrics(_fake_daemon())
    for i, (status, ms, epi) in enumerate([(Status.OK, 120.0, 0.4), (Status.OK, 180.0, 2.5),
                                           (Status.NOT_FOUND, 90.0, None)]):
        residuals = {} if epi is None else {"epipolar_px": epi}
        result = JobResult(job_id=i + 1, status=status, residuals=residuals,
                           timings_ms={"acquire": 10.0, "process": 60.0})
        metrics.observe(SimpleNamespace(result=result, cycle_ms=ms, published=status))
    m = _samples(metrics.render().decode())
    assert m[("vgripd_jobs_total", (("status", "OK"),))] == 2
    assert m[("vgripd_jobs_total", (("status", "NOT_FOUND"),))] == 1
    assert m[("vgripd_jobs_total", (("status", "CAMERA_ERROR"),))] == 0
    assert ("vgripd_jobs_total", (("status", "BUSY"),)) not in m  # a refusal, not a job
    assert m[("vgripd_cycle_seconds_count", ())] == 3
    assert m[("vgripd_cycle_seconds_sum", ())] == pytest.approx(0.39)
    assert m[("vgripd_cycle_seconds_bucket", (("le", "0.15"),))] == 2
    assert m[("vgripd_stage_seconds_count", (("stage", "process"),))] == 3
    assert m[("vgripd_epipolar_residual_px_count", ())] == 2
    assert m[("vgripd_epipolar_residual_last_px", ())] == 2.5
    assert m[("vgripd_link_up", (("link", "plc"),))] == 1
    assert m[("vgripd_recipe_active", (("name", "plate-b"), ("recipe", "2")))] == 1
    assert m[("vgripd_recipe_active", (("name", "default"), ("recipe", "0")))] == 0
    assert m[("vgripd_link_up", (("link", "robot"),))] == 0
    assert m[("vgripd_link_state", (("link", "robot"), ("state", "connecting")))] == 1
    assert m[("vgripd_link_reconnects_total", (("link", "plc"),))] == 2
    assert m[("vgripd_refusals_total", (("status", "BUSY"),))] == 1
    assert m[("vgripd_epipolar_share_above", ())] == 0.25
    # Its own registry: a second daemon in the same process does not clash.
    assert Metrics(_fake_daemon()).registry is not metrics.registry


async def test_a_page_that_does_not_read_is_dropped_not_buffered() -> None:
    hub = EventHub()
    from vgripd.service.web.events import _Client

    slow, fast = _Client(), _Client()
    hub.clients |= {slow, fast}
    for i in range(MAX_EVENTS_QUEUED):
        hub.publish("job", {"id": i})
        await fast.queue.get()
    assert slow in hub.clients
    hub.publish("job", {"id": "one too many"})
    assert slow not in hub.clients
    assert fast in hub.clients
    assert slow.queue.get_nowait() is None  # its stream ends
    frame = await fast.queue.get()
    assert frame == b'event: job\ndata: {"id": "one too many"}\n\n'


async def test_the_trigger_link_waits_for_its_own_answer() -> None:
    link = WebTriggerLink()
    seen: list[Trigger] = []

    def on_trigger(trigger: Trigger) -> None:
        seen.append(trigger)
        result = JobResult(job_id=7, status=Status.OK)
        asyncio.get_running_loop().call_soon(
            lambda: asyncio.ensure_future(link.publish(trigger.seq, result)))

    with pytest.raises(RuntimeError, match="not open"):
        await link.trigger(1.0)
    await link.open(on_trigger)
    assert link.health().state is LinkState.UP
    result = await link.trigger(5.0)
    assert (result.job_id, result.status) == (7, Status.OK)
    assert seen[0].link == "web"
    assert seen[0].seq == 1
    await link.close()


def test_render_draws_downscaled_jpegs_of_a_failed_job() -> None:
    left = np.full((1200, 1600), 90, np.uint8)
    pair = ImagePair(left=left, right=left.copy(), t_mono_ns=0)
    jpegs = render(pair, JobResult(job_id=1, status=Status.NOT_FOUND, message="no blobs"))
    assert len(jpegs) == 2
    img = cv2.imdecode(np.frombuffer(jpegs[0], np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (768, 1024, 3)
    assert (img[:40] != 90).any()  # the status line is written
    mono = render(((left,), None), JobResult(job_id=2, status=Status.CAMERA_ERROR),
                  max_width=400)
    assert len(mono) == 1
    assert cv2.imdecode(np.frombuffer(mono[0], np.uint8), cv2.IMREAD_COLOR).shape[1] == 400


def test_the_grafana_dashboard_and_docs_use_only_exported_metrics() -> None:
    """Every metric the shipped dashboard and docs/web.md query is one the daemon exports."""
    import json
    import re

    from tests.conftest import REPO

    daemon = _fake_daemon()
    daemon.rooms.jobs.recorder = SimpleNamespace(total_bytes=10)
    daemon.rooms.jobs.record_dropped = 0
    daemon.rooms.jobs.undelivered = Counter({"OK": 1})
    metrics = Metrics(daemon, SimpleNamespace(failures=0, lockouts=0, refused_locked=0))
    result = JobResult(job_id=1, status=Status.OK, timings_ms={"process": 1.0})
    metrics.observe(SimpleNamespace(result=result, cycle_ms=1.0, published=None))
    exported = {s.name for fam in text_string_to_metric_families(metrics.render().decode())
                for s in fam.samples}
    dashboard = json.loads((REPO / "docs/grafana/vgripd.json").read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p["targets"]]
    assert exprs
    used = {m for e in exprs for m in re.findall(r"vgripd_\w+", e)}
    used |= set(re.findall(r"`(vgripd_\w+)", (REPO / "docs/web.md").read_text()))
    unknown = sorted(m for m in used if m not in exported
                     and not any(m + suffix in exported for suffix in ("_bucket", "_count")))
    assert not unknown, unknown


def test_view_names_cover_stereo_n_cameras_and_views() -> None:
    """The web view's image list: left/right, every camera by name, every view of a views
    cell (the same names the pipeline gives them)."""
    from tests.conftest import REPO
    from vgripd.config import config_from_dict, read_config_data
    from vgripd.service.web.app import view_names

    img = np.zeros((4, 4), np.uint8)
    stereo = ImagePair(left=img, right=img, t_mono_ns=0)
    plain = config_from_dict({})
    assert view_names(plain, stereo) == [["left", "left"], ["right", "right"]]
    cell = config_from_dict(read_config_data(REPO / "config" / "samples" /
                                             "two_rigs_frame.toml"))
    four = ImagePair.of_views([img] * 4, 0)
    assert view_names(cell, four) == [["view0", "north_left"], ["view1", "north_right"],
                                      ["view2", "south_left"], ["view3", "south_right"]]
    left = {"fx": 1000.0, "fy": 1000.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
    views = config_from_dict({"calibration": {"left": left, "hand_eye": {
        "mounting": "robot", "T_flange_camera": {"translation_mm": [0, 0, 100]}}},
        "vision": {"views": 3}})
    three = ImagePair.of_views([img] * 3, 0)
    assert view_names(views, three) == [["view0", "view1"], ["view1", "view2"],
                                        ["view2", "view3"]]


def test_redact_hides_credentials_in_urls_anywhere() -> None:
    """A security review's finding: ``rtsp://admin:pw@host/stream`` in a camera option stayed in
    /api/config (redaction went by key name only)."""
    data = {"camera": {"type": "opencv", "left": "rtsp://admin:pw@cam/stream",
                       "right": "http://u:p%40ss@10.0.0.5:8080/mjpg?x=1&token=abc&key=k"},
            "about": {"notes": ["see rtsp://op:p@ss@cam2/s for the spare", "x@y.z"]},
            "links": [{"endpoint": "opc.tcp://plc:4840", "apikey": 7}]}
    out = redact(data)
    assert out["camera"]["left"] == "rtsp://<redacted>@cam/stream"
    assert out["camera"]["right"] == ("http://<redacted>@10.0.0.5:8080/mjpg?x=1&token=<redacted>"
                                      "&key=<redacted>")
    assert out["about"]["notes"] == ["see rtsp://<redacted>@cam2/s for the spare", "x@y.z"]
    assert out["links"] == [{"endpoint": "opc.tcp://plc:4840", "apikey": "<redacted>"}]
    # The same function serves a real config (driver options are extra keys).
    cfg = config_from_dict({"camera": {"type": "opencv", "left": "rtsp://admin:pw@cam/stream"}})
    assert "admin:pw" not in str(redact(cfg.model_dump(mode="json", exclude_none=True)))


def test_allowed_hosts_are_names_and_a_redacted_token_loads() -> None:
    st = config_from_dict({"status": {"allowed_hosts": ["Cell-07.Plant.Example.", "[::1]",
                                                         "10.0.0.5"]}}).status
    assert st.allowed_hosts == ["cell-07.plant.example", "::1", "10.0.0.5"]
    for bad in ["http://cell", "cell:8730", "cell/x", ""]:
        with pytest.raises(ConfigError, match=r"status\.allowed_hosts"):
            config_from_dict({"status": {"allowed_hosts": [bad]}})
    # A recorded config (token redacted) still loads for replay; the web view refuses it.
    assert config_from_dict({"status": {"token": "<redacted>"}}).status.token == "<redacted>"
    assert config_from_dict({"status": {"host": "0.0.0.0", "token": TOKEN}}).status.guards_reads
    assert not config_from_dict({"status": {"host": "0.0.0.0", "token": TOKEN,
                                            "public_read": True}}).status.guards_reads
    assert not config_from_dict({"status": {"token": TOKEN}}).status.guards_reads


def test_event_streams_without_the_token_are_capped_and_holders_always_admitted() -> None:
    from vgripd.service.web.events import (
        MAX_EVENT_CLIENTS,
        MAX_EVENT_CLIENTS_PER_ADDRESS,
        MAX_HOLDER_STREAMS,
    )

    hub = EventHub()
    admitted = [hub.admit(f"10.0.0.{i % 50}", holder=False) for i in range(200)]
    assert sum(c is not None for c in admitted) == MAX_EVENT_CLIENTS
    assert hub.admit("10.0.0.1", holder=False) is None
    first = [hub.admit("10.0.1.1", holder=True) for _ in range(MAX_HOLDER_STREAMS)]
    assert all(first)
    newest = hub.admit("10.0.1.1", holder=True)
    assert newest is not None
    assert first[0] not in hub.clients  # the oldest holder stream made room
    assert newest in hub.clients
    hub2 = EventHub()
    one = [hub2.admit("10.0.0.9", holder=False) for _ in range(10)]
    assert sum(c is not None for c in one) == MAX_EVENT_CLIENTS_PER_ADDRESS


def test_check_warns_about_the_test_trigger_and_public_reads(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A security review's finding: ``vgripd check`` printed OK, no warning, with allow_trigger
    on."""
    from vgripd.__main__ import main

    cfg = tmp_path / "cell.toml"
    cell = (f'[[links]]\ntype = "modbus_server"\nhost = "127.0.0.1"\nport = 0\n'
            f'[status]\nport = 0\ntoken = "{TOKEN}"\n')
    cfg.write_text(cell)
    assert main(["check", "-c", str(cfg)]) == 0
    assert "warning:" not in capsys.readouterr().out
    cfg.write_text(cell + "allow_trigger = true\n")
    assert main(["check", "-c", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("OK ")
    assert "warning:" in out
    assert "status.allow_trigger" in out
    cfg.write_text(cell.replace("[status]", '[status]\nhost = "0.0.0.0"') + "public_read = true\n")
    assert main(["check", "-c", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "status.public_read" in out
    assert "status.allow_trigger" not in out


def test_closing_the_image_helper_waits_for_helpers_a_reload_let_go() -> None:
    """A reload lets the image helper go without waiting (renders it holds finish); the
    daemon's stop then waits for it too: right after close() no helper's manager thread is
    left, even when the reload came while the helper was still starting (a spawn takes
    seconds on a busy machine)."""
    from vgripd.service.web.images import ImageRenderer

    before = set(threading.enumerate())
    config = config_from_dict({})
    renderer = ImageRenderer(config)

    async def main() -> None:
        pair = ImagePair(np.zeros((64, 80), np.uint8), np.zeros((64, 80), np.uint8),
                         time.monotonic_ns())
        renderer.submit(1, pair, JobResult(job_id=1, status=Status.OK))
        renderer.reconfigure(config)  # the first helper is still spawning
        renderer.submit(2, pair, JobResult(job_id=2, status=Status.OK))
        renderer.reconfigure(config)
        renderer.close()  # as the web server's close does, on the loop
        left = [t.name for t in threading.enumerate()
                if t not in before and t.is_alive() and not t.daemon]
        assert left == []

    asyncio.run(main())


def test_a_render_sent_to_a_helper_that_just_died_is_drawn_by_a_new_one() -> None:
    """The pool learns of a dead helper only when its manager thread wakes: a render submitted
    in between fails ``BrokenProcessPool``. It is given once to a new helper, so the page gets
    its picture and not a 404."""
    from vgripd.service.web.images import ImageRenderer

    renderer = ImageRenderer(config_from_dict({}))
    pair = ImagePair(np.zeros((64, 80), np.uint8), np.zeros((64, 80), np.uint8),
                     time.monotonic_ns())

    async def main() -> None:
        first = renderer.submit(1, pair, JobResult(job_id=1, status=Status.OK))
        assert first is not None
        assert (await asyncio.wait_for(first, 120))[0][:2] == b"\xff\xd8"  # a JPEG
        pool = renderer._pool
        assert pool is not None
        (helper,) = pool._processes.values()
        os.kill(helper.pid, signal.SIGKILL)  # dies idle, between two renders
        # at once, before the pool's manager thread can notice
        second = renderer.submit(2, pair, JobResult(job_id=2, status=Status.OK))
        assert second is not None
        assert (await asyncio.wait_for(second, 120))[0][:2] == b"\xff\xd8"
        assert renderer._pool is not pool  # a new helper drew it
        renderer.close()

    asyncio.run(main())
