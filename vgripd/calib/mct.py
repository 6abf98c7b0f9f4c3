"""Camera Calibration Toolbox for Matlab (Bouguet, "MCT") result scripts: read and write.

The toolbox saves a single-camera calibration as ``Calib_Results.m``, a MATLAB script of
assignments (``fc = [ 657.46 ; 657.94 ];``, ``alpha_c = 0.0;``, ``nx = 640;`` ...). Its stereo
calibration is saved only as a binary ``Calib_Results_stereo.mat``; we read that directly
(MAT-file level 5, what MATLAB's ``save`` writes by default) and also read and write a script of
the ``Calib_Results.m`` style holding its variables (``fc_left``, ``cc_left``, ``kc_left``,
``alpha_c_left``, ``fc_right`` ..., ``om``, ``T``, ``R``, ``nx``, ``ny`` and their ``*_error``),
so a MATLAB ``run`` of it gives the toolbox's stereo workspace.

Conventions (evidence in docs/calibration-mct.md and tests/unit/test_calib_mct.py):

- ``kc = [k1; k2; p1; p2; k3]`` is OpenCV's distortion order; old 4-element ``kc`` means k3 = 0.
- ``alpha_c`` is a skew *coefficient*: our ``skew`` (``K[0, 1]``, px) = ``alpha_c * fc(1)``.
- Pixel origin: the toolbox documents (0, 0) as the centre of the top-left pixel, as OpenCV;
  its stored corners agree with OpenCV's ``cornerSubPix`` on the same images, so ``cc`` is
  copied unchanged (no 0.5 or 1 px shift).
- ``om``/``T``: ``X_R = rodrigues(om) X_L + T`` = our ``T_right_left``; ``T`` is in the unit of
  the board square ``dX`` (mm when the board was given in mm, as we need).
- ``*_error`` is about three standard deviations (the toolbox prints it as "±"); we keep one
  standard deviation, ``std = error / 3``, in the result file's ``[about]``, and write
  ``error = 3 std`` back.
"""

from __future__ import annotations

import math
import os
import re
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from vgripd.config import IntrinsicsConfig, PoseConfig, read_config_data
from vgripd.errors import CalibrationError, ConfigError
from vgripd.geometry.transforms import matrix_from_rotvec, rotvec_from_matrix
from vgripd.vision.scene import matrix_from_pose

SIGMAS_PER_ERROR = 3.0  # the toolbox's *_error is about 3 standard deviations
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "skew", "dist")
SIDES = ("left", "right")
_R_TOL = 1e-6  # om and R of a stereo script must agree to the printed precision


@dataclass(frozen=True)
class MctCamera:
    """One camera in our units and order.

    ``camera``: the keys of ``IntrinsicsConfig`` (fx, fy, cx, cy, skew px, dist [k1, k2, p1,
    p2, k3], width, height); ``std``: one standard deviation of fx, fy, cx, cy, skew, dist, or
    None when the file has no uncertainties.
    """

    camera: dict[str, Any]
    std: dict[str, Any] | None = None


@dataclass(frozen=True)
class MctStereo:
    """A stereo rig: both cameras and ``T_right_left`` (``X_R = R(rotvec) X_L + t``, mm)."""

    left: MctCamera
    right: MctCamera
    rotvec_rad: tuple[float, float, float]
    translation_mm: tuple[float, float, float]
    rotvec_std: tuple[float, float, float] | None = None
    translation_std: tuple[float, float, float] | None = None
    warnings: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# reading the MATLAB script

_ASSIGNMENT = re.compile(r"\s*([A-Za-z]\w*)\s*=\s*(.*\S)\s*", re.S)
_SEPARATORS = re.compile(r"[\s,;]+")


@dataclass(frozen=True)
class _Var:
    value: NDArray[np.float64] | None  # None: not a plain numeric literal
    line: int


def _statements(text: str) -> list[tuple[str, int]]:
    """``(statement, line)`` of a MATLAB script: split at ``;``, ``,`` and line ends outside
    brackets; comments (``%`` to the end of the line) dropped."""
    out: list[tuple[str, int]] = []
    depth, start, line = 0, 1, 1
    current: list[str] = []
    code = "\n".join(raw.split("%", 1)[0] for raw in text.splitlines())
    for ch in code + "\n":
        if ch in "[(":
            depth += 1
        elif ch in "])":
            depth = max(depth - 1, 0)
        if depth == 0 and ch in ";,\n":
            out.append(("".join(current), start))
            current = []
            start = line + (ch == "\n")
        else:
            current.append(ch)
        line += ch == "\n"
    return [(st, n) for st, n in out if st.strip()]


def _assignments(text: str) -> dict[str, _Var]:
    """``name -> value`` of every ``name = literal`` statement (the last one wins, as when the
    script runs)."""
    found: dict[str, _Var] = {}
    for statement, line in _statements(text):
        m = _ASSIGNMENT.fullmatch(statement)
        if m:
            found[m.group(1)] = _Var(_numbers(m.group(2).rstrip("'")), line)
    return found


def _numbers(literal: str) -> NDArray[np.float64] | None:
    body = literal.strip()
    if body.startswith("["):
        body = body[1:-1]
    parts = [p for p in _SEPARATORS.split(body) if p]
    try:
        return np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        return None


class _Script:
    """The variables of one script, with errors naming the file, line and variable."""

    def __init__(self, variables: dict[str, _Var], source: str) -> None:
        self.vars = variables
        self.source = source

    def has(self, name: str) -> bool:
        return name in self.vars

    def get(self, name: str, sizes: tuple[int, ...]) -> NDArray[np.float64]:
        var = self.vars.get(name)
        if var is None:
            raise CalibrationError(f"{self.source}: variable {name} missing")
        where = f"{self.source}:{var.line}: {name}" if var.line else f"{self.source}: {name}"
        if var.value is None:
            raise CalibrationError(f"{where}: not a numeric literal")
        if var.value.size not in sizes:
            want = " or ".join(str(s) for s in sizes)
            raise CalibrationError(f"{where}: expected {want} numbers, got {var.value.size}")
        if not np.isfinite(var.value).all():
            raise CalibrationError(f"{where}: not finite ({var.value.tolist()})")
        return var.value

    def optional(self, name: str, sizes: tuple[int, ...]) -> NDArray[np.float64] | None:
        return self.get(name, sizes) if self.has(name) else None


def _kc5(kc: NDArray[np.float64]) -> list[float]:
    """kc as 5 coefficients; toolbox versions before k3 wrote 4 (k3 = 0)."""
    return [float(v) for v in kc] + [0.0] * (5 - kc.size)


def _camera_from(script: _Script, suffix: str) -> MctCamera:
    fc = script.get("fc" + suffix, (2,))
    cc = script.get("cc" + suffix, (2,))
    alpha = float(script.get("alpha_c" + suffix, (1,))[0])
    kc = script.get("kc" + suffix, (4, 5))
    size = [int(script.get(n + suffix if script.has(n + suffix) else n, (1,))[0])
            for n in ("nx", "ny")]
    camera: dict[str, Any] = {
        "fx": float(fc[0]), "fy": float(fc[1]), "cx": float(cc[0]), "cy": float(cc[1]),
        "skew": alpha * float(fc[0]), "dist": _kc5(kc), "width": size[0], "height": size[1],
    }
    try:
        IntrinsicsConfig(**camera)
    except ValidationError as err:
        why = "; ".join(e["msg"] for e in err.errors())
        raise CalibrationError(f"{script.source}: camera{suffix or ''}: {why}") from None
    errors = [script.optional(f"{n}{suffix}_error", s) for n, s in
              (("fc", (2,)), ("cc", (2,)), ("alpha_c", (1,)), ("kc", (4, 5)))]
    std = None
    if all(e is not None for e in errors):
        fce, cce, ae, kce = (np.asarray(e) / SIGMAS_PER_ERROR for e in errors)
        std = {"fx": float(fce[0]), "fy": float(fce[1]), "cx": float(cce[0]),
               "cy": float(cce[1]), "skew": float(ae[0]) * float(fc[0]), "dist": _kc5(kce)}
    return MctCamera(camera, std)


def parse_mct(text: str, source: str) -> MctCamera | MctStereo:
    """A toolbox result script's camera (``fc``, ...) or stereo rig (``fc_left``, ..., ``om``,
    ``T``). CalibrationError names ``source``, the line and the variable that is wrong."""
    return _result_from(_Script(_assignments(text), source))


def _result_from(script: _Script) -> MctCamera | MctStereo:
    source = script.source
    if not script.has("fc") and not script.has("fc_left"):
        raise CalibrationError(
            f"{source}: not a Camera Calibration Toolbox result (no 'fc = [...]' or "
            "'fc_left = [...]' assignment)")
    if not script.has("fc_left"):
        return _camera_from(script, "")
    left, right = (_camera_from(script, "_" + side) for side in SIDES)
    om = script.get("om", (3,))
    t = script.get("T", (3,))
    R = script.optional("R", (9,))
    if R is not None:  # MATLAB writes a matrix row by row: [r11 r12 r13 ; r21 ...]
        gap = float(np.abs(R.reshape(3, 3) - matrix_from_rotvec(om)).max())
        if gap > _R_TOL:
            raise CalibrationError(f"{source}: R disagrees with rodrigues(om) by {gap:.2g}")
    om_e, t_e = script.optional("om_error", (3,)), script.optional("T_error", (3,))
    warnings = []
    baseline = float(np.linalg.norm(t))
    if baseline < 5.0:
        warnings.append(
            f"{source}: baseline |T| = {baseline:.4g}; the toolbox gives T in the unit of the "
            "board square dX and vgripd needs mm (was dX given in m or cm?)")
    return MctStereo(
        left, right, _vec3(om), _vec3(t),
        None if om_e is None else _vec3(om_e / SIGMAS_PER_ERROR),
        None if t_e is None else _vec3(t_e / SIGMAS_PER_ERROR), warnings)


def _vec3(a: Any) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in np.asarray(a, dtype=float).reshape(3))
    return x, y, z


def read_mct(path: str | Path) -> MctCamera | MctStereo:
    """Read ``Calib_Results.m``, a stereo script (see :func:`parse_mct`) or the toolbox's
    binary ``Calib_Results.mat`` / ``Calib_Results_stereo.mat`` (same variables)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise CalibrationError(f"{p}: cannot read: {err.strerror}") from None
    if raw.startswith(b"MATLAB"):
        return _result_from(_Script(_mat_variables(raw, str(p)), str(p)))
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # MATLAB on Windows writes comments in the local code page
    if "\x00" in text:
        raise CalibrationError(f"{p}: not a text file (not a toolbox result script)")
    return parse_mct(text, str(p))


# MAT-file level 5 (MATLAB 5 .. 7.2 "save" without -v7.3): a 128-byte header, then tagged
# elements; a variable is an miMATRIX (flags, dims, name, data), possibly zlib-compressed.
_MI_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8",
             12: "i8", 13: "u8"}
_MI_MATRIX, _MI_COMPRESSED = 14, 15
_NUMERIC_CLASSES = range(6, 16)  # mxDOUBLE .. mxUINT64


def _mat_variables(raw: bytes, source: str) -> dict[str, _Var]:
    """The numeric variables of a level-5 MAT-file as flat arrays in row-major order (so a
    3x3 ``R`` reads as the script writes it); other classes (strings, cells) are skipped."""
    if len(raw) < 128 or raw[124:126] not in (b"\x00\x01", b"\x01\x00"):
        raise CalibrationError(
            f"{source}: not a level-5 MAT-file (a -v7.3 HDF5 file? save with -v7)")
    order = "<" if raw[126:128] == b"IM" else ">"
    found: dict[str, _Var] = {}
    try:
        pos = 128
        while pos + 8 <= len(raw):
            kind, size, data, pos = _mat_element(raw, pos, order)
            if kind == _MI_COMPRESSED:
                kind, size, data, _ = _mat_element(zlib.decompress(data), 0, order)
            if kind == _MI_MATRIX:
                named = _mat_matrix(data, order)
                if named is not None:
                    found[named[0]] = _Var(named[1], 0)
    except (ValueError, zlib.error, IndexError) as err:
        raise CalibrationError(f"{source}: corrupt MAT-file ({err})") from None
    return found


def _mat_element(buf: bytes, pos: int, order: str) -> tuple[int, int, bytes, int]:
    """``(type, size, data, next position)`` of the element at ``pos``."""
    kind, size = struct.unpack_from(order + "II", buf, pos)
    if kind >> 16:  # small element: size in the upper half, data in the tag's second word
        size, kind = kind >> 16, kind & 0xFFFF
        return kind, size, buf[pos + 4:pos + 4 + size], pos + 8
    end = pos + 8 + size
    if end > len(buf):
        raise ValueError(f"element at byte {pos} runs past the end")
    step = size if kind == _MI_COMPRESSED else (size + 7) // 8 * 8
    return kind, size, buf[pos + 8:end], pos + 8 + step


def _mat_matrix(data: bytes, order: str) -> tuple[str, NDArray[np.float64]] | None:
    _, _, flags, pos = _mat_element(data, 0, order)
    _, _, dims_raw, pos = _mat_element(data, pos, order)
    _, _, name, pos = _mat_element(data, pos, order)
    mx_class = struct.unpack_from(order + "I", flags)[0] & 0xFF
    if mx_class not in _NUMERIC_CLASSES:
        return None
    dims = np.frombuffer(dims_raw, order + "i4")
    kind, _, real, _ = _mat_element(data, pos, order)
    values = np.frombuffer(real, order + _MI_TYPES[kind]).astype(np.float64)
    matrix = values.reshape(tuple(int(d) for d in dims), order="F")  # MATLAB is column-major
    return name.decode("ascii"), matrix.ravel()


# ---------------------------------------------------------------------------------------------
# our result files

def _about_std(std: Mapping[str, Any] | None) -> dict[str, Any]:
    return {} if std is None else {"std": dict(std)}


def result_tables(result: MctCamera | MctStereo, source: str, camera: str = "left",
                  ) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(sections, about)`` of our result file for an imported toolbox result.

    A single camera goes to ``[calibration.<camera>]``; a rig to ``[calibration.left]``,
    ``[calibration.right]`` and ``[calibration.stereo.T_right_left]``. ``[about]`` keeps the
    standard deviations (``std``, or ``left_std``, ``right_std``, ``rotvec_std``,
    ``translation_std``) = toolbox error / 3.
    """
    about: dict[str, Any] = {
        "command": "vgripd calibrate import-mct", "source": source,
        "std_note": "std = one standard deviation = toolbox *_error / 3",
    }
    if isinstance(result, MctCamera):
        about.update(_about_std(result.std))
        return {"calibration": {camera: result.camera}}, about
    sections = {"calibration": {
        "left": result.left.camera, "right": result.right.camera,
        "stereo": {"T_right_left": {"translation_mm": list(result.translation_mm),
                                    "rotvec_rad": list(result.rotvec_rad)}}}}
    for side, cam in (("left", result.left), ("right", result.right)):
        if cam.std is not None:
            about[f"{side}_std"] = cam.std
    if result.rotvec_std is not None:
        about["rotvec_std"] = list(result.rotvec_std)
    if result.translation_std is not None:
        about["translation_std"] = list(result.translation_std)
    return sections, about


def from_result_file(path: str | Path, camera: str | None = None) -> MctCamera | MctStereo:
    """A camera or rig from our result file or a config (with its includes).

    ``camera`` picks one camera of a rig; None exports the rig when the file has one. The
    standard deviations come from the result file's ``[about]`` (a config's includes lose
    theirs, so exporting a config writes no ``*_error``).
    """
    try:
        data = read_config_data(path)
    except ConfigError as err:
        raise CalibrationError(str(err)) from None
    about = data.get("about", {})
    calib = data.get("calibration")
    if not isinstance(calib, dict) or not isinstance(calib.get("left", calib.get("right")), dict):
        raise CalibrationError(f"{path}: no [calibration.left] or [calibration.right] section")

    def cam(side: str) -> MctCamera:
        table = calib.get(side)
        if not isinstance(table, dict):
            raise CalibrationError(f"{path}: no [calibration.{side}] section")
        try:
            model = IntrinsicsConfig(**table)
        except (ValidationError, TypeError) as err:
            raise CalibrationError(f"{path}: calibration.{side}: {err}") from None
        std = _camera_std(about, side)
        return MctCamera(model.model_dump(mode="json"),
                         std if _std_complete(std) else None)

    stereo = calib.get("stereo")
    if camera is not None:
        return cam(camera)
    if not (isinstance(stereo, dict) and "right" in calib):
        only = "left" if "left" in calib else "right"
        return cam(only)
    try:
        pose = PoseConfig(**stereo.get("T_right_left", {}))
    except (ValidationError, TypeError) as err:
        raise CalibrationError(f"{path}: calibration.stereo.T_right_left: {err}") from None
    T = matrix_from_pose(pose)
    nested = about.get("std") if isinstance(about.get("std"), Mapping) else {}
    rv_std = about.get("rotvec_std", nested.get("rotvec_rad"))
    t_std = about.get("translation_std", nested.get("translation_mm"))
    return MctStereo(cam("left"), cam("right"),
                     _vec3(rotvec_from_matrix(T[:3, :3])), _vec3(T[:3, 3]),
                     None if rv_std is None else _vec3(rv_std),
                     None if t_std is None else _vec3(t_std))


def _camera_std(about: Mapping[str, Any], side: str) -> Any:
    """One camera's standard deviations in any layout our files use: ``[about.std.<side>]``
    (``calibrate stereo``), ``<side>_std`` (``import-mct`` of a rig) or ``[about.std]`` itself
    (one camera: ``calibrate intrinsics``, ``import-mct`` of a camera)."""
    std = about.get("std")
    if isinstance(std, Mapping) and isinstance(std.get(side), Mapping):
        return std[side]
    if f"{side}_std" in about:
        return about[f"{side}_std"]
    return std


def _std_complete(std: Any) -> bool:
    return isinstance(std, Mapping) and all(k in std for k in INTRINSIC_KEYS)


# ---------------------------------------------------------------------------------------------
# writing the MATLAB script

def _col(values: Any) -> str:
    """A MATLAB column vector as the toolbox prints it (15 decimals)."""
    return "[ " + " ; ".join(_num(v) for v in values) + " ]"


def _num(v: float) -> str:
    if not math.isfinite(v):
        raise CalibrationError(f"refusing to write non-finite value {v}")
    return f"{v:.15f}"


def _camera_lines(c: MctCamera, suffix: str) -> list[str]:
    cam = c.camera
    fx = float(cam["fx"])
    lines = [
        "%-- Focal length:", f"fc{suffix} = {_col([cam['fx'], cam['fy']])};", "",
        "%-- Principal point:", f"cc{suffix} = {_col([cam['cx'], cam['cy']])};", "",
        "%-- Skew coefficient (skew angle coefficient; K(1,2) = alpha_c * fc(1)):",
        f"alpha_c{suffix} = {_num(float(cam['skew']) / fx)};", "",
        "%-- Distortion coefficients [k1 k2 p1 p2 k3]:",
        f"kc{suffix} = {_col(cam['dist'])};", "",
    ]
    if c.std is not None:
        e = {k: np.asarray(v, dtype=float) * SIGMAS_PER_ERROR for k, v in c.std.items()}
        lines += [
            "%-- Focal length uncertainty (about 3 standard deviations):",
            f"fc{suffix}_error = {_col([e['fx'], e['fy']])};", "",
            "%-- Principal point uncertainty:",
            f"cc{suffix}_error = {_col([e['cx'], e['cy']])};", "",
            "%-- Skew coefficient uncertainty:",
            f"alpha_c{suffix}_error = {_num(float(e['skew']) / fx)};", "",
            "%-- Distortion coefficients uncertainty:",
            f"kc{suffix}_error = {_col(e['dist'])};", "",
        ]
    return lines


_HEADER = [
    "% Camera Calibration Toolbox for Matlab: calibration parameters, written by vgripd",
    "%",
    "% A script of assignments in the toolbox's own variable names; run it in MATLAB to get them.",
    "% Pixel coordinates: (0,0) is the centre of the upper left pixel (the toolbox's convention).",
    "% *_error: about three standard deviations (as the toolbox reports).",
    "",
    "",
]


def mct_text(result: MctCamera | MctStereo) -> str:
    """The toolbox script for a camera (Calib_Results.m layout) or a rig (the stereo .mat's
    variables in the same layout)."""
    lines = list(_HEADER)
    if isinstance(result, MctCamera):
        lines += _camera_lines(result, "")
        cam = result.camera
    else:
        R = matrix_from_rotvec(np.asarray(result.rotvec_rad))
        lines += [
            "%-- Rotation vector and translation (left to right): X_R = rodrigues(om) * X_L + T",
            f"om = {_col(result.rotvec_rad)};",
            f"T = {_col(result.translation_mm)};", "",
            "%-- Rotation matrix: R = rodrigues(om)",
            "R = [ " + " ; ".join(" ".join(_num(v) for v in row) for row in R) + " ];", "",
        ]
        if result.rotvec_std is not None and result.translation_std is not None:
            lines += [
                "%-- Rotation vector and translation uncertainty:",
                f"om_error = {_col(np.asarray(result.rotvec_std) * SIGMAS_PER_ERROR)};",
                f"T_error = {_col(np.asarray(result.translation_std) * SIGMAS_PER_ERROR)};",
                "",
            ]
        for side, c in (("left", result.left), ("right", result.right)):
            lines += [f"%-- Intrinsic parameters of {side} camera:", ""]
            lines += _camera_lines(c, "_" + side)
        cam = result.left.camera
        if (result.right.camera["width"], result.right.camera["height"]) != (
                cam["width"], cam["height"]):
            r = result.right.camera
            lines += ["%-- Image size of the right camera:",
                      f"nx_right = {int(r['width'])};", f"ny_right = {int(r['height'])};", ""]
    lines += ["%-- Image size:", f"nx = {int(cam['width'])};", f"ny = {int(cam['height'])};", ""]
    return "\n".join(lines) + "\n"


def write_mct(path: str | Path, result: MctCamera | MctStereo) -> Path:
    """Write :func:`mct_text` atomically; CalibrationError names the path on failure."""
    p = Path(path)
    text = mct_text(result)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        raise CalibrationError(f"{p}: cannot write: {err.strerror}") from None
    return p
