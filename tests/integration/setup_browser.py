"""Driving the whole setup of the learning cell in headless Chromium, as an integrator would:
``vgripd demo --setup`` started as a command (its printed URL, token and PLC port), the page
``/setup`` opened, every step done by clicking the page's own buttons (no request made behind
its back, no file written by hand), then a pymodbus PLC client triggering the first job over
Modbus/TCP. Shared by tests/integration/test_web_setup.py and bench/bench_setup_flow.py.

Every wait is on what the page shows (polled, with a generous deadline: a loaded machine's
grabs and calibration are slow), never a fixed sleep.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tests.integration.test_daemon import Plc
from tests.integration.test_web import _chromium
from vgripd.peer.registers import Reg

Evaluate = Callable[[str], Awaitable[Any]]
#: Sets the calibration step captures before it calibrates.
SETS = 8
STEP_WAIT_S = 300.0


@dataclass
class Cell:
    """A running ``vgripd demo --setup``: where its page is, its token, its PLC port."""

    url: str
    token: str
    plc_port: int
    folder: Path
    proc: asyncio.subprocess.Process


@dataclass
class Flow:
    """What the drive measured: page actions (clicks, form submits), seconds per step."""

    actions: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    plc_status: int = 0
    plc_values: list[int] = field(default_factory=list)


@contextlib.asynccontextmanager
async def demo_setup(folder: Path) -> AsyncIterator[Cell]:
    """``vgripd demo --setup --state-dir folder`` on free ports until the block ends."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "demo", "--setup", "--state-dir", str(folder),
        "--port", "0", "--web-port", "0", stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert proc.stdout is not None
    try:
        seen = ""
        async with asyncio.timeout(120):
            while "PLC link:" not in seen:
                line = await proc.stdout.readline()
                assert line, f"vgripd demo --setup ended: {seen}"
                seen += line.decode()
        url = re.search(r"setup page: (\S+)", seen)
        token = re.search(r"token:\s+(\S+)", seen)
        port = re.search(r"Modbus/TCP on 127\.0\.0\.1:(\d+)", seen)
        assert url, seen
        assert token, seen
        assert port, seen
        drain = asyncio.ensure_future(proc.stdout.read())
        yield Cell(url.group(1), token.group(1), int(port.group(1)), folder, proc)
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(30):
                    await proc.wait()
            except TimeoutError:
                proc.kill()
                await proc.wait()
        with contextlib.suppress(NameError):
            await drain


def seed_calibrated(folder: Path) -> None:
    """The learning cell's files as ``vgripd demo --setup`` lays them out, with the calibration
    and hand-eye steps already done by their true values (the board camera's truth cameras):
    for the tests of the later steps, which need a calibrated cell but not the minutes its
    capture takes. The object, the reference and the link stay as demo --setup writes them."""
    from vgripd.cli.demo_setup import write_cell
    from vgripd.config import DEMO_CALIBRATION
    from vgripd.geometry.fingerprint import camera_about
    from vgripd.serialize import toml_from_dict

    write_cell(folder, 0, 0)
    cal = DEMO_CALIBRATION.model_dump(mode="json", exclude_none=True)
    rig = {k: cal[k] for k in ("left", "right", "stereo")}
    (folder / "rig.toml").write_text(toml_from_dict({"calibration": rig}), encoding="utf-8")
    (folder / "handeye.toml").write_text(toml_from_dict({
        "about": camera_about(rig), "calibration": {"hand_eye": cal["hand_eye"]}}),
        encoding="utf-8")
    progress = folder / "setup" / "progress.json"
    progress.parent.mkdir(exist_ok=True)
    progress.write_text(json.dumps({"done": {"cameras": 1.0, "calibration": 1.0,
                                             "handeye": 1.0}}))


async def open_page(evaluate: Evaluate, token: str) -> None:
    """The page loaded and the token typed into it."""
    await until(evaluate, "document.getElementById('nav-cameras') !== null")
    await evaluate(f"""(() => {{ const t = document.getElementById('token');
        t.value = {json.dumps(token)}; t.dispatchEvent(new Event('change'));
        return true; }})()""")


def drag(img_selector: str, box: tuple[int, int, int, int]) -> str:
    """JS: a mouse drag over the image ``img_selector`` across ``box`` (x, y, w, h in the full
    camera image's pixels; the image is shown scaled), as the integrator draws a region."""
    x, y, w, h = box
    return f"""(() => {{
        const im = document.querySelector({json.dumps(img_selector)});
        const r = im.getBoundingClientRect(), s = im.clientWidth / Number(im.dataset.width);
        const at = (type, px, py) => im.dispatchEvent(new MouseEvent(type, {{bubbles: true,
            clientX: r.left + im.clientLeft + px * s, clientY: r.top + im.clientTop + py * s,
            buttons: 1}}));
        at('mousedown', {x}, {y}); at('mousemove', {x + w / 2}, {y + h / 2});
        at('mousemove', {x + w}, {y + h}); at('mouseup', {x + w}, {y + h});
        return true; }})()"""


async def until(evaluate: Evaluate, expression: str, wait_s: float = STEP_WAIT_S,
                every: str | None = None) -> Any:
    """The first truthy value of ``expression``; ``every``: a click (JS) repeated while the
    answer is not there yet (a grab refused while a reload is applied, say)."""
    async with asyncio.timeout(wait_s):
        while not (value := await evaluate(expression)):
            if every is not None:
                await evaluate(every)
            await asyncio.sleep(0.25)
    return value


def text(id_: str) -> str:
    return f"(document.getElementById({json.dumps(id_)})?.textContent ?? '')"


def click(id_: str) -> str:
    return f"document.getElementById({json.dumps(id_)}).click(), true"


async def capture_and_calibrate(evaluate: Evaluate, kind: str = "auto") -> str:
    """On the calibration step: auto-capture until ``SETS`` sets are kept, calibrate as
    ``kind`` (the page's "Calibrate as"), wait for the result; its figures."""
    await evaluate(click("calib-auto"))
    await until(evaluate, f"/^(\\d+) set/.test({text('calib-sets')}) && "
                          f"Number(/^(\\d+) set/.exec({text('calib-sets')})[1]) >= {SETS}",
                wait_s=900.0)
    await evaluate(click("calib-auto"))
    await evaluate(f"document.getElementById('calib-kind').value = {json.dumps(kind)}, true")
    await evaluate(click("btn-calib-run"))
    await until(evaluate, f"{text('calib-progress')}.startsWith('calibrated in')", 900.0)
    figures = str(await evaluate(text("calib-figures")))
    assert "RMS" in figures, figures
    if kind != "cameras":  # the chosen distortion model, named with how it was chosen
        assert "model: " in figures, figures
        assert "[object Object]" not in figures, figures
    return figures


async def drive(cell: Cell, tmp_path: Path) -> Flow:
    """Every step of the page, in order; then the PLC's first job."""
    flow = Flow()
    async with _chromium(tmp_path, cell.url) as evaluate:
        t = time.monotonic()

        async def lap(step: str) -> None:
            nonlocal t
            flow.seconds[step] = round(time.monotonic() - t, 1)
            t = time.monotonic()

        async def done(step: str, nxt: str) -> None:
            await evaluate(click("btn-done"))
            await until(evaluate, f"{text('check-summary')}.startsWith('vgripd check')")
            await until(evaluate, f"!document.getElementById('step-{nxt}').hidden")
            await lap(step)

        await until(evaluate, "document.getElementById('nav-cameras') !== null")
        await evaluate(f"""(() => {{ const t = document.getElementById('token');
            t.value = {json.dumps(cell.token)}; t.dispatchEvent(new Event('change'));
            return true; }})()""")
        # 1 cameras: the live preview shows, then the check
        await until(evaluate, "[...document.querySelectorAll('#cam-previews img')]"
                              ".some((i) => i.complete && i.naturalWidth > 0)",
                    every="true")
        await done("cameras", "calibration")
        # 2 calibration: auto-capture until SETS sets, calibrate, accept
        await capture_and_calibrate(evaluate)
        await evaluate(click("btn-calib-accept"))
        await until(evaluate, f"{text('calib-accepted')}.startsWith('ACCEPTED')")
        await done("calibration", "handeye")
        # 3 hand-eye: the learning cell's camera pose, judged and saved with the rig
        await evaluate(click("btn-he-learning"))
        await evaluate(click("btn-he-save"))
        await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('he-result')})")
        assert (await evaluate(text("he-result"))).startswith("APPLIED"), \
            await evaluate(text("he-result"))
        await done("handeye", "object")
        # 4 object: the marks, all ticked, saved; three shots taught
        await until(evaluate, "document.querySelectorAll('#obj-marks tbody tr').length >= 6",
                    every=click("btn-obj-find") + " && new Promise((r) => setTimeout(r, 2000))")
        await evaluate(click("btn-obj-save"))
        await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('obj-result')})")
        assert (await evaluate(text("obj-result"))).startswith("APPLIED"), \
            await evaluate(text("obj-result"))
        shots, tries = 0, 0
        while shots < 3:
            tries += 1
            assert tries <= 20, f"no OK test job in 20 tries: {await evaluate(text('teach-result'))}"
            await evaluate(click("btn-teach-trigger"))
            status = await until(evaluate, f"/^(test job|\\d)/.test({text('teach-result')}) "
                                           f"&& {text('teach-result')}")
            if not status.startswith("test job: OK"):
                continue  # a job the board happened to spoil: trigger again
            await evaluate(click("btn-teach-shot"))
            shots = int(await until(evaluate, f"/(\\d+) shot/.test({text('teach-result')}) && "
                                              f"/(\\d+) shot/.exec({text('teach-result')})[1]"))
        await evaluate(click("btn-teach-save"))
        await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('teach-result')})")
        assert (await evaluate(text("teach-result"))).startswith("APPLIED"), \
            await evaluate(text("teach-result"))
        await done("object", "link")
        # 5 link: the register map as the PLC reads it
        assert "CMD" in await until(evaluate, text("link-registers"))
        await done("link", "pick")
        # 6 test pick from the page
        await evaluate(click("btn-pick-trigger"))
        await until(evaluate, f"/^job \\d+ \\(web\\): OK/.test({text('pick-status')})")
        assert await until(evaluate, "document.querySelectorAll('#pick-values tr').length >= 6")
        await lap("pick")
        flow.actions = int(await evaluate("window.setupActions"))
    # the PLC's first job over Modbus/TCP
    async with Plc(cell.plc_port) as plc:
        await plc.trigger(1)
        words = await plc.result(1)
    flow.plc_status = words[Reg.STATUS]
    flow.plc_values = words
    flow.seconds["plc"] = round(time.monotonic() - t, 1)
    return flow
