"""Every config write is one judged transaction (``vgripd.service.host.configtxn``), tried the way a
plant's day goes: a reload and a save at the same moment, a camera setting saved while a tuning
save is judged, a hand-annotated CRLF include, a 0600 include, a link planted beside the
include, and ``vgripd run`` killed (SIGKILL, SIGTERM) at many points of many saves: the include
never holds an unjudged edit, a refused edit leaves it byte for byte, and the daemon always
starts again on the old or the new judged file."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.conftest import REPO
from tests.integration.test_daemon_process import _free_port
from tests.integration.test_web_reload import (
    _line,
    post,
    running_file,
    write_cell,
    write_replay_cell,
)

pytestmark = pytest.mark.slow(minutes=2)

WAIT_S = 120.0


def _leftovers(folder: Path) -> list[str]:
    """Files beside the include that a writer made (links planted by the test not counted)."""
    return sorted(p.name for p in folder.glob(".cell.toml.*") if not p.is_symlink())


async def _watch(path: Path, seen: set[bytes], stop: asyncio.Event) -> None:
    """Every distinct content of ``path`` until ``stop`` (read every few milliseconds)."""
    while not stop.is_set():
        try:
            seen.add(await asyncio.to_thread(path.read_bytes))
        except FileNotFoundError:
            seen.add(b"<missing>")
        await asyncio.sleep(0.005)  # the poll period of the watcher, not a wait for a state


async def _until_judging(s: aiohttp.ClientSession, base: str) -> None:
    """Until the daemon's config writer holds its lock (a reload or save is judged)."""
    async with asyncio.timeout(WAIT_S):
        while True:
            async with s.get(f"{base}/api/audit") as r:
                if (await r.json())["reloading"]:
                    return
            await asyncio.sleep(0.01)


async def test_a_reload_and_a_refused_save_at_once_leave_file_and_running_config_agreeing(
        tmp_path: Path) -> None:
    """POST /api/reload, and while it is judged a tuning save the check refuses (a contrast no
    mark reaches on the replay samples): the reload may apply only what it judged, the refused
    edit is applied by no one, and the include never holds it, not even while it is judged."""
    main = write_replay_cell(tmp_path, "dark")
    cell = tmp_path / "cell.toml"
    before = cell.read_bytes()
    async with running_file(main) as run, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        contrast = run.daemon.config.vision.min_contrast
        seen: set[bytes] = set()
        stop = asyncio.Event()
        watcher = asyncio.create_task(_watch(cell, seen, stop))
        reload = asyncio.create_task(post(s, f"{base}/api/reload"))
        await _until_judging(s, base)
        save = asyncio.create_task(post(s, f"{base}/api/tuning",
                                        {"vision": {"min_contrast": 250}}))
        (code_r, out_r), (code_s, out_s) = await asyncio.gather(reload, save)
        stop.set()
        await watcher
        assert code_r == 200, out_r
        assert not any("min_contrast" in line for line in out_r["diff"]), out_r
        assert code_s == 422, out_s
        assert "vision.min_contrast" in out_s["message"] or "no pose" in out_s["message"], out_s
        assert run.daemon.config.vision.min_contrast == contrast
        assert seen == {before}  # the refused edit never sat in the include
        assert cell.read_bytes() == before
        assert not _leftovers(tmp_path)


async def test_a_camera_setting_saved_while_a_tuning_save_is_judged_is_kept(
        tmp_path: Path) -> None:
    """A tuning save the check refuses is judged; meanwhile the page sets the exposure. The
    exposure is saved after the refused save (in turn), and the refusal takes nothing with it."""
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    async with running_file(main) as run, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        save = asyncio.create_task(post(s, f"{base}/api/tuning",
                                        {"vision": {"min_contrast": -5}}))
        await _until_judging(s, base)
        code_c, out_c = await post(s, f"{base}/api/cameras/0/settings", {"exposure_us": 6000})
        code_s, out_s = await save
        assert code_s == 422, out_s
        assert code_c == 200, out_c
        assert out_c["saved"]["applied"], out_c
        assert "saved to cell.toml" in out_c["saved"]["message"], out_c
        data = tomllib.loads(cell.read_text())
        assert data["camera"]["exposure_us"] == 6000.0  # kept, not put back with the old text
        assert data["vision"]["min_contrast"] == 25.0
        assert run.daemon.reloader is not None
        entries = [(e.applied, e.message) for e in run.daemon.reloader.audit]
        assert [a for a, _ in entries] == [True, False], entries  # the save first, in turn


async def test_a_crlf_0600_include_keeps_its_bytes_and_mode_and_a_planted_link_is_not_followed(
        tmp_path: Path) -> None:
    """A hand-annotated include with CRLF line ends, mode 0600, and links planted where writers
    put their temporary files: a refused save leaves it byte for byte; an accepted one keeps
    CRLF and 0600, its backup is a byte copy with the same mode, and no link is written
    through."""
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    text = "# cell 7, tuned by hand on the night shift\n" + cell.read_text()
    original = text.replace("\n", "\r\n").encode()
    cell.write_bytes(original)
    cell.chmod(0o600)
    outside = tmp_path / "elsewhere.txt"
    outside.write_bytes(b"not the config\n")
    for name in (".cell.toml.tmp", ".cell.toml.candidate"):
        (tmp_path / name).symlink_to(outside)
    async with running_file(main) as run, aiohttp.ClientSession() as s:
        assert run.daemon.status_server is not None
        base = f"http://127.0.0.1:{run.daemon.status_server.port}"
        code, out = await post(s, f"{base}/api/tuning", {"vision": {"min_contrast": -5}})
        assert code == 422, out
        assert cell.read_bytes() == original
        assert cell.stat().st_mode & 0o777 == 0o600
        assert not cell.is_symlink()
        assert outside.read_bytes() == b"not the config\n"

        code, out = await post(s, f"{base}/api/tuning", {"vision": {"min_contrast": 20}})
        assert code == 200, out
        assert out["written"] == ["cell.toml (backup cell.toml.1)"], out
        assert run.daemon.config.vision.min_contrast == 20.0
        new = cell.read_bytes()
        assert tomllib.loads(new.decode())["vision"]["min_contrast"] == 20.0
        assert new.count(b"\n") == new.count(b"\r\n")  # CRLF kept
        assert not cell.is_symlink()
        assert cell.stat().st_mode & 0o777 == 0o600
        backup = tmp_path / "cell.toml.1"
        assert backup.read_bytes() == original  # comments and CRLF: a byte copy
        assert backup.stat().st_mode & 0o777 == 0o600
        assert outside.read_bytes() == b"not the config\n"
        assert (tmp_path / ".cell.toml.tmp").is_symlink()  # not ours: left alone
        assert _leftovers(tmp_path) == []  # the planted candidate link: gone, not followed


def _process_cell(folder: Path) -> tuple[Path, int]:
    """``write_cell``'s config with the web view on a port known before the start."""
    port = _free_port()
    main = write_cell(folder, link_port=_free_port())
    main.write_text(main.read_text().replace("[status]\nport = 0", f"[status]\nport = {port}"))
    return main, port


async def _start(main: Path, seen: list[str]) -> asyncio.subprocess.Process:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(main), cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE)
    assert proc.stderr is not None
    try:
        await _line(proc.stderr, "ready:", seen)
    except BaseException:
        proc.kill()
        await proc.wait()
        raise
    return proc


async def _stop(proc: asyncio.subprocess.Process, how: signal.Signals) -> int:
    proc.send_signal(how)
    async with asyncio.timeout(WAIT_S):
        return await proc.wait()


#: Edits the check refuses, killed early in their judge or later.
REFUSED: list[dict[str, Any]] = [{"vision": {"downscale": 99}}, {"vision": {"min_contrast": -5}}]
#: Kill points, as fractions of an accepted save's own duration: a refused edit early (the
#: child starting, reading, judging), an accepted one late (judged, applied, committed, and
#: just after its answer).
REFUSED_AT = [0.05, 0.3, 0.6]
ACCEPTED_AT = [0.5, 0.75, 0.9, 1.0, 1.1, 1.3]


def _expected(old: bytes, edit: dict[str, Any]) -> dict[str, Any]:
    data = tomllib.loads(old.decode())
    data["vision"].update(edit.get("vision", {}))
    if "polarity" in edit:
        for feature in data["object"]["features"]:
            feature["polarity"] = edit["polarity"]
    return data


@pytest.mark.timeout(900)
async def test_killed_at_many_points_of_many_saves_the_daemon_starts_on_a_judged_file(
        tmp_path: Path) -> None:
    """``vgripd run`` with the web view; a save posted, the daemon killed (SIGKILL or SIGTERM)
    at a different point of each save: while it is judged, once it is judged, after its answer.
    After each kill the include holds its old bytes or (an accepted edit) exactly the new
    judged data, never a refused edit, and the new data once the save answered; the daemon
    starts again on it every time, and ``vgripd check`` accepts the last file."""
    main, port = _process_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    base = f"http://127.0.0.1:{port}"
    seen: list[str] = []
    kills: list[tuple[signal.Signals, float, dict[str, Any], bool]] = []
    for i in range(len(ACCEPTED_AT)):  # interleaved: refused, accepted, refused, ...
        how = (signal.SIGKILL, signal.SIGTERM)[i % 2]
        kills.append((how, REFUSED_AT[i % len(REFUSED_AT)], REFUSED[i % len(REFUSED)], False))
        # each accepted edit a value of its own: it always changes the file
        kills.append(((signal.SIGTERM, signal.SIGKILL)[i % 2], ACCEPTED_AT[i],
                      {"vision": {"min_contrast": 40.0 + i}}, True))
    async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=WAIT_S)) as s:
        proc = await _start(main, seen)
        try:
            # A save to its end first: how long the first save after a start takes here now
            # (each kill below is followed by a start); updated by every accepted save that
            # answers before its kill.
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            code, out = await post(s, f"{base}/api/tuning", {"vision": {"min_contrast": 24}})
            duration = loop.time() - t0
            assert code == 200, out
            for i, (how, fraction, edit, good) in enumerate(kills):
                old = cell.read_bytes()
                t0 = loop.time()
                task = asyncio.create_task(post(s, f"{base}/api/tuning", edit))
                # not a wait for a state: the kill lands where it lands, each time elsewhere
                done, _ = await asyncio.wait({task}, timeout=duration * fraction)
                if done and good:  # answered before the kill: the next point from this one
                    duration = loop.time() - t0
                rc = await _stop(proc, how)
                try:
                    answer: Any = await task
                except (aiohttp.ClientError, TimeoutError) as err:
                    answer = repr(err)  # killed before it answered
                now = cell.read_bytes()
                state = (f"kill {i} ({how.name} at {fraction} of {duration:.1f} s, edit {edit}, "
                         f"answer {answer}, rc {rc})")
                print(state, "-> new" if now != old else "-> old")  # the points, for the log
                if now != old:
                    assert good, f"{state}: a refused edit reached the include"
                    assert tomllib.loads(now.decode()) == _expected(old, edit), state
                elif isinstance(answer, tuple) and answer[0] == 200:
                    raise AssertionError(f"{state}: answered saved, but the include is old")
                if how == signal.SIGTERM:
                    assert rc == 0, f"{state}: {''.join(seen[-20:])}"
                proc = await _start(main, seen)  # it starts again, on the file as it is
                left = _leftovers(tmp_path)
                assert not left, f"{state}: {left} left beside the include after the start"
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    assert proc.returncode is not None
    check = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "check", "--running", "-c", str(main), cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT)
    out_check, _ = await check.communicate()
    assert check.returncode == 0, out_check.decode()
