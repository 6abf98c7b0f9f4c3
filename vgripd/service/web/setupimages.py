"""The setup page's image work, run in the web view's image helper process (``images.
ImageRenderer.call``), never on the daemon's loop: the board's corners found and drawn in every
camera, the marks surveyed in a stereo pair and drawn numbered (a template taught from a region
of the left image among them), and a capture folder's account read back (which detects the board
in every image kept so far).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.boards import Board, Detection
from vgripd.calib.capturesets import Capture, detect_or_none
from vgripd.calib.coverage import Coverage
from vgripd.config import Config
from vgripd.service.web.images import _encode
from vgripd.vision import scene
from vgripd.vision.survey import (
    SURVEY_DICTIONARIES,
    Mark,
    TemplateRefused,
    survey_marks,
    survey_template,
    template_patch,
)


def _bgr(image: Any) -> np.ndarray:
    import cv2

    gray = np.asarray(image)
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR) if gray.ndim == 2 else gray.copy()


def board_corners(views: list[Any], spec: str, names: list[str]
                  ) -> tuple[list[bytes], list[Detection | None]]:
    """Each view with the board's corners drawn (green, the first corner red), and the
    detections (None where the board is not seen whole)."""
    import cv2

    board = Board.parse(spec)
    dets = [detect_or_none(board, v, n) for v, n in zip(views, names, strict=True)]
    pictures = []
    for view, det in zip(views, dets, strict=True):
        bgr = _bgr(view)
        scale = max(1, bgr.shape[1] // 800)
        if det is not None:
            for k, (x, y) in enumerate(det.px):
                cv2.circle(bgr, (int(round(x)), int(round(y))), 5 * scale,
                           (0, 0, 255) if k == 0 else (0, 200, 0), 2 * scale)
        else:
            cv2.putText(bgr, "board not seen whole", (20 * scale, 40 * scale),
                        cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 255), 2 * scale)
        pictures.append(bgr)
    return _encode(pictures), dets


def find_marks(views: list[Any], config: Config,
               templates: Mapping[str, np.ndarray] | None = None
               ) -> tuple[list[bytes], list[dict[str, Any]], list[str]]:
    """The marks seen in both images of a stereo pair (``vgripd.vision.survey``): circles, ArUco
    markers (of the dictionaries the object names, and the usual ones) and the ``templates``
    taught so far (name -> patch), numbered on each image, a marker or template outlined; the
    config gives the calibration, the hand-eye and the finder's limits. Also why a taught
    template was not among them."""
    rig = scene.stereo_rig(config)
    if rig is None or len(views) < 2:
        raise ValueError("the object step needs a calibrated stereo pair")
    v = config.vision
    named = [f.dictionary for f in config.object.features if f.kind == "aruco"]
    dictionaries = tuple(dict.fromkeys([*named, *SURVEY_DICTIONARIES]))
    T_base_camera = scene.T_base_camera(config)
    marks = survey_marks(views[0], views[1], rig, T_base_camera, dictionaries,
                         min_contrast=v.min_contrast,
                         min_circularity=max(0.75, v.min_circularity),
                         tolerance_px=v.epipolar_tolerance_px)
    missed = []
    for label, patch in (templates or {}).items():
        try:
            marks.append(survey_template(views[0], views[1], rig, T_base_camera, patch, label,
                                         v.template_min_score, template_tolerance(config),
                                         len(marks) + 1))
        except TemplateRefused as err:
            missed.append(str(err))
    return draw_marks(views, marks), [m.as_dict() for m in marks], missed


def template_tolerance(config: Config) -> float:
    """How far (px) a template's right match may lie off the epipolar line: a patch's centre is
    less sharp than a circle's, so twice the circles' tolerance, 3 px at least."""
    return max(3.0, 2.0 * config.vision.epipolar_tolerance_px)


def teach_template(views: list[Any], config: Config, box: tuple[int, int, int, int],
                   label: str, mark_id: int
                   ) -> tuple[list[bytes], dict[str, Any], np.ndarray, bytes]:
    """The region ``box`` of the left image taught as a template: found once in each image and
    triangulated (``TemplateRefused`` naming why not); the images with it outlined, the mark,
    the patch and the patch as PNG (the file the object's feature names)."""
    import cv2

    rig = scene.stereo_rig(config)
    if rig is None or len(views) < 2:
        raise ValueError("the object step needs a calibrated stereo pair")
    patch = template_patch(views[0], box)
    mark = survey_template(views[0], views[1], rig, scene.T_base_camera(config), patch, label,
                           config.vision.template_min_score, template_tolerance(config),
                           mark_id)
    ok, png = cv2.imencode(".png", patch)
    if not ok:
        raise ValueError("cannot encode the template as PNG")
    return draw_marks(views, [mark]), mark.as_dict(), patch, png.tobytes()


def draw_marks(views: list[Any], marks: list[Mark]) -> list[bytes]:
    """The pair with every mark numbered: a circle ringed, a marker or template outlined."""
    import cv2

    pictures = []
    for side, view in enumerate(views[:2]):
        bgr = _bgr(view)
        scale = max(1, bgr.shape[1] // 800)
        for m in marks:
            x, y = m.px_left if side == 0 else m.px_right
            centre = (int(round(x)), int(round(y)))
            label = str(m.id)
            if m.kind != "circle" and side == 0:
                quad = np.round(np.array(m.outline_left)).astype(np.int32)
                cv2.polylines(bgr, [quad], True, (255, 120, 0), 2 * scale)
                label = f"{m.id} (#{m.marker_id})" if m.kind == "aruco" else f"{m.id} {m.label}"
            else:
                cv2.circle(bgr, centre, 18 * scale, (0, 160, 255), 2 * scale)
            cv2.putText(bgr, label, (centre[0] + 20 * scale, centre[1] - 12 * scale),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.9 * scale, (0, 160, 255), 2 * scale)
        pictures.append(bgr)
    return _encode(pictures)


def resume_capture(spec: str, folder: str, names: list[str], sizes: list[tuple[int, int]]
                   ) -> Capture:
    """The capture account of ``folder`` (its sets read back and detected again), ready for
    more sets; the sets there count for the coverage."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    state = Capture(Board.parse(spec), out, 0, 1.0, 20.0, list(names),
                    [Coverage(size) for size in sizes])
    state.resumed = state.resume()
    return state
