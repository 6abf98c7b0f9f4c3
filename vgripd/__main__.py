"""Command-line entry: ``vgripd <command> ...``.

Each command lives in ``vgripd/cli/<name>.py`` with ``add_arguments(parser)`` and
``run(args) -> int``; this module only parses, dispatches and maps errors to exit codes.

Exit codes: 0 success; 1 runtime failure; 2 bad usage or bad input values;
78 (EX_CONFIG) configuration error, which systemd is told not to restart on.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from vgripd.errors import ConfigError, VgripError

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_CONFIG = 78

# command name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "convert": ("vgripd.cli.convert", "convert a pose between robot vendor conventions"),
    "run": ("vgripd.cli.run", "run the service until SIGTERM (what systemd starts)"),
    "check": ("vgripd.cli.check", "validate a config file without starting"),
    "init": ("vgripd.cli.init", "write a cell's config: main file plus writable includes"),
    "status": ("vgripd.cli.status", "show a running daemon's status"),
    "demo": ("vgripd.cli.demo", "run daemon, synthetic camera and a mock PLC on this computer"),
    "locate": ("vgripd.cli.locate", "locate the object in one image pair and print the pose"),
    "replay": ("vgripd.cli.replay", "run every image pair of a folder, JSON lines + summary"),
    "calibrate": ("vgripd.cli.calibrate", "calibrate cameras, stereo rig, hand-eye; MCT files"),
    "teach": ("vgripd.cli.teach", "measure the object at its reference place, store it"),
    "s7-udt": ("vgripd.cli.s7_udt", "print the S7 link's data block as SCL (UDT + DB) for TIA"),
    "robot-program": ("vgripd.cli.robot_program", "write a brand's robot socket program"),
    "cameras": ("vgripd.cli.cameras", "list the cameras pylon/Aravis find; grab a frame"),
    "capture": ("vgripd.cli.capture", "take calibration image sets with the config's cameras"),
}


def build_parser(command: str | None = None, *, every: bool = True) -> argparse.ArgumentParser:
    """The parser of every command (``every``), or of ``command`` alone: a command's module is
    imported only when its arguments are wanted, so that ``vgripd --help`` and a quick command
    such as ``convert`` do not pay for the daemon, aiohttp and OpenCV."""
    parser = argparse.ArgumentParser(prog="vgripd", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        if not every and name != command:
            sub.add_parser(name, help=help_text)
            continue
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=help_text, description=module.__doc__)
        module.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


def command_of(argv: Sequence[str]) -> str | None:
    """The command named in ``argv`` (its first word that is not an option), if any."""
    return next((word for word in argv if not word.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(command_of(words), every=False).parse_args(words)
    try:
        rc: int = args._module.run(args)
    except ConfigError as err:
        print(f"vgripd: config error: {err}", file=sys.stderr)
        return EXIT_CONFIG
    except VgripError as err:
        print(f"vgripd: {err}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        return 130
    return rc


if __name__ == "__main__":
    sys.exit(main())
