"""The docs say what the code does: each statement below is read from the doc and compared with
the constant or the behaviour of the code it describes, so a change of either side that leaves
the other behind fails here (README's register table, the S7 block size, recording folder
names, OPC UA value names, the S7 refusal wording and DB comment, the asyncua tool lines)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from tests.conftest import REPO
from vgripd.cli.s7_udt import db_source
from vgripd.geometry.vendors import CONVENTIONS
from vgripd.peer.jobcore import Command, HandshakeState
from vgripd.peer.registers import COMMAND_AREA, MAP_SIZE, MAP_VERSIONS, Reg
from vgripd.service.worker.recorder import Recorder
from vgripd.types import ImagePair, JobResult, Status


def doc(name: str) -> str:
    return (REPO / name).read_text(encoding="utf-8")


def section(text: str, heading: str) -> str:
    """The text under a markdown heading, up to the next heading of any level."""
    start = text.index(heading)
    nxt = re.search(r"^#+ ", text[start + len(heading):], re.M)
    return text[start:start + len(heading) + (nxt.start() if nxt else len(text))]


def register_rows(text: str, last_address: int | None = None, scale: int = 1
                  ) -> dict[str, tuple[int, int, str, str]]:
    """``name -> (first address, last address, R/W or writer, meaning)`` of a markdown register
    table whose first columns are ``addr | name``, then R/W (or S7's type and writer). Rows may
    group items: ``4, 5-6, 7-8 | CHECK_*`` or ``15, 16 | REJECT_SEQ, REJECT_CODE``; a lone start
    address (``5``) spans up to the next item's start (docs/registers.md gives starts only), the
    last one up to ``last_address`` (the end of the map as the doc states it). ``scale``: units
    of the address column per register (2 for S7's bytes)."""
    rows: list[tuple[int, int | None, str, str, str]] = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 4 or not re.fullmatch(r"[\d ,\-]+", cells[0]):
            continue
        spans = [p.strip() for p in cells[0].split(",")]
        names = [n.strip() for n in cells[1].split(",")]
        if len(names) == 1 and names[0].endswith("*"):
            names = [r.name for r in Reg if r.name.startswith(names[0][:-1])]
        assert len(spans) == len(names), f"row {line!r}: {spans} against {names}"
        for span, name in zip(spans, names, strict=True):
            first, _, last = span.partition("-")
            assert int(first) % scale == 0, f"row {line!r}: {first} is not a register"
            rows.append((int(first) // scale, int(last) // scale if last else None, name,
                         cells[-2] if scale > 1 else cells[2], cells[-1]))
    rows.sort()
    out = {}
    for i, (first, last, name, rw, meaning) in enumerate(rows):
        end = last if last is not None else (rows[i + 1][0] - 1 if i + 1 < len(rows)
                                             else last_address if last_address is not None
                                             else first)
        out[name] = (first, end, rw, meaning)
    return out


def map_spans() -> dict[str, tuple[int, int]]:
    """Each register's first and last address, from ``Reg`` and ``MAP_SIZE``."""
    starts = sorted((r for r in Reg if r < MAP_SIZE), key=int)  # the version 3 block
    ends = [int(r) - 1 for r in starts[1:]] + [MAP_SIZE - 1]
    return {r.name: (int(r), end) for r, end in zip(starts, ends, strict=True)}


def check_register_table(text: str, where: str, last_address: int | None = None,
                         scale: int = 1, writable: tuple[str, str] = ("RW", "R")
                         ) -> dict[str, tuple[int, int, str, str]]:
    rows = register_rows(text, last_address, scale)
    assert {n: (a, b) for n, (a, b, _, _) in rows.items()} == map_spans(), where
    for name, (first, _, rw, _) in rows.items():
        want = writable[0] if first in COMMAND_AREA else writable[1]
        assert rw == want, f"{where}: {name} is {rw}, not {want}"
    version = re.search(r"\d+", rows["MAP_VERSION"][3].replace("`", ""))
    assert version is not None, f"{where}: no number in the MAP_VERSION row"
    assert int(version.group()) in MAP_VERSIONS, \
        f"{where}: MAP_VERSION row says {rows['MAP_VERSION'][3]!r}, the maps are {MAP_VERSIONS}"
    cmd = rows["CMD"][3].replace("`", "")
    for c in Command:
        assert re.search(rf"\b{int(c)}\s+{c.name}\b", cmd), f"{where}: CMD row lacks {c!r}"
    state = rows["STATE"][3].replace("`", "")
    for s in HandshakeState:
        assert re.search(rf"\b{int(s)}\s+{s.name}\b", state), f"{where}: STATE row lacks {s!r}"
    return rows


def test_readme_register_table_is_the_map() -> None:
    text = section(doc("README.md"), "### Modbus/TCP server")
    beyond = re.search(r"reads beyond (\d+) get Modbus exception 02", text)
    assert beyond is not None
    assert int(beyond.group(1)) == MAP_SIZE - 1, \
        "README: the last readable register is MAP_SIZE - 1"
    check_register_table(text, "README.md", int(beyond.group(1)))


def test_registers_md_table_is_the_map() -> None:
    text = section(doc("docs/registers.md"), "## The map")
    beyond = re.search(r"Everything from (\d+) on does not exist", text)
    assert beyond is not None
    assert int(beyond.group(1)) == MAP_SIZE
    check_register_table(text, "docs/registers.md", int(beyond.group(1)) - 1)


def test_s7_block_table_is_the_map() -> None:
    """docs/s7.md's byte table: register n at byte 2n, the PLC writes the command area only."""
    text = section(doc("docs/s7.md"), "## The block")
    check_register_table(text, "docs/s7.md", MAP_SIZE - 1, scale=2,
                         writable=("PLC", "vgripd"))


def test_register_table_parser_sees_a_stale_row() -> None:
    """The check itself: the README table as shipped before map version 3 (MAP_VERSION 2, no
    pick-list rows) does not pass."""
    stale = ("| 0 | CMD | RW | 1 TRIGGER, 2 CLEAR |\n"
             "| 3 | MAP_VERSION | R | 2 (version 1: the same map without WARNINGS) |\n")
    rows = register_rows(stale)
    assert rows["CMD"][:2] == (0, 2)
    assert "COUNT" not in rows
    assert {n: (a, b) for n, (a, b, _, _) in rows.items()} != map_spans()


def test_s7_block_size_in_the_docs_and_the_example_config() -> None:
    size = 2 * MAP_SIZE
    example = re.findall(r"(\d+)-byte block", doc("config/example.toml"))
    assert example
    assert {int(n) for n in example} == {size}, example
    s7 = re.search(r"The block is (\d+) bytes \(map version (\d+)", doc("docs/s7.md"))
    assert s7 is not None
    assert (int(s7.group(1)), int(s7.group(2))) == (size, MAP_VERSIONS[0])  # S7: version 3
    db = re.search(r"the DB needs (\d+) bytes", doc("docs/registers.md"))
    assert db is not None
    assert int(db.group(1)) == size


def test_s7_bad_request_wording_names_every_command_and_next() -> None:
    """docs/s7.md, "The PLC program": the BAD_REQUEST refusal lists the commands an S7 PLC may
    write (CAPTURE only if the S7 link takes several views, which it does) and NEXT's own
    refusal, as the handshake makes them."""
    from drivers.links.s7 import S7Link

    text = section(doc("docs/s7.md"), "## The PLC program")
    said = re.search(r"32 BAD_REQUEST,\s+CMD is not ([\d, or]+?)\s+\(CAPTURE[^)]*\),\s+"
                     r"or CMD (\d) NEXT with no\s+pick list", text)
    assert said is not None, "docs/s7.md: the BAD_REQUEST wording of the PLC program"
    listed = {int(n) for n in re.findall(r"\d+", said.group(1))}
    takes = {int(c) for c in Command
             if (c is not Command.CAPTURE or getattr(S7Link, "takes_views", False))
             and c is not Command.PREDICT}  # map version 4's: said on its own
    assert listed == takes
    assert int(said.group(2)) == Command.NEXT


def test_s7_udt_db_comment_says_vgripd_never_writes_the_command_area() -> None:
    start = 100
    text = db_source(10, start)
    said = re.search(r"vgripd reads bytes (\d+)\.\.(\d+) and writes bytes (\d+)\.\.(\d+), "
                     r"never ([A-Z_, ]+) \(the PLC's\)", text)
    assert said is not None, text
    last = start + 2 * MAP_SIZE - 1
    assert [int(g) for g in said.groups()[:4]] == [start, last, start + 2 * COMMAND_AREA.stop,
                                                   last]
    assert [n.strip() for n in said.group(5).split(",")] == [
        Reg(a).name for a in COMMAND_AREA]


def test_recording_folder_name_in_the_docs_is_what_the_recorder_writes(tmp_path: Path) -> None:
    said = re.search(r"`(\d{8}-\d{6}\.\d{3}-job(\d+))/`", doc("docs/daemon.md"))
    assert said is not None, "docs/daemon.md: an example recording folder name"
    job_id = int(said.group(2))
    rec = Recorder(tmp_path, 10**8, {})
    rec.scan()
    image = np.zeros((8, 8), np.uint8)
    folder = rec.write(ImagePair(left=image, right=image, t_mono_ns=1, source="test"),
                       JobResult(job_id=job_id, status=Status.NOT_FOUND))
    assert re.fullmatch(r"\d{8}-\d{6}\.\d{3}-job" + said.group(2), folder.name), folder.name


def test_opcua_value_names_example_is_the_convention() -> None:
    said = re.search(r"field names, in order \(`([^`]+)` for KUKA\)", doc("docs/opcua.md"))
    assert said is not None
    assert tuple(said.group(1).split()) == CONVENTIONS["kuka"].fields


def test_opcua_uacall_line_names_the_method_by_browse_name() -> None:
    """asyncua 2.1's ``uacall -m`` takes the method's browse name (``ns:Name``) of a child of
    ``-n``, not a node id; tests/drivers/links/test_opcua.py runs the lines against the link."""
    text = doc("docs/opcua.md")
    block = re.search(r"```sh\n(uals.*?)```", text, re.S)
    assert block is not None
    call = next(line for line in block.group(1).splitlines() if line.startswith("uacall"))
    method = re.search(r'-m "([^"]+)"', call)
    assert method is not None, call
    assert method.group(1) == "2:StartSingleJob", call


def test_mbpoll_lines_use_the_port_the_example_serves() -> None:
    """The docs' mbpoll lines run as written against `vgripd run -c config/example.toml`."""
    import tomllib

    example = tomllib.loads((REPO / "config" / "example.toml").read_text())
    (port,) = [link["port"] for link in example["links"] if link["type"] == "modbus_server"]
    lines = [(path.name, line) for path in sorted((REPO / "docs").glob("*.md"))
             for line in path.read_text().splitlines() if "mbpoll -m tcp" in line]
    assert lines
    wrong = [f"{name}: {line}" for name, line in lines if f"-p {port} " not in line]
    assert not wrong, "\n".join(wrong)
