"""List the cameras each installed camera SDK finds, or take frames from one for aiming.

``vgripd cameras`` prints one line per device that pylon (pypylon) and Aravis discover: stack,
serial number, vendor and model, address, user-defined name (Aravis: its device id). A stack
that is not installed is named with what to install. ``--json``: the same as one JSON object
(``devices`` and ``unavailable``: stack -> why), as the setup page's cameras step reads it.

``vgripd cameras grab NAME -o frame.png [--set Feature=value ...]`` opens NAME (a serial
number, user-defined name, IP address or device id; with ``-c CONFIG``, also a camera name of
the config's pylon/aravis ``[camera]``, whose settings are then used), applies the ``--set``
features after the config's (checked against the device's ranges like the daemon's), takes one
frame on a software trigger with the daemon's own driver, and writes it (8-bit grey, or BGR
with ``--color``). ``--count N`` takes N frames and reports the frame rate. Exit 1 when the
camera cannot be found, opened or configured, or no frame came.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path
from typing import Any

from vgripd.config import Config, load_config
from vgripd.errors import CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class

STACKS = ("pylon", "aravis")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", nargs="?", choices=("list", "grab"), default="list",
                        help="list (default): what each stack finds; grab: frames from NAME")
    parser.add_argument("name", nargs="?", help="grab: serial, user name, IP, device id, or "
                                                "a camera name of -c CONFIG")
    parser.add_argument("-o", "--output", help="grab: the image file to write (.png, .tif, ...)")
    parser.add_argument("--set", action="append", default=[], metavar="FEATURE=VALUE",
                        help="grab: a GenICam feature to set (repeatable), after the config's")
    parser.add_argument("-c", "--config", help="take the camera's settings from this config")
    parser.add_argument("--stack", choices=STACKS, help="only this SDK")
    parser.add_argument("--count", type=int, default=1, help="grab: frames to take (the last "
                                                              "is written); prints frames/s")
    parser.add_argument("--timeout", type=float, default=5.0, help="grab: seconds per frame")
    parser.add_argument("--color", action="store_true", help="grab: keep colour formats BGR")
    parser.add_argument("--json", action="store_true", help="list: one JSON object (the setup "
                                                            "page reads it)")


def parse_value(text: str) -> bool | int | float | str:
    """A ``--set`` value as the device's type would take it: true/false, int, float, text."""
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            continue
    return text


def parse_sets(items: list[str]) -> dict[str, Any]:
    features: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ConfigError(f"--set {item!r}: expected FEATURE=VALUE")
        features[name.strip()] = parse_value(value.strip())
    return features


def _stack(name: str) -> Any:
    cls = load_class(CAMERAS, "camera", name)
    return cls.make_stack()


def discover(stacks: tuple[str, ...]) -> dict[str, Any]:
    """What each stack finds, as data: ``{"devices": [{stack, serial, vendor, model, address,
    user_name, key}], "unavailable": {stack: why}}``."""
    devices: list[dict[str, str]] = []
    unavailable: dict[str, str] = {}
    for name in stacks:
        try:
            found = _stack(name).discover()
        except CameraError as err:
            unavailable[name] = str(err)
            continue
        devices += [{"stack": name, "serial": d.serial, "vendor": d.vendor, "model": d.model,
                     "address": d.address, "user_name": d.user_name, "key": d.key}
                    for d in found]
    return {"devices": devices, "unavailable": unavailable}


def list_devices(stacks: tuple[str, ...]) -> list[str]:
    lines = []
    for name in stacks:
        try:
            found = _stack(name).discover()
        except CameraError as err:
            lines.append(f"{name}: not available: {err}")
            continue
        if not found:
            lines.append(f"{name}: no camera found")
        for d in found:
            lines.append(f"{name}\tserial {d.serial}\t{d.vendor} {d.model}\t"
                         f"{d.address or '-'}\t{d.user_name or '-'}")
    return lines


def grab_options(args: argparse.Namespace) -> tuple[str, dict[str, Any], Config]:
    """The driver type and options for NAME, and the config they are judged with."""
    sets = parse_sets(args.set)
    note = ""  # why the config did not name the camera, for the error below
    if args.config:
        config = load_config(args.config)
        cam = config.camera
        if cam.type not in STACKS:
            note = (f"; {args.config}: camera.type = {cam.type!r}, not a pylon or aravis "
                    f"camera, so NAME was looked for among the discovered devices only")
        else:
            cls = load_class(CAMERAS, "camera", cam.type)
            options = cls.Options.model_validate(cam.options())
            names = cls.names_of(options)
            if args.name in names:
                entry = options.cameras[names.index(args.name)]
                data = options.model_dump(exclude_none=True)
                data["cameras"] = [{**entry.model_dump(exclude_none=True), "name": args.name}]
                data["features"] = {**data.get("features", {}), **sets}
                data["trigger"] = "software"
                return cam.type, data, config
            note = f"; {args.config} names the cameras {', '.join(names)}"
    else:
        config = Config()
    stacks = (args.stack,) if args.stack else STACKS
    seen = []
    for stack_name in stacks:
        try:
            found = _stack(stack_name).discover()
        except CameraError as err:
            seen.append(f"{stack_name}: {err}")
            continue
        for d in found:
            if args.name in (d.serial, d.user_name, d.address, d.key):
                return stack_name, {"cameras": [{"serial": d.serial, "features": sets,
                                                 "name": args.name}],
                                    "trigger": "software"}, config
        seen += [f"{stack_name}: {d.label()}" for d in found]
    raise CameraError(f"no camera {args.name!r} (found: {'; '.join(seen) or 'none'}{note})")


async def grab(type_name: str, data: dict[str, Any], config: Config, count: int,
               timeout_s: float) -> tuple[Any, float, dict[str, Any]]:
    cls = load_class(CAMERAS, "camera", type_name)
    driver = cls(cls.Options.model_validate(data), config)
    await driver.open()
    try:
        applied = {**driver.applied[0], "PixelFormat": driver.formats[0]}
        t0 = time.perf_counter()
        for _ in range(count):
            pair = await driver.grab(timeout_s)
        elapsed = time.perf_counter() - t0
    finally:
        await driver.close()
    return pair.left, count / elapsed if elapsed > 0 else 0.0, applied


def run(args: argparse.Namespace) -> int:
    if args.action == "list" and args.json:
        import json

        print(json.dumps(discover((args.stack,) if args.stack else STACKS)))
        return 0
    if args.action == "list":
        print("\n".join(list_devices((args.stack,) if args.stack else STACKS)))
        return 0
    if not args.name or not args.output:
        raise ConfigError("cameras grab needs NAME and -o FILE")
    if args.count < 1 or args.timeout <= 0:
        raise ConfigError("--count must be >= 1 and --timeout > 0")
    import cv2

    type_name, data, config = grab_options(args)
    if args.color:
        data["grayscale"] = False
    image, fps, applied = asyncio.run(grab(type_name, data, config, args.count, args.timeout))
    out = Path(args.output)
    if not cv2.imwrite(str(out), image):
        raise CameraError(f"cannot write {out} (unknown suffix or unwritable folder)")
    fmt = applied.get("PixelFormat", "")
    rate = f", {fps:.1f} frames/s over {args.count}" if args.count > 1 else ""
    print(f"wrote {out}: {image.shape[1]}x{image.shape[0]} from {type_name} camera "
          f"{args.name}{(' ' + str(fmt)) if fmt else ''}{rate}")
    return 0
