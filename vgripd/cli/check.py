"""Validate a config file (fields, links against output.vendor, driver options, calibration)
without starting anything."""

from __future__ import annotations

import argparse

from vgripd.cli.run import DEFAULT_CONFIG
from vgripd.config import load_config
from vgripd.errors import ConfigError
from vgripd.service.daemon import Daemon


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", default=DEFAULT_CONFIG,
                        help=f"TOML config file (default {DEFAULT_CONFIG})")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    daemon = Daemon(config)  # drivers validated and the pipeline built, no I/O
    if daemon.not_calibrated:
        raise ConfigError(f"{args.config}: not calibrated: {daemon.not_calibrated}")
    links = ", ".join(daemon.links) or "none"
    print(f"OK {args.config}: camera {config.camera.type}, links {links}, "
          f"output {config.output.vendor}, job timeout {config.daemon.job_timeout_s:g} s, "
          f"recording {'on' if config.record.enabled else 'off'}")
    return 0
