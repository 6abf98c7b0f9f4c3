"""Convert a pose between robot vendor conventions.

Examples:

    vgripd convert --from kuka --to ur 100 -20 300 90 0 0
    vgripd convert --from abb --to kuka --json 100 -20 300 0.7071068 0 0 0.7071068
    vgripd convert --from kuka --to fanuc < poses.txt      # one pose per line

Output: the values on one line in the target's field order and units (``%.9g``, enough to
round-trip), or with ``--json`` an object ``{"vendor", "fields", "values"}``. Without values on
the command line, poses are read one per line from standard input (blank lines and lines
starting with '#' skipped; numbers separated by spaces or commas). Bad input is a one-line error
on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence

from vgripd.errors import ConversionError
from vgripd.geometry.vendors import (
    CONVENTIONS,
    VENDORS,
    convention,
    target_from_transform,
    transform_from_vendor,
)

EXIT_OK = 0
EXIT_USAGE = 2

# argparse treats "-20" as a positional only if it matches its own negative-number pattern,
# which misses forms like "-1e-3" or "-.5e2"; widen it for this sub-command so that any number
# can be given without a "--" separator (no option of this command starts with "-<digit>").
_NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|nan)$", re.IGNORECASE)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter  # keep the examples' layout
    table = "; ".join(
        f"{c.name}: {' '.join(c.fields) if c.rotation != 'matrix' else '16 numbers, row-major'}"
        f" ({c.length_unit}{', ' + c.angle_unit if c.angle_unit else ''})"
        for c in CONVENTIONS.values())
    parser.add_argument("--from", dest="src", required=True, metavar="VENDOR",
                        help=f"convention of the input, one of: {', '.join(VENDORS)}")
    parser.add_argument("--to", dest="dst", required=True, metavar="VENDOR",
                        help="convention of the output (same names)")
    parser.add_argument("--json", action="store_true",
                        help="print a JSON object with vendor, fields and values")
    parser.add_argument("values", nargs="*", metavar="VALUE",
                        help=f"the pose in the input convention; none: read lines from stdin. "
                             f"Fields: {table}")
    parser._negative_number_matcher = _NEGATIVE_NUMBER


def convert_line(src: str, dst: str, values: Sequence[str], as_json: bool = False) -> str:
    """One pose from ``src`` to ``dst`` as the output line (raises ConversionError)."""
    T = transform_from_vendor(src, values)
    target = target_from_transform(dst, T)
    if as_json:
        return json.dumps({"vendor": target.vendor, "fields": list(target.fields),
                           "values": list(target.values)})
    return " ".join(f"{v:.9g}" for v in target.values)


def run(args: argparse.Namespace) -> int:
    try:
        # Unknown names are reported before any input is read.
        convention(args.src)
        convention(args.dst)
    except ConversionError as err:
        print(f"vgripd convert: {err}", file=sys.stderr)
        return EXIT_USAGE
    if args.values:
        try:
            print(convert_line(args.src, args.dst, args.values, args.json))
        except ConversionError as err:
            print(f"vgripd convert: {err}", file=sys.stderr)
            return EXIT_USAGE
        return EXIT_OK
    for lineno, line in enumerate(sys.stdin, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        try:
            out = convert_line(args.src, args.dst, text.replace(",", " ").split(), args.json)
        except ConversionError as err:
            print(f"vgripd convert: stdin line {lineno}: {err}", file=sys.stderr)
            return EXIT_USAGE
        print(out, flush=True)
    return EXIT_OK
