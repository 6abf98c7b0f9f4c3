"""A simulated conveyor cell for the demo and the bench: a straight belt carrying parts, its
truth at any travel, stereo images rendered at chosen travels with the motion blur of the
exposure, and the PLC of register map version 4 (docs/conveyor.md, docs/registers.md).

The belt is simulated here on its own arithmetic (the part's pose in a frame built from the
config's direction, normal and origin, moved by the travel), not with
``vgripd.geometry.belt``, so that the daemon's answers are judged against an independent truth.

Images: the synthetic camera's renderer (through the registry) draws each part that lies whole
in both images over the exposure, at the travel the frame is rendered for (the exposure's
start, where a strobe-triggered latch takes the count); the motion during the exposure is a
line blur along the parts' projected travel, ``speed x exposure`` long, applied before the
sensor noise. A part cut by an image edge is not drawn (the renderer draws whole parts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vgripd.config import Config, ConveyorConfig
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import MAP_SIZE_V4, Reg
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.sim.plc import CycleResult, MockPlc
from vgripd.types import FloatArray
from vgripd.vision import scene

#: Pixels a whole part's mark centres keep clear of the image edges (a mark's radius and
#: more in the demo cell).
EDGE_PX = 30.0


@dataclass(frozen=True)
class SimPart:
    """A part at belt travel 0: along the belt from its origin (mm), across it (to the left of
    the direction, mm), and its rotation about the belt's normal (deg)."""

    along_mm: float
    across_mm: float
    theta_deg: float


class SimBelt:
    """The belt's truth: parts carried along ``conveyor.direction``; the encoder at
    ``count0`` when the belt has travelled 0 mm, counting ``counts_per_mm``, wrapping at
    ``2^encoder_bits``."""

    def __init__(self, conveyor: ConveyorConfig, parts: list[SimPart], count0: int) -> None:
        self.conveyor = conveyor
        self.parts = parts
        self.count0 = count0
        z = np.asarray(conveyor.normal, dtype=np.float64)
        z /= np.linalg.norm(z)
        x = np.asarray(conveyor.direction, dtype=np.float64)
        x = x - z * (x @ z)
        x /= np.linalg.norm(x)
        self.frame = np.eye(4)
        self.frame[:3, 0], self.frame[:3, 1], self.frame[:3, 2] = x, np.cross(z, x), z
        self.frame[:3, 3] = conveyor.origin_mm

    @property
    def span(self) -> int:
        return 1 << self.conveyor.encoder_bits

    def count_at(self, travel_mm: float) -> int:
        return (self.count0 + round(travel_mm * self.conveyor.counts_per_mm)) % self.span

    def travel_of(self, count: int) -> float:
        """The travel at ``count`` (the belt never runs half the counter's range)."""
        d = (count - self.count0) % self.span
        return (d - self.span if d >= self.span // 2 else d) / self.conveyor.counts_per_mm

    def truth(self, part: int, travel_mm: float) -> FloatArray:
        """Part ``part``'s pose ``T_base_obj`` after the belt travelled ``travel_mm``."""
        p = self.parts[part]
        t = math.radians(p.theta_deg)
        T = np.eye(4)
        T[:2, :2] = [[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]
        T[:3, 3] = (p.along_mm + travel_mm, p.across_mm, 0.0)
        return self.frame @ T

    def along(self, part: int, travel_mm: float) -> float:
        return self.parts[part].along_mm + travel_mm


def footprint_mm(config: Config) -> float:
    """The radius of a part about its origin (its marks and their rims), mm."""
    pts = scene.object_points(config)
    diameters = [getattr(f, "diameter_mm", 0.0) for f in config.object.features]
    return float(np.max(np.linalg.norm(pts[:, :2], axis=1)) + max(diameters) / 2)


def random_parts(rng: np.random.Generator, n: int, first_mm: float, gap_mm: tuple[float, float],
                 across_mm: float, theta_deg: float) -> list[SimPart]:
    """``n`` parts upstream of ``first_mm`` (the first there), spaced by gaps drawn uniformly in
    ``gap_mm``, across the belt within +-``across_mm``, turned within +-``theta_deg``."""
    parts, along = [], first_mm
    for _ in range(n):
        parts.append(SimPart(along, float(rng.uniform(-across_mm, across_mm)),
                             float(rng.uniform(-theta_deg, theta_deg))))
        along -= float(rng.uniform(*gap_mm))
    return parts


class BeltCamera:
    """What the fixed stereo camera of ``config`` sees of a ``SimBelt``, and its images."""

    def __init__(self, config: Config, belt: SimBelt) -> None:
        self.config = config
        self.belt = belt
        left, right = scene.camera_models(config)
        T_cam_base = np.linalg.inv(scene.T_base_camera(config))
        self.cams = [(left, T_cam_base)]
        T_rl = scene.T_right_left(config)
        if right is not None and T_rl is not None:
            self.cams.append((right, T_rl @ T_cam_base))
        self.points = scene.object_points(config)

    def _pixels(self, T_base_obj: FloatArray) -> list[FloatArray]:
        pts = self.points @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]
        return [model.project(pts @ T[:3, :3].T + T[:3, 3]) for model, T in self.cams]

    def whole(self, T_base_obj: FloatArray) -> bool:
        """Every mark (and its rim) inside both images, clear of the edges."""
        margin = EDGE_PX
        for (model, _), px in zip(self.cams, self._pixels(T_base_obj), strict=True):
            if not (np.all(px >= margin) and np.all(px[:, 0] < model.width - margin)
                    and np.all(px[:, 1] < model.height - margin)):
                return False
        return True

    def visible(self, travel_mm: float, motion_mm: float = 0.0) -> list[int]:
        """The parts whole in view at ``travel_mm`` and ``motion_mm`` later."""
        return [k for k in range(len(self.belt.parts))
                if self.whole(self.belt.truth(k, travel_mm))
                and self.whole(self.belt.truth(k, travel_mm + motion_mm))]

    def view_along(self, step_mm: float = 2.0) -> tuple[float, float]:
        """The along range over which a part (upright, on the belt's middle) is whole in view."""
        frame = self.belt.frame
        ok = []
        for a in np.arange(-2000.0, 4000.0, step_mm):
            T = frame.copy()
            T[:3, 3] = frame[:3, :3] @ [a, 0.0, 0.0] + frame[:3, 3]
            if self.whole(T):
                ok.append(a)
        if not ok:
            raise ValueError("the camera sees no part of the belt (conveyor.origin_mm, "
                             "calibration.hand_eye)")
        return min(ok), max(ok)

    def blur_px(self, T_base_obj: FloatArray, motion_mm: float) -> list[FloatArray]:
        """Each camera's image displacement (px, (2,)) of the part's marks' mean while it
        travels ``motion_mm`` along the belt."""
        moved = T_base_obj.copy()
        moved[:3, 3] += self.belt.frame[:3, 0] * motion_mm
        return [b.mean(axis=0) - a.mean(axis=0)
                for a, b in zip(self._pixels(T_base_obj), self._pixels(moved), strict=True)]

    async def render(self, folder: Path, index: int, travel_mm: float, motion_mm: float,
                     seed: int, noise_std: float = 2.0) -> list[int]:
        """``left_<index>.png`` (and the right image) of the belt at ``travel_mm``, its parts
        smeared over ``motion_mm`` of travel; the parts drawn (empty: a belt without parts in
        view, the images drawn all the same)."""
        shown = self.visible(travel_mm, motion_mm)
        poses = [self.belt.truth(k, travel_mm) for k in shown]
        rng = np.random.default_rng(seed)
        images = await self._draw(poses, seed)
        for c, (name, image) in enumerate(zip(("left", "right"), images, strict=False)):
            albedo: FloatArray = image.astype(np.float64)
            if poses and motion_mm > 0:
                shift = np.mean([self.blur_px(T, motion_mm)[c] for T in poses], axis=0)
                albedo = np.asarray(cv2.filter2D(albedo, -1, line_kernel(shift),
                                                 borderType=cv2.BORDER_REPLICATE),
                                    dtype=np.float64)
            if noise_std > 0:
                albedo += rng.normal(0.0, noise_std, albedo.shape)
            cv2.imwrite(str(folder / f"{name}_{index}.png"),
                        np.clip(np.rint(albedo), 0, 255).astype(np.uint8))
        return shown

    async def _draw(self, poses: list[FloatArray], seed: int) -> list[np.ndarray]:
        from vgripd.config import config_from_dict

        data = self.config.model_dump(mode="json", exclude_none=True)
        if not poses:  # the empty belt: the renderer's background
            return [np.full((model.height, model.width), 190, np.uint8)
                    for model, _ in self.cams]
        instances = [{"translation_mm": T[:3, 3].tolist(),
                      "rotvec_rad": cv2.Rodrigues(T[:3, :3])[0].ravel().tolist()}
                     for T in poses]
        data["camera"] = {"type": "synthetic", "seed": seed, "noise_std": 0.0,
                          "instances": instances}
        cfg = config_from_dict(data)
        cls = load_class(CAMERAS, "camera", "synthetic")
        camera = cls(validate_options(cls, cfg.camera, "camera"), cfg)
        await camera.open()
        try:
            pair = await camera.grab(60.0)
        finally:
            await camera.close()
        return [pair.left] + ([pair.right] if pair.right is not None else [])


def line_kernel(shift_px: FloatArray, samples: int = 64) -> FloatArray:
    """The correlation kernel of a uniform motion by ``shift_px`` (dx, dy) during the exposure:
    the image is the mean of the scene shifted by ``s * shift`` for s in [0, 1]."""
    half = int(math.ceil(float(np.max(np.abs(shift_px))))) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1))
    for s in (np.arange(samples) + 0.5) / samples:
        # dst(x) = src(x - s d): the correlation kernel's weight sits at -s d
        u, v = -s * shift_px[0] + half, -s * shift_px[1] + half
        x0, y0 = int(math.floor(u)), int(math.floor(v))
        fx, fy = u - x0, v - y0
        k[y0, x0] += (1 - fx) * (1 - fy)
        k[y0, x0 + 1] += fx * (1 - fy)
        k[y0 + 1, x0] += (1 - fx) * fy
        k[y0 + 1, x0 + 1] += fx * fy
    return k / k.sum()


@dataclass(frozen=True)
class BeltAnswer:
    """One answered request with its belt words (map version 4, 50-61)."""

    cycle: CycleResult
    result_count: int
    source: int
    error_mm: float
    along_mm: float
    across_mm: float
    theta_deg: float
    queued: int


class BeltPlc(MockPlc):
    """The scripted PLC of a conveyor cell (map version 4): LATCH_COUNT (and LATCH_FRAME)
    written before each request, the belt words read with each answer."""

    async def __aenter__(self) -> BeltPlc:
        await self.connect()
        return self

    async def read(self, address: int = 0, count: int = MAP_SIZE_V4) -> list[int]:
        return await super().read(address, count)

    async def request(self, command: Command, count: int, frame: int | None = None,
                      recipe: int = 0) -> BeltAnswer:
        words = self.client.convert_to_registers(count, self.client.DATATYPE.UINT32,
                                                 self.word_order)
        if frame is not None:
            words += self.client.convert_to_registers(frame, self.client.DATATYPE.UINT32,
                                                      self.word_order)
        await self.write(Reg.LATCH_COUNT, words)
        seq = await self.trigger(recipe, command)
        answer = await self.wait_answer(seq, following=command is not Command.TRIGGER)
        w = await self.read(Reg.RESULT_COUNT, MAP_SIZE_V4 - Reg.RESULT_COUNT)

        def at(reg: int) -> list[int]:
            i = reg - Reg.RESULT_COUNT
            return w[i:i + 2]

        return BeltAnswer(answer, self._u32(at(Reg.RESULT_COUNT)),
                          w[Reg.LATCH_SOURCE - Reg.RESULT_COUNT], self._value(at(Reg.LATCH_ERR_MM)),
                          self._value(at(Reg.ALONG)), self._value(at(Reg.ACROSS)),
                          self._value(at(Reg.THETA)), w[Reg.QUEUED - Reg.RESULT_COUNT])
