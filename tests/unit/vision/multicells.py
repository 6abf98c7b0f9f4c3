"""Multi-camera cells built from a few numbers, for the robustness tests of the N-camera path.

A cell is an object (marks on the faces of a box, each face with its outward normal) and
cameras placed by where they stand and what they look at. The config is written the way an
integrator writes one (``[[calibration.cameras]]`` poses in the base frame); the images come
from the synthetic camera, whose truth is the pose it rendered, never the code under test.
"""

from __future__ import annotations

import asyncio
import copy
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from vgripd.config import config_from_dict
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.types import ImagePair

#: Reference pose of the object: 1.5 m in front of the robot, 0.8 m up, axes as the base's.
REFERENCE = (1500.0, 0.0, 800.0)


def look_at(eye: Any, target: Any, up: Any = (0.0, 0.0, 1.0)) -> dict[str, list[float]]:
    """``T_base_camera`` of a camera at ``eye`` (mm, base frame) looking at ``target``: camera
    z forward, x right, y down (OpenCV), image rows going down along -``up``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: any right will do
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    rotvec, _ = cv2.Rodrigues(R)
    return {"translation_mm": [float(v) for v in eye],
            "rotvec_rad": [float(v) for v in rotvec.ravel()]}


@dataclass
class Cam:
    """One camera: where it stands and looks (base frame, mm) and its lens."""

    name: str
    eye: tuple[float, float, float]
    target: tuple[float, float, float] = REFERENCE
    fx: float = 1400.0
    size: tuple[int, int] = (1280, 1024)
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def entry(self) -> dict[str, Any]:
        w, h = self.size
        return {"name": self.name, "mounting": "fixed",
                "intrinsics": {"fx": self.fx, "fy": self.fx, "cx": (w - 1) / 2 + 3.1,
                               "cy": (h - 1) / 2 - 2.3, "dist": list(self.dist),
                               "width": w, "height": h},
                "T_base_camera": look_at(self.eye, self.target, self.up)}


#: The faces of a box: name -> (outward normal, the two in-plane axes).
FACES = {
    "+x": ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "-x": ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "+y": ((0, 1, 0), (1, 0, 0), (0, 0, 1)), "-y": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "+z": ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
}


def box_marks(size_mm: tuple[float, float, float], faces: dict[str, int], diameter_mm: float,
              seed: int = 3, normals: bool = True) -> list[dict[str, Any]]:
    """``count`` circle marks on each named face of a box centred on the object origin, at
    random places (seeded) at least 3 diameters apart and one diameter from the edges, so no
    two faces have the same layout (rigid distances must tell the marks apart)."""
    rng = np.random.default_rng(seed)
    half = np.asarray(size_mm, dtype=np.float64) / 2
    out: list[dict[str, Any]] = []
    for face, count in faces.items():
        n, u, v = (np.asarray(a, dtype=np.float64) for a in FACES[face])
        centre = n * half
        span_u, span_v = abs(u @ half) - 1.5 * diameter_mm, abs(v @ half) - 1.5 * diameter_mm
        placed: list[np.ndarray] = []
        for _ in range(10_000):
            if len(placed) == count:
                break
            p = centre + rng.uniform(-span_u, span_u) * u + rng.uniform(-span_v, span_v) * v
            if all(np.linalg.norm(p - q) >= 3 * diameter_mm for q in placed):
                placed.append(p)
        assert len(placed) == count, f"cannot place {count} marks on face {face}"
        for k, p in enumerate(placed):
            mark: dict[str, Any] = {"name": f"m{face[0] == '+' and 'p' or 'n'}{face[1]}{k}",
                                    "kind": "circle", "xyz_mm": [float(c) for c in p],
                                    "diameter_mm": diameter_mm}
            if normals:
                mark["normal"] = [float(c) for c in n]
            out.append(mark)
    return out


@dataclass
class Cell:
    """A multi-camera cell; :meth:`data` is its config as parsed TOML."""

    cams: list[Cam]
    marks: list[dict[str, Any]]
    rigs: dict[str, list[str]] = field(default_factory=dict)
    working_distance_mm: tuple[float, float] = (500.0, 4000.0)
    camera: dict[str, Any] = field(default_factory=dict)
    vision: dict[str, Any] = field(default_factory=dict)

    def data(self) -> dict[str, Any]:
        cam = {"type": "synthetic", "seed": 5, "max_shift_mm": 15.0, "max_tilt_deg": 2.0,
               "noise_std": 2.0, **self.camera}
        out: dict[str, Any] = {
            "camera": cam,
            "calibration": {"cameras": [c.entry() for c in self.cams]},
            "object": {"name": "cell_object", "definition": "cad", "features": self.marks},
            "reference": {"T_base_obj": {"translation_mm": list(REFERENCE),
                                         "rotvec_rad": [0.0, 0.0, 0.0]}},
            "vision": {"working_distance_mm": list(self.working_distance_mm), **self.vision},
        }
        if self.rigs:
            out["calibration"]["rigs"] = [{"name": k, "cameras": v}
                                          for k, v in self.rigs.items()]
        return out

    def config(self, **camera: Any) -> Any:
        data = self.data()
        data["camera"].update(camera)
        return config_from_dict(data)


def moved(data: dict[str, Any], index: int, dt_mm: Any = (0, 0, 0), drot_rad: Any = (0, 0, 0)
          ) -> Any:
    """The config of ``data`` with camera ``index``'s calibrated pose off by a small motion
    (the camera was knocked after calibration: images stay, the numbers are now wrong)."""
    data = copy.deepcopy(data)
    pose = data["calibration"]["cameras"][index]["T_base_camera"]
    pose["translation_mm"] = list(np.add(pose["translation_mm"], dt_mm))
    pose["rotvec_rad"] = list(np.add(pose["rotvec_rad"], drot_rad))
    return config_from_dict(data)


def grab(cfg: Any, n: int) -> list[ImagePair]:
    """``n`` acquisitions of the config's camera driver."""
    async def run() -> list[ImagePair]:
        cls = load_class(CAMERAS, "camera", cfg.camera.type)
        cam = cls(validate_options(cls, cfg.camera, "camera"), cfg)
        await cam.open()
        try:
            return [await cam.grab(30.0) for _ in range(n)]
        finally:
            await cam.close()
    return asyncio.run(run())
