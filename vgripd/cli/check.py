"""Validate a config file and commission the cell without starting anything.

Fields, links against output.vendor, driver options and calibration first (any problem: exit
78). Then the commissioning checks (docs/daemon.md, "vgripd check"): the taught reference object
projected through each camera (in front, inside the image, at a size the finder searches for,
seen by both cameras), a replay folder with frames, at least one link, the listening ports
free. An ERROR means the config cannot work here: exit 78, one line per problem naming the
config key. WARNINGs are printed after the OK line; the exit code stays 0.
"""

from __future__ import annotations

import argparse

from vgripd.cli.run import DEFAULT_CONFIG
from vgripd.config import load_config
from vgripd.errors import ConfigError
from vgripd.service.commissioning import Options, commission
from vgripd.service.daemon import Daemon


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", default=DEFAULT_CONFIG,
                        help=f"TOML config file (default {DEFAULT_CONFIG})")
    parser.add_argument("--running", action="store_true",
                        help="vgripd already runs with this config: skip the port checks")
    parser.add_argument("--no-links-ok", action="store_true",
                        help="accept a config without [[links]] (for locate/replay only)")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    daemon = Daemon(config)  # drivers validated and the pipeline built, no I/O
    if daemon.not_calibrated:
        raise ConfigError(f"{args.config}: not calibrated: {daemon.not_calibrated}")
    findings = commission(config, Options(running=args.running, no_links_ok=args.no_links_ok))
    errors = [f for f in findings if f.level == "ERROR"]
    others = [f"{f.level.lower()}: {args.config}: {f}" for f in findings if f.level != "ERROR"]
    if errors:
        if others:
            print("\n".join(others))
        raise ConfigError("\n".join(f"{args.config}: {f}" for f in errors))
    links = ", ".join(daemon.links) or "none"
    print(f"OK {args.config}: camera {config.camera.type}, links {links}, "
          f"output {config.output.vendor}, job timeout {config.daemon.job_timeout_s:g} s, "
          f"recording {'on' if config.record.enabled else 'off'}")
    if others:
        print("\n".join(others))
    return 0
