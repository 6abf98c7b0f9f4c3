"""The config writer's parts (``vgripd.service.host.configtxn``, ``vgripd.configsnapshot``): the byte
snapshot the judge and the daemon both read, the judge in its child process reading that
snapshot and not the disk, the journal that ``recover`` finishes, and the writes the writer
refuses before anything is written."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
from pathlib import Path

import pytest

from tests.integration.test_web_reload import write_cell
from vgripd.config import load_config
from vgripd.configsnapshot import Snapshot
from vgripd.errors import ConfigError
from vgripd.service.host.configtxn import (
    ConfigWriter,
    candidate_path,
    create_file,
    journal_path,
    judge,
    recover,
)


def test_the_snapshot_holds_the_bytes_read_once_and_names_them(tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    snap = Snapshot.read(main)
    assert list(snap.files) == [str(main), str(cell)]
    assert snap.data(cell) == cell.read_bytes()
    cell.write_text(cell.read_text().replace("min_contrast = 25.0", "min_contrast = 30.0"))
    # the config loaded from the snapshot is the one read then, not the disk now
    assert load_config(main, snap.files).vision.min_contrast == 25.0
    assert load_config(main).vision.min_contrast == 30.0
    again = Snapshot.loads(snap.dumps())
    assert again == snap
    assert again.digest() == snap.digest()
    edited = snap.replaced({cell: snap.data(cell) + b"\n"})
    assert edited.digest() != snap.digest()
    assert snap.data(cell) != edited.data(cell)  # the original snapshot is unchanged
    with pytest.raises(ConfigError, match="not a file of the config"):
        snap.replaced({tmp_path / "other.toml": b""})
    with pytest.raises(ConfigError, match="not a config snapshot"):
        Snapshot.loads(b"{}")


def test_crlf_is_kept_in_new_bytes(tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    cell.write_bytes(cell.read_bytes().replace(b"\n", b"\r\n"))
    snap = Snapshot.read(main)
    assert snap.encoded(cell, "a = 1\nb = 2\n") == b"a = 1\r\nb = 2\r\n"
    assert snap.encoded(main, "a = 1\n") == b"a = 1\n"


@pytest.mark.timeout(240)
async def test_the_judge_reads_the_snapshot_not_the_disk(tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    good = Snapshot.read(main)
    bad = good.replaced({cell: good.data(cell).replace(b"min_contrast = 25.0",
                                                       b"min_contrast = -5.0")})
    cell.write_bytes(bad.data(cell))  # the disk holds the bad edit, the snapshot the good one
    assert await judge(good) == ""
    cell.write_bytes(good.data(cell))
    problem = await judge(bad)
    assert "vision.min_contrast" in problem, problem


def test_recover_finishes_the_journal_for_its_own_candidates_only(tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    old = cell.read_bytes()
    new = old.replace(b"min_contrast = 25.0", b"min_contrast = 20.0")
    cand, journal = candidate_path(cell), journal_path(cell)

    def plant(candidate: bytes, named: bytes) -> None:
        cand.unlink(missing_ok=True)
        create_file(cand, candidate)
        journal.write_text(json.dumps([[str(cand), str(cell),
                                        hashlib.sha256(named).hexdigest()]]))

    plant(new, new)  # killed inside the commit, before the rename
    assert recover(main) == [str(cell)]
    assert cell.read_bytes() == new
    assert not os.path.lexists(cand)
    assert not journal.exists()

    cell.write_bytes(old)
    plant(b"[vision]\ndownscale = 99\n", new)  # a candidate the journal does not name
    assert recover(main) == []
    assert cell.read_bytes() == old
    assert not os.path.lexists(cand)
    assert not journal.exists()

    create_file(cand, b"never judged\n")  # killed before the commit: no journal
    assert recover(main) == []
    assert cell.read_bytes() == old
    assert not os.path.lexists(cand)


async def test_the_writer_refuses_the_main_file_and_a_linked_include(tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    cell = tmp_path / "cell.toml"
    writer = ConfigWriter(main)
    before = main.read_bytes()
    outcome = await writer.write(lambda snap: {snap.main: b"# gone\n"}, "test")
    assert not outcome.applied
    assert "never the main file" in outcome.message
    assert main.read_bytes() == before
    real = tmp_path / "real.toml"
    cell.rename(real)
    cell.symlink_to(real)
    text = real.read_bytes()
    outcome = await writer.write(lambda snap: {cell: snap.data(cell) + b"\n"}, "test")
    assert not outcome.applied
    assert "not a regular file" in outcome.message
    assert real.read_bytes() == text
    assert cell.is_symlink()
    assert [o.applied for o in writer.audit] == [False, False]
    outcome = await writer.write(lambda snap: {cell: snap.data(cell)}, "test")
    assert outcome.applied
    assert outcome.message.startswith("no change")


async def test_a_plan_file_is_replaced_atomically_and_a_config_file_is_refused(
        tmp_path: Path) -> None:
    main = write_cell(tmp_path)
    writer = ConfigWriter(main)
    plan = tmp_path / "plan.toml"
    await writer.write_file(plan, b"[plan]\nposes = 1\n")
    assert plan.read_bytes() == b"[plan]\nposes = 1\n"
    await asyncio.to_thread(plan.chmod, 0o640)
    candidate_path(plan).symlink_to(tmp_path / "outside.txt")  # planted: removed, not followed
    await writer.write_file(plan, b"[plan]\nposes = 2\n")
    assert plan.read_bytes() == b"[plan]\nposes = 2\n"
    assert plan.stat().st_mode & 0o777 == 0o640
    assert not (tmp_path / "outside.txt").exists()
    assert not candidate_path(plan).is_symlink()
    assert not candidate_path(plan).exists()
    with pytest.raises(ConfigError, match="a file of the config"):
        await writer.write_file(tmp_path / "cell.toml", b"[plan]\n")
