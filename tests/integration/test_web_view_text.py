"""What the web view says, read as an integrator reads it: the register map's words are
numbers (STATE 3 = DONE, not the word "DONE"), REJECT_CODE 0 means no refusal (not IDLE), one
recipe is not listed as a choice among one, and the cell drawing's camera labels do not cover
each other (four cameras in two rigs, a few pixels apart from above)."""

from __future__ import annotations

from pathlib import Path

import aiohttp

from tests.integration.test_daemon import Plc, running
from tests.integration.test_daemon_multicam import cell
from tests.integration.test_web import _base, _chromium, _until
from vgripd.peer.registers import Reg
from vgripd.types import Status

LABELS = """(() => {
  const out = {};
  for (const id of ['cell-top', 'cell-side']) {
    const t = [...document.querySelectorAll(`#${id} text.cell-label`)];
    if (t.length !== 4) return null;
    out[id] = t.map((e) => { const b = e.getBBox(); return [e.textContent, b.x, b.y, b.width, b.height]; });
  }
  return out;
})()"""


def _overlapping(boxes: list[list]) -> list[tuple[str, str]]:
    out = []
    for i, (na, xa, ya, wa, ha) in enumerate(boxes):
        for nb, xb, yb, wb, hb in boxes[i + 1:]:
            if xa < xb + wb and xb < xa + wa and ya < yb + hb and yb < ya + ha:
                out.append((na, nb))
    return out


async def test_registers_recipe_header_and_camera_labels_read_plainly(tmp_path: Path) -> None:
    config = cell(tmp_path)
    async with running(config) as run, Plc(run.port()) as plc, aiohttp.ClientSession() as http:
        base = _base(run)
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        async with http.get(f"{base}/api/registers") as resp:
            rows = {r["name"]: r for r in (await resp.json())[0]["rows"]}
        assert rows["STATE"]["words"] == [3]
        assert rows["STATE"]["value"] == 3
        assert rows["STATE"]["meaning"] == "DONE"
        assert rows["REJECT_CODE"]["words"] == [0]
        assert rows["REJECT_CODE"]["meaning"] == "none"
        assert rows["STATUS"]["meaning"] == "OK"
        async with _chromium(tmp_path, base + "/") as evaluate:
            header = await _until(evaluate, "(document.getElementById('recipe') || {}).textContent")
            assert header == "recipe 0 default"
            labels = await _until(evaluate, LABELS)
            for view, boxes in labels.items():
                assert sorted(b[0] for b in boxes) == sorted(
                    f"{c.name} ({r.name})" for r in config.calibration.rigs
                    for c in config.calibration.cameras if c.name in r.cameras), view
                assert _overlapping(boxes) == [], (view, boxes)
