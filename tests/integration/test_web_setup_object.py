"""The setup page's object step with a taught template, clicked in headless Chromium against
``vgripd demo --setup`` on the learning cell, calibrated beforehand with its true values
(``seed_calibrated``: the capture is the acceptance test's, test_web_setup.py). A region dragged
round one plate mark is refused (the plate has six alike); a region round three marks is taught,
found in both images, offered as a mark beside the circles, saved with them as a template
feature (its patch a file in the state folder), found again by the next "Find marks", and taught
and picked as the circles are."""

from __future__ import annotations

import tomllib
from pathlib import Path

import cv2
import pytest

from tests.integration.setup_browser import (
    Evaluate,
    click,
    demo_setup,
    drag,
    open_page,
    seed_calibrated,
    text,
    until,
)
from tests.integration.test_web import _chromium

pytestmark = pytest.mark.slow(minutes=3)

#: Regions of the learning cell's left image (its plate marks lie at fixed pixels): one mark
#: alone, and three marks (an uneven triangle, there once).
ONE_MARK = (580, 371, 40, 40)
THREE_MARKS = (455, 365, 170, 210)

#: The page's next answer to "Find marks" held back 4 s after it arrived (``window.lateFind``
#: says when it is handed on).
SLOW_NEXT_FIND = """(() => {
  const original = window.fetch;
  window.lateFind = "none";
  window.fetch = async (url, options) => {
    const answer = await original(url, options);
    if (String(url).includes("/object/find")) {
      window.fetch = original;
      window.lateFind = "held";
      await new Promise((r) => setTimeout(r, 4000));
      window.lateFind = "answered";
    }
    return answer;
  };
  return true;
})()"""


async def _teach(evaluate: Evaluate, box: tuple[int, int, int, int]) -> str:
    """The region dragged on the left image (the page fills its box field), then taught."""
    await evaluate("document.getElementById('obj-template-result').textContent = '', true")
    await evaluate(drag("#obj-left", box))
    drawn = await evaluate("document.getElementById('obj-box').value")
    # a CSS pixel of the scaled picture is a few camera pixels
    assert max(abs(a - b) for a, b in zip(map(int, drawn.split()), box, strict=True)) <= 5, drawn
    await evaluate(click("btn-obj-template"))
    return str(await until(evaluate, f"/^(TAUGHT|REFUSED)/.test("
                                     f"{text('obj-template-result')}) && "
                                     f"{text('obj-template-result')}", 120.0))


@pytest.mark.timeout(900)
async def test_a_template_is_taught_from_a_dragged_region_and_picked(tmp_path: Path) -> None:
    folder = tmp_path / "cell"
    seed_calibrated(folder)
    async with demo_setup(folder) as cell, _chromium(tmp_path, cell.url) as evaluate:
        await open_page(evaluate, cell.token)
        await until(evaluate, "!document.getElementById('step-object').hidden", 60.0)
        # clicked twice, "Find marks" sends one request: the second click finds it greyed (a
        # pile of finds behind the daemon's lock once held the picture's request a minute)
        assert await evaluate("(() => { const b = document.getElementById('btn-obj-find'), "
                              "n = window.setupActions; b.click(); b.click(); "
                              "return [window.setupActions - n, b.disabled]; })()") == [1, True]
        await until(evaluate, "document.querySelectorAll('#obj-marks tbody tr').length >= 6",
                    120.0, every=click("btn-obj-find")
                    + " && new Promise((r) => setTimeout(r, 2000))")
        await until(evaluate, "document.getElementById('obj-left')?.complete", 60.0)

        refused = await _teach(evaluate, ONE_MARK)
        assert refused.startswith("REFUSED (422)"), refused
        assert "two places in the left image" in refused, refused
        assert await evaluate("document.querySelectorAll('#obj-marks tbody tr').length") == 6

        taught = await _teach(evaluate, THREE_MARKS)
        assert taught.startswith("TAUGHT: mark 7, template template"), taught
        rows = await evaluate("[...document.querySelectorAll('#obj-marks tbody tr')]"
                              ".map((r) => r.cells[2].textContent).join('|')")
        assert rows.count("circle") == 6, rows
        assert "template template" in rows, rows

        # a "Find marks" whose answer comes after "Save" was clicked (a busy cell) does not
        # overwrite the save's outcome: the page drops an answer a later action overtook
        await evaluate(SLOW_NEXT_FIND)
        await evaluate(click("btn-obj-find"))
        await evaluate(click("btn-obj-save"))
        saved = await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('obj-result')}) && "
                                      f"{text('obj-result')}", 300.0)
        assert saved.startswith("APPLIED"), saved
        await until(evaluate, "window.lateFind === 'answered'", 120.0)
        await evaluate("new Promise((r) => setTimeout(r, 1000))")  # its handler's turn
        assert (await evaluate(text("obj-result"))).startswith("APPLIED"), \
            await evaluate(text("obj-result"))
        features = tomllib.loads((folder / "cell.toml").read_text())["object"]["features"]
        template = [f for f in features if f["kind"] == "template"]
        assert len(features) == 7, features
        assert len(template) == 1, features
        patch = cv2.imread(template[0]["template"], cv2.IMREAD_GRAYSCALE)
        assert patch is not None
        assert abs(patch.shape[0] - THREE_MARKS[3]) <= 5
        assert abs(patch.shape[1] - THREE_MARKS[2]) <= 5
        assert Path(template[0]["template"]).parent == folder / "setup" / "templates"
        x, y, z = template[0]["xyz_mm"]
        assert 540 < x < 580, template  # on the plate, 10 mm above the table
        assert 95 < y < 135, template
        assert 0 < z < 20, template

        # found again in a new grab, then taught and picked like the circles
        await evaluate(click("btn-obj-find"))
        await until(evaluate, f"{text('obj-result')}.includes('seen by both cameras')", 120.0)
        rows = await evaluate("[...document.querySelectorAll('#obj-marks tbody tr')]"
                              ".map((r) => r.cells[2].textContent).join('|')")
        assert "template template" in rows, (rows, await evaluate(text("obj-result")))
        shots, tries = 0, 0
        while shots < 3:
            tries += 1
            assert tries <= 20, f"no OK test job in 20 tries: {await evaluate(text('teach-result'))}"
            await evaluate(click("btn-teach-trigger"))
            status = await until(evaluate, f"/^(test job|\\d)/.test({text('teach-result')}) "
                                           f"&& {text('teach-result')}", 120.0)
            if not status.startswith("test job: OK"):
                continue  # a job the moving board happened to spoil: trigger again
            await evaluate(click("btn-teach-shot"))
            shots = int(await until(evaluate, f"/(\\d+) shot/.test({text('teach-result')}) && "
                                              f"/(\\d+) shot/.exec({text('teach-result')})[1]",
                                    60.0))
        await evaluate(click("btn-teach-save"))
        result = await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('teach-result')}) "
                                       f"&& {text('teach-result')}", 300.0)
        assert result.startswith("APPLIED"), result
    reference = tomllib.loads((folder / "reference.toml").read_text())["reference"]
    assert template[0]["name"] in reference["points_mm"], reference
