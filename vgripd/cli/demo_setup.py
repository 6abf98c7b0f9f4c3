"""``vgripd demo --setup``: the learning cell with nothing set up, and the browser's setup page
to set it up (docs/setup.md).

The learning cell's board camera (``drivers/cameras/board.py``, with ``plate = true``): a
virtual operator holds a chessboard in front of two cameras while the demo plate lies on the
table. The config is laid out as ``vgripd init`` lays one out: a main file and writable
includes in the state folder: the camera and the link in ``camera.toml`` and ``links.toml``,
the cell's includes empty (no calibration, no hand-eye, no object, no reference: jobs end
NOT_CALIBRATED until the page has set them), plus ``access.toml`` with a new
token, ``allow_config_edit`` and ``allow_trigger``. Then the daemon runs on it as ``vgripd run``
does (the web view's writes are its config transactions), until Ctrl-C.

``--state-dir DIR`` keeps the folder (a new temporary one otherwise, named at start): run it
again with the same folder to go on where the page left off.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import secrets
import socket
import tempfile
from pathlib import Path
from typing import Any

from vgripd.serialize import toml_from_dict

INCLUDES = ("camera.toml", "links.toml", "rig.toml", "handeye.toml", "cell.toml",
            "reference.toml", "access.toml")
BOARD = "chessboard:9x6:30"
WHAT = {"camera.toml": "the cameras (the setup page's cameras step; a restart applies them)",
        "links.toml": "the PLC link (the setup page's link step; a restart applies it)",
        "rig.toml": "the cameras' calibration (the setup page's calibration step)",
        "handeye.toml": "where the cameras are (the setup page's hand-eye step)",
        "cell.toml": "the object and the vision parameters (the setup page's object step)",
        "reference.toml": "the taught reference (the setup page's teaching)",
        "access.toml": "the web view's token: keep this file private"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--setup", action="store_true",
                        help="the learning cell with nothing set up and the browser setup page "
                             "(docs/setup.md); runs until Ctrl-C")
    parser.add_argument("--state-dir", type=Path, default=None, metavar="DIR",
                        help="with --setup: the folder of the config and its writable "
                             "includes (default: a new temporary folder); again the same "
                             "folder goes on where the page left off")


def write_cell(folder: Path, modbus_port: int, web_port: int, seed: int = 1) -> tuple[Path, str]:
    """The learning cell's files in ``folder`` unless there (the main file, the includes);
    the main file and the token."""
    folder.mkdir(parents=True, exist_ok=True)
    main = folder / "vgripd.toml"
    access = folder / "access.toml"
    if main.exists() and access.exists():  # resumed: the files as the page left them
        import tomllib

        token = str(tomllib.loads(access.read_text())["status"]["token"])
        return main, token
    token = secrets.token_urlsafe(24)
    modbus_port, web_port = modbus_port or free_port(), web_port or free_port()
    parts: dict[str, dict[str, Any]] = {name: {} for name in INCLUDES}
    parts["access.toml"] = {"status": {"port": web_port, "token": token,
                                       "allow_config_edit": True, "allow_trigger": True}}
    # each place held for two grabs: the first is refused as the board just moved there, the
    # second is still and kept
    parts["camera.toml"] = {"camera": {"type": "board", "board": BOARD, "plate": True,
                                       "seed": seed, "hold_frames": 2, "move_frames": 0}}
    parts["links.toml"] = {"links": [{"type": "modbus_server", "host": "127.0.0.1",
                                      "port": modbus_port}]}
    for name, data in parts.items():
        text = f"# {WHAT[name]}\n# written by `vgripd demo --setup`\n" + toml_from_dict(data)
        path = folder / name
        path.write_text(text, encoding="utf-8")
        if name == "access.toml":
            path.chmod(0o600)
    main.write_text("# the learning cell (vgripd demo --setup): the service; the camera, the "
                    "link and the cell live in the includes\n" + toml_from_dict({
                        "include": [str(folder / name) for name in INCLUDES],
                        "daemon": {"log_level": "WARNING"}}), encoding="utf-8")
    return main, token


async def serve_setup(main: Path, token: str, announce: Any = print) -> None:
    """The daemon on ``main`` as ``vgripd run`` runs it, the setup page announced, until
    Ctrl-C or SIGTERM; a restart asked for on the page starts it again on the files as saved
    (where ``vgripd run`` leaves that to systemd)."""
    from vgripd.cli.run import serve
    from vgripd.config import load_config
    from vgripd.service.daemon import Daemon
    from vgripd.service.ops.reload import Reloader

    while True:
        daemon = Daemon(load_config(main))
        daemon.reloader = reloader = Reloader(daemon, main)

        async def tell(daemon: Daemon = daemon) -> None:
            await daemon.wait_for(lambda: daemon.status_server is not None
                                  and daemon.run_state.value == "running", 120.0)
            assert daemon.status_server is not None
            link = next(iter(daemon.rooms.links.links.values()))
            announce(f"vgripd demo --setup: the learning cell (config {main})\n"
                     f"  setup page: http://127.0.0.1:{daemon.status_server.port}/setup\n"
                     f"  token:      {token}\n"
                     f"  PLC link:   Modbus/TCP on 127.0.0.1:{getattr(link, 'port', '?')}\n"
                     f"up until Ctrl-C (the page and the link end with it; the folder stays: "
                     f"vgripd demo --setup --state-dir {main.parent} goes on)")

        teller = asyncio.ensure_future(tell())
        try:
            await serve(daemon)
        finally:
            teller.cancel()
        if not reloader.restart_requested:
            return
        announce(f"vgripd demo --setup: restarting (asked by {reloader.restart_requested}) "
                 "with the files as saved")


def free_port() -> int:
    """A port free on 127.0.0.1 now (written into the cell, so a restart keeps it)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def bindable(port: int) -> int:
    """``port`` when 127.0.0.1 has it free, else 0 (any free one)."""
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return 0
    return port


def run(args: argparse.Namespace) -> int:
    from vgripd.service.host.logsetup import configure_logging

    folder = args.state_dir or Path(tempfile.mkdtemp(prefix="vgripd-setup-"))
    main, token = write_cell(folder.absolute(), bindable(args.port), bindable(args.web_port),
                             args.seed)
    configure_logging("INFO" if args.verbose else "WARNING")
    if not args.verbose:
        logging.getLogger("vgripd").setLevel(logging.ERROR)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve_setup(main, token, lambda text: print(text, flush=True)))
    print("vgripd demo --setup: stopped")
    return 0
