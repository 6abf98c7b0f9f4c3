"""Write the robot-side program of the ``robot_socket`` link for one robot brand.

    vgripd robot-program --brand kuka -c /etc/vgripd/vgripd.toml -o kuka/
    vgripd robot-program --brand ur -c cell.toml -o ur/ --host 192.168.1.20

The templates in ``robots/<brand>/`` are filled with what the config says: the address the robot
dials (the link's ``host``, or ``--host`` when vgripd listens on all addresses), the port, the
value encoding (int32 scale or float32), the answer timeout (``daemon.job_timeout_s`` + 2 s),
the BUSY retry, the frame words of docs/robot_socket.md and the walk routine's speed and settle
time (``[calibration_walk]``). The brand's pose convention must be
the config's ``output.vendor`` and its value format and connection direction the link's; a
mismatch is refused naming both sides (exit 2). docs/robots/<brand>.md says how to load and
call the program. The programs cannot be run here: they are checked by emulating their message
exchange and by the instructions they use, not on a controller.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from importlib.resources.abc import Traversable
from pathlib import Path

from vgripd.cli.paths import DEFAULT_CONFIG
from vgripd.config import Config, DriverSection, load_config
from vgripd.geometry.vendors import CONVENTIONS
from vgripd.peer.socket_frames import (
    BRANDS,
    CAPTURE_AT_SIZE,
    COUNTED,
    COUNTED_SIZE,
    AnswerKind,
    RobotBrand,
    SocketCommand,
    header_word,
)
from vgripd.registry import LINKS, load_class, validate_options
from vgripd.resources import DOCS, ROBOTS, shared

EXIT_OK = 0
EXIT_USAGE = 2
TEMPLATES = shared(ROBOTS)  # the robots/ folder, installed with the package
LINK_TYPE = "robot_socket"
ATTEMPTS = 3  # unanswered requests before the program stops
BUSY_WAIT_S = 0.25  # pause before asking again after BUSY
CONNECT_TIMEOUT_S = 3.0
ANSWER_MARGIN_S = 2.0  # added to daemon.job_timeout_s: the daemon answers within its timeout
WILDCARD_HOSTS = ("", "0.0.0.0", "::")
MARKER = re.compile(r"@@([A-Z0-9_]+)@@")


class ProgramRefused(Exception):
    """The program cannot be generated for this config (the message names both sides)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--brand", required=True, choices=sorted(BRANDS),
                        help="robot brand: " + "; ".join(f"{b.name}: {b.title}"
                                                          for b in BRANDS.values()))
    parser.add_argument("-c", "--config", default=DEFAULT_CONFIG,
                        help=f"TOML config file (default {DEFAULT_CONFIG})")
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="folder for the program files (created)")
    parser.add_argument("--link", type=int, default=None, metavar="INDEX",
                        help=f"index of the [[links]] entry (needed when the config has more "
                             f"than one {LINK_TYPE} link)")
    parser.add_argument("--host", default=None,
                        help="address of the vgripd computer as the robot reaches it (needed "
                             "when the link listens on all addresses)")
    parser.add_argument("--templates", type=Path, default=TEMPLATES,
                        help="a folder of templates laid out as robots/ of the vgripd source "
                             "(default: the templates installed with vgripd)")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    try:
        texts = render(BRANDS[args.brand], config, args.link, args.host, args.templates,
                       source=Path(args.config).name)
    except ProgramRefused as err:
        print(f"vgripd robot-program: {err}", file=sys.stderr)
        return EXIT_USAGE
    args.output.mkdir(parents=True, exist_ok=True)
    for name, text in texts.items():
        (args.output / name).write_text(text, encoding="utf-8")
        print(f"wrote {args.output / name}")
    print(f"set-up steps: docs/robots/{args.brand}.md "
          f"(installed with vgripd: {shared(DOCS, 'robots', f'{args.brand}.md')})")
    return EXIT_OK


def render(brand: RobotBrand, config: Config, link: int | None = None, host: str | None = None,
           templates: Traversable = TEMPLATES, source: str = "the config") -> dict[str, str]:
    """The brand's program files (name -> text) for ``config``; ``ProgramRefused`` saying why
    not. ``source`` names the config in the programs' header."""
    values = program_values(brand, config, link, host, source)
    folder = templates / brand.name
    texts = {}
    for name in brand.files:
        path = folder / name
        try:
            template = path.read_text(encoding="utf-8")
        except OSError as err:
            raise ProgramRefused(f"cannot read template {path}: {err.strerror} (the package "
                                 f"is installed without its share/robots/ folder, or "
                                 f"--templates names the wrong folder)") from None
        texts[name] = fill(template, values, str(path))
    return texts


def fill(template: str, values: dict[str, str], where: str) -> str:
    """``@@NAME@@`` markers replaced by ``values``; an unknown marker is a bug of the template."""
    unknown = sorted(set(MARKER.findall(template)) - set(values))
    if unknown:
        raise ProgramRefused(f"{where}: unknown markers {', '.join(unknown)}")
    return MARKER.sub(lambda m: values[m.group(1)], template)


def program_values(brand: RobotBrand, config: Config, link: int | None, host: str | None,
                   source: str = "the config") -> dict[str, str]:
    """What the templates' markers stand for."""
    index, section = _socket_link(config, link)
    cls = load_class(LINKS, "link", LINK_TYPE)
    options = validate_options(cls, section, f"links.{index}")
    field = f"links[{index}]"
    vendor = config.output.vendor
    if vendor != brand.convention:
        conv = CONVENTIONS[brand.convention]
        raise ProgramRefused(
            f'--brand {brand.name} reads its pose in the "{brand.convention}" convention '
            f"({', '.join(conv.fields)}: {conv.summary}), but the config has output.vendor = "
            f'"{vendor}"; set output.vendor = "{brand.convention}"')
    if options.value_format != brand.value_format:
        raise ProgramRefused(
            f'--brand {brand.name} unpacks {brand.value_format} values, but {field}.value_format'
            f' = "{options.value_format}"; set value_format = "{brand.value_format}"')
    if options.mode != brand.mode:
        who = "the robot runs the server" if brand.mode == "client" else "the robot dials vgripd"
        raise ProgramRefused(
            f'--brand {brand.name} needs {field}.mode = "{brand.mode}" ({who}), the config has '
            f'mode = "{options.mode}"')
    if options.value_format == "int32" and options.scale < brand.min_scale:
        raise ProgramRefused(
            f"--brand {brand.name} needs {field}.scale >= {brand.min_scale} (its position "
            f"variables count 0.001 mm and 0.0001 deg), the config has scale = {options.scale}")
    address = host or ("" if options.host in WILDCARD_HOSTS else options.host)
    if brand.mode == "server" and not address:
        raise ProgramRefused(
            f'{field}.host = "{options.host}" listens on every address: give the address the '
            f"robot dials with --host (the vgripd computer on the robot's network)")
    if brand.mode == "server" and options.port == 0:
        raise ProgramRefused(f"{field}.port = 0 (any free port): the robot needs a fixed port")
    timeout_s = config.daemon.job_timeout_s + ANSWER_MARGIN_S
    connect_s = 2.0 if brand.name == "ur" else CONNECT_TIMEOUT_S  # socket_open's own limit
    conv = CONVENTIONS[brand.convention]
    scale = options.scale if options.value_format == "int32" else 0
    walk = config.calibration_walk
    return {
        "GENERATED": (f"generated by `vgripd robot-program --brand {brand.name}` from "
                      f"{source}; set-up: docs/robots/{brand.name}.md"),
        "HOST": address or "0.0.0.0",
        "PORT": str(options.port),
        "SCALE": str(scale),
        "SCALE_REAL": f"{float(scale):.1f}",
        "TIMEOUT_S": f"{timeout_s:g}",
        "TIMEOUT_MS": str(round(timeout_s * 1000)),
        "CONNECT_TIMEOUT_S": f"{connect_s:g}",
        "CONNECT_TIMEOUT_MS": str(round(connect_s * 1000)),
        "BUSY_WAIT_S": f"{BUSY_WAIT_S:g}",
        "BUSY_WAIT_MS": str(round(BUSY_WAIT_S * 1000)),
        "BUSY_TRIES": str(math.ceil(timeout_s / BUSY_WAIT_S)),
        "ATTEMPTS": str(ATTEMPTS),
        "LOCATE": str(header_word(SocketCommand.LOCATE)),
        "CLEAR": str(header_word(SocketCommand.CLEAR)),
        "NEXT": str(header_word(SocketCommand.NEXT)),
        "CAPTURED": str(header_word(AnswerKind.CAPTURED)),
        "RESULT": str(header_word(AnswerKind.RESULT)),
        "REFUSED": str(header_word(AnswerKind.REFUSED)),
        "CAPTURE_AT": str(header_word(SocketCommand.CAPTURE_AT)),
        "AT_BYTES": str(CAPTURE_AT_SIZE),
        "LOCATE_AT": str(header_word(SocketCommand.LOCATE | COUNTED)),
        "NEXT_AT": str(header_word(SocketCommand.NEXT | COUNTED)),
        "PREDICT": str(header_word(SocketCommand.PREDICT | COUNTED)),
        "BELT": str(header_word(AnswerKind.BELT)),
        "COUNTED_BYTES": str(COUNTED_SIZE),
        "WALK_SPEED_MM_S": decimal(walk.speed_mm_s),
        "WALK_SPEED_M_S": decimal(walk.speed_mm_s / 1000),
        "WALK_SETTLE_S": decimal(walk.settle_s),
        "WALK_SETTLE_MS": str(round(walk.settle_s * 1000)),
        "WALK_SPEED_V": f"{walk.speed_mm_s:.1f}",  # INFORM: V= in 0.1 mm/s
        "WALK_SETTLE_T": f"{walk.settle_s:.2f}",  # INFORM: TIMER T= in 0.01 s
        "FIELDS": " ".join(conv.fields),
        "CONVENTION": conv.summary,
        "UNITS": f"{conv.length_unit}, {conv.angle_unit or 'unit quaternion'}",
    }


def decimal(value: float) -> str:
    """A number as every robot language reads a REAL literal: digits, a point, no exponent."""
    text = f"{value:.6f}".rstrip("0")
    return text + "0" if text.endswith(".") else text


def _socket_link(config: Config, link: int | None) -> tuple[int, DriverSection]:
    found = [(i, s) for i, s in enumerate(config.links) if s.type == LINK_TYPE]
    if link is not None:
        if not 0 <= link < len(config.links) or config.links[link].type != LINK_TYPE:
            indices = ", ".join(str(i) for i, _ in found) or "none"
            raise ProgramRefused(f"--link {link}: not a {LINK_TYPE} link (its indices: "
                                 f"{indices})")
        return link, config.links[link]
    if not found:
        raise ProgramRefused(f'the config has no [[links]] entry with type = "{LINK_TYPE}" '
                             f"(docs/robot_socket.md)")
    if len(found) > 1:
        raise ProgramRefused(f"the config has {len(found)} {LINK_TYPE} links (indices "
                             f"{', '.join(str(i) for i, _ in found)}): choose one with --link")
    return found[0]
