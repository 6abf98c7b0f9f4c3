"""Pick lists on scenes their first tests did not show: other plate designs, other pallets,
every order rule and pick points against the renderer's truth.

The renderer (``drivers/cameras/synthetic``) places the plates with its own arithmetic and
reports each plate's true pose; which marks lie inside an image is decided here with OpenCV's
projection. Each scene asserts the two things a robot depends on: **no pickable instance is
wrong** (every pickable pose is within the bound of a true plate, each plate at most once),
and every plate that shows four or more marks comes back pickable.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.unit.vision.test_picklist import _errors, _grab
from vgripd.config import Config, config_from_dict
from vgripd.types import ImagePair, JobResult, PickInstance, Status
from vgripd.vision.pipeline import Pipeline

REF = {"T_base_obj": {"translation_mm": [600.0, 100.0, 10.0], "rotvec_rad": [0.0, 0.0, 0.05]}}
WIDE = {"max_translation_mm": 600.0, "max_rotation_deg": 180.0}
DEMO = [(-62, 29, 0), (-65, -44, 0), (-16, 46, 0), (-32, -15, 0), (48, -41, 20), (58, 16, 12)]
FOUR = [(-50, 30, 0), (-45, -35, 0), (40, -30, 0), (55, 25, 0)]
EIGHT = [(-70, -50, 0), (-20, -55, 0), (45, -48, 0), (72, 5, 0), (50, 50, 0), (-5, 40, 0),
         (-60, 35, 0), (5, -10, 0)]
TEN = [(-24.6, -35.8, 0), (1.8, 46.1, 0), (62.6, 21.6, 0), (44.1, 41.9, 0), (-29.1, 17.3, 0),
       (67.9, -11.2, 0), (-4.7, 2.0, 0), (31.0, 11.2, 0), (-62.8, 43.5, 0), (-63.3, -7.4, 0)]
TINY = [(-18, -12, 0), (4, -13, 0), (19, 2, 0), (-3, 12, 0), (-16, 9, 0)]
LARGE = [(-150, 90, 0), (-140, -95, 0), (30, 100, 0), (-20, -40, 0), (140, -85, 0), (150, 60, 0)]
RECT = [(-40, -25, 0), (40, -25, 0), (40, 25, 0), (-40, 25, 0)]


def _object(marks: list[tuple[float, float, float]], diameter: float | list[float] = 10.0
            ) -> dict[str, Any]:
    sizes = diameter if isinstance(diameter, list) else [diameter] * len(marks)
    return {"name": "plate", "definition": "cad", "features": [
        {"name": f"m{i + 1}", "xyz_mm": list(map(float, p)), "kind": "circle",
         "diameter_mm": d} for i, (p, d) in enumerate(zip(marks, sizes, strict=True))]}


def _config(camera: dict[str, Any], obj: dict[str, Any] | None = None,
            picking: dict[str, Any] | None = None, **sections: Any) -> Config:
    doc: dict[str, Any] = {"camera": {"type": "synthetic", "seed": 3, **camera},
                           "limits": WIDE, "picking": {"max_objects": 64, **(picking or {})},
                           **sections}
    if obj is not None:
        doc["object"], doc["reference"] = obj, doc.get("reference", REF)
    return config_from_dict(doc)


def _visible(config: Config, truths: np.ndarray, dropped: tuple[tuple[str, ...], ...]
             ) -> list[int]:
    """Per plate, the marks drawn and inside both images (a 20 px margin), by OpenCV's
    projection of the truth (not vgripd's camera model)."""
    cal = config.calibration
    assert cal is not None
    assert cal.right is not None
    assert cal.stereo is not None
    he = cal.hand_eye.T_base_camera
    assert he is not None
    assert he.translation_mm is not None
    assert he.rotvec_rad is not None
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = Rotation.from_rotvec(he.rotvec_rad).as_matrix()
    T_base_cam[:3, 3] = he.translation_mm
    rl = cal.stereo.T_right_left
    assert rl.translation_mm is not None
    assert rl.rotvec_rad is not None
    T_rl = np.eye(4)
    T_rl[:3, :3] = Rotation.from_rotvec(rl.rotvec_rad).as_matrix()
    T_rl[:3, 3] = rl.translation_mm
    names = [f.name for f in config.object.features]
    model = np.array([f.xyz_mm for f in config.object.features])
    out = []
    for T, gone in zip(truths, dropped, strict=True):
        inside = np.ones(len(names), dtype=bool)
        for cam, T_cam in ((cal.left, np.linalg.inv(T_base_cam) @ T),
                           (cal.right, T_rl @ np.linalg.inv(T_base_cam) @ T)):
            K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
            px, _ = cv2.projectPoints(model @ T_cam[:3, :3].T + T_cam[:3, 3], np.zeros(3),
                                      np.zeros(3), K, np.asarray(cam.dist))
            px = px.reshape(-1, 2)
            inside &= ((px >= 20) & (px <= [cam.width - 21, cam.height - 21])).all(axis=1)
        out.append(int(sum(ok and n not in gone for ok, n in zip(inside, names, strict=True))))
    return out


def _judge(result: JobResult, truths: np.ndarray, bound: tuple[float, float]
           ) -> dict[int, PickInstance]:
    """Each pickable instance -> the true plate it is (within ``bound`` mm, deg); fails on a
    pickable pose that is no plate's or on a plate given twice."""
    out: dict[int, PickInstance] = {}
    for inst in result.instances:
        if not inst.status.pose_valid:
            assert inst.target is None
            continue
        assert inst.T_base_obj is not None
        errs = [_errors(T, inst.T_base_obj) for T in truths]
        k = int(np.argmin([e[0] + e[1] for e in errs]))
        assert errs[k][0] < bound[0], f"pickable pose off every plate: nearest {k}, {errs[k]}"
        assert errs[k][1] < bound[1], f"pickable pose off every plate: nearest {k}, {errs[k]}"
        assert k not in out, f"plate {k} given twice"
        out[k] = inst
    return out


def _run(config: Config, frames: int = 1, bound: tuple[float, float] = (0.15, 0.15),
         every: bool = True
         ) -> list[tuple[JobResult, np.ndarray, list[int], dict[int, PickInstance]]]:
    """Every frame's result, truth, visible mark counts and the pickable plates; asserts that
    no pickable pose is wrong and (``every``) that every plate showing four marks or more is
    pickable with exactly the marks it shows."""
    pipeline = Pipeline(config)
    out = []
    for pair in _grab(config, frames):
        truths = pair.truth.get("instances_T_base_obj")
        if truths is None:
            truths = np.array([pair.truth["T_base_obj"]])
        dropped = pair.truth.get("instances_dropped", ((),) * len(truths))
        result = pipeline.process(pair, 1)
        visible = _visible(config, truths, dropped)
        found = _judge(result, truths, bound)
        for k, n in enumerate(visible):
            if every and n >= 4 and len(result.instances) < config.picking.max_objects:
                assert k in found, f"plate {k} shows {n} marks and is not pickable"
                assert len(found[k].features_used) == n, (k, found[k].features_used)
        out.append((result, truths, visible, found))
    return out


# --------------------------------------------------------------------------- plate designs

@pytest.mark.parametrize(("name", "obj", "pallet", "bound"), [
    # Four marks near the plate's corners: marks of neighbouring plates touch in the image.
    # Before the finder split merged blobs, 4 and 2 of 6 plates were pickable in these frames
    # (the others PARTIAL with 3 marks); now 6 and 6, within 0.031 mm, 0.051 deg.
    ("four marks, touching", _object(FOUR), {"count": 6, "cols": 3, "gap_mm": 0.0}, None),
    ("eight marks", _object(EIGHT), {"count": 6, "cols": 3, "gap_mm": 0.0}, None),
    # Ten marks: before, two plates had 9 in each frame (two marks merged); now 10.
    ("ten marks", _object(TEN), {"count": 6, "cols": 3, "gap_mm": 0.0}, None),
    ("two diameters", _object(DEMO, [6.0, 14.0, 6.0, 14.0, 6.0, 14.0]),
     {"count": 6, "cols": 3, "gap_mm": 0.0}, None),
    # A 40 x 30 mm plate with 4 mm marks: its rotation is measured on a 37 mm lever
    # (measured 0.23 deg at worst).
    ("tiny plates x24", _object(TINY, 4.0),
     {"count": 24, "cols": 6, "gap_mm": 3.0, "jitter_deg": 10.0}, (0.1, 0.4)),
    # 300 x 200 mm plates: two do not fit the image, each shows the marks inside.
    ("large plates", _object(LARGE, 16.0), {"count": 2, "cols": 2, "gap_mm": 5.0}, None),
])
def test_plate_designs(name: str, obj: dict[str, Any], pallet: dict[str, Any],
                       bound: tuple[float, float] | None) -> None:
    config = _config({"pallet": {"jitter_mm": 2.0, "jitter_deg": 3.0, **pallet}}, obj)
    for _result, _truths, visible, found in _run(config, 2, bound or (0.15, 0.15)):
        assert sorted(found) == [k for k, n in enumerate(visible) if n >= 4], name
        assert all(i.status is Status.OK for i in found.values())


def test_a_rectangle_of_marks_is_ambiguous_never_a_wrong_pose() -> None:
    """Four marks on a rectangle fit themselves turned by 180 deg: every plate is AMBIGUOUS
    (some are reported at the turned pose, none is sent). A corner moved by 1 mm is still
    ambiguous; by 3 mm it is told apart, right (as the single-object path decides)."""
    pallet = {"count": 6, "cols": 3, "gap_mm": 8.0}
    for dx, expect in ((0.0, Status.AMBIGUOUS), (1.0, Status.AMBIGUOUS), (3.0, Status.OK)):
        marks = [*RECT[:2], (40.0 + dx, 25.0, 0.0), RECT[3]]
        config = _config({"pallet": pallet}, _object(marks))
        for result, _, _, found in _run(config, 2, every=expect is Status.OK):
            assert [i.status for i in result.instances] == [expect] * 6, dx
            assert len(found) == (6 if expect is Status.OK else 0)


def test_a_symmetric_subset_left_by_a_covered_mark_is_ambiguous() -> None:
    """A rectangle plus a fifth mark that breaks the symmetry: the plates whose fifth mark is
    covered are AMBIGUOUS, the others pickable at their true pose."""
    marks = [*RECT, (10.0, 5.0, 0.0)]
    config = _config({"pallet": {"count": 6, "cols": 3, "gap_mm": 8.0},
                      "drop_features": ["1/m5", "4/m5"]}, _object(marks))
    for result, _truths, _, found in _run(config, 2, every=False):
        assert sorted(found) == [0, 2, 3, 5]
        flagged = [i for i in result.instances if i.status is Status.AMBIGUOUS]
        assert len(flagged) == 2


# --------------------------------------------------------------------------- pallets

def _pose(x: float, y: float, z: float = 10.0, yaw_deg: float = 0.0) -> dict[str, Any]:
    return {"translation_mm": [x, y, z], "rotvec_rad": [0.0, 0.0, float(np.radians(yaw_deg))]}


def _tilted(rotvec: list[float], z: float = 10.0) -> dict[str, Any]:
    return {"T_base_obj": {"translation_mm": [600.0, 100.0, z], "rotvec_rad": rotvec}}


@pytest.mark.parametrize(("name", "camera", "reference"), [
    ("two plates", {"pallet": {"count": 2, "cols": 2, "gap_mm": 0.0}}, None),
    ("twelve plates, 1.1 m away",
     {"pallet": {"count": 12, "cols": 4, "gap_mm": 5.0}}, _tilted([0.0, 0.0, 0.05], -400.0)),
    ("turned 90/180/270 deg against each other", {"instances": [
        _pose(470, 30), _pose(620, 40, yaw_deg=90), _pose(760, 30, yaw_deg=180),
        _pose(470, 190, yaw_deg=270), _pose(620, 170, yaw_deg=180),
        _pose(760, 180, yaw_deg=-90)]}, None),
    ("pallet tilted 15 deg about x", {"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0}},
     _tilted([0.26, 0.0, 0.05])),
    ("pallet tilted 20 deg about y", {"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0}},
     _tilted([0.0, 0.35, 0.05])),
    ("jitter up to touching", {"pallet": {"count": 6, "cols": 3, "gap_mm": 0.0,
                                          "jitter_mm": 6.0, "jitter_deg": 6.0}}, None),
    ("any yaw", {"pallet": {"count": 6, "cols": 3, "gap_mm": 40.0, "jitter_mm": 5.0,
                            "jitter_deg": 180.0}}, None),
    ("partly outside the image", {"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0}},
     _tilted([0.0, 0.0, 0.05]) | {"T_base_obj": {"translation_mm": [720.0, 100.0, 10.0],
                                                 "rotvec_rad": [0.0, 0.0, 0.05]}}),
    ("25 clutter blobs", {"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0},
                          "extra_blobs": 25}, None),
    ("marks missing on every plate", {"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0},
                                      "drop_features": ["0/m1", "1/m5", "2/m2", "2/m6", "3/m3",
                                                        "4/m4", "5/m6"]}, None),
])
def test_pallets(name: str, camera: dict[str, Any], reference: dict[str, Any] | None) -> None:
    """Every plate showing four marks or more is pickable, at its true pose (0.15 mm,
    0.15 deg), with exactly the marks it shows; nothing else is pickable."""
    sections = {"reference": reference} if reference is not None else {}
    config = _config(camera, None, **sections)
    for result, _truths, visible, found in _run(config, 2):
        assert sorted(found) == [k for k, n in enumerate(visible) if n >= 4], name
        for inst in result.instances:
            if not inst.status.pose_valid:
                assert inst.status is Status.PARTIAL, (name, inst.message)


def _stacked() -> tuple[list[dict[str, Any]], list[str]]:
    """Six plates on the pallet and two on top of them (35 mm higher, each over two plates);
    the lower plates' marks under an upper plate's footprint (its marks' box plus 8 mm) are
    covered."""
    lower = [_pose(470, 40, yaw_deg=2), _pose(610, 40, yaw_deg=-1), _pose(750, 40, yaw_deg=3),
             _pose(470, 150), _pose(610, 150, yaw_deg=-2), _pose(750, 150, yaw_deg=1)]
    upper = [_pose(540, 95, 45.0, 5), _pose(690, 100, 45.0, -4)]
    model = np.array(DEMO, dtype=float)
    lo, hi = model[:, :2].min(axis=0) - 8.0, model[:, :2].max(axis=0) + 8.0

    def matrix(p: dict[str, Any]) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(p["rotvec_rad"]).as_matrix()
        T[:3, 3] = p["translation_mm"]
        return T

    drop = []
    for k, p in enumerate(lower):
        for i, m in enumerate(model):
            world = matrix(p) @ np.r_[m, 1.0]
            for u in upper:
                local = np.linalg.inv(matrix(u)) @ world
                if (local[:2] >= lo).all() and (local[:2] <= hi).all():
                    drop.append(f"{k}/m{i + 1}")
    return lower + upper, drop


def test_a_second_layer_partly_stacked_comes_first_with_order_z() -> None:
    """order = "z": the two upper plates first, then the lower ones showing four marks or
    more; those with three are PARTIAL, last."""
    poses, drop = _stacked()
    config = _config({"instances": poses, "drop_features": drop}, None, {"order": "z"})
    ((result, truths, visible, found),) = _run(config)
    order = [k for k in (int(np.argmin([np.linalg.norm(i.T_base_obj[:3, 3] - T[:3, 3])
                                         for T in truths]))
                         for i in result.instances if i.T_base_obj is not None)]
    assert set(order[:2]) == {6, 7}
    assert len(found) == sum(n >= 4 for n in visible)
    assert all(i.status is Status.PARTIAL for i in result.instances[len(found):])


# --------------------------------------------------------------------------- orders, picks

def _centroids(truths: np.ndarray) -> np.ndarray:
    model = np.array(DEMO, dtype=float)
    return np.array([(model @ T[:3, :3].T + T[:3, 3]).mean(axis=0) for T in truths])


@pytest.mark.parametrize(("picking", "key"), [
    ({"order": "nearest", "point_mm": [350.0, -50.0, 0.0]},
     lambda c: np.linalg.norm(c - [350.0, -50.0, 0.0], axis=1)),
    ({"order": "axis", "axis": [-1.0, 2.0, 0.0]}, lambda c: c @ np.array([-1.0, 2.0, 0.0])),
    ({"order": "z"}, lambda c: -c[:, 2]),
])
def test_order_rules_against_the_truth(picking: dict[str, Any], key: Any) -> None:
    """On a pallet tilted 12 deg about x (so z differs by row), the list comes in the order of
    the rule applied to the true plates' mark centroids; max_objects = 4 of 6 keeps the first
    four of that order."""
    config = _config({"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0}}, None,
                     {**picking, "max_objects": 4}, reference=_tilted([0.21, 0.0, 0.05]))
    ((result, truths, _, found),) = _run(config)
    expected = [int(k) for k in np.argsort(key(_centroids(truths)), kind="stable")[:4]]
    by_instance = {id(inst): k for k, inst in found.items()}
    assert [by_instance[id(i)] for i in result.instances] == expected


def test_order_score_puts_plates_with_covered_marks_last() -> None:
    config = _config({"pallet": {"count": 6, "cols": 3, "gap_mm": 5.0},
                      "drop_features": ["1/m2", "4/m3", "4/m5"]}, None, {"order": "score"})
    ((result, _, _, found),) = _run(config)
    by_instance = {id(inst): k for k, inst in found.items()}
    assert [by_instance[id(i)] for i in result.instances][-2:] == [1, 4]
    scores = [i.score for i in result.instances]
    assert scores == sorted(scores, reverse=True)


def test_pick_points_by_priority_on_turned_plates_against_the_truth() -> None:
    """Plates turned 0/90/180/270 deg: pick point 5 (priority 1) sits 90 mm off the plate's +x
    side, so for some plates it leaves the workspace box and pick point 9 (priority 2) is sent;
    the grip sent is truth @ P of the chosen point (0.2 mm). A pick point beyond every limit
    (10 m out, limits.point = "grip": a 3 deg turn moves it 500 mm) is never chosen; alone it
    rejects every plate."""
    picks = [{"id": 9, "priority": 2, "pose": {"translation_mm": [0.0, 0.0, 5.0],
                                               "rotvec_rad": [np.pi, 0.0, 0.0]}},
             {"id": 5, "priority": 1, "pose": {"translation_mm": [90.0, 0.0, 5.0],
                                               "rotvec_rad": [np.pi, 0.0, 0.0]}},
             {"id": 3, "priority": 0, "pose": {"translation_mm": [10000.0, 0.0, 0.0]}}]
    box = {"workspace_min_mm": [380.0, -80.0, -50.0], "workspace_max_mm": [840.0, 280.0, 100.0]}
    instances = [_pose(470, 30), _pose(620, 40, yaw_deg=90), _pose(760, 30, yaw_deg=180),
                 _pose(470, 190, yaw_deg=270), _pose(620, 170, yaw_deg=180), _pose(760, 180)]
    config = _config({"instances": instances}, None, {"pick_points": picks},
                     output={"vendor": "kuka", "mode": "grip"},
                     limits={"max_translation_mm": 300.0, "max_rotation_deg": 180.0,
                             "point": "grip", **box})
    ((result, truths, _, found),) = _run(config, bound=(0.15, 0.15))
    assert sorted(found) == [0, 1, 2, 3, 4, 5]
    P = {}
    for p in picks:
        P[p["id"]] = np.eye(4)
        P[p["id"]][:3, :3] = Rotation.from_rotvec(p["pose"].get("rotvec_rad", [0, 0, 0])
                                                  ).as_matrix()
        P[p["id"]][:3, 3] = p["pose"]["translation_mm"]
    lo, hi = np.array(box["workspace_min_mm"]), np.array(box["workspace_max_mm"])
    for k, inst in found.items():
        at5 = (truths[k] @ P[5])[:3, 3]
        assert inst.pick_id == (5 if ((at5 >= lo) & (at5 <= hi)).all() else 9), k
        grip = truths[k] @ P[inst.pick_id]
        assert inst.target is not None
        np.testing.assert_allclose(inst.target.values[:3], grip[:3, 3], atol=0.2)
    assert {i.pick_id for i in found.values()} == {5, 9}  # both are exercised

    lever = _config({"instances": instances}, None, {"pick_points": picks[2:]},
                    limits={"max_translation_mm": 300.0, "max_rotation_deg": 180.0,
                            "point": "grip"})
    ((result, _, _, found),) = _run(lever, every=False)
    assert found == {}
    assert all(i.status is Status.OUT_OF_LIMITS and i.target is None
               for i in result.instances)


# --------------------------------------------------------------------------- one camera

def _aruco(poses: list[np.ndarray], hide: tuple[tuple[int, int], ...] = ()
           ) -> tuple[JobResult, Config, np.ndarray]:
    from tests.unit.vision.test_picklist import _aruco_config, _render_tags

    base = _aruco_config()
    config = base.model_copy(update={
        "limits": base.limits.model_copy(update={"max_translation_mm": 1000.0,
                                                 "max_rotation_deg": 180.0}),
        "picking": base.picking.model_copy(update={"max_objects": 64})})
    image = _render_tags(config, poses, hide=hide)
    pair = ImagePair(left=image, right=None, t_mono_ns=0)
    return Pipeline(config).process(pair, 1), config, image


def _tag_plate(x: float, y: float, yaw_deg: float, z: float = 10.0, tilt_deg: float = 0.0
               ) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zx", [yaw_deg, tilt_deg], degrees=True).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


@pytest.mark.parametrize(("name", "poses", "hide", "bound"), [
    ("turned 0/90/180/270, tilted 10 deg",
     [_tag_plate(450, 15, 0, tilt_deg=10), _tag_plate(615, 15, 90, tilt_deg=10),
      _tag_plate(450, 185, 180, tilt_deg=10), _tag_plate(615, 185, 270, tilt_deg=10)], (),
     (2.0, 1.0)),
    # Plate 1 loses one marker (found with four), plate 3 two (not found).
    ("markers hidden", [_tag_plate(450, 30, 3), _tag_plate(615, 30, -2),
                        _tag_plate(450, 170, 1), _tag_plate(615, 170, 4)],
     ((1, 0), (3, 1), (3, 4)), (3.0, 1.0)),
    # Twelve plates 1.1 m away (4 x 3, 170 x 140 mm pitch); the left column is partly
    # outside the image.
    ("twelve plates", [_tag_plate(525 + (i - 1.5) * 170, 100 + (j - 1) * 140, 7.0 * (i + j),
                                  z=-400.0) for i in range(4) for j in range(3)], (),
     (3.0, 1.5)),
])
def test_one_camera_aruco_on_every_plate(name: str, poses: list[np.ndarray],
                                         hide: tuple[tuple[int, int], ...],
                                         bound: tuple[float, float]) -> None:
    """Every plate with four or more markers in the image comes back once, pickable, at the
    pose the single-object path finds on that plate alone (PnP on the same markers; 0.05 mm),
    near the truth (one camera's depth: bound per scene; measured at worst 1.34 mm 0.53 deg,
    0.49 mm 0.54 deg, 1.91 mm 0.99 deg); none else."""
    from tests.unit.vision.test_picklist import TAGS

    result, config, image = _aruco(poses, hide)
    cal = config.calibration
    assert cal is not None
    K = np.array([[cal.left.fx, 0, cal.left.cx], [0, cal.left.fy, cal.left.cy], [0, 0, 1.0]])
    he = cal.hand_eye.T_base_camera
    assert he is not None
    assert he.rotvec_rad is not None
    assert he.translation_mm is not None
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = Rotation.from_rotvec(he.rotvec_rad).as_matrix()
    T_base_cam[:3, 3] = he.translation_mm
    shown = []
    for k, T in enumerate(poses):
        cam = np.linalg.inv(T_base_cam) @ T
        corners = np.array([[-15.0, -15.0, 0.0], [15.0, 15.0, 0.0], [-15.0, 15.0, 0.0],
                            [15.0, -15.0, 0.0]])
        n = 0
        for i, xyz in enumerate(TAGS):
            px, _ = cv2.projectPoints((corners + xyz) @ cam[:3, :3].T + cam[:3, 3],
                                      np.zeros(3), np.zeros(3), K, np.zeros(5))
            px = px.reshape(-1, 2)
            inside = ((px >= 2) & (px <= [cal.left.width - 3, cal.left.height - 3])).all()
            n += int(inside and (k, i) not in hide)
        shown.append(n)
    found = _judge(result, np.array(poses), bound)
    assert sorted(found) == [k for k, n in enumerate(shown) if n >= 4], (name, shown)
    single = config.model_copy(update={"picking": config.picking.model_copy(
        update={"max_objects": 1})})
    from tests.unit.vision.test_picklist import _render_tags

    for k, inst in found.items():
        assert len(inst.features_used) == shown[k]
        alone = _render_tags(config, [poses[k]],
                             hide=tuple((0, i) for kk, i in hide if kk == k))
        one = Pipeline(single).process(ImagePair(left=alone, right=None, t_mono_ns=0), 1)
        assert one.T_base_obj is not None
        assert inst.T_base_obj is not None
        dt, dr = _errors(one.T_base_obj, inst.T_base_obj)
        assert dt < 0.05, (k, dt)
        assert dr < 0.05, (k, dr)


def test_a_mark_partly_covered_by_a_neighbours_mark_is_left_out_of_the_fit() -> None:
    """Two plates at different heights (17 mm apart), tilted, so that in the left image a mark
    of plate 1 overlaps one of plate 0 and is partly covered (found in a random stress scene):
    its centre is pulled by 0.7 px, well inside every gate, and before the fit left it out,
    plate 1 was 0.29-0.31 mm and 0.50-0.52 deg off in three frames of noise. Leaving each mark
    out in turn shows the one the others do not agree with: now 0.002-0.023 mm, 0.01-0.02
    deg, with four marks."""
    inst = [{"translation_mm": [605.8, 7.8, 18.4], "rotvec_rad": [0.193, -0.0789, 0.7732]},
            {"translation_mm": [750.2, -10.5, 1.9], "rotvec_rad": [0.1199, -0.0108, 0.1794]}]
    for seed in (1, 2, 3):
        config = _config({"instances": inst, "drop_features": ["0/m2", "1/m4"],
                          "seed": seed}, None)
        ((result, truths, _, found),) = _run(config, bound=(0.1, 0.1), every=False)
        assert sorted(found) == [0, 1]
        assert found[1].features_used == ("m2", "m3", "m5", "m6")
        assert len(found[0].features_used) == 5


@pytest.mark.parametrize(("design", "seed"), [("demo", 2), ("four", 4), ("ten", 3),
                                              ("rect5", 1)])
def test_random_scenes_never_send_another_plate(design: str, seed: int) -> None:
    """Random scenes: eight plates at any yaw, tilted up to 15 deg, 0-30 mm high, 10 % of the
    marks covered, up to 14 clutter blobs. No pickable pose is another plate's or a plate's
    turned pose (bound 1 mm, 1 deg). Measured over 84 such scenes (672 plates, four designs):
    none; 4 plates with exactly four marks, one of them partly covered by another plate's mark
    in one image, were 0.07-0.26 mm, 0.17-0.51 deg off (docs/picklists.md, limits)."""
    model = np.array({"demo": DEMO, "four": FOUR, "ten": TEN,
                      "rect5": [*RECT, (10.0, 5.0, 0.0)]}[design], dtype=float)
    obj = None if design == "demo" else _object([(p[0], p[1], p[2]) for p in model])
    rng = np.random.default_rng(seed)
    for trial in range(2):
        poses: list[np.ndarray] = []
        for _ in range(3000):
            if len(poses) == 8:
                break
            T = np.eye(4)
            T[:3, :3] = Rotation.from_euler("zx", [rng.uniform(-180, 180), rng.uniform(0, 15)],
                                            degrees=True).as_matrix()
            T[:3, 3] = (rng.uniform(420, 780), rng.uniform(-20, 220), rng.uniform(0, 30))
            marks = model @ T[:3, :3].T + T[:3, 3]
            if all(np.linalg.norm(marks[:, None, :2] - (model @ P[:3, :3].T + P[:3, 3])[None, :, :2],
                                  axis=2).min() > 11.0 for P in poses):
                poses.append(T)
        drop = [f"{k}/m{i + 1}" for k in range(len(poses)) for i in range(len(model))
                if rng.random() < 0.1]
        instances = [{"translation_mm": P[:3, 3].tolist(),
                      "rotvec_rad": Rotation.from_matrix(P[:3, :3]).as_rotvec().tolist()}
                     for P in poses]
        config = _config({"instances": instances, "drop_features": drop,
                          "extra_blobs": int(rng.integers(0, 15)), "seed": 100 * seed + trial},
                         obj)
        ((_, truths, visible, found),) = _run(config, bound=(1.0, 1.0), every=False)
        assert len(found) >= sum(n >= 5 for n in visible)  # every plate showing five marks
