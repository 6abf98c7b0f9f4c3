"""robots/urscript/vgripd.script, read as text (it runs only on a controller): its conveyor
registers and commands are the link's (``URRegisterMap``), and every word it uses is listed
with its manual in docs/ur_rtde.md, "Instructions this program uses"."""

from __future__ import annotations

import re

from tests.conftest import REPO
from vgripd.peer.jobcore import Command
from vgripd.peer.ur_registers import URRegisterMap

SCRIPT = REPO / "robots" / "urscript" / "vgripd.script"
OWN = re.compile(r"^(vgripd_|VGRIPD_)")


def code() -> str:
    """The script without comments and strings."""
    text = re.sub(r"#[^\n]*", " ", SCRIPT.read_text())
    return re.sub(r'"[^"\n]*"', " ", text)


def function(name: str) -> str:
    text = SCRIPT.read_text()
    start = text.index(f"def {name}(")
    return text[start:text.index("\nend\n", start)]


def test_the_conveyor_registers_and_commands_are_the_links() -> None:
    regs, upper = URRegisterMap(conveyor=True), URRegisterMap(upper=True, conveyor=True)
    c = code()
    assert f"global VGRIPD_BELT_FIRST = {regs.belt_first}" in c
    assert (regs.belt_first, upper.belt_first) == (24, 30)
    assert upper.latch - regs.latch == 24  # VGRIPD_OFFSET applies to the latch
    request = function("vgripd_request")
    assert f"write_output_integer_register({regs.latch} + o, vgripd_predict_count)" in request
    assert f"if command == {int(Command.PREDICT)}:" in request
    # the block's sequence, RESULT_COUNT and QUEUED, at the places belt_values puts them
    assert "vgripd_wait_int(VGRIPD_BELT_FIRST, seq, timeout_s)" in request
    names = regs.belt_names
    assert names[1] == f"input_int_register_{regs.belt_first + 1}"  # RESULT_COUNT
    assert "vgripd_belt_count = read_input_integer_register(VGRIPD_BELT_FIRST + 1)" in request
    assert names[3] == f"input_int_register_{regs.belt_first + 3}"  # QUEUED
    assert "vgripd_belt_queued = read_input_integer_register(VGRIPD_BELT_FIRST + 3)" in request
    # the latch goes before the trigger (same controller step: no sync between them)
    latch = request.index(f"write_output_integer_register({regs.latch} + o")
    trigger = request.index(f"write_output_integer_register({regs.seq} + o, seq)")
    assert latch < trigger
    assert "sync()" not in request[latch:trigger]
    track = function("vgripd_belt_track")
    assert f"vgripd_locate({int(Command.NEXT)}, timeout_s)" in track
    assert track.index("encoder_get_tick_count") < track.index("track_conveyor_linear")
    intercept = function("vgripd_belt_intercept")
    assert intercept.index(f"vgripd_locate({int(Command.NEXT)}") < intercept.index(
        f"vgripd_locate({int(Command.PREDICT)}")


def defined(text: str) -> set[str]:
    """Names the script defines: functions, globals, locals and parameters."""
    names = set(re.findall(r"\b(?:def|global|local)\s+([A-Za-z_]\w*)", text))
    for params in re.findall(r"\bdef\s+\w+\(([^)]*)\)", text):
        names |= {p.strip() for p in params.split(",") if p.strip()}
    return names


def listed() -> set[str]:
    text = (REPO / "docs" / "ur_rtde.md").read_text()
    table = text.split("## Instructions this program uses", 1)[1]
    words: set[str] = set()
    for first, manual in re.findall(r"^\| (`.+?) \| (.+?) \|$", table, re.MULTILINE):
        assert manual.strip(), f"a row without its manual: {first}"
        words |= set(re.findall(r"`([^`]+)`", first))
    return words


def test_every_word_of_the_script_is_listed_with_its_manual() -> None:
    c = code()
    words = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", c))
    own = defined(c)
    used = {w for w in words if not OWN.match(w) and w not in own}
    allowed = listed()
    assert not used - allowed, f"not listed in docs/ur_rtde.md: {sorted(used - allowed)}"
    assert not allowed - used, f"listed but never used: {sorted(allowed - used)}"
