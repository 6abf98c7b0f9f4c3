"""The generated robot programs (``vgripd robot-program``, ``robots/<brand>/``).

Robot-side syntax cannot run here, so each program is checked twice:

- its message exchange: the program's Python twin (``vgripd.sim.robot_socket_client``), set up
  from the very text the CLI wrote, sends the bytes the program sends and reads the answers as
  it does, against the real daemon (in-process with the synthetic camera, and once as a
  ``vgripd run`` process); the pose it decodes must be what the daemon published. Its timeouts,
  retries and BUSY handling are exercised against a silent peer and a busy link;
- its text: every word outside comments and strings is a name the program defines (``vg...``)
  or is listed, with the manual it comes from, in the brand's page docs/robots/<brand>.md,
  and every listed word is used.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO
from tests.integration.test_daemon import running
from vgripd.__main__ import main
from vgripd.cli.robot_program import ProgramRefused, render
from vgripd.config import config_from_dict
from vgripd.peer.socket_frames import BRANDS, Request, SocketCommand
from vgripd.service.links.protocol import LinkState
from vgripd.sim.robot_socket_client import ProgramSettings, ProgramStopped, ProgramTwin
from vgripd.types import Status

pytestmark = pytest.mark.timeout(300)
WAIT_S = 30.0
START_S = 90.0  # a daemon started as a process until its first answer (job budget 60 s)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def cell(brand: str, port: int, worker: bool = False, **link: Any) -> dict[str, Any]:
    """A synthetic cell whose robot_socket link suits ``brand``'s program."""
    b = BRANDS[brand]
    return {
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "output": {"vendor": b.convention},
        "links": [{"type": "robot_socket", "host": "127.0.0.1", "port": port, "mode": b.mode,
                   "value_format": b.value_format,
                   "scale": 1000000 if brand == "ur" else 10000, **link}],
        "status": {"port": 0},
        "daemon": {"worker": worker, "job_timeout_s": 10.0},
    }


def program(brand: str, data: dict[str, Any]) -> dict[str, str]:
    return render(BRANDS[brand], config_from_dict(data), source="cell.toml")


# --- the CLI ------------------------------------------------------------------------------


def toml(data: dict[str, Any]) -> str:
    """Just enough TOML for ``cell()``'s dictionaries."""
    def value(v: Any) -> str:
        return json.dumps(v) if not isinstance(v, bool) else str(v).lower()
    out = []
    for key, section in data.items():
        if key == "links":
            for link in section:
                out.append("[[links]]")
                out += [f"{k} = {value(v)}" for k, v in link.items()]
        else:
            out.append(f"[{key}]")
            out += [f"{k} = {value(v)}" for k, v in section.items()]
    return "\n".join(out) + "\n"


def test_cli_writes_each_brand_filled_in(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                         ) -> None:
    for brand, b in BRANDS.items():
        cfg = tmp_path / f"{brand}.toml"
        cfg.write_text(toml(cell(brand, 50100)))
        out = tmp_path / brand
        assert main(["robot-program", "--brand", brand, "-c", str(cfg), "-o", str(out)]) == 0
        assert sorted(p.name for p in out.iterdir()) == sorted(b.files)
        text = "\n".join((out / name).read_text() for name in b.files)
        assert "@@" not in text
        assert "50100" in text
        if b.mode == "server" and brand != "staubli":
            assert "127.0.0.1" in text  # the address the program dials
        settings = ProgramSettings.parse(brand, {n: (out / n).read_text() for n in b.files})
        assert settings.timeout_s == 12.0  # job_timeout_s + 2
        assert settings.scale == (0 if b.value_format == "float32" else
                                  1000000 if brand == "ur" else 10000)
        assert settings.words["LOCATE"] == 0x56470101
        assert settings.words["NEXT"] == 0x56470103
        assert settings.words["CAPTURE_AT"] == 0x56470104  # the walk routine's request
        assert settings.at_bytes == 44
        assert settings.walk_speed_mm_s == 50.0  # [calibration_walk] defaults
        assert settings.walk_settle_s == 1.0
        assert settings.attempts == 3
    assert "docs/robots/ur.md" in capsys.readouterr().out


@pytest.mark.parametrize(("brand", "change", "message"), [
    ("fanuc", {"output": {"vendor": "kuka"}},
     '--brand fanuc reads its pose in the "fanuc" convention (X, Y, Z, W, P, R: W, P, R deg '
     'about fixed X, Y, Z: Rz(R) Ry(P) Rx(W)), but the config has output.vendor = "kuka"'),
    ("abb", {"value_format": "int32"},
     '--brand abb unpacks float32 values, but links[0].value_format = "int32"'),
    ("yaskawa", {"mode": "server"}, '--brand yaskawa needs links[0].mode = "client"'),
    ("yaskawa", {"scale": 1000}, "--brand yaskawa needs links[0].scale >= 10000"),
    ("kuka", {"host": "0.0.0.0"}, 'links[0].host = "0.0.0.0" listens on every address'),
    ("kuka", {"type": "modbus_server"}, 'no [[links]] entry with type = "robot_socket"'),
])
def test_cli_refuses_what_the_program_cannot_work_with(brand: str, change: dict[str, Any],
                                                       message: str) -> None:
    data = cell(brand, 50100)
    if "output" in change:
        data["output"] = change["output"]
    else:
        data["links"][0].update(change)
        if data["links"][0]["type"] != "robot_socket":
            data["links"][0] = {"type": "modbus_server", "port": 1502}
    with pytest.raises(ProgramRefused) as err:
        program(brand, data)
    assert message in str(err.value)


def test_cli_refusal_exits_2_naming_both_fields(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "cell.toml"
    cfg.write_text(toml({**cell("kuka", 50100), "output": {"vendor": "abb"}}))
    rc = main(["robot-program", "--brand", "kuka", "-c", str(cfg), "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "--brand kuka" in err
    assert 'output.vendor = "abb"' in err
    assert not (tmp_path / "o").exists()


# --- the instructions each program uses ---------------------------------------------------

CASE_SENSITIVE = {".pgx", ".c", ".script"}
COMMENTS = {
    ".src": [r";[^\n]*"], ".dat": [r";[^\n]*"], ".xml": [r"<!--.*?-->"],
    ".mod": [r"![^\n]*"], ".kl": [r"--[^\n]*"], ".ls": [r"![^;\n]*"],
    ".pgx": [r"//[^\n]*"], ".c": [r"/\*.*?\*/", r"//[^\n]*"], ".jbi": [r"^'[^\n]*"],
    ".script": [r"#[^\n]*"],
}
STRINGS = [r'"[^"\n]*"', r"'[^'\n]*'"]
SIGILS = {".src": "[&$]?", ".dat": "[&$]?", ".kl": "%?"}
OWN = re.compile(r"^(vg|VG_|l_vg|x_vg)", re.IGNORECASE)
INFORM_VARIABLE = re.compile(r"^[BIDRP]\d{3}$", re.IGNORECASE)


def listed(brand: str) -> set[str]:
    """The words of the brand page's instruction table (first column), each with a manual."""
    text = (REPO / "docs" / "robots" / f"{brand}.md").read_text()
    table = text.split("## Instructions", 1)[1]
    words: set[str] = set()
    for row in re.findall(r"^\| (`.+?) \| (.+?) \|$", table, re.MULTILINE):
        assert row[1].strip(), f"{brand}: a row without its manual"
        words |= set(re.findall(r"`([^`]+)`", row[0]))
    return words


def words_of(name: str, text: str) -> set[str]:
    """The words of a program file outside comments and strings (code only for VAL3)."""
    ext = Path(name).suffix.lower()
    if ext in (".pjx", ".dtx"):
        return set()  # VAL3 project and data declarations: no instructions
    if ext == ".pgx":
        text = "\n".join(re.findall(r"<!\[CDATA\[(.*?)\]\]>", text, re.DOTALL))
    if ext == ".jbi":
        text = re.sub(r"^(///COMM)[^\n]*", r"\1", text, flags=re.MULTILINE)
    for pattern in COMMENTS.get(ext, []) + STRINGS:
        text = re.sub(pattern, " ", text, flags=re.DOTALL | re.MULTILINE)
    return set(re.findall(SIGILS.get(ext, "") + r"[A-Za-z_][A-Za-z0-9_]*", text))


@pytest.mark.parametrize("brand", sorted(BRANDS))
def test_programs_use_only_the_instructions_their_page_lists(brand: str) -> None:
    texts = program(brand, cell(brand, 50100))
    allowed = listed(brand)
    used: set[str] = set()
    unlisted = []
    for name, text in texts.items():
        sensitive = Path(name).suffix.lower() in CASE_SENSITIVE
        known = allowed if sensitive else {w.upper() for w in allowed}
        for word in sorted(words_of(name, text)):
            if OWN.match(word) or (name.upper().endswith(".JBI") and INFORM_VARIABLE.match(word)):
                continue
            key = word if sensitive else word.upper()
            used.add(key)
            if key not in known:
                unlisted.append(f"{name}: {word}")
    assert not unlisted, f"not listed in docs/robots/{brand}.md: {unlisted}"
    never = sorted(w for w in allowed if w not in used and w.upper() not in used)
    assert not never, f"docs/robots/{brand}.md lists words no program uses: {never}"


# --- the message exchange against the real daemon -----------------------------------------


@contextlib.asynccontextmanager
async def twin_for(brand: str, port: int, data: dict[str, Any],
                   **changes: Any) -> Any:
    settings = ProgramSettings.parse(brand, program(brand, data))
    if changes:
        settings = dataclasses.replace(settings, **changes)
    async with ProgramTwin(settings, "127.0.0.1", port) as twin:
        yield twin


@pytest.mark.parametrize("brand", sorted(BRANDS))
async def test_each_program_locates_against_the_daemon(brand: str) -> None:
    port = free_port()
    data = cell(brand, port)
    data["recipes"] = {"3": {"name": "tighter", "limits": {"max_rotation_deg": 9.0}}}
    async with twin_for(brand, port, data) as twin, running(config_from_dict(data)) as run:
        link = next(iter(run.daemon.rooms.links.links.values()))
        await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
        for n, recipe in ((1, 0), (2, 3)):
            outcome = await twin.locate(recipe)
            _, record = await run.job_done(n)
            assert record.recipe == recipe  # the program's recipe word selects the recipe
            assert outcome.status == Status.OK, outcome
            assert outcome.captured
            assert outcome.job_id == record.job_id
            assert outcome.request_ids == [n]
            assert twin.sent[-1] == Request(SocketCommand.LOCATE, n, recipe).encode()
            target = record.result.target
            assert target is not None
            assert target.vendor == BRANDS[brand].convention
            scale = twin.s.scale
            for got, want in zip(outcome.values, target.values, strict=True):
                if scale:  # int32: the program reads the published value to its scale
                    assert abs(got - want) <= 0.5 / scale + 1e-12
                else:
                    assert got == pytest.approx(want, rel=1e-6, abs=1e-9)
        assert run.daemon.rooms.jobs.counters == {"OK": 2}
        expected_connects = 2 if BRANDS[brand].connection == "per_request" else 1
        assert twin.connects == expected_connects


async def test_a_program_waits_out_busy_and_then_gets_its_pose() -> None:
    port = free_port()
    data = cell("kuka", port)
    async with twin_for("kuka", port, data) as first, \
            twin_for("kuka", port, data, busy_wait_s=0.05) as second, \
            running(config_from_dict(data)) as run:
        job = asyncio.create_task(first.locate())
        await run.busy()  # the first robot's job runs: the link refuses the second BUSY
        outcome = await second.locate()
        assert (await job).status == Status.OK
        assert outcome.status == Status.OK
        assert len(outcome.request_ids) >= 2  # asked again with a new id after BUSY
        assert outcome.request_ids == list(range(1, len(outcome.request_ids) + 1))
        refusals = run.daemon.snapshot()["links"][0]["refusals"]
        assert refusals["BUSY"] == len(outcome.request_ids) - 1


class SilentVgripd:
    """A peer that takes the connection and never answers (or answers ``garbage``)."""

    def __init__(self, garbage: bytes = b"") -> None:
        self.garbage = garbage
        self.requests = 0
        self.writers: list[asyncio.StreamWriter] = []

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                await reader.readexactly(16)
                self.requests += 1
                if self.garbage:
                    writer.write(self.garbage)

    def close(self) -> None:
        for w in self.writers:
            w.close()


@pytest.mark.parametrize(("brand", "garbage"), [
    *((b, b"") for b in sorted(BRANDS)), ("kuka", b"HTTP/1.0 400 Bad\r\n" * 4)])
async def test_a_silent_or_garbled_peer_makes_each_program_give_up(brand: str,
                                                                   garbage: bytes) -> None:
    b = BRANDS[brand]
    peer = SilentVgripd(garbage[:64])
    port = free_port()
    async with twin_for(brand, port, cell(brand, port), timeout_s=0.2,
                        connect_timeout_s=1.0) as twin:
        if b.connection == "robot_server":  # vgripd's role: dial the robot, then stay silent
            reader, writer = await asyncio.open_connection("127.0.0.1", twin.port)
            serving = asyncio.create_task(peer.serve(reader, writer))
            server = None
        else:
            server = await asyncio.start_server(peer.serve, "127.0.0.1", port)
        try:
            if brand in ("staubli", "yaskawa"):  # these return -1 to their caller
                outcome = await twin.locate()
                assert outcome.status == -1
                assert len(outcome.request_ids) == twin.s.attempts
            else:
                with pytest.raises(ProgramStopped, match="no answer to 3 requests"):
                    await twin.locate()
        finally:
            peer.close()
            if server is not None:
                server.close()
                await server.wait_closed()
            else:
                serving.cancel()
    assert twin.vg_id == twin.s.attempts  # a new id for every attempt
    if b.connection != "robot_server":
        assert peer.requests == twin.s.attempts
        assert twin.connects == twin.s.attempts  # dropped and dialled again after each


# --- `vgripd run` as a process ------------------------------------------------------------


async def test_vgripd_run_with_a_robot_socket_link_serves_the_kuka_program(
        tmp_path: Path) -> None:
    port, status_port = free_port(), free_port()
    data = cell("kuka", port, worker=True)
    data["status"] = {"port": status_port}
    data["daemon"]["job_timeout_s"] = 60.0  # the first job waits for the worker's start
    cfg = tmp_path / "cell.toml"
    cfg.write_text(toml(data))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    made = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "robot-program", "--brand", "kuka", "-c", str(cfg),
        "-o", str(tmp_path / "kuka"), cwd=REPO, env=env, stderr=subprocess.PIPE)
    async with asyncio.timeout(WAIT_S):
        _, made_err = await made.communicate()
    assert made.returncode == 0, made_err.decode()
    texts = {p.name: p.read_text() for p in (tmp_path / "kuka").iterdir()}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        async with ProgramTwin(ProgramSettings.parse("kuka", texts), "127.0.0.1", port) as twin:
            outcomes = [await locate_when_up(twin) for _ in range(2)]
        status = await asyncio.to_thread(fetch_status, status_port)
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(WAIT_S):
            _, err = await proc.communicate()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0, err.decode()
    assert [o.status for o in outcomes] == [Status.OK, Status.OK]
    assert all(len(o.values) == 6 for o in outcomes)
    assert status["counters"] == {"OK": 2}
    assert status["last_job"]["id"] == outcomes[1].job_id
    link = status["links"][0]
    assert (link["name"], link["state"]) == ("robot_socket", "up")
    assert "Traceback" not in err.decode()


async def locate_when_up(twin: ProgramTwin) -> Any:
    """The program's locate, retried until the service listens (it starts in the background),
    within the first job's own budget (the daemon's start and the worker's, on a busy machine)."""
    async with asyncio.timeout(START_S):
        while True:
            with contextlib.suppress(ProgramStopped):
                return await twin.locate()
            await asyncio.sleep(0.2)


def fetch_status(port: int) -> dict[str, Any]:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(b"GET /status HTTP/1.0\r\n\r\n")
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    result: dict[str, Any] = json.loads(data.partition(b"\r\n\r\n")[2])
    return result
