"""Taught references that a new hand-eye makes wrong (the order is rig -> hand-eye -> teach).

A reference's pose ``T_base_obj`` was measured through the hand-eye of its day: with another
hand-eye every found pose moves, the reference does not, and the offset handed to the robot is
off by the difference. So accepting a walked hand-eye from the web view first lists the taught
references (``[reference]``, ``[recipes.N.reference]`` with ``T_base_obj`` or ``points_mm``)
not measured with the new hand-eye (their ``[about] hand_eye`` fingerprint, none recorded
counting as another), and accepts only when told to **set them aside**: each included file
holding one is backed up and rewritten without the measured pose (``grip`` and other keys
stay, the fingerprints of the old measurement go). Jobs of those recipes then end
NOT_CALIBRATED (31) until the reference is taught again (the teaching page records the new
fingerprints). A reference in the main config file is never rewritten: the accept is refused,
naming it.
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from vgripd.config import MEASURED_REFERENCE_KEYS, measured_references, read_config_data
from vgripd.geometry.fingerprint import hand_eye_fingerprint
from vgripd.serialize import toml_from_dict

#: The ``[about]`` keys that record what a measurement was made with.
FINGERPRINTS = ("camera_model", "camera_model_parts", "hand_eye")


def stale_references(config_path: Path, calibration: dict[str, Any],
                     files: Mapping[str, bytes] | None = None) -> tuple[list[Path], bool]:
    """(the included files whose taught references were not measured with the hand-eye of
    ``calibration``, whether the main config file holds such a reference itself); ``files``:
    the config's bytes (a snapshot) instead of the disk."""
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    raw = (config_path.read_bytes() if files is None or str(config_path) not in files
           else files[str(config_path)])
    main = tomllib.loads(raw.decode("utf-8"))
    read_config_data(config_path, {}, included, files)
    now = hand_eye_fingerprint(calibration)
    stale = [Path(path) for path, part, about in included
             if any(True for _ in measured_references(part)) and about.get("hand_eye") != now]
    return stale, any(True for _ in measured_references(main))


def set_aside(text: str) -> str:
    """An included file's text without its references' measurements and without the
    fingerprints of that measurement in its ``[about]`` (``grip`` and the rest stay)."""
    data = tomllib.loads(text)
    for table in measured_references(data):
        for key in MEASURED_REFERENCE_KEYS:
            table.pop(key, None)
    about = data.get("about")
    if isinstance(about, dict):
        for key in FINGERPRINTS:
            about.pop(key, None)
        about["set_aside"] = "the measured reference was set aside when a new hand-eye was " \
                             "accepted: teach again"
    return toml_from_dict(data)
