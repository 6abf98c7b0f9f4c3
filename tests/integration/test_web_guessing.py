"""The web view against a guessing client and malformed bodies, over loopback: wrong tokens
(Bearer header and ``/login``) are slowed and then locked out per client address, counted in
``/metrics``; a body or a name the daemon cannot use is a 4xx that says why, never a 500; the
calibration health shows anonymous readers no secret of ``[about]`` and no absolute path.
Every flood is bounded (a few hundred requests) and stays on 127.0.0.0/8.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiohttp

from tests.integration.test_web_reload import AUTH, TOKEN, running_file, write_cell

FLOOD = 120
WRONG = {"Authorization": "Bearer wrong-token-xxxxxxxxxxxxxxxxx"}


async def _statuses(base: str, n: int, method: str, path: str, local: str,
                    **kwargs: object) -> list[int]:
    """``n`` requests, 16 at a time, from ``local``: their status codes."""
    connector = aiohttp.TCPConnector(limit=16, local_addr=(local, 0))
    async with aiohttp.ClientSession(connector=connector) as http:
        async def one() -> int:
            async with http.request(method, f"{base}{path}", allow_redirects=False,
                                    **kwargs) as resp:  # type: ignore[arg-type]
                await resp.read()
                return resp.status
        return list(await asyncio.gather(*(one() for _ in range(n))))


def _metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in /metrics")


async def test_wrong_bearer_tokens_are_slowed_then_locked_out_per_address(
        tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    async with running_file(main) as run:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        got = await _statuses(base, FLOOD, "GET", "/api/status", "127.0.0.1", headers=WRONG)
        # Ten judged (a public read on a loopback bind: served, the token counted), every
        # later one refused unchecked.
        assert got.count(200) == 10, got
        assert got.count(429) == FLOOD - 10, got
        # The right token from the locked-out address: refused unchecked too.
        async with aiohttp.ClientSession() as http:
            async with http.get(f"{base}/api/status", headers=AUTH) as resp:
                assert resp.status == 429
                assert "status.login_lockout_s" in await resp.text()
                assert int(resp.headers["Retry-After"]) > 0
            async with http.post(f"{base}/api/reload", headers=AUTH) as resp:
                assert resp.status == 429
            # Reads without a token are no guess: served.
            async with http.get(f"{base}/api/status") as resp:
                assert resp.status == 200
        # Another address is not locked out by this one.
        assert await _statuses(base, 1, "GET", "/api/status", "127.0.0.2",
                               headers=AUTH) == [200]
        async with aiohttp.ClientSession() as http, http.get(f"{base}/metrics") as resp:
            metrics = await resp.text()
        assert _metric(metrics, "vgripd_web_login_failures_total") == 10
        assert _metric(metrics, "vgripd_web_lockouts_total") == 1
        assert _metric(metrics, "vgripd_web_login_refused_locked_total") >= FLOOD - 10 + 2


async def test_wrong_tokens_at_login_lock_the_address_out_the_right_one_too(
        tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    async with running_file(main) as run:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        got = await _statuses(base, FLOOD, "POST", "/login", "127.0.0.3",
                              data={"token": "wrong-token-xxxxxxxxxxxx"})
        assert got.count(403) == 10, got
        assert got.count(429) == FLOOD - 10, got
        assert await _statuses(base, 1, "POST", "/login", "127.0.0.3",
                               data={"token": TOKEN}) == [429]
        # A right token resets an address's count: a mistyped one does not add up.
        for _ in range(3):
            assert await _statuses(base, 9, "POST", "/login", "127.0.0.4",
                                   data={"token": "wrong-token-xxxxxxxxxxxx"}) == [403] * 9
            assert await _statuses(base, 1, "POST", "/login", "127.0.0.4",
                                   data={"token": TOKEN}) == [303]


async def test_bodies_and_names_the_daemon_cannot_use_are_4xx_with_the_reason(
        tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    deep = ("[" * 30000 + "]" * 30000).encode()
    async with running_file(main) as run, aiohttp.ClientSession() as http:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        json_type = {**AUTH, "Content-Type": "application/json"}
        for path in ("/api/tuning", "/api/tuning/try", "/api/cameras/0/settings",
                     "/api/handeye/plan", "/api/handeye/walk/start"):
            async with http.post(f"{base}{path}", data=deep, headers=json_type) as resp:
                assert resp.status == 400, path
                assert "nested" in await resp.text(), path
            async with http.post(f"{base}{path}", data=b'{"a": "\xff"}',
                                 headers=json_type) as resp:
                assert resp.status == 400, path
                assert "not UTF-8" in await resp.text(), path

        for name, why in [("a\x00b.toml", "control character"), ("p" * 300 + ".toml", "at most")]:
            async with http.post(f"{base}/api/handeye/plan", json={"save": name},
                                 headers=AUTH) as resp:
                assert resp.status == 422, name[:20]
                assert why in (await resp.json())["refused"]
            async with http.post(f"{base}/api/handeye/walk/start", json={"plan": name},
                                 headers=AUTH) as resp:
                assert 400 <= resp.status < 500, name[:20]
        async with http.post(f"{base}/api/handeye/plan", json={"board": "a\x00b"},
                             headers=AUTH) as resp:
            assert resp.status == 422
            assert "control character" in (await resp.json())["refused"]

        # The login form: multipart is refused with the type it must be, bytes that are no
        # UTF-8 with the reason; the right token in either body does not log in.
        form = aiohttp.FormData()
        form.add_field("token", TOKEN)
        form.add_field("file", b"x", filename="x.bin")
        async with http.post(f"{base}/login", data=form, allow_redirects=False) as resp:
            assert resp.status == 415
            assert "x-www-form-urlencoded" in await resp.text()
        for body in (b"token=" + TOKEN.encode() + b"&x=\xff", b"token=%ff%fe"):
            async with http.post(f"{base}/login", data=body, allow_redirects=False,
                                 headers={"Content-Type": "application/x-www-form-urlencoded"}
                                 ) as resp:
                assert resp.status == 400, body
                text = await resp.text()
                assert "UTF-8" in text or "utf-8" in text, text
        assert not json.dumps(run.daemon.snapshot(), default=str).count(TOKEN)


async def test_calibration_health_redacts_about_and_keeps_paths_from_anonymous_readers(
        tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    cell.write_text('[about]\ncamera = "rtsp://user:pass-of-cam@cam.local/s"\n'
                    'api_key = "k-123456"\nnote = "taught"\n\n' + cell.read_text())
    async with running_file(main) as run, aiohttp.ClientSession() as http:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        async with http.get(f"{base}/api/calibration") as resp:
            assert resp.status == 200
            text = await resp.text()
        files = json.loads(text)["files"]
        assert "pass-of-cam" not in text
        assert "k-123456" not in text
        assert str(tmp_path) not in text
        entry = next(f for f in files if f["file"] == "cell.toml")
        assert entry["about"] == {"camera": "rtsp://<redacted>@cam.local/s",
                                  "api_key": "<redacted>", "note": "taught"}
        async with http.get(f"{base}/api/calibration", headers=AUTH) as resp:
            held = await resp.json()
        assert str(cell) in [f["file"] for f in held["files"]]
        assert "k-123456" not in json.dumps(held)
