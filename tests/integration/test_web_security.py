"""The web view's doors, tried as a raw client on the cell network would:
the token on every route of a non-loopback bind (bound to 0.0.0.0, reached through 127.0.0.1),
the login cookie, the Host check, the security headers, bad ids, rate-limited error lines, the
event-stream cap with the operator always served, redaction in the API and in a recorded job,
the recording's file modes and the support bundle with planted links. Raw sockets where the
request must be exactly what a hostile client sends; everything on 127.0.0.0/8, bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import logging
import stat
import tomllib
import zipfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.integration.test_daemon import Plc, Run, make_config, running
from tests.integration.test_web import TOKEN, WAIT_S, _recorded
from vgripd.config import load_config
from vgripd.peer.registers import Reg
from vgripd.service.web.access import SECURITY_HEADERS, SESSION_COOKIE
from vgripd.types import Status

CAMERA_URL = "rtsp://admin:pw-of-the-camera@cam.local/stream"
READ_ROUTES = ["/", "/status", "/api/status", "/api/jobs", "/api/jobs/1",
               "/api/jobs/1/image/left.jpg", "/api/config", "/api/registers", "/metrics",
               "/static/app.js", "/static/style.css", "/static/index.html",
               "/api/handeye", "/handeye/plan", "/handeye/walk", "/static/handeye.js"]


def _port(run: Run) -> int:
    assert run.daemon.status_server is not None
    return run.daemon.status_server.port


async def _raw(port: int, request: bytes, local: str = "127.0.0.1",
               read_body: bool = True) -> tuple[int, dict[str, str], bytes]:
    """One raw HTTP/1.1 exchange from ``local``: status, headers (lower-case names), body."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(local, 0))
    try:
        writer.write(request)
        await writer.drain()
        async with asyncio.timeout(WAIT_S):
            head = await reader.readuntil(b"\r\n\r\n")
            lines = head.decode("latin-1").split("\r\n")
            status = int(lines[0].split()[1])
            headers: dict[str, str] = {}
            for line in lines[1:]:
                if ":" in line:
                    k, v = line.split(":", 1)
                    headers.setdefault(k.strip().lower(), v.strip())
            body = b""
            if read_body and "content-length" in headers:
                body = await reader.readexactly(int(headers["content-length"]))
        return status, headers, body
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()


def _get(path: str, host: str = "127.0.0.1", extra: str = "") -> bytes:
    return f"GET {path} HTTP/1.1\r\nHost: {host}\r\n{extra}Connection: close\r\n\r\n".encode()


@contextlib.asynccontextmanager
async def _guarded(tmp_path: Path, **status: Any) -> AsyncIterator[Run]:
    """A daemon whose view is bound to 0.0.0.0 with the token, recording, one job done."""
    config = make_config(
        record={"enabled": True, "folder": str(tmp_path / "rec"), "max_mb": 50},
        about={"camera_url": CAMERA_URL, "note": f"see {CAMERA_URL} and http://h/x?token=abc"},
        status={"host": "0.0.0.0", "port": 0, "token": TOKEN, **status})
    async with running(config) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        await run.job_done(1)
        yield run


async def test_a_non_loopback_bind_needs_the_token_on_every_route(tmp_path: Path) -> None:
    async with _guarded(tmp_path, allow_trigger=True) as run, aiohttp.ClientSession() as http:
        port = _port(run)
        for path in [*READ_ROUTES, "/api/events", "/no/such/route"]:
            status, headers, _ = await _raw(port, _get(path), read_body=False)
            assert status == 401, path
            assert headers["www-authenticate"].startswith("Bearer")
            status, _, _ = await _raw(port, _get(path, extra="Authorization: Bearer "
                                                            "wrong-token-xxxxxxxxxxxxx\r\n"),
                                      read_body=False)
            assert status == 401, path
            status, _, _ = await _raw(port, _get(path, extra=f"Authorization: Bearer {TOKEN}\r\n"),
                                      read_body=False)
            assert status == (404 if path == "/no/such/route" else 200), path
        # The page without the token is the login form, not the view.
        status, _, body = await _raw(port, _get("/"))
        assert status == 401
        assert b'action="/login"' in body
        assert b"app.js" not in body

        # A browser logs in once: the cookie (HttpOnly, SameSite=Strict) opens the reads.
        base = f"http://127.0.0.1:{port}"
        async with http.post(f"{base}/login", data={"token": "wrong-token-xxxxxxxxxxxx"},
                             allow_redirects=False) as resp:
            assert resp.status == 403
            assert SESSION_COOKIE not in resp.cookies
        async with http.post(f"{base}/login", data={"token": TOKEN},
                             allow_redirects=False) as resp:
            assert resp.status == 303
            assert resp.headers["Location"] == "/"
            cookie = resp.cookies[SESSION_COOKIE]
        assert cookie["httponly"]
        assert cookie["samesite"] == "Strict"
        assert TOKEN not in cookie.value
        session = f"Cookie: {SESSION_COOKIE}={cookie.value}\r\n"
        for path in READ_ROUTES:
            status, _, _ = await _raw(port, _get(path, extra=session), read_body=False)
            assert status == 200, path
        # The cookie never starts an action (a cross-site form could send it): header only.
        status, _, _ = await _raw(port, (
            f"POST /api/trigger HTTP/1.1\r\nHost: 127.0.0.1\r\n{session}Content-Length: 0\r\n"
            f"Connection: close\r\n\r\n").encode())
        assert status == 403
        assert len(run.jobs) == 1


async def test_public_read_opens_the_reads_but_not_the_actions(tmp_path: Path) -> None:
    async with _guarded(tmp_path, public_read=True, allow_trigger=True) as run:
        port = _port(run)
        for path in READ_ROUTES:
            status, _, _ = await _raw(port, _get(path), read_body=False)
            assert status == 200, path
        status, _, _ = await _raw(port, (
            b"POST /api/trigger HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 0\r\n"
            b"Connection: close\r\n\r\n"))
        assert status == 403
        for action in ("/api/handeye/walk/start", "/api/handeye/plan", "/api/handeye/accept",
                       "/api/tuning", "/api/teach/save"):
            status, _, body = await _raw(port, (
                f"POST {action} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}"
                f"\r\nContent-Length: 0\r\nConnection: close\r\n\r\n").encode())
            assert status == 404, action  # status.allow_config_edit is off
            assert b"needs status.allow_config_edit = true" in body, (action, body[-200:])


async def test_vgripd_status_sends_the_token(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from vgripd.cli.status import run as status_run

    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    async with _guarded(tmp_path) as run:
        url = f"http://127.0.0.1:{_port(run)}/api/status"
        loop = asyncio.get_running_loop()

        async def status(**kw: Any) -> int:
            args = argparse.Namespace(url=url, config=None, json=True, timeout=5.0, **kw)
            return await loop.run_in_executor(None, status_run, args)

        monkeypatch.delenv("VGRIPD_TOKEN", raising=False)
        assert await status(token_file=None) == 1
        assert "401" in capsys.readouterr().err
        assert await status(token_file=str(token_file)) == 0
        assert json.loads(capsys.readouterr().out)["last_job"]["id"] == 1
        monkeypatch.setenv("VGRIPD_TOKEN", TOKEN)
        assert await status(token_file=None) == 0


async def test_a_foreign_host_header_is_refused(caplog: pytest.LogCaptureFixture) -> None:
    """DNS rebinding: a page of evil.example whose name now resolves to 127.0.0.1 sends its
    own name as Host. The view answers only to its own names."""
    config = make_config(status={"port": 0, "allowed_hosts": ["cell-07.plant.example"]})
    async with running(config) as run:
        port = _port(run)
        for host in ["evil.example", f"evil.example:{port}", "127.0.0.2", "cell-07.plant",
                     "localhost.evil.example"]:
            for path in ["/api/status", "/", "/api/config", "/metrics"]:
                status, _, _ = await _raw(port, _get(path, host=host))
                assert status == 421, (host, path)
        # An absolute-form target names the host too (aiohttp goes by it).
        status, _, _ = await _raw(port, b"GET http://evil.example/api/status HTTP/1.1\r\n"
                                        b"Host: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert status == 421
        status, _, _ = await _raw(port, b"GET http://localhost/api/status HTTP/1.1\r\n"
                                        b"Host: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert status == 200
        for host in ["127.0.0.1", f"127.0.0.1:{port}", f"localhost:{port}", "LOCALHOST",
                     "cell-07.plant.example", f"Cell-07.Plant.Example.:{port}"]:
            status, _, _ = await _raw(port, _get("/api/status", host=host))
            assert status == 200, host
    refused = [r for r in caplog.records if "refused Host" in r.getMessage()]
    assert len(refused) == 1  # 20 refusals from one client: one line
    # Bound to all addresses: an address literal is the view's name only when it is the
    # address the client connected to.
    config = make_config(status={"host": "0.0.0.0", "port": 0, "token": TOKEN,
                                 "public_read": True})
    async with running(config) as run:
        port = _port(run)
        for host in ["192.0.2.7", "127.0.0.2", f"[::ffff:127.0.0.9]:{port}", "evil.example"]:
            status, _, _ = await _raw(port, _get("/api/status", host=host))
            assert status == 421, host
        for host in ["127.0.0.1", f"127.0.0.1:{port}", "localhost"]:
            status, _, _ = await _raw(port, _get("/api/status", host=host))
            assert status == 200, host
        reader, writer = await asyncio.open_connection("127.0.0.3", port)
        writer.write(_get("/api/status", host=f"127.0.0.3:{port}"))
        async with asyncio.timeout(WAIT_S):
            assert b" 200 " in await reader.readline()
        writer.close()


async def test_every_answer_carries_the_security_headers(tmp_path: Path) -> None:
    async with _guarded(tmp_path, allow_trigger=True) as run:
        port = _port(run)
        auth = f"Authorization: Bearer {TOKEN}\r\n"
        requests = [_get(p, extra=auth) for p in [*READ_ROUTES, "/api/events", "/nope",
                                                    "/api/jobs/77"]]
        requests += [_get("/api/status"), _get("/api/status", host="evil.example"),
                     _get("/login"),
                     b"POST /login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 11\r\n"
                     b"Content-Type: application/x-www-form-urlencoded\r\n"
                     b"Connection: close\r\n\r\ntoken=wrong"]
        seen = set()
        for request in requests:
            status, headers, _ = await _raw(port, request, read_body=False)
            seen.add(status)
            for name, value in SECURITY_HEADERS.items():
                assert headers.get(name.lower()) == value, (request, status, name)
        assert seen == {200, 401, 403, 404, 421}
    assert "frame-ancestors 'none'" in SECURITY_HEADERS["Content-Security-Policy"]
    assert "script-src 'self'" in SECURITY_HEADERS["Content-Security-Policy"]
    assert SECURITY_HEADERS["X-Frame-Options"] == "DENY"


async def test_bad_ids_answer_404_without_a_traceback(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    digits = "9" * 5000
    config = make_config(status={"port": 0, "token": TOKEN, "allow_trigger": True},
                         daemon={"worker": False})
    async with running(config) as run:
        port = _port(run)
        for path in [f"/api/jobs/{digits}", f"/api/jobs/{digits}/image/left.jpg",
                     f"/api/jobs/1/image/view{digits}.jpg", "/api/jobs/-1", "/api/jobs/abc",
                     "/api/jobs/%EF%BC%91", "/api/jobs/-1/image/left.jpg", "/api/jobs/1.5",
                     f"/api/jobs/{'1' * 19}", "/api/jobs/00000000000000000001"]:
            for _ in range(3):
                status, _, body = await _raw(port, _get(path))
                assert status == 404, (path[:40], status, body[:200])
        for recipe in [digits, "%C2%B2", "-1", "65536"]:  # the second: a superscript 2
            status, _, _ = await _raw(port, (
                f"POST /api/trigger?recipe={recipe} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                f"Authorization: Bearer {TOKEN}\r\nContent-Length: 0\r\nConnection: close\r\n"
                f"\r\n").encode())
            assert status == 400, recipe[:20]
        assert not run.jobs
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]


async def test_malformed_requests_log_one_line_per_client(
        caplog: pytest.LogCaptureFixture) -> None:
    """A client that sends broken requests (a header line without a colon) decides nothing
    about the journal's size: one line a minute per client, no traceback."""
    caplog.set_level(logging.DEBUG, logger="aiohttp")
    async with running(make_config(daemon={"worker": False})) as run:
        port = _port(run)
        for _ in range(20):
            status, _, _ = await _raw(port, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                                            b"this is no header\r\n\r\n")
            assert status == 400
    lines = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) <= 1, [r.getMessage() for r in lines]
    assert not [r for r in lines if r.exc_info]


async def test_event_streams_are_capped_per_address_and_the_operator_is_served() -> None:
    """100 anonymous EventSource clients from 25 loopback addresses: at most 4 streams each and
    32 in all; the operator who carries the token (header or login cookie) is served anyway and
    gets the next job live."""
    from vgripd.service.web.events import MAX_EVENT_CLIENTS, MAX_EVENT_CLIENTS_PER_ADDRESS

    config = make_config(status={"port": 0, "token": TOKEN}, daemon={"worker": False})
    async with running(config) as run, Plc(run.port()) as plc:
        port = _port(run)
        server = run.daemon.status_server
        assert server is not None
        held: list[asyncio.StreamWriter] = []
        served: dict[str, int] = {}
        try:
            for i in range(100):
                local = f"127.0.0.{2 + i % 25}"
                reader, writer = await asyncio.open_connection(
                    "127.0.0.1", port, local_addr=(local, 0))
                writer.write(_get("/api/events"))
                async with asyncio.timeout(WAIT_S):
                    line = await reader.readline()
                if b" 200 " in line:
                    served[local] = served.get(local, 0) + 1
                    held.append(writer)
                else:
                    assert b" 503 " in line
                    writer.close()
            assert max(served.values()) <= MAX_EVENT_CLIENTS_PER_ADDRESS
            assert sum(served.values()) == MAX_EVENT_CLIENTS
            # The operator: the token in the header, and a browser with the login cookie.
            base = f"http://127.0.0.1:{port}"
            auth = {"Authorization": f"Bearer {TOKEN}"}
            async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http, \
                    aiohttp.ClientSession() as other:
                async with http.get(f"{base}/api/events", headers=auth) as sse:
                    assert sse.status == 200
                    async with http.post(f"{base}/login", data={"token": TOKEN}) as resp:
                        assert resp.status == 200  # followed to the page
                    async with http.get(f"{base}/api/events") as by_cookie:
                        assert by_cookie.status == 200
                        await plc.trigger(1)
                        assert (await plc.result(1))[Reg.STATUS] == Status.OK
                        for stream in (sse, by_cookie):
                            async with asyncio.timeout(WAIT_S):
                                async for raw in stream.content:
                                    if raw.startswith(b"event: job"):
                                        break
                async with other.get(f"{base}/api/events") as anon:
                    assert anon.status == 503  # still full for the others
        finally:
            for writer in held:
                writer.close()


async def test_redaction_in_the_api_and_the_recorded_job(tmp_path: Path) -> None:
    async with _guarded(tmp_path, allow_support_bundle=True) as run, \
            aiohttp.ClientSession() as http:
        base = f"http://127.0.0.1:{_port(run)}"
        auth = {"Authorization": f"Bearer {TOKEN}"}
        async with http.get(f"{base}/api/config", headers=auth) as resp:
            text = await resp.text()
        assert TOKEN not in text
        assert "pw-of-the-camera" not in text
        assert "token=abc" not in text
        cfg = json.loads(text)
        assert cfg["about"]["camera_url"] == "rtsp://<redacted>@cam.local/stream"
        assert cfg["status"]["token"] == "<redacted>"

        await _recorded(tmp_path / "rec", 1)
        (job,) = (tmp_path / "rec").glob("2*-job*")
        assert stat.S_IMODE(job.stat().st_mode) == 0o750
        files = sorted(job.iterdir())
        assert {f.name for f in files} >= {"config.toml", "pair.json", "result.json", "left.png"}
        for f in files:
            assert stat.S_IMODE(f.stat().st_mode) == 0o640, f.name
            data = f.read_bytes()
            assert TOKEN.encode() not in data, f.name
            assert b"pw-of-the-camera" not in data, f.name
        recorded = tomllib.loads((job / "config.toml").read_text())
        assert recorded["status"]["token"] == "<redacted>"
        assert recorded["about"]["camera_url"] == "rtsp://<redacted>@cam.local/stream"
        # Still a config replay loads; a daemon refuses to serve with the redacted token.
        assert load_config(job / "config.toml").status.token == "<redacted>"

        async with http.get(f"{base}/api/support-bundle", headers=auth) as resp:
            bundle = zipfile.ZipFile(io.BytesIO(await resp.read()))
        for name in bundle.namelist():
            data = bundle.read(name)
            assert TOKEN.encode() not in data, name
            assert b"pw-of-the-camera" not in data, name


async def test_a_daemon_does_not_serve_with_a_redacted_token(tmp_path: Path) -> None:
    from vgripd.service.web.app import StatusEndpointError

    config = make_config(status={"port": 0, "token": "<redacted>"}, daemon={"worker": False})
    with pytest.raises(StatusEndpointError, match="status.token"):
        async with running(config):
            pass


async def test_the_support_bundle_follows_no_planted_link(tmp_path: Path) -> None:
    secret = tmp_path / "private"
    secret.mkdir()
    (secret / "key.pem").write_text("PRIVATE KEY OF THE PLANT")
    (secret / "left.png").write_text("PRIVATE KEY OF THE PLANT")
    async with _guarded(tmp_path, allow_support_bundle=True) as run, \
            aiohttp.ClientSession() as http:
        rec = tmp_path / "rec"
        await _recorded(rec, 1)
        (job,) = rec.glob("2*-job*")
        # Links named as the recorder names its files and folders, and a stray file.
        (job / "view7.png").symlink_to(secret / "key.pem")
        (job / "notes.txt").write_text("PRIVATE KEY OF THE PLANT")
        (rec / "29990101-000000.000-job999999").symlink_to(secret)
        (rec / "29990101-000000.001-job999998").mkdir()
        (rec / "29990101-000000.001-job999998" / "result.json").symlink_to(secret / "key.pem")
        base = f"http://127.0.0.1:{_port(run)}"
        async with http.get(f"{base}/api/support-bundle",
                            headers={"Authorization": f"Bearer {TOKEN}"}) as resp:
            assert resp.status == 200
            bundle = zipfile.ZipFile(io.BytesIO(await resp.read()))
        names = bundle.namelist()
        assert f"jobs/{job.name}/left.png" in names
        assert f"jobs/{job.name}/result.json" in names
        for name in names:
            assert b"PRIVATE KEY" not in bundle.read(name), name
        assert not [n for n in names if "job999999" in n or "view7" in n or "notes" in n]
        assert not [n for n in names if n.endswith("job999998/result.json")]



SCRAPE_CONFIG = Path(__file__).parents[2] / "docs" / "prometheus" / "prometheus.yml"


async def test_the_shipped_prometheus_config_scrapes_a_guarded_view(tmp_path: Path) -> None:
    """A real Prometheus with docs/prometheus/prometheus.yml (its token file and target pointed
    at this daemon, bound to 0.0.0.0 with the token): the vgripd job is up and its metrics are
    queryable; the same job with a wrong token is down with a 401 (on the old code /metrics
    answered anyone)."""
    import socket

    from tests.conftest import need_tool

    prometheus = need_tool("prometheus")
    shipped = SCRAPE_CONFIG.read_text()
    assert "credentials_file: /etc/prometheus/vgripd.token" in shipped
    assert 'targets: ["127.0.0.1:8730"]' in shipped
    good, bad = tmp_path / "vgripd.token", tmp_path / "wrong.token"
    good.write_text(TOKEN + "\n")
    bad.write_text("not-the-token-of-this-daemon\n")
    with socket.socket() as s:  # a free port for Prometheus' own API (loopback only)
        s.bind(("127.0.0.1", 0))
        api_port = s.getsockname()[1]
    async with _guarded(tmp_path) as run:
        target = f"127.0.0.1:{_port(run)}"
        config = shipped.replace("scrape_interval: 5s", "scrape_interval: 1s").replace(
            "127.0.0.1:8730", target)
        wrong = config[config.index("  - job_name: vgripd"):config.index("# either")].replace(
            "job_name: vgripd", "job_name: wrong").replace("/etc/prometheus/vgripd.token",
                                                           str(bad))
        config = config.replace("/etc/prometheus/vgripd.token", str(good)).replace(
            "# either", wrong + "# either", 1)
        (tmp_path / "prometheus.yml").write_text(config)
        proc = await asyncio.create_subprocess_exec(
            prometheus, f"--config.file={tmp_path / 'prometheus.yml'}",
            f"--storage.tsdb.path={tmp_path / 'tsdb'}",
            f"--web.listen-address=127.0.0.1:{api_port}",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
        try:
            async with aiohttp.ClientSession() as http, asyncio.timeout(60):
                api = f"http://127.0.0.1:{api_port}/api/v1"
                while True:  # noqa: ASYNC110 (Prometheus pushes nothing: its API is polled)
                    with contextlib.suppress(aiohttp.ClientError):
                        async with http.get(f"{api}/targets") as resp:
                            active = (await resp.json())["data"]["activeTargets"]
                        health = {t["labels"]["job"]: t for t in active}
                        if len(health) == 2 and all(t["health"] != "unknown"
                                                    for t in health.values()):
                            break
                    await asyncio.sleep(0.2)
                assert health["vgripd"]["health"] == "up", health["vgripd"]["lastError"]
                assert health["wrong"]["health"] == "down"
                assert "401" in health["wrong"]["lastError"]
                while True:  # noqa: ASYNC110
                    async with http.get(f"{api}/query",
                                        params={"query": 'vgripd_jobs_total{status="OK"}'}) as resp:
                        result = (await resp.json())["data"]["result"]
                    if result:
                        break
                    await asyncio.sleep(0.2)
                assert result[0]["metric"]["job"] == "vgripd"
                assert result[0]["value"][1] == "1"
        finally:
            if proc.returncode is None:
                proc.terminate()
            await proc.wait()
