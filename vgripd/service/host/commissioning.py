"""Commissioning checks of what the daemon will need around it (``vgripd check``, docs/daemon.md
"vgripd check"): at least one link, the listening ports free, the replay folder readable with
frames of the calibrated size. The scene (where the reference object lands in the images) is
``vgripd.vision.commissioning``; this module gathers both.

Levels: ERROR when the daemon could not work with this config here (no link at all; an address
that is not this machine's; a replay folder without frames); WARNING when it may (a port taken,
most likely by a vgripd that already runs; a privileged port).
"""

from __future__ import annotations

import errno
import ipaddress
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vgripd.config import Config
from vgripd.errors import CameraError, VgripError
from vgripd.imagefiles import list_frames, list_views
from vgripd.registry import CAMERAS, LINKS, load_class, validate_options
from vgripd.types import ImagePair
from vgripd.vision.commissioning import Finding


@dataclass(frozen=True)
class Options:
    """What ``vgripd check`` was told: ``running`` skips the port checks (the daemon holds
    them), ``no_links_ok`` accepts a config without links (for locate/replay only)."""

    running: bool = False
    no_links_ok: bool = False


def check_links(config: Config, options: Options) -> list[Finding]:
    """A daemon without links can be triggered by nothing and answer nobody."""
    if config.links:
        return []
    if options.no_links_ok:
        return [Finding("NOTE", "links", "no [[links]] (accepted: --no-links-ok)")]
    if config.status.enabled and getattr(config.status, "allow_trigger", False):
        return [Finding("WARNING", "links", "no [[links]]: only the web view's test trigger "
                        "(status.allow_trigger) can start a job, no robot can")]
    return [Finding("ERROR", "links", "no [[links]]: no robot or PLC can trigger a job or "
                    "receive a result; add one (config/example.toml) or pass --no-links-ok "
                    "for a config used only with locate/replay")]


def check_link_exposure(config: Config) -> list[Finding]:
    """What a link's own options open to the network: a link class may say so with
    ``exposure(options)``, a list of ``(level, field, message)`` (the opcua link warns when
    SecurityPolicy None is listed)."""
    findings: list[Finding] = []
    for i, section in enumerate(config.links):
        cls = load_class(LINKS, "link", section.type)
        exposure = getattr(cls, "exposure", None)
        if exposure is None:
            continue
        opts: Any = validate_options(cls, section, f"links.{i}")
        findings += [Finding(level, f"links[{i}].{field}", message)
                     for level, field, message in exposure(opts)]
    return findings


def check_web(config: Config) -> list[Finding]:
    """What the web view lets others do (docs/web.md, "Security model"): a test trigger that
    starts jobs from a browser, and read routes open to the network without the token."""
    st = config.status
    if not st.enabled:
        return []
    found = []
    if st.allow_trigger:
        found.append(Finding("WARNING", "status.allow_trigger", "the web view's test trigger "
                             "is on: whoever holds status.token can start jobs from a browser "
                             "(BUSY for the PLC meanwhile); turn it off for production"))
    if st.allow_config_edit:
        found.append(Finding("NOTE", "status.allow_config_edit", "the web view can reload the "
                             "config and save vision tuning to its include (with status.token); "
                             "every change is logged and listed on the page"))
    if st.public_read and st.host != "localhost" and not _loopback(st.host):
        found.append(Finding("WARNING", "status.public_read", f"status.public_read = true on "
                             f"{st.host}: anyone who reaches the port sees the cell's images, "
                             f"jobs, registers and (redacted) config without the token"))
    return found


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _listening(config: Config) -> list[tuple[str, str, int]]:
    """``(key, host, port)`` of every address the daemon listens on (port 0 excluded): server
    links (``type`` ending in ``_server``, ``mode = "server"``, or a class that says
    ``listens = True``) and the status endpoint."""
    found = []
    for i, section in enumerate(config.links):
        cls = load_class(LINKS, "link", section.type)
        opts: Any = validate_options(cls, section, f"links.{i}")
        host, port = getattr(opts, "host", None), getattr(opts, "port", None)
        server = (section.type.endswith("_server") or getattr(opts, "mode", None) == "server"
                  or getattr(cls, "listens", False))
        if server and isinstance(host, str) and isinstance(port, int) and port:
            found.append((f"links[{i}]", host, port))
    if config.status.enabled and config.status.port:
        found.append(("status", config.status.host, config.status.port))
    return found


def _bind(host: str, port: int) -> OSError | None:
    """Try listening on ``host:port`` the way asyncio's ``create_server`` does; the error."""
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM,
                                   flags=socket.AI_PASSIVE)
    except socket.gaierror as err:
        return OSError(errno.EADDRNOTAVAIL, f"cannot resolve {host!r}: {err.strerror}")
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(1)
        except OSError as err:
            return err
    return None


def _overlap(a: str, b: str) -> bool:
    wildcard = ("", "0.0.0.0", "::")
    return a == b or a in wildcard or b in wildcard


def check_ports(config: Config, options: Options) -> list[Finding]:
    """Every listening address free and bindable here, and no two on one port."""
    listening = _listening(config)
    if options.running and listening:
        return [Finding("NOTE", "links", "port checks skipped (--running: the daemon holds "
                        "them)")]
    findings: list[Finding] = []
    for k, (key, host, port) in enumerate(listening):
        for other, other_host, other_port in listening[:k]:
            if port == other_port and _overlap(host, other_host):
                findings.append(Finding("ERROR", f"{key}.port",
                                        f"{host}:{port} is also where {other} listens"))
    for key, host, port in listening:
        err = _bind(host, port)
        where = f"{key}.port" if key != "status" else "status.port"
        if err is None:
            continue
        if err.errno == errno.EADDRINUSE:
            findings.append(Finding("WARNING", where, f"{host}:{port} is in use: is vgripd "
                                    "already running? (if not, another program holds it and "
                                    f"{key} cannot start)"))
        elif err.errno == errno.EACCES:
            findings.append(Finding("WARNING", where, f"port {port} is privileged: the daemon "
                                    "needs CAP_NET_BIND_SERVICE (the systemd unit grants it) or "
                                    "a port above 1023"))
        else:
            findings.append(Finding("ERROR", f"{key}.host" if key != "status" else "status.host",
                                    f"cannot listen on {host}:{port}: "
                                    f"{err.strerror or err} (not an address of this machine?)"))
    return findings


def check_replay(config: Config) -> list[Finding]:
    """A replay camera's folder exists and holds frames (pairs for stereo) of the size the
    calibration says."""
    if config.camera.type != "replay":
        return []
    cls = load_class(CAMERAS, "camera", "replay")
    opts: Any = validate_options(cls, config.camera, "camera")
    folder = Path(opts.folder or ".")
    if not folder.is_dir():
        return [Finding("ERROR", "camera.folder",
                        f"replay folder {folder} does not exist (relative paths start at the "
                        f"working directory {Path.cwd()})")]
    if opts.globs is not None:
        return _check_replay_views(config, folder, opts.globs)
    try:
        frames = list_frames(folder, glob=opts.glob, left_glob=opts.left_glob,
                             right_glob=opts.right_glob)
    except CameraError as err:
        key = "camera.glob" if opts.glob is not None else "camera.left_glob"
        return [Finding("ERROR", key, str(err))]
    findings = []
    if opts.flange_poses is not None and not (folder / opts.flange_poses).is_file():
        findings.append(Finding("ERROR", "camera.flange_poses",
                                f"flange pose file {folder / opts.flange_poses} does not exist"))
    if config.calibration is not None:
        first = [("left", frames.left[0], config.calibration.left)]
        if frames.right is not None and config.calibration.right is not None:
            first.append(("right", frames.right[0], config.calibration.right))
        for side, path, intrinsics in first:
            size = _image_size(path)
            want = (intrinsics.width, intrinsics.height)
            if size is not None and size != want:
                findings.append(Finding(
                    "ERROR", f"calibration.{side}.width",
                    f"{path} is {size[0]}x{size[1]} but calibration.{side} is "
                    f"{want[0]}x{want[1]}: every job would end with CAMERA_ERROR"))
    return findings


def _check_replay_views(config: Config, folder: Path, globs: Sequence[str]) -> list[Finding]:
    """A multi-camera replay: one glob per camera of ``calibration.cameras``, frames for all,
    each camera's first image of its calibrated size."""
    cameras = config.calibration.cameras if config.calibration is not None else None
    if cameras is None:
        return [Finding("ERROR", "camera.globs", "one glob per camera needs the cameras in "
                                                 "calibration.cameras")]
    if len(globs) != len(cameras):
        return [Finding("ERROR", "camera.globs",
                        f"{len(globs)} globs for the {len(cameras)} cameras of "
                        "calibration.cameras (one pattern per camera, in their order)")]
    try:
        views = list_views(folder, globs)
    except CameraError as err:
        return [Finding("ERROR", "camera.globs", str(err))]
    findings = []
    for j, (files, cam) in enumerate(zip(views, cameras, strict=True)):
        size = _image_size(files[0])
        want = (cam.intrinsics.width, cam.intrinsics.height)
        if size is not None and size != want:
            findings.append(Finding(
                "ERROR", f"calibration.cameras.{j}.intrinsics.width",
                f"{files[0]} is {size[0]}x{size[1]} but camera {cam.name!r} is "
                f"{want[0]}x{want[1]}: every job would end with CAMERA_ERROR"))
    return findings


def _replay_paths(opts: Any) -> list[list[Path]]:
    """The files of each replay frame (all cameras, camera order), in frame order."""
    folder = Path(opts.folder or ".")
    if opts.globs is not None:
        views = list_views(folder, opts.globs)
        return [list(files) for files in zip(*views, strict=True)]
    frames = list_frames(folder, glob=opts.glob, left_glob=opts.left_glob,
                         right_glob=opts.right_glob)
    if frames.right is None:
        return [[path] for path in frames.left]
    return [[a, b] for a, b in zip(frames.left, frames.right, strict=True)]


def _image_size(path: Path) -> tuple[int, int] | None:
    import cv2  # heavy; only for a replay folder

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    return int(image.shape[1]), int(image.shape[0])


def check_scene(config: Config) -> list[Finding]:
    """Where the reference object lands in the images (``vgripd.vision.commissioning``)."""
    from vgripd.vision.commissioning import check_scene as scene_findings
    from vgripd.vision.pipeline import Pipeline  # heavy (OpenCV)

    try:
        pipeline = Pipeline(config)
    except VgripError:  # not calibrated or taught: vgripd check says so on its own
        return []
    return scene_findings(pipeline)


#: Replay frames ``check_samples`` runs through the pipeline.
SAMPLE_FRAMES = 3
#: Statuses of a job whose object was found and then stopped by a gate.
GATED = frozenset({"OUT_OF_LIMITS", "OUT_OF_WORKSPACE"})


def check_samples(config: Config, frames_wanted: int = SAMPLE_FRAMES) -> list[Finding]:
    """Run the first replay frames through the pipeline: when the object is found on none, the
    config cannot work on these images and the diagnosis names the key (polarity, working
    distance, the stereo transform's direction, contrast ...); when some fail, or the object is
    found but stopped by a limit (the samples may not show it at its taught place), a warning
    with the key (a hand-eye or reference that is off, the limits)."""
    if config.camera.type != "replay" or config.calibration is None:
        return []
    import cv2  # heavy; only for a replay folder

    from vgripd.vision.pipeline import diagnose

    cls = load_class(CAMERAS, "camera", "replay")
    opts: Any = validate_options(cls, config.camera, "camera")
    try:
        frames = _replay_paths(opts)
    except (CameraError, OSError):
        return []  # check_replay reports it
    failed: list[tuple[str, str, str, str]] = []
    tried = 0
    for paths in frames[:frames_wanted]:
        read = [cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) for path in paths]
        images = [image for image in read if image is not None]
        if len(images) < len(paths):
            continue  # check_replay and the job itself report unreadable files
        pair = ImagePair.of_views(images, 0, source=str(paths[0]))
        try:
            diagnosis = diagnose(config, pair)
        except VgripError:
            return []  # not calibrated or taught: vgripd check says so on its own
        tried += 1
        if diagnosis.causes:
            top = diagnosis.causes[0]
            failed.append((paths[0].name, diagnosis.status, top.key, top.reason))
    if not failed:
        return []
    name, status, key, reason = failed[0]
    # Found but gated (OUT_OF_LIMITS, OUT_OF_WORKSPACE): the samples may show the object away
    # from its taught place, so that is a warning; not found on any frame cannot work.
    found = all(s in GATED for _, s, _, _ in failed)
    if len(failed) == tried and not found:
        return [Finding("ERROR", key, f"no pose on any of the first {tried} replay frame(s) "
                                      f"({status} on {name}): {reason}")]
    return [Finding("WARNING", key, f"{len(failed)} of the first {tried} replay frames gave no "
                                    f"pose ({status} on {name}): {reason}")]


def check_conveyor(config: Config) -> list[Finding]:
    """The belt's motion blur: at ``conveyor.speed_mm_s`` the belt travels speed x exposure
    during one image; projected through the calibrated camera at the pick window's middle this
    is the smear in pixels, an ERROR above ``conveyor.max_blur_px`` (the features smear and
    the pose is taken at the exposure's middle, not its start). Needs ``camera.exposure_us``
    and a fixed camera; a robot-mounted one is a WARNING (it cannot watch a belt in motion)."""
    belt = config.conveyor
    if belt is None or config.calibration is None:
        return []
    from vgripd.geometry.belt import blur_px
    from vgripd.vision import scene

    if config.calibration.hand_eye.mounting != "fixed":
        return [Finding("WARNING", "calibration.hand_eye.mounting",
                        "conveyor: a robot-mounted camera moves with the robot; the belt's "
                        "images need a fixed camera (mounting = \"fixed\")")]
    exposure_us = config.camera.options().get("exposure_us")
    if not isinstance(exposure_us, int | float):
        return [Finding("WARNING", "camera.exposure_us",
                        "conveyor: set the exposure time so that the motion blur at "
                        f"{belt.speed_mm_s:g} mm/s can be judged")]
    try:
        left, _ = scene.camera_models(config)
        T_base_cam = scene.T_base_camera(config)
    except VgripError:
        return []  # not calibrated: vgripd check says so on its own
    travel = belt.speed_mm_s * exposure_us * 1e-6
    middle = sum(belt.window_mm) / 2
    point = [o + middle * d for o, d in zip(belt.origin_mm, belt.direction, strict=True)]
    px = blur_px(left.K, T_base_cam, point, belt.direction, travel)
    if px > belt.max_blur_px:
        limit_us = exposure_us * belt.max_blur_px / px
        return [Finding("ERROR", "camera.exposure_us",
                        f"conveyor: at {belt.speed_mm_s:g} mm/s the belt moves {travel:.3g} mm "
                        f"in {exposure_us:g} us, {px:.2f} px in the image (conveyor.max_blur_px "
                        f"{belt.max_blur_px:g}): expose at most {limit_us:.0f} us, or lower "
                        "the speed")]
    return []


def commission(config: Config, options: Options = Options()) -> list[Finding]:
    """Every commissioning check, ERRORs first."""
    findings = (check_scene(config) + check_conveyor(config) + check_replay(config)
                + check_links(config, options)
                + check_ports(config, options) + check_link_exposure(config) + check_web(config))
    if not any(f.level == "ERROR" for f in findings):  # the scene must hold before images
        findings += check_samples(config)
    order = {"ERROR": 0, "WARNING": 1, "NOTE": 2}
    return sorted(findings, key=lambda f: order[f.level])
