"""Calibrate cameras, the stereo rig and the hand-eye pose; read and write MCT result files.

Every subcommand writes a TOML result file (``-o``) that a config pulls in with
``include = ["camera.toml", ...]``, can draw a PNG report (``--report``) and with ``--json``
prints a JSON summary on stdout (parameters in OpenCV's order and pixel convention).
See docs/calibration.md.
"""

from __future__ import annotations

import argparse
import importlib

# subcommand -> (module, one-line help); each module has add_arguments(parser), run(args)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "intrinsics": ("vgripd.cli.calibrate_intrinsics", "one camera from board images"),
    "stereo": ("vgripd.cli.calibrate_stereo", "both cameras and the left->right transform"),
    "cameras": ("vgripd.cli.calibrate_cameras", "2-8 cameras' poses from shared board views"),
    "handeye": ("vgripd.cli.calibrate_handeye", "camera to flange (or base) from robot poses"),
    "conveyor": ("vgripd.cli.calibrate_conveyor", "the belt's direction and encoder scale"),
    "import-mct": ("vgripd.cli.calibrate_mct", "read a Matlab Calibration Toolbox result"),
    "export-mct": ("vgripd.cli.calibrate_mct", "write a result as an MCT Calib_Results*.m"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="calibrate_command", required=True, metavar="WHAT")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=help_text, description=module.__doc__)
        if name.endswith("-mct"):
            module.add_arguments(p, name)  # one module serves both directions
        else:
            module.add_arguments(p)
        p.set_defaults(_calibrate_module=module)


def run(args: argparse.Namespace) -> int:
    rc: int = args._calibrate_module.run(args)
    return rc
