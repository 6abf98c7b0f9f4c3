"""Create a cell's config in the layout the service and its web view can work with.

    sudo vgripd init                          # the demo cell: /etc/vgripd, /var/lib/vgripd
    sudo vgripd init --example pylon-stereo   # from config/examples/pylon-stereo.toml
    vgripd init -c cell/vgripd.toml --state-dir cell/state --example robot-socket-kuka

The main file (``-c``, default /etc/vgripd/vgripd.toml) keeps what only an installer changes:
output, daemon, record, status. What the web view and the calibration commands write goes into
includes in the state directory (``--state-dir``, default /var/lib/vgripd, the unit's
``StateDirectory``, writable by the service):

    camera.toml     [camera] (the setup page's cameras step; a restart applies it)
    links.toml      [[links]] (the setup page's link step; a restart applies it)
    rig.toml        [calibration] without the hand-eye (``vgripd calibrate stereo|cameras``)
    handeye.toml    [calibration.hand_eye] (``calibrate handeye``, the walk page's accept)
    cell.toml       [object] and [vision] (the page's tuning save, camera exposure and gain)
    reference.toml  [reference] (``vgripd teach``, the page's teaching)

The main file lists them with absolute paths in ``include = [...]``. ``--allow-edit`` also
writes access.toml there: ``[status]`` with ``allow_config_edit`` and a new random token
(printed once), readable by the service alone once it runs. Nothing that exists is overwritten
(exit 2 naming it) unless ``--force``. The result is judged as ``vgripd check`` judges a config
before anything is written: a config that fails is not written (exit 78).
"""

from __future__ import annotations

import argparse
import os
import secrets
import sys
import tomllib
from pathlib import Path
from typing import Any

from vgripd.cli.paths import DEFAULT_CONFIG, DEFAULT_STATE_DIR
from vgripd.config import config_from_dict, read_config_data
from vgripd.errors import ConfigError
from vgripd.geometry.fingerprint import camera_about, hand_eye_fingerprint
from vgripd.resources import EXAMPLES, shared
from vgripd.serialize import toml_from_dict

EXIT_OK = 0
EXIT_USAGE = 2
#: Sections the main file keeps; every other one of the source goes to an include.
MAIN_SECTIONS = ("output", "daemon", "record", "status", "picking", "limits",
                 "recipes", "calibration_walk")
#: The demo cell's link when no example is named: the register map on an unprivileged port.
DEMO_LINK = {"type": "modbus_server", "host": "127.0.0.1", "port": 1502}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("-c", "--config", type=Path, default=Path(DEFAULT_CONFIG),
                        help=f"the main config file to write (default {DEFAULT_CONFIG})")
    parser.add_argument("--state-dir", type=Path, default=Path(DEFAULT_STATE_DIR),
                        help=f"folder of the writable includes (default {DEFAULT_STATE_DIR})")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--example", metavar="NAME",
                        help="start from an installed example (config/examples/NAME.toml: "
                             + ", ".join(example_names()) + "); default: the demo cell with "
                             "a Modbus/TCP server on 127.0.0.1:1502")
    source.add_argument("--from", dest="source", type=Path, metavar="FILE",
                        help="start from this config file (its includes merged in)")
    parser.add_argument("--allow-edit", action="store_true",
                        help="let the web view save tuning, teaching and hand-eye results: "
                             "status.allow_config_edit with a new token, in access.toml")
    parser.add_argument("--force", action="store_true",
                        help="overwrite files that exist")


def example_names() -> list[str]:
    folder = shared(EXAMPLES)
    return sorted(p.name.removesuffix(".toml") for p in folder.iterdir()
                  if p.name.endswith(".toml"))


def source_data(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """The config to start from, as data, and what to call it."""
    if args.source is not None:
        return read_config_data(args.source), str(args.source)
    if args.example is None:
        return {"camera": {"type": "synthetic"}, "links": [dict(DEMO_LINK)]}, "the demo cell"
    node = shared(EXAMPLES, f"{args.example}.toml")
    if not node.is_file():
        raise ConfigError(f"--example {args.example}: no such example (the examples: "
                          f"{', '.join(example_names())})")
    return tomllib.loads(node.read_text(encoding="utf-8")), f"example {args.example}"


def layout(data: dict[str, Any], state_dir: Path, allow_edit: bool,
           source: str) -> dict[str, dict[str, Any]]:
    """File name (main file: "") -> its data. The cell's calibration, object and reference
    come from the judged config, so that a source that leaves them out (the demo cell) gets
    the values the daemon would run with written out."""
    config = config_from_dict(data, source)
    main = {k: v for k, v in data.items() if k in MAIN_SECTIONS}
    files: dict[str, dict[str, Any]] = {}
    # The camera and the links in includes of their own: the setup page chooses them.
    for section, name in (("camera", "camera.toml"), ("links", "links.toml")):
        if section in data:
            files[name] = {section: data[section]}
    # The hand-eye and the reference record the camera model (and the reference the hand-eye)
    # they belong to, as the calibrate and teach commands do, so check finds them consistent.
    about: dict[str, Any] = {}
    if config.calibration is not None:
        calibration = config.calibration.model_dump(mode="json", exclude_none=True)
        about = camera_about(calibration)
        hand_eye = calibration.pop("hand_eye", None)
        files["rig.toml"] = {"calibration": calibration}
        if hand_eye is not None:
            files["handeye.toml"] = {"about": dict(about),
                                     "calibration": {"hand_eye": hand_eye}}
        about["hand_eye"] = hand_eye_fingerprint({**calibration, "hand_eye": hand_eye})
    files["cell.toml"] = {"object": config.object.model_dump(mode="json", exclude_none=True),
                          "vision": data.get("vision", {})}
    files["reference.toml"] = {
        **({"about": about} if about else {}),
        "reference": config.reference.model_dump(mode="json", exclude_none=True)}
    if allow_edit:
        status = dict(main.pop("status", {}))
        status.update(allow_config_edit=True, token=secrets.token_urlsafe(24))
        files["access.toml"] = {"status": status}
    unknown = sorted(set(data) - set(MAIN_SECTIONS) - {"camera", "links", "calibration",
                                                        "object", "vision", "reference"})
    if unknown:
        raise ConfigError(f"{source}: sections {', '.join(unknown)}: not known to vgripd init")
    main = {"include": [str(state_dir / name) for name in files], **main}
    return {"": main, **files}


def run(args: argparse.Namespace) -> int:
    data, source = source_data(args)
    state_dir = args.state_dir.absolute()
    config_path = args.config.absolute()
    files = layout(data, state_dir, args.allow_edit, source)
    targets = {name: (state_dir / name if name else config_path) for name in files}
    existing = [str(p) for p in targets.values() if p.exists()]
    if existing and not args.force:
        print(f"vgripd init: {', '.join(existing)} exist: nothing written (--force overwrites)",
              file=sys.stderr)
        return EXIT_USAGE
    texts = {name: header(name, source) + toml_from_dict(part) for name, part in files.items()}
    # Judged before anything is written: the same data, read back as the daemon reads it.
    config_from_dict(merged(files), str(config_path))
    config_path.parent.mkdir(parents=True, exist_ok=True)
    state_dir.mkdir(parents=True, exist_ok=True)
    for name, path in targets.items():
        # The token stays readable by the owner alone (the service, once systemd hands it the
        # state directory); the rest as the umask says.
        mode = 0o600 if name == "access.toml" else 0o644
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(texts[name])
        print(f"wrote {path}")
    if args.allow_edit:
        print(f"web view token (status.token in {targets['access.toml']}): "
              f"{files['access.toml']['status']['token']}")
    print(f"next: vgripd check -c {config_path}")
    return EXIT_OK


def merged(files: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The includes' sections as one config (the main file's ``include`` merge, in memory)."""
    out: dict[str, Any] = {}
    for name, part in files.items():
        for key, value in part.items():
            if key in ("include", "about"):
                continue
            if key == "calibration" and "calibration" in out:
                out["calibration"] = {**out["calibration"], **value}
            elif name and key == "status":
                out["status"] = {**out.get("status", {}), **value}
            else:
                out[key] = value
    return out


def header(name: str, source: str) -> str:
    what = {
        "": "the main file: output, service; the cameras, links and cell live in the includes",
        "camera.toml": "the cameras (the setup page's cameras step; a restart applies a change)",
        "links.toml": "the PLC or robot links (the setup page's link step; a restart applies "
                      "a change)",
        "rig.toml": "the cameras' calibration (vgripd calibrate stereo | cameras writes one)",
        "handeye.toml": "where the camera is (vgripd calibrate handeye, the walk page's accept)",
        "cell.toml": "the object and the vision parameters (the web view's tuning save)",
        "reference.toml": "the taught reference (vgripd teach, the web view's teaching)",
        "access.toml": "the web view's token: keep this file private",
    }[name]
    return f"# {what}\n# written by `vgripd init` from {source} (docs/daemon.md, \"vgripd init\")\n"
