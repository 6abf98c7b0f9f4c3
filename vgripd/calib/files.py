"""Calibration result files: small TOML fragments that a config pulls in with ``include``.

A result file holds the config sections it fills (``[calibration.left]``,
``[calibration.stereo.T_right_left]``, ``[calibration.hand_eye]``, ``[reference]``) plus an
``[about]`` table (how it was made: command, date, RMS, standard deviations; the camera model's
fingerprint, ``vgripd.geometry.fingerprint``) that the config loader checks and drops. Floats are
written with ``repr``, so a value round-trips exactly.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from vgripd.errors import CalibrationError
from vgripd.serialize import jsonable, toml_from_dict

Table = Mapping[str, Any]


def _finite(value: Any, where: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise CalibrationError(f"{where}: refusing to write non-finite value {value}")
    if isinstance(value, Mapping):
        for k, v in value.items():
            _finite(v, f"{where}.{k}" if where else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _finite(v, f"{where}[{i}]")


def dumps(data: Table, header: str = "") -> str:
    """TOML text for nested JSON-like data (numpy allowed), ``header`` as ``#`` comments."""
    plain = jsonable(data)
    _finite(plain, "")
    head = "".join(f"# {h}".rstrip() + "\n" for h in header.splitlines())
    return head + ("\n" if head else "") + toml_from_dict(plain)


def write_result(path: str | Path, sections: Table, about: Table, header: str = "") -> Path:
    """Write a result file atomically: ``sections`` (config tables) plus ``[about]``.

    ``about`` gets ``written`` (UTC, ISO 8601) added. The file is written beside its final name
    and renamed, so a crash never leaves half a calibration behind.
    """
    p = Path(path)
    if "about" in sections:
        raise CalibrationError("result sections must not contain 'about'")
    stamp = _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()
    body = dict(sections)
    about = dict(about)
    calibration = sections.get("calibration")
    if isinstance(calibration, Mapping) and "camera_model" not in about:
        from vgripd.geometry.fingerprint import camera_about, camera_parts

        plain = jsonable(calibration)
        try:  # a calibration of the cameras records the model it defines
            if camera_parts(plain):
                about.update(camera_about(plain))
        except (KeyError, TypeError, ValueError):
            pass  # incomplete sections: no fingerprint (dumps names a non-finite value)
    body["about"] = {**about, "written": stamp}
    text = dumps(body, header)
    tmp = p.with_name(p.name + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        raise CalibrationError(f"{p}: cannot write result: {err.strerror}") from None
    return p


def pose_table(T: Any) -> dict[str, Any]:
    """A 4x4 transform as a config pose table (``translation_mm`` + ``rotvec_rad``)."""
    import numpy as np

    from vgripd.geometry.transforms import rotvec_from_matrix

    M = np.asarray(T, dtype=float)
    return {
        "translation_mm": [float(x) for x in M[:3, 3]],
        "rotvec_rad": [float(x) for x in rotvec_from_matrix(M[:3, :3])],
    }
