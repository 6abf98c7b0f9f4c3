"""What every calibration command shares: ``-o``, ``--report``, ``--json`` and the summary.

A summary is JSON data. ``emit`` prints it as JSON with ``--json``, else a few human lines
(``lines``), and always the warnings on stderr, so a pipeline reading stdout stays clean.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Mapping
from typing import Any

from vgripd.serialize import jsonable


def add_output_arguments(parser: argparse.ArgumentParser, default_out: str) -> None:
    parser.add_argument("-o", "--output", default=default_out,
                        help=f"result file (TOML, for a config's include; default {default_out})")
    parser.add_argument("--report", metavar="PNG", default=None,
                        help="also draw a PNG report (residual vectors, per-image errors)")
    parser.add_argument("--json", action="store_true",
                        help="print the summary as JSON on stdout")


def emit(args: argparse.Namespace, summary: Mapping[str, Any], lines: Iterable[str]) -> None:
    """Print the summary (JSON or text) on stdout and its ``warnings`` on stderr."""
    for w in summary.get("warnings", ()):
        print(f"warning: {w}", file=sys.stderr)
    if args.json:
        json.dump(jsonable(summary), sys.stdout, indent=2, allow_nan=False)
        sys.stdout.write("\n")
    else:
        for line in lines:
            print(line)
