"""Print the S7 link's data block layout as SCL source for TIA Portal: a UDT, and a DB using it.

The layout is the register map of ``vgripd.peer.registers`` (docs/registers.md) with map
register n at byte 2 n of the block: the same items in the same order, 16-bit items as Int or
Word, 32-bit items as DInt, DWord or Real, all big-endian (S7's own byte order). Offsets come
from ``Reg``; this module adds only each item's S7 type. With ``-c CONFIG`` the value format
and the DB's number and start offset are the config's ``s7`` link's, and so is its map version
(4 adds the conveyor's latch, which the PLC writes, and belt result: 124 bytes instead of 92);
without, float32 values, map version 3 (``--map-version 4`` for the conveyor's) and a block at
byte 0.

Examples:

    vgripd s7-udt -c /etc/vgripd/vgripd.toml -o vgripd_s7.scl
    vgripd s7-udt --value-format int32
    vgripd s7-udt --map-version 4

In TIA Portal: External source files > Add new external file (the .scl), then "Generate blocks
from source"; docs/s7.md has the steps and the settings the DB and the CPU need.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vgripd.config import load_config
from vgripd.errors import ConfigError
from vgripd.peer.registers import (
    COMMAND_AREA,
    LATCH_AREA,
    MAP_VERSIONS,
    MAX_VALUES,
    Reg,
    ValueFormat,
    map_size,
)
from vgripd.registry import LINKS, load_class, validate_options

#: The map version without ``map_version`` in the link's options (4 is the conveyor's).
S7_MAP_VERSION = MAP_VERSIONS[0]

# What each map item holds, by the item's name in ``Reg``. "int": a number (16 or 32 bit, by
# the item's size in the map), "bits": a bit pattern, "real": float32, "value": a pose value in
# the link's value format. Meaning in a few words for the UDT's comments.
ITEMS: dict[str, tuple[str, str]] = {
    "CMD": ("int", "PLC writes: 1 TRIGGER (run a job), 2 CLEAR, 3 NEXT (pick list), "
                   "view * 256 + 4 CAPTURE"),
    "REQ_SEQ": ("int", "PLC writes: a change to a non-zero value is a request"),
    "RECIPE": ("int", "PLC writes: job parameter (0 = default)"),
    "MAP_VERSION": ("int", "the link's map_version"),  # the version itself: members()
    "CHECK_U16": ("bits", "16#1234"),
    "CHECK_U32": ("bits", "16#12345678"),
    "CHECK_F32": ("real", "123.456"),
    "VALUE_FORMAT": ("int", "1 = VALUES are Real, 2 = DInt scaled by VALUE_SCALE"),
    "VALUE_SCALE": ("int", "DInt mode: raw = value * scale; 0 in Real mode"),
    "HEARTBEAT": ("int", "+1 every heartbeat_ms while vgripd is connected (wraps)"),
    "STATE": ("int", "0 IDLE, 1 TRIGGERED, 2 BUSY (image taken), 3 DONE, 4 VIEWS"),
    "CAPTURED_SEQ": ("int", "request whose image is taken: the robot may move"),
    "REJECT_SEQ": ("int", "last refused request (written after REJECT_CODE)"),
    "REJECT_CODE": ("int", "why: 40 BUSY, 32 BAD_REQUEST"),
    "ACK_SEQ": ("int", "request whose result is below; 0 = none. Written LAST"),
    "STATUS": ("int", "job status code (docs/registers.md)"),
    "JOB_ID": ("int", "vgripd job id"),
    "RESULT_AGE_MS": ("int", "ms since the result was produced; -1 = none"),
    "N_VALUES": ("int", "valid pose values: 0, 6 or 7"),
    "VALUES": ("value", "pose in the output vendor's convention and units"),
    "FIT_RMS": ("value", "fit residual in mm; -1 = unknown"),
    "WARNINGS": ("bits", "live warning bits: bit 0 RECALIBRATE"),
    "COUNT": ("int", "pickable objects of the job"),
    "INDEX": ("int", "object shown (1-based); 0 = none, COUNT + 1 = list used up"),
    "PICK_ID": ("int", "pick point id of the object shown (0 = the object's grip)"),
    "SCORE": ("value", "detection score 0..1 of the object shown; -1 = none"),
    "LATCH_COUNT": ("int", "PLC writes before or with REQ_SEQ: the encoder count latched at "
                           "the exposure; PREDICT: the count N"),
    "LATCH_FRAME": ("int", "PLC writes (latch = \"frame_id\"): the camera frame of that count"),
    "RESULT_COUNT": ("int", "encoder count the pose shown belongs to"),
    "LATCH_SOURCE": ("int", "0 none (still part), 1 link, 2 frame id, 3 timestamp"),
    "LATCH_ERR_MM": ("value", "one-sigma error along the belt the latch leaves (mm)"),
    "ALONG": ("value", "the pose at RESULT_COUNT: along the belt (mm)"),
    "ACROSS": ("value", "across the belt in its plane, to the left (mm)"),
    "THETA": ("value", "rotation about the belt's normal (deg)"),
    "QUEUED": ("int", "parts waiting in the recipe's queue after this answer"),
}
#: CMD's comment in map version 4 (PREDICT is the conveyor's).
CMD_V4 = ("PLC writes: 1 TRIGGER, 2 CLEAR, 3 NEXT (pick list, belt queue), view * 256 + 4 "
          "CAPTURE, 5 PREDICT")

S7_TYPES = {("int", 2): "Int", ("int", 4): "DInt", ("bits", 2): "Word", ("bits", 4): "DWord",
            ("real", 4): "Real"}
VALUE_TYPES: dict[str, str] = {"float32": "Real", "int32": "DInt"}
ELEMENT_BYTES = {"Int": 2, "Word": 2, "DInt": 4, "DWord": 4, "Real": 4}
UDT_NAME = "vgripd_Block"
DB_NAME = "vgripd_DB"


@dataclass(frozen=True)
class Member:
    """One UDT member: ``offset`` in bytes from the block's start; ``count`` > 1 is an array."""

    name: str
    offset: int
    s7_type: str
    count: int
    comment: str

    @property
    def declaration(self) -> str:
        if self.count == 1:
            return self.s7_type
        return f"Array[0..{self.count - 1}] of {self.s7_type}"


def members(value_format: ValueFormat = "float32",
            version: int = S7_MAP_VERSION) -> list[Member]:
    """The block's items of map ``version`` with their byte offsets (from ``Reg``) and S7
    types."""
    size = map_size(version)
    regs = sorted((r for r in Reg if r < size), key=int)
    ends = [int(r) for r in regs[1:]] + [size]
    if set(ITEMS) != {r.name for r in Reg}:
        raise AssertionError(f"ITEMS and Reg differ: {set(ITEMS) ^ {r.name for r in Reg}}")
    out = []
    for reg, end in zip(regs, ends, strict=True):
        kind, comment = ITEMS[reg.name]
        if reg is Reg.MAP_VERSION:
            comment = f"{version}"
        elif reg is Reg.CMD and version >= 4:
            comment = CMD_V4
        size = 2 * (end - reg)
        if kind == "value":
            s7_type = VALUE_TYPES[value_format]
        elif (kind, size) in S7_TYPES:
            s7_type = S7_TYPES[(kind, size)]
        else:
            raise AssertionError(f"{reg.name}: no S7 type for {size} bytes of {kind}")
        count, rest = divmod(size, ELEMENT_BYTES[s7_type])
        if rest or (count > 1 and reg is not Reg.VALUES):
            raise AssertionError(f"{reg.name}: {size} bytes do not hold {s7_type} items")
        if reg is Reg.VALUES and count != MAX_VALUES:
            raise AssertionError(f"VALUES holds {count} values, the map {MAX_VALUES}")
        out.append(Member(reg.name, 2 * int(reg), s7_type, count, comment))
    return out


def plc_items(version: int) -> str:
    """The items the PLC writes in map ``version``, for the sources' comments."""
    names = [Reg(a).name for a in COMMAND_AREA]
    if version >= 4:
        names += [r.name for r in (Reg.LATCH_COUNT, Reg.LATCH_FRAME)]
    return ", ".join(names)


def udt_source(value_format: ValueFormat = "float32", name: str = UDT_NAME,
               version: int = S7_MAP_VERSION) -> str:
    """The block of map ``version`` as an SCL ``TYPE`` (a PLC data type) for TIA Portal."""
    items = members(value_format, version)
    rows = [f"      {m.name} : {m.declaration};" for m in items]
    width = max(len(r) for r in rows) + 1
    body = "\n".join(f"{r:<{width}}// +{m.offset:<3d} {m.comment}"
                     for r, m in zip(rows, items, strict=True))
    belt_values = ", LATCH_ERR_MM, ALONG, ACROSS, THETA" if version >= 4 else ""
    return (
        f'TYPE "{name}"\n'
        "VERSION : 0.1\n"
        f"//vgripd register map {version} as an S7 block: {2 * map_size(version)} bytes, "
        "big-endian, for a DB with optimized block access OFF.\n"
        f"//VALUES, FIT_RMS and SCORE{belt_values}: {VALUE_TYPES[value_format]} "
        f"(value_format = \"{value_format}\")."
        f" The PLC writes {plc_items(version)}; vgripd all the rest.\n"
        "   STRUCT\n"
        f"{body}\n"
        "   END_STRUCT;\n"
        "\n"
        "END_TYPE\n"
    )


def db_source(db: int | None, start: int = 0, udt_name: str = UDT_NAME,
              name: str = DB_NAME, version: int = S7_MAP_VERSION) -> str:
    """A global DB holding the block of map ``version`` at byte ``start`` (standard access,
    not retentive)."""
    size = 2 * map_size(version)
    latch = (f" except {start + 2 * LATCH_AREA.start}..{start + 2 * LATCH_AREA.stop - 1}"
             if version >= 4 else "")
    number = (f"give this DB the number {db} (Properties > General, number: manual)"
              if db is not None else "give this DB the number set as the link's db")
    pad = (f"      reserved : Array[0..{start - 1}] of Byte;   // bytes 0..{start - 1}: "
           "the link's start offset\n" if start else "")
    return (
        f'DATA_BLOCK "{name}"\n'
        "{ S7_Optimized_Access := 'FALSE' }\n"
        "VERSION : 0.1\n"
        f"//{number}; vgripd reads bytes {start}..{start + size - 1} and writes bytes "
        f"{start + 2 * COMMAND_AREA.stop}..{start + size - 1}{latch}, never "
        f"{plc_items(version)} (the PLC's).\n"
        "NON_RETAIN\n"
        "   STRUCT\n"
        f"{pad}"
        f'      vgripd : "{udt_name}";   // byte {start}\n'
        "   END_STRUCT;\n"
        "\n"
        "BEGIN\n"
        "\n"
        "END_DATA_BLOCK\n"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("-c", "--config", help="TOML config with an s7 link: its value_format, "
                        "db and start are used")
    parser.add_argument("--link", type=int, metavar="N",
                        help="which [[links]] table (0-based) when the config has several s7 links")
    parser.add_argument("--value-format", choices=sorted(VALUE_TYPES),
                        help="without a config: Real (float32, default) or DInt (int32) values")
    parser.add_argument("--map-version", type=int, choices=MAP_VERSIONS,
                        help="without a config: 3 (default) or 4 (the conveyor's latch and "
                        "belt result)")
    parser.add_argument("--udt-only", action="store_true", help="print the UDT, not the DB")
    parser.add_argument("-o", "--output", help="write the source to this file (default: stdout)")


def _link_options(config_path: str, index: int | None) -> Any:
    config = load_config(config_path)
    s7 = [i for i, s in enumerate(config.links) if s.type == "s7"]
    if not s7:
        raise ConfigError(f'{config_path}: no [[links]] table with type = "s7"')
    if index is None:
        if len(s7) > 1:
            raise ConfigError(f"{config_path}: links {s7} are s7 links; choose one with --link")
        index = s7[0]
    elif index not in s7:
        raise ConfigError(f"{config_path}: links[{index}] is not an s7 link (s7 links: {s7})")
    cls = load_class(LINKS, "link", "s7")
    return validate_options(cls, config.links[index], f"links.{index}")


def run(args: argparse.Namespace) -> int:
    db: int | None = None
    start = 0
    value_format: ValueFormat = args.value_format or "float32"
    version: int = args.map_version or S7_MAP_VERSION
    if args.config:
        if args.value_format or args.map_version:
            raise ConfigError("--value-format and --map-version are taken from the config's "
                              "link; give one or the other")
        options = _link_options(args.config, args.link)
        db, start, value_format = options.db, options.start, options.value_format
        version = options.map_version
    text = udt_source(value_format, version=version)
    if not args.udt_only:
        text += "\n" + db_source(db, start, version=version)
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0
