"""Reading a config: the TOML files, ``include = [...]`` merged in (a key set twice is an
error naming both files), validation into ``Config``, and the check that the included
calibration files belong together (camera model -> hand-eye -> taught reference)."""

from __future__ import annotations

import tomllib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from vgripd.config.top import Config, config_from_dict
from vgripd.configsnapshot import include_path
from vgripd.errors import ConfigError


def _read_toml(p: Path, what: str, files: Mapping[str, bytes] | None = None) -> dict[str, Any]:
    try:
        if files is None:
            text = p.read_text(encoding="utf-8")
        elif str(p) in files:
            text = files[str(p)].decode("utf-8")
        else:
            raise ConfigError(f"{p}: {what}: not in the snapshot judged (read before it "
                              f"was named)")
    except OSError as err:
        raise ConfigError(f"{p}: cannot read {what}: {err.strerror}") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{p}: {what}: not UTF-8 text: {err}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from None


def _merge(into: dict[str, Any], owner: dict[str, str], data: dict[str, Any],
           source: str, prefix: str = "") -> None:
    """Deep-merge ``data`` into ``into``; a leaf set by two files is an error naming both."""
    for key, value in data.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and isinstance(into.get(key, {}), dict):
            _merge(into.setdefault(key, {}), owner, value, source, path + ".")
        elif key in into:
            raise ConfigError(f"{source}: {path} is already set in {owner.get(path, '?')}")
        else:
            into[key] = value
            owner[path] = source


def read_config_data(
    path: str | Path, owner: dict[str, str] | None = None,
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] | None = None,
    files: Mapping[str, bytes] | None = None,
) -> dict[str, Any]:
    """The config file as a dict, with its ``include = [...]`` files merged in.

    Included files (calibration results, the taught reference) are resolved relative to the
    including file, may not include further files, and may not set what another file sets.
    Their ``[about]`` tables (how a calibration was made) are dropped from the result; with
    ``included`` given, each included file is appended to it as (path, its tables, its
    ``[about]``), for the consistency check of :func:`check_calibration_files`. With ``files``
    (``vgripd.configsnapshot.Snapshot.files``) the bytes come from there, not from disk.
    """
    p = Path(path)
    data = _read_toml(p, "config", files)
    includes = data.pop("include", [])
    if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
        raise ConfigError(f"{p}: include: must be a list of file names")
    merged: dict[str, Any] = {}
    owner = {} if owner is None else owner
    _merge(merged, owner, data, str(p))
    for name in includes:
        inc = include_path(p, name)
        part = _read_toml(inc, f"included file (from {p}: include)", files)
        about = part.pop("about", None)
        if included is not None:
            included.append((str(inc), part, about if isinstance(about, dict) else {}))
        if "include" in part:
            raise ConfigError(f"{inc}: include: included files may not include others")
        _merge(merged, owner, part, str(inc))
    return merged


#: The calibrations in the order they build on each other (cameras -> hand-eye -> teach).
REDO_STEPS = ("hand_eye", "reference")


def load_config(path: str | Path, files: Mapping[str, bytes] | None = None,
                redo: str | None = None) -> Config:
    """Read and validate a TOML config file (with its includes); every failure is a
    ``ConfigError``. ``files``: the bytes to read instead of the disk (a judged snapshot).
    ``redo``: the step a command measures again (``hand_eye``: the walked hand-eye's plan and
    walk; ``reference``: teaching). The included files of that step and of the steps after it
    may then belong to another camera model or hand-eye (a warning, not an error): they are
    what the command replaces, and the hand-eye's plan needs only a rough one."""
    owner: dict[str, str] = {}
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    data = read_config_data(path, owner, included, files)
    config = config_from_dict(data, str(path), owner)
    config._load_warnings = check_calibration_files(data, owner, included, redo)
    return config


def _holder(owner: dict[str, str], prefixes: tuple[str, ...], default: str) -> str:
    """The file that set the first key under one of ``prefixes``."""
    for key, source in owner.items():
        if key.startswith(prefixes):
            return source
    return default


#: The keys of a taught reference that are its measurement (what ``vgripd teach`` measures).
MEASURED_REFERENCE_KEYS = ("T_base_obj", "points_mm")


def measured_references(part: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """The reference tables (``[reference]``, ``[recipes.N.reference]``) of one file's tables
    that hold a measurement; one set aside (``grip`` alone) is not taught."""
    tables = [part.get("reference")]
    recipes = part.get("recipes")
    if isinstance(recipes, dict):
        tables += [r.get("reference") for r in recipes.values() if isinstance(r, dict)]
    for table in tables:
        if isinstance(table, dict) and any(k in table for k in MEASURED_REFERENCE_KEYS):
            yield table


def check_calibration_files(
    data: dict[str, Any], owner: dict[str, str],
    included: list[tuple[str, dict[str, Any], dict[str, Any]]], redo: str | None = None,
) -> list[str]:
    """Whether the included hand-eye and taught-reference files were made with this config's
    camera model (and the reference with its hand-eye): the fingerprints their ``[about]``
    recorded (``vgripd.geometry.fingerprint``) against the config's own sections.

    A mismatch is a ConfigError naming both files; a file without a fingerprint (made before
    they were recorded) is a warning, returned, so that existing configs still load. A
    mismatch of a file that ``redo`` measures again (``load_config``) is a warning too.
    """
    from vgripd.geometry.fingerprint import camera_fingerprint, hand_eye_fingerprint

    if redo is not None and redo not in REDO_STEPS:
        raise ValueError(f"redo {redo!r}: one of {REDO_STEPS}")
    redone = set(REDO_STEPS[REDO_STEPS.index(redo):]) if redo else set()

    calibration = data.get("calibration")
    if not isinstance(calibration, dict):
        return []
    camera_parts = ("calibration.left", "calibration.right", "calibration.stereo",
                    "calibration.cameras")
    camera_file = _holder(owner, camera_parts, "the config")
    hand_eye_file = _holder(owner, ("calibration.hand_eye", "calibration.cameras"),
                            "the config")
    warnings: list[str] = []
    problems: list[str] = []
    order = "(the order is: cameras/rig -> hand-eye -> teach)"
    for path, part, about in included:
        cal_value = part.get("calibration")
        cal: dict[str, Any] = cal_value if isinstance(cal_value, dict) else {}
        holds_camera = any(k in cal for k in ("left", "right", "stereo", "cameras"))
        taught = any(True for _ in measured_references(part))
        holds_hand_eye = "hand_eye" in cal and not holds_camera
        if not (holds_hand_eye or taught):
            continue
        what = "taught reference" if taught else "hand-eye"
        found = warnings if ("reference" if taught else "hand_eye") in redone else problems
        recorded = about.get("camera_model")
        if recorded is None:
            warnings.append(f"{path}: the {what} records no camera model fingerprint ([about] "
                            f"camera_model; made before vgripd recorded one): cannot check that "
                            f"it was made with the camera model of {camera_file} {order}")
        else:
            parts = about.get("camera_model_parts") or ["left"]
            try:
                now = camera_fingerprint(calibration, parts)
            except (KeyError, TypeError, ValueError) as err:
                problems.append(f"{path}: [about] camera_model_parts {parts!r}: {err}")
                continue
            if now != recorded:
                again = ("teach it again" if taught else "calibrate the hand-eye again (then "
                         "teach again)")
                found.append(
                    f"{path}: the {what} was made with camera model {recorded}, but the camera "
                    f"model of this config ({camera_file}) is {now}: they do not belong "
                    f"together; {again} with {camera_file} {order}")
                continue
        if taught:
            recorded_he = about.get("hand_eye")
            if recorded_he is None:
                if recorded is not None:
                    warnings.append(f"{path}: the taught reference records no hand-eye "
                                    f"fingerprint ([about] hand_eye)")
            elif recorded_he != hand_eye_fingerprint(calibration):
                found.append(
                    f"{path}: the taught reference was measured with hand-eye {recorded_he}, "
                    f"but the hand-eye of this config ({hand_eye_file}) is "
                    f"{hand_eye_fingerprint(calibration)}: teach it again {order}")
    if problems:
        raise ConfigError("\n".join(problems))
    return warnings
