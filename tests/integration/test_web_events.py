"""The status pushed to the web view over ``/api/events`` by a running daemon: a job and a link
going down and back up reach an open stream without anyone asking ``/api/status``; the stream
obeys the read rule of ``/api/status``; a burst of changes is coalesced; event streams leave
connections for ordinary requests. Real daemon, real pymodbus peers, aiohttp's client, all on
127.0.0.1; every wait is on a pushed event or a daemon state, with a timeout.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.integration.test_daemon import Plc, Run, make_config, running
from tests.integration.test_web import TOKEN, WAIT_S, _chromium, _events, _until
from vgripd.config import config_from_dict
from vgripd.peer.registers import Reg
from vgripd.service.web.events import MAX_EVENT_CLIENTS_PER_ADDRESS, PUSH_INTERVAL_S
from vgripd.sim.robot_modbus import MockRobotModbus
from vgripd.types import Status

pytestmark = pytest.mark.slow

Doc = dict[str, Any]


def _base(run: Run) -> str:
    assert run.daemon.status_server is not None
    return f"http://127.0.0.1:{run.daemon.status_server.port}"


async def _pushed(stream: AsyncIterator[tuple[str, Any, float]],
                  wanted: Callable[[Doc], bool]) -> Doc:
    """The first pushed ``status`` document for which ``wanted`` holds (within ``WAIT_S``)."""
    async with asyncio.timeout(WAIT_S):
        async for event, data, _ in stream:
            if event == "status" and wanted(data):
                return dict(data)
    raise AssertionError("the event stream ended")


def _link(doc: Doc, name: str) -> Doc:
    found: Doc = next(link for link in doc["links"] if link["name"] == name)
    return found


async def test_a_job_is_pushed_to_an_open_stream() -> None:
    async with running(make_config()) as run, aiohttp.ClientSession() as http:
        async with http.get(f"{_base(run)}/api/events") as sse:
            stream = _events(sse)
            first = await _pushed(stream, lambda d: True)  # the state on connecting
            assert first["last_job"] is None
            assert first["web"]["history"] == 100  # the same document as /api/status
            async with Plc(run.port()) as plc:
                doc = await _pushed(stream, lambda d: _link(d, "modbus_server")["peers"] == 1)
                assert doc["last_job"] is None
                await plc.trigger(1)
                assert (await plc.result(1))[Reg.STATUS] == Status.OK
                doc = await _pushed(stream, lambda d: d["last_job"] is not None)
        assert doc["last_job"]["id"] == 1
        assert doc["last_job"]["status"] == "OK"


async def test_a_link_going_down_and_up_is_pushed() -> None:
    robot = MockRobotModbus()
    await robot.start()
    try:
        config = config_from_dict({
            "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
            "links": [{"type": "modbus_client", "host": robot.host, "port": robot.port,
                       "backoff_initial_s": 0.1, "backoff_max_s": 0.5}],
            "status": {"port": 0}})
        async with running(config) as run, aiohttp.ClientSession() as http, \
                http.get(f"{_base(run)}/api/events") as sse:
            stream = _events(sse)
            await _pushed(stream, lambda d: _link(d, "modbus_client")["state"] == "up")
            await robot.go_offline()
            down = await _pushed(stream, lambda d: _link(d, "modbus_client")["state"] != "up")
            assert _link(down, "modbus_client")["state"] in ("down", "connecting")
            await robot.come_back()
            up = await _pushed(stream, lambda d: _link(d, "modbus_client")["state"] == "up")
            assert _link(up, "modbus_client")["reconnects"] >= 1
    finally:
        await robot.stop()


async def test_the_stream_follows_the_read_rule_of_the_status(tmp_path: Path) -> None:
    """Bound to 0.0.0.0 with a token (reached through 127.0.0.1): ``/api/events`` answers
    exactly what ``/api/status`` answers, for no token, a wrong one, the token in the header
    and the login cookie; with ``public_read`` both are open."""
    bearer = {"Authorization": f"Bearer {TOKEN}"}
    wrong = {"Authorization": "Bearer wrong-token-of-32-characters-xx"}
    for public_read in (False, True):
        config = make_config(status={"host": "0.0.0.0", "port": 0, "token": TOKEN,
                                     "public_read": public_read})
        async with running(config) as run, \
                aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
            base = _base(run)
            seen = []
            for headers in ({}, wrong, bearer):
                answers = []
                for path in ("/api/status", "/api/events"):
                    async with http.get(base + path, headers=headers) as resp:
                        answers.append(resp.status)
                        if resp.status == 200 and path == "/api/events":
                            doc = await _pushed(_events(resp), lambda d: True)
                            assert doc["pid"] == (await _status(http, base, bearer))["pid"]
                seen.append(tuple(answers))
            async with http.post(f"{base}/login", data={"token": TOKEN}) as resp:
                assert resp.status == 200
            async with http.get(f"{base}/api/status") as a, http.get(f"{base}/api/events") as b:
                seen.append((a.status, b.status))
        closed = 200 if public_read else 401
        assert seen == [(closed, closed), (closed, closed), (200, 200), (200, 200)]


async def _status(http: aiohttp.ClientSession, base: str, headers: dict[str, str]) -> Doc:
    async with http.get(f"{base}/api/status", headers=headers) as resp:
        assert resp.status == 200
        doc: Doc = await resp.json()
        return doc


async def test_a_burst_of_changes_is_coalesced() -> None:
    """400 state changes spread over several push intervals: the stream gets at most one
    document per ``PUSH_INTERVAL_S`` (plus the one under way), and the last one pushed
    describes the state after the burst."""
    async with running(make_config()) as run, aiohttp.ClientSession() as http, \
            http.get(f"{_base(run)}/api/events") as sse:
        server = run.daemon.status_server
        assert server is not None
        stream = _events(sse)
        await _pushed(stream, lambda d: True)
        before = server.feed.pushed
        t0 = time.monotonic()
        for _ in range(40):
            for _ in range(10):
                run.daemon.show_state()
            await asyncio.sleep(PUSH_INTERVAL_S / 4)  # pacing the burst, no state awaited
        elapsed_s = time.monotonic() - t0
        pushed = server.feed.pushed - before
        assert 1 <= pushed <= 2 + elapsed_s / PUSH_INTERVAL_S
        final = run.daemon.changes
        async with asyncio.timeout(WAIT_S):  # the feed's own counter: no daemon state, polled
            while server.feed.documented < final:  # noqa: ASYNC110
                await asyncio.sleep(0.02)
        assert server.feed.documented == final


async def test_event_streams_leave_connections_for_requests() -> None:
    """``max_connections = 4``: two pages without the token get a stream, a third is refused
    (503) and a plain request is still answered while the streams stay open."""
    config = make_config(status={"port": 0, "max_connections": 4, "header_timeout_s": 60.0})
    async with running(config) as run, aiohttp.ClientSession() as http:
        base = _base(run)
        opened = []
        try:
            for _ in range(3):
                resp = await http.get(f"{base}/api/events")
                opened.append(resp)
            assert [r.status for r in opened] == [200, 200, 503]
            async with aiohttp.ClientSession() as other, other.get(f"{base}/api/jobs") as resp:
                assert resp.status == 200
        finally:
            for resp in opened:
                resp.close()


async def test_the_page_polls_while_its_stream_is_refused_and_streams_again(
        tmp_path: Path) -> None:
    """Headless Chromium: while every stream its address may hold is taken, the page's own is
    refused and it polls ``/api/status`` (a new job still shows); once streams are free it
    opens one again and is fed by the daemon."""
    text = "(id) => document.getElementById(id)?.textContent ?? ''"
    async with running(make_config()) as run, Plc(run.port()) as plc, \
            aiohttp.ClientSession() as http:
        base = _base(run)
        taken = [await http.get(f"{base}/api/events")
                 for _ in range(MAX_EVENT_CLIENTS_PER_ADDRESS)]
        try:
            assert [r.status for r in taken] == [200] * MAX_EVENT_CLIENTS_PER_ADDRESS
            async with _chromium(tmp_path, base + "/") as evaluate:
                assert await _until(evaluate, "document.body?.dataset.live === 'polling'")

                async def job_shows(seq: int) -> None:
                    await plc.trigger(seq)
                    assert (await plc.result(seq))[Reg.STATUS] == Status.OK
                    assert f"job {seq}: OK" in await _until(
                        evaluate, f"({text})('job-status').includes('job {seq}') && "
                                  f"({text})('job-status')")

                await job_shows(1)  # while polling
                for resp in taken:
                    resp.close()
                assert await _until(evaluate, "document.body?.dataset.live === 'events'")
                await job_shows(2)  # streaming again
        finally:
            for resp in taken:
                resp.close()
