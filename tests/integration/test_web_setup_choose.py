"""The setup page's cameras and link steps over real HTTP against ``vgripd demo --setup``: the
devices the stacks find, a camera and a link chosen and written through the config transaction
into ``camera.toml`` and ``links.toml`` (judged first, the keys a restart applies named), a bad
choice refused naming its field with nothing written, and each link type's contract; the
restart the page offers to run a chosen camera."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.integration.setup_browser import click, demo_setup, open_page, text, until
from tests.integration.test_web import _chromium


async def call(s: aiohttp.ClientSession, method: str, url: str, token: str,
               body: Any = None) -> tuple[int, Any]:
    async with s.request(method, url, json=body,
                         headers={"Authorization": f"Bearer {token}"}) as r:
        text = await r.text()
        return r.status, (await r.json() if r.content_type == "application/json" else text)


@pytest.mark.timeout(600)
async def test_cameras_and_link_are_chosen_through_the_transaction(tmp_path: Path) -> None:
    async with demo_setup(tmp_path / "cell") as cell, aiohttp.ClientSession() as s:
        base = cell.url.removesuffix("/setup")
        camera_file, links_file = cell.folder / "camera.toml", cell.folder / "links.toml"

        code, found = await call(s, "GET", f"{base}/api/setup/cameras/discover", cell.token)
        assert code == 200, found
        assert {"devices", "unavailable", "types", "current"} <= set(found)
        assert found["current"]["type"] == "board"
        code, _ = await call(s, "GET", f"{base}/api/setup/cameras/discover", "wrong")
        assert code == 403

        # a bad choice: 400 naming the field, the include untouched
        before = camera_file.read_bytes()
        code, text = await call(s, "POST", f"{base}/api/setup/cameras/choose", cell.token,
                                {"type": "pylon", "cameras": [{"name": "left"}]})
        assert code == 400
        assert "camera.cameras[0]: exactly one of serial, ip, user_name" in text
        # judged and refused by the check (a replay camera without its images): 422
        code, answer = await call(s, "POST", f"{base}/api/setup/cameras/choose", cell.token,
                                  {"type": "replay"})
        assert code == 422, answer
        assert "camera" in answer["message"], answer
        assert camera_file.read_bytes() == before

        # the board camera, other settings: written, applied at the next start (named)
        code, answer = await call(s, "POST", f"{base}/api/setup/cameras/choose", cell.token,
                                  {"type": "board", "options": {"seed": 7}})
        assert code == 200, answer
        assert "camera.seed" in answer["restart"], answer
        assert tomllib.loads(camera_file.read_text())["camera"]["seed"] == 7
        assert (cell.folder / "camera.toml.1").read_bytes() == before  # numbered backup

        code, options = await call(s, "GET", f"{base}/api/setup/link/options", cell.token)
        assert code == 200
        assert {t["type"] for t in options["types"]} >= {"modbus_server", "s7", "opcua",
                                                         "robot_socket", "ur_rtde"}
        assert options["running"][0]["type"] == "modbus_server"
        code, text = await call(s, "POST", f"{base}/api/setup/link/choose", cell.token,
                                {"links": [{"type": "profibus"}]})
        assert code == 400
        assert "links[0].type" in text
        code, answer = await call(s, "POST", f"{base}/api/setup/link/choose", cell.token,
                                  {"links": [{"type": "modbus_server", "host": "127.0.0.1",
                                              "port": 70000}]})
        assert code == 422, answer
        assert "port" in answer["message"], answer
        link = {"type": "robot_socket", "host": "127.0.0.1", "port": 0}
        code, answer = await call(s, "POST", f"{base}/api/setup/link/choose", cell.token,
                                  {"links": [link]})
        assert code == 200, answer
        assert any(k.startswith("links.") for k in answer["restart"]), answer
        assert tomllib.loads(links_file.read_text())["links"] == [link]

        code, contract = await call(s, "GET", f"{base}/api/setup/link/contract?type=s7",
                                    cell.token)
        assert code == 200, contract
        assert contract["kind"] == "registers"
        assert contract["s7_udt"]["ok"], contract
        assert "TYPE" in contract["s7_udt"]["source"]
        assert contract["registers"][0]["rows"]  # the running Modbus link's map, decoded
        code, contract = await call(s, "GET", f"{base}/api/setup/link/contract?type=opcua",
                                    cell.token)
        assert code == 200
        assert "VisionSystem.Plc.StartJob" in [m["node"] for m in contract["opcua"]["methods"]]
        code, contract = await call(s, "GET",
                                    f"{base}/api/setup/link/contract?type=robot_socket",
                                    cell.token)
        assert code == 200
        assert {"kuka", "ur", "abb"} <= set(contract["brands"])


@pytest.mark.timeout(600)
async def test_the_page_discovers_chooses_and_shows_the_contract_in_chromium(
        tmp_path: Path) -> None:
    """The same choices clicked in the page: the focus control says why the learning cell has
    none; Discover lists the camera types, a synthetic camera
    chosen lands in camera.toml with the restart named; the link step lists the link types,
    shows the S7 UDT of the s7 contract, and a robot socket chosen from the settings box lands
    in links.toml."""
    async with demo_setup(tmp_path / "cell") as cell, \
            _chromium(tmp_path, cell.url) as evaluate:
        await until(evaluate, "document.getElementById('nav-cameras') !== null")
        await evaluate(f"""(() => {{ const t = document.getElementById('token');
            t.value = {json.dumps(cell.token)}; t.dispatchEvent(new Event('change'));
            return true; }})()""")
        # the learning cell's cameras have no lens: the focus control says so, and a value
        # sent anyway is refused with the same reason
        focus = await until(evaluate, f"{text('cam-focus-state')}.startsWith('not available')"
                                      f" && {text('cam-focus-state')}", 120.0)
        assert focus == ("not available: board: the learning cell renders its images: no lens "
                         "to focus (blur_px sets their sharpness)"), focus
        assert await evaluate("document.getElementById('cam-focus-form').hidden")
        refused = await evaluate(f"""fetch('/api/setup/focus', {{method: 'POST', headers: {{
            Authorization: 'Bearer ' + {json.dumps(cell.token)},
            'Content-Type': 'application/json'}}, body: JSON.stringify({{value: 3}})}})
            .then(async (r) => r.status + ' ' + await r.text())""")
        assert refused.startswith("409 no focus to set: board: the learning cell"), refused
        await evaluate(click("btn-cam-discover"))
        await until(evaluate, f"{text('cam-choose-result')}.startsWith('now: board')", 120.0)
        types = await evaluate("[...document.getElementById('cam-type').options]"
                               ".map((o) => o.value).join(' ')")
        assert {"board", "synthetic", "replay", "pylon", "aravis"} <= set(types.split()), types
        await evaluate("document.getElementById('cam-type').value = 'synthetic', true")
        await evaluate(click("btn-cam-choose"))
        result = await until(evaluate, f"/^(APPLIED|ACCEPTED|REFUSED)/.test("
                                       f"{text('cam-choose-result')}) && "
                                       f"{text('cam-choose-result')}", 120.0)
        assert result.startswith(("APPLIED", "ACCEPTED")), result
        assert "next start" in result, result
        assert tomllib.loads((cell.folder / "camera.toml").read_text())["camera"]["type"] == (
            "synthetic")

        await evaluate(click("nav-link"))
        await until(evaluate, "document.getElementById('link-type').options.length > 4", 60.0)
        await evaluate("(() => { const s = document.getElementById('link-type');"
                       " s.value = 's7'; s.dispatchEvent(new Event('change')); return true; })()")
        await evaluate(click("btn-link-contract"))
        contract = await until(evaluate, f"{text('link-contract')}.includes('TYPE') && "
                                         f"{text('link-contract')}", 120.0)
        assert "vgripd s7-udt" in contract, contract
        link = {"type": "robot_socket", "host": "127.0.0.1", "port": 0}
        await evaluate(f"document.getElementById('link-settings').value = "
                       f"{json.dumps(json.dumps(link))}, true")
        await evaluate(click("btn-link-choose"))
        result = await until(evaluate, f"/^(APPLIED|ACCEPTED|REFUSED)/.test("
                                       f"{text('link-choose-result')}) && "
                                       f"{text('link-choose-result')}", 120.0)
        assert result.startswith(("APPLIED", "ACCEPTED")), result
        assert tomllib.loads((cell.folder / "links.toml").read_text())["links"] == [link]


@pytest.mark.timeout(600)
async def test_a_chosen_camera_runs_after_the_restart_the_page_offers(tmp_path: Path) -> None:
    """A camera chosen on the page is saved, and the page offers the restart that runs it: the
    files are judged first (a camera include broken by hand meanwhile is refused naming it, the
    daemon answering on), then the daemon stops between jobs and ``vgripd demo --setup`` starts
    it again on the saved files: the page reconnects to a daemon running the chosen camera."""
    async with demo_setup(tmp_path / "cell") as cell, \
            _chromium(tmp_path, cell.url) as evaluate:
        await open_page(evaluate, cell.token)
        instance = await until(evaluate, "state && state.instance", 60.0)
        await evaluate(click("btn-cam-discover"))
        await until(evaluate, f"{text('cam-choose-result')}.startsWith('now: board')", 120.0)
        await evaluate("document.getElementById('cam-type').value = 'synthetic', true")
        await evaluate(click("btn-cam-choose"))
        result = await until(evaluate, f"/^(APPLIED|ACCEPTED|REFUSED)/.test("
                                       f"{text('cam-choose-result')}) && "
                                       f"{text('cam-choose-result')}", 120.0)
        assert result.startswith("APPLIED"), result
        assert await evaluate("!document.getElementById('restart-bar').hidden")
        assert "camera.type" in await evaluate(text("restart-keys"))

        camera_file = cell.folder / "camera.toml"
        saved = camera_file.read_bytes()
        camera_file.write_text('[camera]\ntype = "replay"\n')  # broken by hand meanwhile
        await evaluate(click("btn-restart"))
        refused = await until(evaluate, f"/^(REFUSED|RESTARTING)/.test("
                                        f"{text('restart-result')}) && "
                                        f"{text('restart-result')}", 300.0)
        assert refused.startswith("REFUSED (422): refused, the daemon keeps running"), refused
        assert "camera" in refused, refused
        assert await evaluate("fetch('/api/setup').then((r) => r.json())"
                              ".then((d) => d.instance)") == instance
        assert cell.proc.returncode is None

        camera_file.write_bytes(saved)
        await evaluate(click("btn-restart"))
        await until(evaluate, f"{text('restart-result')}.startsWith('RESTARTING')", 300.0)
        note = await until(evaluate, f"{text('setup-note')}.startsWith('RESTARTED') && "
                                     f"{text('setup-note')}", 300.0)
        assert "camera type synthetic" in note, note
        assert await evaluate("state.instance") != instance
        assert (await evaluate(text("cam-describe"))).startswith("camera type synthetic")
        assert cell.proc.returncode is None  # the same demo process, its daemon started again
