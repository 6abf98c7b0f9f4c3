"""The finders of one image (``_Finder``, prepared once from the config) and what they found
(``Found``): made by the pipeline, read by the diagnosis and the pick lists."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vgripd.config import Config
from vgripd.types import FloatArray
from vgripd.vision import features as ft


@dataclass(frozen=True)
class Found:
    """Features of one image: identified ones by feature index, anonymous circle candidates."""

    identified: dict[int, FloatArray]  # feature index -> (2,) px
    circles: FloatArray  # (k, 2) px
    # The circle finder's output per spec (``_Finder.specs``), rejected blobs included: what
    # the diagnosis of a failed job reads.
    blobs: tuple[ft.Blobs, ...] = ()
    # Pick lists with ArUco markers (``_Finder.keep_all``): every detection as (feature index,
    # marker), an id as often as it is seen.
    markers: tuple[tuple[int, ft.Marker], ...] = ()


class _Finder:
    """The finders the object's features need, prepared once from the config."""

    def __init__(self, config: Config, focal_px: float,
                 templates: dict[int, ft.UInt8Image]) -> None:
        vision = config.vision
        near, far = vision.working_distance_mm
        self.specs: list[ft.CircleSpec] = []
        self.aruco: dict[str, dict[int, int]] = {}  # dictionary -> marker id -> feature index
        self.templates: list[tuple[int, ft.UInt8Image]] = []
        circles: dict[str, list[float]] = {}
        for i, f in enumerate(config.object.features):
            if f.kind == "circle":
                circles.setdefault(f.polarity, []).append(f.diameter_mm)
            elif f.kind == "aruco":  # ids unique, dictionaries known: judged by the config
                self.aruco.setdefault(f.dictionary, {})[f.marker_id] = i
            else:  # read (and judged readable) by vgripd.vision.readiness
                self.templates.append((i, templates[i]))
        for polarity, diameters in circles.items():
            self.specs.append(
                ft.CircleSpec(
                    polarity="dark" if polarity == "dark" else "bright",
                    min_diameter_px=max(3.0, focal_px * min(diameters) / far),
                    max_diameter_px=focal_px * max(diameters) / near,
                    min_contrast=vision.min_contrast,
                    min_circularity=vision.min_circularity,
                    downscale=vision.downscale,
                    separate_neighbours=config.picking.max_objects > 1,
                )
            )
        self.min_score = vision.template_min_score
        self.keep_all = False  # set for pick lists: keep repeated marker ids (Found.markers)

    def __call__(self, gray: ft.UInt8Image) -> Found:
        identified: dict[int, FloatArray] = {}
        markers: list[tuple[int, ft.Marker]] = []
        for dictionary, ids in self.aruco.items():
            if self.keep_all:
                markers += [(ids[m.marker_id], m) for m in ft.find_aruco_all(gray, dictionary)
                            if m.marker_id in ids]
                continue
            for marker_id, marker in ft.find_aruco(gray, dictionary).items():
                if marker_id in ids:
                    identified[ids[marker_id]] = marker.centre
        for index, patch in self.templates:
            hit = ft.find_template(gray, patch, self.min_score)
            if hit is not None:
                identified[index] = hit[0]
        blobs = tuple(ft.find_circles(gray, spec) for spec in self.specs)
        circles = np.vstack([b.xy for b in blobs]) if blobs else np.zeros((0, 2))
        return Found(identified, circles, blobs, tuple(markers))

