"""ArUco markers for a new object (``vgripd.vision.survey.survey_aruco``): markers printed on a
flat sheet at known base-frame positions are rendered through the demo cell's two calibrated
cameras (distortion included, by ray casting every pixel onto the sheet); the survey finds each
by its id in both images and measures its centre and side against the printed truth. The
layout judgement keeps an identified marker's label: a square of ArUco markers is no symmetry."""

from __future__ import annotations

import cv2
import numpy as np

from vgripd.config import Config, config_from_dict
from vgripd.geometry.transforms import invert_transform, pose_error
from vgripd.service.web.setupsteps import feature_of, mark_name
from vgripd.types import ImagePair, Status
from vgripd.vision import features as ft
from vgripd.vision import scene
from vgripd.vision.pipeline import Pipeline
from vgripd.vision.survey import judge_layout, survey_aruco, survey_marks

#: The sheet: base-frame z of its face, the area printed (mm) and the print resolution.
Z_MM = 10.0
X0, Y1, SHEET_MM, MM_PER_PX = 480.0, 220.0, 240.0, 0.2
#: (dictionary, id, centre x, centre y, side) in the base frame, mm.
MARKERS = [("DICT_4X4_50", 3, 540.0, 60.0, 30.0), ("DICT_4X4_50", 17, 650.0, 75.0, 30.0),
           ("DICT_4X4_50", 8, 560.0, 165.0, 24.0), ("DICT_5X5_100", 42, 655.0, 150.0, 36.0)]


def _sheet() -> np.ndarray:
    n = int(SHEET_MM / MM_PER_PX)
    sheet = np.full((n, n), 200, np.uint8)
    for dictionary, marker_id, x, y, side in MARKERS:
        # A white quiet zone of one module around the marker, as printed.
        px = int(round(side / MM_PER_PX))
        image = cv2.aruco.generateImageMarker(ft.aruco_dictionary(dictionary), marker_id, px)
        quiet = int(round(px / 5))
        col = int(round((x - X0) / MM_PER_PX)) - px // 2
        row = int(round((Y1 - y) / MM_PER_PX)) - px // 2
        sheet[row - quiet:row + px + quiet, col - quiet:col + px + quiet] = 255
        sheet[row:row + px, col:col + px] = image
    return sheet


def _render(sheet: np.ndarray, model, T_base_cam: np.ndarray) -> np.ndarray:
    """What ``model`` at ``T_base_cam`` sees of the sheet (texture column = base x, row =
    -base y, so the print is not mirrored from above)."""
    K = np.array([[model.fx, model.skew, model.cx], [0, model.fy, model.cy], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(model.width, dtype=np.float64),
                       np.arange(model.height, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(pts, K, np.array(model.dist)).reshape(-1, 2)
    rays = np.c_[rays, np.ones(len(rays))] @ T_base_cam[:3, :3].T
    t = (Z_MM - T_base_cam[2, 3]) / rays[:, 2]
    x = T_base_cam[0, 3] + t * rays[:, 0]
    y = T_base_cam[1, 3] + t * rays[:, 1]
    map_x = ((x - X0) / MM_PER_PX - 0.5).reshape(model.height, model.width).astype(np.float32)
    map_y = ((Y1 - y) / MM_PER_PX - 0.5).reshape(model.height, model.width).astype(np.float32)
    return cv2.remap(sheet, map_x, map_y, cv2.INTER_LINEAR, borderValue=200)


def _views(config: Config) -> tuple[np.ndarray, np.ndarray]:
    left, right = scene.camera_models(config)
    assert right is not None
    T_left = scene.T_base_camera(config)
    T_rl = scene.T_right_left(config)
    assert T_rl is not None
    sheet = _sheet()
    return _render(sheet, left, T_left), _render(sheet, right, T_left @ invert_transform(T_rl))


def test_markers_are_found_by_id_in_both_images_and_measured_in_the_base_frame() -> None:
    config = Config()
    left, right = _views(config)
    rig = scene.stereo_rig(config)
    assert rig is not None
    marks = survey_aruco(left, right, rig, scene.T_base_camera(config), first_id=5)
    got = {(m.dictionary, m.marker_id): m for m in marks}
    assert set(got) == {(d, i) for d, i, *_ in MARKERS}
    assert sorted(m.id for m in marks) == [5, 6, 7, 8]
    for dictionary, marker_id, x, y, side in MARKERS:
        m = got[(dictionary, marker_id)]
        assert m.kind == "aruco"
        assert m.identified
        # Corners to ~0.1 px at ~0.4 mm/px, depth over a 700 mm range: 1 mm bounds both.
        assert np.linalg.norm(np.subtract(m.xyz_base_mm, (x, y, Z_MM))) < 1.0, m
        assert abs(m.diameter_mm - side) < 1.0, m
        assert m.as_dict()["marker_id"] == marker_id
        assert m.as_dict()["size_mm"] == round(m.diameter_mm, 2)
    # A marker's dark squares can pass for circles; the page's survey lists the markers only.
    everything = survey_marks(left, right, rig, scene.T_base_camera(config))
    assert [(m.kind, m.marker_id) for m in everything] == [("aruco", 3), ("aruco", 8),
                                                           ("aruco", 17), ("aruco", 42)]
    assert [m.id for m in everything] == [1, 2, 3, 4]


def test_circles_beside_markers_are_numbered_first_and_kept() -> None:
    config = Config()
    T = scene.T_base_camera(config)
    left, right = _views(config)
    # Two dark 10 mm circles drawn at known base points beside the markers, in both views.
    models = scene.camera_models(config)
    T_rl = scene.T_right_left(config)
    truth = [(600.0, 30.0), (610.0, 190.0)]
    for image, model, T_cam in ((left, models[0], T), (right, models[1],
                                                        T @ invert_transform(T_rl))):
        for x, y in truth:
            # Ray-cast the disc: every pixel whose sheet point lies within 5 mm goes dark.
            K = np.array([[model.fx, 0, model.cx], [0, model.fy, model.cy], [0, 0, 1]])
            p_cam = invert_transform(T_cam) @ [x, y, Z_MM, 1.0]
            centre = cv2.projectPoints(p_cam[None, :3], np.zeros(3), np.zeros(3), K,
                                       np.array(model.dist))[0].ravel()
            r = 5.0 * model.fx / p_cam[2]
            cv2.circle(image, (int(round(centre[0] * 16)), int(round(centre[1] * 16))),
                       int(round(r * 16)), 40, -1, cv2.LINE_AA, 4)
    rig = scene.stereo_rig(config)
    assert rig is not None
    marks = survey_marks(left, right, rig, T)
    assert [m.kind for m in marks] == ["circle", "circle"] + ["aruco"] * 4
    circles = sorted(marks[:2], key=lambda m: m.xyz_base_mm[1])
    for m, (x, y) in zip(circles, truth, strict=True):
        # The disc is drawn as an image circle (not the ellipse of the perspective): 1.5 mm.
        assert np.linalg.norm(np.subtract(m.xyz_base_mm[:2], (x, y))) < 1.5, m


def test_a_marker_seen_by_one_camera_only_is_not_listed() -> None:
    config = Config()
    left, right = _views(config)
    rig = scene.stereo_rig(config)
    assert rig is not None
    col = int(np.mean([m.px_right[0] for m in survey_aruco(
        left, right, rig, scene.T_base_camera(config)) if m.marker_id == 17]))
    right[:, col - 80:col + 80] = 200
    ids = {m.marker_id for m in survey_aruco(left, right, rig, scene.T_base_camera(config))}
    assert 17 not in ids
    assert 3 in ids


def test_identified_markers_keep_their_labels_in_the_symmetry_judgement() -> None:
    square = np.array([[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0]], float)
    names = ["a", "b", "c", "d"]
    assert any("symmetric layout" in f.message for f in judge_layout(names, square, [10.0] * 4))
    assert judge_layout(names, square, [10.0] * 4, identified=[True] * 4) == []
    # One marker identified, three circles: the mirror through the marker still flips.
    findings = judge_layout(names, square, [10.0] * 4, identified=[True, False, False, False])
    assert any("symmetric layout" in f.message and "b->d" in f.message for f in findings)
    # Too few and too close are judged for markers as for circles.
    assert judge_layout(names[:2], square[:2], [10.0] * 2, identified=[True] * 2)[0].level \
        == "ERROR"
    close = judge_layout(names, square * [0.3, 1, 1], [10.0] * 4, identified=[True] * 4)
    assert any("a and b are 15.0 mm apart" in f.message for f in close)


def test_the_saved_markers_are_an_object_the_pipeline_finds() -> None:
    """The page's save (``object_edit``'s features) from the surveyed markers: the config
    takes them as ArUco features, and a job on the same views finds the object where it was
    measured (a reference object: identity pose, zero offset)."""
    config = Config()
    left, right = _views(config)
    rig = scene.stereo_rig(config)
    assert rig is not None
    marks = [m.as_dict() for m in survey_marks(left, right, rig, scene.T_base_camera(config))]
    features = [feature_of({**m, "name": mark_name(m)}) for m in marks]
    data = config.model_dump(mode="json", exclude_none=True)
    data["object"] = {"name": "tagged", "definition": "reference", "features": features}
    data["reference"] = {}
    cell = config_from_dict(data)
    assert [(f.kind, f.marker_id, f.dictionary) for f in cell.object.features] == [
        ("aruco", i, d) for d, i in sorted((d, i) for d, i, *_ in MARKERS)]
    assert cell.object.features[0].name == "m1-aruco3"
    result = Pipeline(cell).process(ImagePair(left=left, right=right, t_mono_ns=0), 1)
    assert result.status is Status.OK, result.message
    assert result.T_base_obj is not None
    err_t, err_r = pose_error(result.T_base_obj, np.eye(4))
    assert err_t < 0.5
    assert err_r < 0.2
