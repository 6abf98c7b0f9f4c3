"""Validate a config file and commission the cell without starting anything.

Fields, links against output.vendor, driver options and calibration first (any problem: exit
78). Then the commissioning checks (docs/daemon.md, "vgripd check"): the taught reference object
projected through each camera (in front, inside the image, at a size the finder searches for,
seen by both cameras), a replay folder with frames, at least one link, the listening ports
free. A camera whose driver can judge its settings on the device (``pylon``, ``aravis``) is opened,
configured, read back and closed (skipped with ``--running`` or ``--no-camera``): a feature the
device lacks or refuses, or a value out of its range, is a config error naming the camera, the
feature and the device's range. An ERROR means the config cannot work here: exit 78, one line per
problem naming the config key. WARNINGs are printed after the OK line; the exit code stays 0.
With ``--snapshot FILE`` (the daemon's judge of a save or reload, ``vgripd.service.host.configtxn``)
the config's bytes are read from that one file, not from disk, and their digest is printed.

Every recipe (docs/recipes.md) is checked: its effective config is validated with the file, a
recipe that is not calibrated or taught is an error naming it (``recipe 2 (plate-b): not
calibrated: ...``), and the scene check runs for each recipe's object and reference (its keys
prefixed ``recipes.N.``). The replay samples are run through recipe 0 only: they show one plate.
"""

from __future__ import annotations

import argparse
import asyncio

from vgripd.cli.paths import DEFAULT_CONFIG
from vgripd.config import Config, load_config
from vgripd.configsnapshot import Snapshot
from vgripd.errors import CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.daemon import Daemon
from vgripd.service.host.commissioning import Options, check_scene, commission
from vgripd.vision.commissioning import Finding


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", default=DEFAULT_CONFIG,
                        help=f"TOML config file (default {DEFAULT_CONFIG})")
    parser.add_argument("--running", action="store_true",
                        help="vgripd already runs with this config: skip the port checks")
    parser.add_argument("--no-links-ok", action="store_true",
                        help="accept a config without [[links]] (for locate/replay only)")
    parser.add_argument("--no-camera", action="store_true",
                        help="do not open the cameras to check their settings on the devices")
    parser.add_argument("--snapshot", metavar="FILE",
                        help="judge the config's bytes from this snapshot file (written by the "
                             "daemon for a save or reload) instead of the files on disk; "
                             "prints the snapshot's digest")
    parser.add_argument("--untaught-ok", action="store_true",
                        help="a recipe whose reference is not taught (yet, or again after a new "
                             "hand-eye) is a warning, not an error: its jobs end NOT_CALIBRATED")
    parser.add_argument("--uncalibrated-ok", action="store_true",
                        help="a recipe not calibrated (yet) is a warning, not an error: its "
                             "jobs end NOT_CALIBRATED (the setup page's camera and link "
                             "choices on a cell it has not calibrated yet)")


def check_camera_settings(config: Config) -> None:
    """Open the configured cameras, apply and read back their settings, close them:
    ``ConfigError`` naming the camera, the feature and the device's range, or a camera whose
    image size is not the calibrated one. Only drivers with ``check_settings`` (the GenICam SDK
    drivers) are judged, also as entries of a ``multi`` camera (``camera.cameras.<i>``)."""
    cls = load_class(CAMERAS, "camera", config.camera.type)
    driver = cls(validate_options(cls, config.camera, "camera"), config)
    parts = [(f"camera.cameras.{i}", d) for i, d in enumerate(getattr(driver, "drivers", []))]
    parts = parts or [("camera", driver)]
    names: list[str] = []
    sizes: list[tuple[int, int]] | None = []
    problems = []
    for where, part in parts:
        if not hasattr(part, "check_settings"):
            sizes = None  # how many images it delivers is unknown: no size check
            continue
        try:
            got = asyncio.run(part.check_settings())
        except CameraError as err:
            problems.append(f"{where}: {err}")
            continue
        names += part.names
        if sizes is not None:
            sizes += got
    if problems:
        raise ConfigError("\n".join(problems))
    cal = config.calibration
    if cal is None or not sizes:
        return
    if cal.cameras:
        calibrated = [(f"calibration.cameras.{i}.intrinsics", c.intrinsics)
                      for i, c in enumerate(cal.cameras)]
    else:
        calibrated = [("calibration.left", cal.left)] + (
            [("calibration.right", cal.right)] if cal.right is not None else [])
    wrong = [f"camera: camera {name} delivers {w}x{h} images (Width x Height after the "
             f"settings) but {key} is calibrated for {k.width}x{k.height}: set camera.roi"
             for name, (w, h), (key, k) in zip(names, sizes, calibrated, strict=False)
             if (w, h) != (k.width, k.height)]
    if wrong:
        raise ConfigError("\n".join(wrong))


def run(args: argparse.Namespace) -> int:
    if args.snapshot is None:
        config = load_config(args.config)
    else:
        snapshot = Snapshot.load(args.snapshot)
        if str(snapshot.main) != str(args.config):
            raise ConfigError(f"{args.snapshot}: a snapshot of {snapshot.main}, not of "
                              f"{args.config}")
        config = load_config(snapshot.main, snapshot.files)
        print(f"snapshot {snapshot.digest()}")
    try:  # drivers validated and every recipe judged (vgripd.vision.readiness)
        daemon = Daemon(config)
    except ConfigError as err:  # a template file, driver options: name the file judged
        raise ConfigError(f"{args.config}: {err}") from None
    if not (args.running or args.no_camera):
        try:
            check_camera_settings(config)
        except ConfigError as err:
            raise ConfigError(f"{args.config}: {err}") from None
    problems = {number: problem for number, problem in daemon.recipe_problems.items()
                if not (args.untaught_ok and number in daemon.untaught)
                and not args.uncalibrated_ok}
    if problems:
        raise ConfigError("\n".join(
            f"{args.config}: not calibrated: {problem}" if number == 0 else
            f"{args.config}: recipe {daemon.recipe_label(number)}: not calibrated: {problem}"
            for number, problem in sorted(problems.items())))
    untaught = [f"warning: {args.config}: "
                + ("" if number == 0 else f"recipe {daemon.recipe_label(number)}: ")
                + f"not taught, its jobs end NOT_CALIBRATED: {daemon.recipe_problems[number]}"
                for number in sorted(daemon.untaught) if number not in problems]
    if args.uncalibrated_ok:
        untaught += [f"warning: {args.config}: "
                     + ("" if number == 0 else f"recipe {daemon.recipe_label(number)}: ")
                     + f"not calibrated, its jobs end NOT_CALIBRATED: {problem}"
                     for number, problem in sorted(daemon.recipe_problems.items())
                     if number not in daemon.untaught]
    findings = commission(config, Options(running=args.running, no_links_ok=args.no_links_ok))
    for number in config.recipe_numbers()[1:]:
        findings += [Finding(f.level, f"recipes.{number}.{f.key}",
                             f"recipe {daemon.recipe_label(number)}: {f.message}")
                     for f in check_scene(config.for_recipe(number))]
    errors = [f for f in findings if f.level == "ERROR"]
    others = [f"{f.level.lower()}: {args.config}: {f}" for f in findings if f.level != "ERROR"]
    others += [f"warning: {args.config}: {w}" for w in config.load_warnings] + untaught
    if errors:
        if others:
            print("\n".join(others))
        raise ConfigError("\n".join(f"{args.config}: {f}" for f in errors))
    links = ", ".join(daemon.rooms.links.links) or "none"
    recipes = "".join(f", recipe {daemon.recipe_label(n)}" for n in config.recipe_numbers()[1:])
    print(f"OK {args.config}: camera {config.camera.type}, links {links}, "
          f"output {config.output.vendor}, job timeout {config.daemon.job_timeout_s:g} s, "
          f"recording {'on' if config.record.enabled else 'off'}{recipes}")
    if others:
        print("\n".join(others))
    return 0
