"""Run the vgripd service until SIGTERM/SIGINT (what systemd starts); SIGHUP reloads the config
file (``systemctl reload vgripd``, ``vgripd.service.ops.reload``). A restart asked for on the setup
page ends it with exit status 75 (``EXIT_RESTART``), which systemd's ``Restart=on-failure``
starts again."""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal

from vgripd.cli.paths import DEFAULT_CONFIG
from vgripd.config import load_config
from vgripd.errors import ConfigError
from vgripd.service.daemon import Daemon
from vgripd.service.host.configtxn import recover
from vgripd.service.host.logsetup import configure_logging
from vgripd.service.ops.reload import EXIT_RESTART, Reloader


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", default=DEFAULT_CONFIG,
                        help=f"TOML config file (default {DEFAULT_CONFIG})")


async def serve(daemon: Daemon) -> None:
    """Serve until a signal; SIGTERM and SIGINT both stop cleanly (job aborted, links closed);
    SIGHUP reloads the config between jobs when the daemon knows its file (``reloader``)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, daemon.request_stop)
    reloader = daemon.reloader
    if reloader is not None:
        loop.add_signal_handler(signal.SIGHUP, reloader.request)
    try:
        await daemon.serve()
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            loop.remove_signal_handler(sig)
        if reloader is not None:
            await reloader.close()


def run(args: argparse.Namespace) -> int:
    recover(args.config)  # a config write a kill interrupted in its commit: finished first
    config = load_config(args.config)
    configure_logging(config.daemon.log_level)
    for warning in config.load_warnings:  # e.g. a hand-eye file without a camera fingerprint
        logging.getLogger("vgripd.config").warning("%s: %s", args.config, warning)
    try:
        daemon = Daemon(config)
    except ConfigError as err:  # a template file, driver options: name the file judged
        raise ConfigError(f"{args.config}: {err}") from None
    daemon.reloader = Reloader(daemon, args.config)
    # The process is the daemon's alone: its start-up heap leaves the collector's walks.
    daemon.freeze_heap_at_ready = True
    asyncio.run(serve(daemon))
    if daemon.reloader.restart_requested:  # systemd (Restart=on-failure) starts it again
        logging.getLogger("vgripd").warning(
            "stopped for a restart (asked by %s): exit %d", daemon.reloader.restart_requested,
            EXIT_RESTART)
        return EXIT_RESTART
    return 0
