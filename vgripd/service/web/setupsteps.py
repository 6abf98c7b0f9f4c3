"""The guided setup's server-side steps, apart from the routes (``setup.py``): the steps and
their order, what the page keeps between visits (resumable), ``vgripd check``'s findings sorted
to the step they belong to, and the config edits each step makes through the one config
transaction (``vgripd.service.host.configtxn``).

Where a step writes: the include that sets the keys now (as the tuning save and teaching find
theirs), else the include of the layout ``vgripd init`` writes (``rig.toml`` for the cameras'
calibration, ``handeye.toml``, ``cell.toml`` for the object, ``reference.toml``). The main file
is never written.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vgripd.config import read_config_data
from vgripd.configsnapshot import Snapshot
from vgripd.geometry.fingerprint import camera_about
from vgripd.serialize import toml_from_dict
from vgripd.service.host.configtxn import Edit, EditRefused

#: (id, title) of each step, in the order of a commissioning.
STEPS = (("cameras", "Cameras"), ("calibration", "Calibration"), ("handeye", "Hand-eye"),
         ("object", "Object"), ("link", "Link"), ("pick", "Test pick"))
STEP_IDS = tuple(s for s, _ in STEPS)
#: What a check finding talks about, tried in this order: the first step whose pattern matches
#: the finding's text gets it (the test pick gets the rest: it needs everything).
STEP_PATTERNS = (
    ("handeye", re.compile(r"hand_eye|hand-eye|T_base_camera|T_flange_camera")),
    ("calibration", re.compile(r"calibration|camera model|not calibrated|epipolar")),
    ("object", re.compile(r"\bobject\b|object\.|reference|vision\.|not taught|feature")),
    ("link", re.compile(r"links|status\.|\bport\b|link")),
    ("cameras", re.compile(r"\bcamera\b|camera\.")),
)
#: Where a step writes when no include sets its keys yet (``vgripd init``'s layout).
DEFAULT_INCLUDES = {"calibration.left.": "rig.toml", "calibration.hand_eye.": "handeye.toml",
                    "object.": "cell.toml", "reference.": "reference.toml",
                    "camera.": "camera.toml", "links": "links.toml"}
#: The board of the learning cell, and the one offered otherwise.
DEFAULT_BOARD = "chessboard:9x6:30"


@dataclass(frozen=True)
class CheckFinding:
    """One line of ``vgripd check``: level, the step it belongs to, the text."""

    level: str
    step: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {"level": self.level, "step": self.step, "message": self.message}


def step_of(message: str) -> str:
    for step, pattern in STEP_PATTERNS:
        if pattern.search(message):
            return step
    return "pick"


def parse_check(rc: int, out: str, err: str, config_path: str) -> tuple[bool, list[CheckFinding]]:
    """``vgripd check``'s outcome (passed, findings) from its exit code and output: an error
    line per problem on stderr (exit 78), ``warning:``/``note:`` lines after the OK line."""
    findings = []
    prefix = f"{config_path}: "
    for line in out.splitlines():
        level, _, text = line.partition(": ")
        if level in ("warning", "note", "error") and text:
            text = text.removeprefix(prefix)
            findings.append(CheckFinding(level.upper(), step_of(text), text))
    if rc != 0:
        body = err.strip().removeprefix("vgripd: config error: ").removeprefix("vgripd: ")
        for line in body.splitlines():
            text = line.strip().removeprefix(prefix)
            if text:
                findings.append(CheckFinding("ERROR", step_of(text), text))
        if not body:
            findings.append(CheckFinding("ERROR", "pick", f"vgripd check exited with {rc}"))
    return rc == 0, findings


# --- resumable progress ---------------------------------------------------------------------

def load_progress(path: Path) -> dict[str, Any]:
    """The page's progress file (steps done, the board, an accepted calibration); empty when
    there is none or it cannot be read (the page starts over, nothing else depends on it)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {"done": {}}
    if not isinstance(data, dict) or not isinstance(data.get("done"), dict):
        return {"done": {}}
    return data


def dump_progress(data: Mapping[str, Any]) -> bytes:
    return (json.dumps(data, indent=1, sort_keys=True) + "\n").encode()


# --- where a step writes --------------------------------------------------------------------

def include_for(snapshot: Snapshot, prefix: str) -> Path:
    """The include a step writes the keys under ``prefix`` to: the one file setting them now,
    else the layout's file of that name among the includes; ``EditRefused`` naming why not."""
    owner: dict[str, str] = {}
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    read_config_data(snapshot.main, owner, included, snapshot.files)
    holders = {src for key, src in owner.items() if key.startswith(prefix)}
    main = str(snapshot.main)
    if holders and main in holders:
        raise EditRefused(f"{main}: {prefix.rstrip('.')} is set in the main config file: the "
                          "setup writes only the includes (vgripd init lays a config out so)")
    if len(holders) == 1:
        return Path(next(iter(holders)))
    if len(holders) > 1:
        raise EditRefused(f"{prefix.rstrip('.')} is set in several files "
                          f"({', '.join(sorted(holders))})")
    name = DEFAULT_INCLUDES[prefix]
    for path, _, _ in included:
        if Path(path).name == name:
            return Path(path)
    raise EditRefused(f"{main}: no include holds {prefix.rstrip('.')} and none is named {name} "
                      "(vgripd init lays out rig.toml, handeye.toml, cell.toml, reference.toml)")


def state_dir(config_path: Path, files: Mapping[str, bytes] | None = None) -> Path | None:
    """The folder of the config's writable includes (the first one's), None without any."""
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    read_config_data(config_path, None, included, files)
    return Path(included[0][0]).parent if included else None


# --- the calibration's command and its result ------------------------------------------------

#: What the calibration step may be asked for: the usual command for the cameras captured, or
#: ``calibrate cameras`` (each camera relative to the first) for a pair too.
CALIBRATION_KINDS = ("auto", "cameras")


def calibration_command(names: list[str], folder: Path, board: str, out: Path,
                        kind: str = "auto") -> list[str]:
    """The ``vgripd calibrate`` arguments for the sets kept in ``folder`` (``NAME_NNN.png``
    per camera): one camera ``intrinsics``, the pair ``left``/``right`` ``stereo`` (or
    ``cameras`` with ``kind = "cameras"``), any other cameras ``cameras`` (one ``--camera
    NAME=GLOB`` each)."""
    if not names:
        raise ValueError("no camera in the capture")
    if kind not in CALIBRATION_KINDS:
        raise ValueError(f"kind: one of {', '.join(CALIBRATION_KINDS)}, got {kind!r}")
    if len(names) == 1:
        return ["calibrate", "intrinsics", "--images", str(folder / f"{names[0]}_*.png"),
                "--board", board, "-o", str(out)]
    if names == ["left", "right"] and kind == "auto":
        return ["calibrate", "stereo", "--left", str(folder / "left_*.png"),
                "--right", str(folder / "right_*.png"), "--board", board, "-o", str(out)]
    args = ["calibrate", "cameras"]
    for name in names:
        args += ["--camera", f"{name}={folder / f'{name}_*.png'}"]
    return [*args, "--board", board, "-o", str(out)]


def read_result(text: str) -> dict[str, Any]:
    """What the page shows of a ``calibrate intrinsics``/``stereo``/``cameras`` result: the
    figures of its ``[about]`` (RMS, standard deviations, per set, rejected, warnings) and the
    fitted values; ``kind`` says which, ``usable`` whether it holds a calibration a config can
    take (a ``cameras`` result placed in no base frame holds only ``[about]``)."""
    data = tomllib.loads(text)
    about = data.get("about", {})
    cal = data.get("calibration", {})
    out: dict[str, Any] = {
        "rms_px": about.get("rms_px"), "std": about.get("std"),
        "rejected": about.get("rejected"), "warnings": about.get("warnings"),
        "model_choice": about.get("model_choice")}
    if "cameras" in about or "cameras" in cal:
        out.update(kind="cameras", usable="cameras" in cal, sets=about.get("sets"),
                   reference=about.get("reference"), base_frame=about.get("base_frame"),
                   cameras=about.get("cameras"), pairs=about.get("pairs"))
    elif "stereo" in cal:
        out.update(kind="stereo", usable=True, pairs_used=about.get("pairs_used"),
                   per_pair=about.get("per_pair"), epipolar_px=about.get("epipolar_px"),
                   left=cal.get("left"), right=cal.get("right"),
                   T_right_left=cal["stereo"].get("T_right_left"))
    else:
        camera = next((cal[k] for k in ("left", "right") if k in cal), None)
        out.update(kind="intrinsics", usable=camera is not None,
                   images_used=about.get("images_used"), per_pair=about.get("per_image"),
                   std_model=about.get("std_model"), left=camera)
    return out


# --- the edits ------------------------------------------------------------------------------

def placed_cameras(result_text: str, T_base_reference: Mapping[str, Any] | None
                   ) -> dict[str, Any]:
    """The ``[calibration]`` of a ``calibrate cameras`` result: as it is when the command placed
    the cameras in the base frame; else every camera placed by the reference camera's pose in
    the base frame (``T_base_reference``, a pose table; required then): ``T_base_camera =
    T_base_reference @ T_reference_camera``, each fixed, with the intrinsics of ``[about]``.
    ``EditRefused`` naming what is missing."""
    data = tomllib.loads(result_text)
    if data.get("calibration", {}).get("cameras"):
        return dict(data["calibration"])
    about = data.get("about", {})
    cameras = about.get("cameras")
    if not isinstance(cameras, list) or not cameras:
        raise EditRefused("the calibration result has neither [[calibration.cameras]] nor "
                          "[about] cameras")
    if T_base_reference is None:
        raise EditRefused(f"calibration.cameras: the cameras are placed relative to "
                          f"{about.get('reference')}: its pose in the base frame is needed")
    import numpy as np

    from vgripd.calib.files import pose_table
    from vgripd.geometry.transforms import make_transform, matrix_from_rotvec

    def matrix(pose: Mapping[str, Any]) -> Any:
        return make_transform(matrix_from_rotvec(pose.get("rotvec_rad") or (0.0, 0.0, 0.0)),
                              pose["translation_mm"])

    T_base_ref = matrix(T_base_reference)
    out = []
    for k, cam in enumerate(cameras):
        if not isinstance(cam, dict) or not {"name", "intrinsics", "T_reference_camera"} <= set(
                cam):
            raise EditRefused(f"the calibration result's [about] cameras[{k}]: no name, "
                              "intrinsics and T_reference_camera")
        T = np.asarray(T_base_ref @ matrix(cam["T_reference_camera"]), np.float64)
        out.append({"name": cam["name"], "intrinsics": cam["intrinsics"], "mounting": "fixed",
                    "T_base_camera": pose_table(T)})
    return {"cameras": out}


def cameras_edit(calibration: dict[str, Any]) -> Edit:
    """N cameras placed in the base frame (``[[calibration.cameras]]``) into the calibration's
    include, as one write with the single-camera hand-eye taken out of its include (each camera
    carries its pose; the first camera's is the cell's hand-eye), so no old pose contradicts
    them."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        texts: dict[Path, dict[str, Any]] = {}

        def data(path: Path) -> dict[str, Any]:
            if path not in texts:
                texts[path] = tomllib.loads(snapshot.text(path))
            return texts[path]

        target = include_for(snapshot, "calibration.left.")
        data(target)["calibration"] = dict(calibration)
        try:
            hand_eye = include_for(snapshot, "calibration.hand_eye.")
        except EditRefused:
            hand_eye = None  # no include holds or is laid out for it: nothing to take out
        if hand_eye is not None and hand_eye != target:
            part = data(hand_eye)
            part.get("calibration", {}).pop("hand_eye", None)
            if not part.get("calibration"):
                part.pop("calibration", None)
            about = part.get("about", {})
            for key in ("camera_model", "camera_model_parts"):
                about.pop(key, None)
            if not about:
                part.pop("about", None)
        return {p: snapshot.encoded(p, toml_from_dict(d)) for p, d in texts.items()}
    return edit


def pending_view(text: str | None) -> dict[str, Any] | None:
    """What the hand-eye step shows of an accepted calibration waiting for it: its kind, and
    for a ``calibrate cameras`` result the reference camera, the cameras and whether the
    command placed them in the base frame already."""
    if text is None:
        return None
    result = read_result(text)
    out: dict[str, Any] = {"kind": result["kind"]}
    if result["kind"] == "cameras":
        out.update(reference=result.get("reference"), placed=bool(result.get("usable")),
                   cameras=[c.get("name") for c in result.get("cameras") or []])
    return out


def rig_sections(rig_text: str) -> dict[str, Any]:
    """``[calibration]`` of a ``vgripd calibrate stereo`` result (left, right, stereo)."""
    calibration = dict(tomllib.loads(rig_text).get("calibration", {}))
    calibration.pop("hand_eye", None)
    if "left" not in calibration:
        raise EditRefused("the calibration result has no [calibration.left]")
    return calibration


def calibration_edit(rig_text: str | None, hand_eye: dict[str, Any] | None) -> Edit:
    """The cameras' calibration (a result file's text) and/or the hand-eye, into their
    includes as one write. The hand-eye's ``[about]`` records the camera model it belongs to,
    as ``vgripd calibrate handeye`` writes it."""
    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        texts: dict[Path, dict[str, Any]] = {}

        def data(path: Path) -> dict[str, Any]:
            if path not in texts:
                texts[path] = tomllib.loads(snapshot.text(path))
            return texts[path]

        current = read_config_data(snapshot.main, files=snapshot.files).get("calibration", {})
        calibration = {k: v for k, v in current.items() if k != "hand_eye"}
        if rig_text is not None:
            calibration = rig_sections(rig_text)
            target = include_for(snapshot, "calibration.left.")
            part = data(target)
            kept = part.get("calibration", {}).get("hand_eye")
            part["calibration"] = {**calibration, **({"hand_eye": kept} if kept else {})}
        if hand_eye is not None:
            target = include_for(snapshot, "calibration.hand_eye.")
            part = data(target)
            part.setdefault("calibration", {})["hand_eye"] = hand_eye
            if calibration.get("left"):
                about = part.setdefault("about", {})
                about.update(camera_about(calibration))
        return {p: snapshot.encoded(p, toml_from_dict(d)) for p, d in texts.items()}
    return edit


def object_edit(name: str, marks: list[dict[str, Any]], polarity: str = "dark") -> Edit:
    """The chosen marks as an ``object.definition = "reference"`` object (their measured
    base-frame points as ``xyz_mm``) in the object's include, and the reference reset for it
    (no ``T_base_obj``; ``points_mm`` come with teaching; a taught ``grip`` stays). A mark of
    ``kind = "aruco"`` becomes an ArUco feature (its id, dictionary and measured side), one of
    ``kind = "template"`` a template feature (its patch file), any other a circle of
    ``polarity``."""
    features = [feature_of(m, polarity) for m in marks]

    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        cell = include_for(snapshot, "object.")
        ref = include_for(snapshot, "reference.")
        cell_data = tomllib.loads(snapshot.text(cell))
        cell_data["object"] = {"name": name, "definition": "reference", "features": features}
        out = {cell: cell_data}
        ref_data = cell_data if ref == cell else tomllib.loads(snapshot.text(ref))
        grip = ref_data.get("reference", {}).get("grip")
        ref_data["reference"] = {"grip": grip} if grip else {}
        out[ref] = ref_data
        return {p: snapshot.encoded(p, toml_from_dict(d)) for p, d in out.items()}
    return edit


def mark_name(mark: Mapping[str, Any]) -> str:
    """The feature name of a surveyed mark: ``m<number>``, a marker's id added."""
    if mark.get("kind") == "aruco":
        return f"m{mark['id']}-aruco{mark['marker_id']}"
    if mark.get("kind") == "template":
        return f"m{mark['id']}-{mark['label']}"
    return f"m{mark['id']}"


def feature_of(mark: Mapping[str, Any], polarity: str = "dark") -> dict[str, Any]:
    """One surveyed mark (``Mark.as_dict`` with a ``name``; a template's with ``template``, the
    path of its patch) as an ``[[object.features]]`` table of its kind."""
    xyz = [round(float(v), 3) for v in mark["xyz_mm"]]
    if mark.get("kind") == "template":
        return {"name": mark["name"], "kind": "template", "template": str(mark["template"]),
                "size_px": int(mark["size_px"]), "xyz_mm": xyz}
    if mark.get("kind") == "aruco":
        return {"name": mark["name"], "kind": "aruco", "marker_id": int(mark["marker_id"]),
                "dictionary": str(mark["dictionary"]),
                "size_mm": round(float(mark["size_mm"]), 1), "xyz_mm": xyz}
    return {"name": mark["name"], "kind": "circle", "polarity": polarity,
            "diameter_mm": round(float(mark["diameter_mm"]), 1), "xyz_mm": xyz}


#: A taught template's name: it becomes part of a feature name and of its file's name.
TEMPLATE_LABEL = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,23}")


def template_box(body: Any) -> tuple[tuple[int, int, int, int], str]:
    """The page's region and name for a template: ``{"box": [x, y, w, h], "label": "..."}``
    (left image px); ``ValueError`` naming the field."""
    if not isinstance(body, dict):
        raise ValueError('a JSON object {"box": [x, y, width, height], "label": "..."}')
    box = body.get("box")
    if not (isinstance(box, list) and len(box) == 4 and all(
            isinstance(v, int | float) and not isinstance(v, bool) and v == v
            and abs(v) < 1e6 for v in box)):
        raise ValueError(f"box: four numbers x, y, width, height (px of the left image), "
                         f"got {box!r}")
    label = body.get("label") or "template"
    if not isinstance(label, str) or not TEMPLATE_LABEL.fullmatch(label):
        raise ValueError(f"label: a letter, then up to 23 letters, digits, _ or - (got "
                         f"{label!r})")
    x, y, w, h = (int(round(float(v))) for v in box)
    return (x, y, w, h), label


def hand_eye_values(body: Any) -> dict[str, Any]:
    """A fixed camera's ``T_base_camera`` from the page's form: ``{"translation_mm": [3],
    "rotvec_rad": [3]}``; ``ValueError`` naming the field."""
    if not isinstance(body, dict):
        raise ValueError('a JSON object {"translation_mm": [x, y, z], "rotvec_rad": [rx, ry, rz]}')
    pose = {}
    for key in ("translation_mm", "rotvec_rad"):
        value = body.get(key)
        if not (isinstance(value, list) and len(value) == 3 and all(
                isinstance(v, int | float) and not isinstance(v, bool) and v == v
                for v in value)):
            raise ValueError(f"calibration.hand_eye.T_base_camera.{key}: three numbers, "
                             f"got {value!r}")
        pose[key] = [float(v) for v in value]
    return {"mounting": "fixed", "T_base_camera": pose}


def flange_text(T: Any) -> str:
    """A kept set's flange pose (``T_base_flange``, 4x4 mm) as its ``flange.txt`` line reads
    it, for the page's set list: ``x y z`` mm and the rotation vector in rad; "" for none."""
    if T is None:
        return ""
    import numpy as np
    from scipy.spatial.transform import Rotation

    M = np.asarray(T, dtype=np.float64)
    rotvec = Rotation.from_matrix(M[:3, :3]).as_rotvec()
    return (" ".join(f"{v:.1f}" for v in M[:3, 3]) + " mm, "
            + " ".join(f"{v:.4f}" for v in rotvec) + " rad")
