"""Synthetic camera: renders the configured object through the configured cameras.

The accuracy of the whole system is measured on these images, so each circular mark is
rendered as the *true* image of the 3D disc: a pixel's grey level is its area coverage by the
region bounded by the disc's rim projected through the full camera model (distortion included),
estimated with ``supersample`` x ``supersample`` samples per pixel. The reported truth for a mark
is the projection of the 3D circle centre, which is not the centre of the imaged ellipse (the
two differ by a few thousandths of a pixel in the demo cell; the feature finder is judged
against the projected centre, which is what it must recover).

Marks lie in the plane normal to their feature's ``normal`` (default: the object's z axis),
dark or bright per ``polarity``. Only ``kind = "circle"`` features can be rendered.

Multi-camera cells (``calibration.cameras``): every camera renders the same object at the same
pose, concurrently. A mark with a ``normal`` is drawn only in cameras on the side it faces
(back-face culling: marks on the far side of a large frame are hidden by it); a mark behind a
camera is not drawn there either. ``ImagePair.views`` holds the N images in camera order.

Options (``[camera]`` with ``type = "synthetic"``)::

    pose = { translation_mm = [...], rotvec_rad = [...] }   # fixed T_base_obj; else random:
    max_shift_mm = 10.0    # uniform in a box of +- this around the taught reference
    max_tilt_deg = 5.0     # rotation about each base axis, uniform in +- this, about the
                           # centroid of the marks
    seed = 1               # same seed, same sequence of poses and noise
    flange_pose = {...}    # T_base_flange reported with each image (robot-mounted cameras)
    blur_px = 0.7          # Gaussian blur sigma (px): lens and focus
    noise_std = 2.0        # Gaussian sensor noise (grey levels)
    background = 190       # grey level of the background; marks at dark_level / bright_level
    gradient = 0.0         # uneven lighting: relative brightness change across the image
    drop_features = []     # faults: marks not drawn (still in truth, listed as "dropped")
    extra_blobs = 0        # faults: spurious mark-like blobs
    black = false          # faults: black images (lens cap, flash failed)
    recipe = 0             # render the object (and reference) of this recipe ([recipes.N]);
                           # 0 = the top-level [object]. Which plate lies in the cell.

``ImagePair.truth``: ``T_base_obj``, ``T_cam_obj`` (left camera), ``feature_names``,
``pixels_left`` (n, 2) and ``pixels_right`` (n, 2) or None (projected 3D centres, px),
``dropped`` (names) and ``extra_blobs_px`` (k, 2). Multi-camera cells add ``camera_names``
and ``pixels_views`` (n, N, 2): each mark's projected centre in each camera, NaN where the
camera does not see it (culled, behind it, or outside its image).
"""

from __future__ import annotations

import math
import time
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import CircleFeature, Config, PoseConfig
from vgripd.errors import CameraError, ConfigError, VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
from vgripd.types import FloatArray, ImagePair
from vgripd.vision import scene

#: Vertices of the projected rim; the polygon is within 1e-3 px of the curve for 30 px marks.
RIM_VERTICES = 256


class SyntheticOptions(DriverOptions):
    pose: PoseConfig | None = None
    max_shift_mm: float = Field(default=10.0, ge=0)
    max_tilt_deg: float = Field(default=5.0, ge=0, le=45)
    seed: int | None = None
    flange_pose: PoseConfig | None = None
    blur_px: float = Field(default=0.7, ge=0, le=10)
    noise_std: float = Field(default=2.0, ge=0, le=50)
    background: int = Field(default=190, ge=0, le=255)
    dark_level: int = Field(default=35, ge=0, le=255)
    bright_level: int = Field(default=250, ge=0, le=255)
    gradient: float = Field(default=0.0, ge=0, le=1)
    supersample: int = Field(default=8, ge=1, le=32)
    drop_features: tuple[str, ...] = ()
    extra_blobs: int = Field(default=0, ge=0, le=100)
    black: bool = False
    recipe: int = Field(default=0, ge=0, le=65535)


def disc_coverage(rim_px: FloatArray, inside_px: FloatArray, x0: int, y0: int, w: int, h: int,
                  supersample: int) -> FloatArray:
    """Area coverage of the pixels ``[x0, x0+w) x [y0, y0+h)`` by a star-shaped polygon.

    Parameters
    ----------
    rim_px : (m, 2) polygon vertices (px), any order around ``inside_px``.
    inside_px : (2,) a point from which every vertex is visible (the projected disc centre).
    supersample : samples per pixel along each axis; pixel (x, y) spans [x-0.5, x+0.5).

    Returns
    -------
    (h, w) coverage in [0, 1].
    """
    rel = rim_px - inside_px
    angles = np.arctan2(rel[:, 1], rel[:, 0])
    order = np.argsort(angles)
    angles, rel = angles[order], rel[order]
    # Close the fan across the +-pi cut so that every sample angle falls inside one edge.
    angles = np.concatenate(([angles[-1] - 2 * np.pi], angles, [angles[0] + 2 * np.pi]))
    rel = np.concatenate((rel[-1:], rel, rel[:1]))
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    xs = (np.arange(x0, x0 + w)[:, None] + offsets).ravel() - inside_px[0]
    ys = (np.arange(y0, y0 + h)[:, None] + offsets).ravel() - inside_px[1]
    dx, dy = np.meshgrid(xs, ys)
    k = np.clip(np.searchsorted(angles, np.arctan2(dy, dx)), 1, len(angles) - 1)
    a, b = rel[k - 1], rel[k]
    # Vertices sorted by angle run counter-clockwise: inside is left of edge a -> b.
    cross = (b[..., 0] - a[..., 0]) * (dy - a[..., 1]) - (b[..., 1] - a[..., 1]) * (dx - a[..., 0])
    inside = (cross >= 0).astype(np.float64)
    return inside.reshape(h, supersample, w, supersample).mean(axis=(1, 3))


def paint_disc(albedo: FloatArray, rim_px: FloatArray, centre_px: FloatArray, level: float,
               supersample: int) -> None:
    """Blend a disc of grey ``level`` into ``albedo`` (in place), touching only its bounding box."""
    h_img, w_img = albedo.shape
    x0 = max(int(math.floor(rim_px[:, 0].min())) - 1, 0)
    y0 = max(int(math.floor(rim_px[:, 1].min())) - 1, 0)
    x1 = min(int(math.ceil(rim_px[:, 0].max())) + 2, w_img)
    y1 = min(int(math.ceil(rim_px[:, 1].max())) + 2, h_img)
    if x1 <= x0 or y1 <= y0:
        return  # entirely outside the image
    cov = disc_coverage(rim_px, centre_px, x0, y0, x1 - x0, y1 - y0, supersample)
    patch = albedo[y0:y1, x0:x1]
    patch += cov * (level - patch)


def _plane_axes(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two orthonormal axes spanning the plane normal to ``normal``; for the object z axis
    exactly x and y (the rim the renderer has always drawn)."""
    n = normal / np.linalg.norm(normal)
    if abs(n[2]) > 1 - 1e-12:
        return np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]) * np.sign(n[2])
    u = np.cross([0.0, 0.0, 1.0], n)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


class SyntheticCamera(CameraDriver):
    """Renders the configured object at a fixed or random pose, with ground truth."""

    Options = SyntheticOptions
    type_name = "synthetic"
    options: SyntheticOptions

    def __init__(self, options: SyntheticOptions, config: Config) -> None:
        if options.recipe:  # the plate of that recipe lies in the cell
            try:
                config = config.for_recipe(options.recipe)
            except ConfigError as err:
                raise ConfigError(f"camera.recipe: {err}") from None
        super().__init__(options, config)
        feats = config.object.features
        for i, f in enumerate(feats):
            if not isinstance(f, CircleFeature):
                raise ConfigError(
                    f"object.features.{i}: the synthetic camera renders circles only, "
                    f"{f.name!r} is {f.kind!r}"
                )
        self._circles = tuple(f for f in feats if isinstance(f, CircleFeature))
        unknown = set(options.drop_features) - {f.name for f in feats}
        if unknown:
            raise ConfigError(f"camera.drop_features: no such features {sorted(unknown)}")

    def _open_blocking(self) -> None:
        self._multi: tuple[tuple[CameraModel, ...], FloatArray, tuple[str, ...]] | None = None
        try:
            if scene.is_multi_camera(self.config):
                flange = self.options.flange_pose
                T_flange = scene.matrix_from_pose(flange) if flange is not None else None
                self._multi = (scene.multi_camera_models(self.config),
                               scene.T_base_cameras(self.config, T_flange),
                               scene.camera_names(self.config))
            self._left, self._right = scene.camera_models(self.config)
            self._T_right_left = scene.T_right_left(self.config)
            flange = self.options.flange_pose
            self._T_base_flange = scene.matrix_from_pose(flange) if flange is not None else None
            self._T_base_camera = scene.T_base_camera(self.config, self._T_base_flange)
        except VgripError as err:
            raise CameraError(f"synthetic: cannot set up the scene: {err}") from None
        # Random poses lie around the taught reference; a fixed pose needs none (teaching).
        self._T_base_obj_ref: FloatArray | None = None
        try:
            self._T_base_obj_ref = scene.T_base_obj_ref(self.config)
        except VgripError as err:
            if self.options.pose is None:
                raise CameraError(f"synthetic: cannot set up the scene: {err}") from None
        self._rng = np.random.default_rng(self.options.seed)

    def describe(self) -> str:
        return "synthetic renderer"

    def next_pose(self) -> FloatArray:
        """T_base_obj for the next frame: the fixed pose, or a random one around the reference."""
        o = self.options
        if o.pose is not None:
            return scene.matrix_from_pose(o.pose)
        shift = self._rng.uniform(-o.max_shift_mm, o.max_shift_mm, 3)
        tilt = np.radians(self._rng.uniform(-o.max_tilt_deg, o.max_tilt_deg, 3))
        ref = self._T_base_obj_ref
        assert ref is not None  # _open_blocking refused random poses without a reference
        pts = scene.object_points(self.config)
        centre = ref[:3, :3] @ pts.mean(axis=0) + ref[:3, 3]
        R = matrix_from_rotvec(tilt)
        # Rotate about the marks' centroid (base frame), then shift.
        delta = make_transform(R, centre - R @ centre + shift)
        return delta @ ref

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        T_base_obj = self.next_pose()
        if self._multi is not None:
            return self._grab_views(T_base_obj, *self._multi)
        T_cam_obj = np.linalg.inv(self._T_base_camera) @ T_base_obj
        cams: list[tuple[str, CameraModel, FloatArray]] = [("left", self._left, T_cam_obj)]
        if self._right is not None and self._T_right_left is not None:
            cams.append(("right", self._right, self._T_right_left @ T_cam_obj))
        images: dict[str, np.ndarray] = {}
        truth: dict[str, Any] = {
            "T_base_obj": T_base_obj,
            "T_cam_obj": T_cam_obj,
            "feature_names": tuple(f.name for f in self._circles),
            "dropped": tuple(self.options.drop_features),
            "pixels_right": None,
        }
        for name, model, T in cams:
            image, centres, blobs = self._render(model, T, name)
            images[name] = image
            truth[f"pixels_{name}"] = centres
            if name == "left":
                truth["extra_blobs_px"] = blobs
        return ImagePair(
            left=images["left"],
            right=images.get("right"),
            t_mono_ns=time.monotonic_ns(),
            source="synthetic",
            meta={"seed": self.options.seed},
            T_base_flange=self._T_base_flange,
            truth=truth,
        )

    def _grab_views(self, T_base_obj: FloatArray, models: tuple[CameraModel, ...],
                    T_base_cameras: FloatArray, names: tuple[str, ...]) -> ImagePair:
        """All N cameras of a multi-camera cell, rendered concurrently (one thread each)."""
        # One generator per camera, seeded from the driver's: the same seed gives the same
        # images whatever order the threads run in.
        seeds = self._rng.integers(0, 2**63, len(models))
        jobs = [(models[j], np.linalg.inv(T_base_cameras[j]) @ T_base_obj, names[j],
                 np.random.default_rng(int(seeds[j]))) for j in range(len(models))]
        rendered = self._per_camera(
            lambda job: self._render(job[0], job[1], job[2], job[3], cull=True), jobs)
        pixels = np.stack([centres for _, centres, _ in rendered], axis=1)
        truth: dict[str, Any] = {
            "T_base_obj": T_base_obj,
            "T_cam_obj": jobs[0][1],
            "feature_names": tuple(f.name for f in self._circles),
            "dropped": tuple(self.options.drop_features),
            "camera_names": names,
            "pixels_views": pixels,
            "pixels_left": pixels[:, 0],
            "pixels_right": pixels[:, 1],
            "extra_blobs_px": rendered[0][2],
        }
        return ImagePair.of_views(
            [image for image, _, _ in rendered], time.monotonic_ns(), source="synthetic",
            meta={"seed": self.options.seed}, T_base_flange=self._T_base_flange, truth=truth)

    def _render(self, model: CameraModel, T_cam_obj: FloatArray, cam_name: str,
                rng: np.random.Generator | None = None, cull: bool = False
                ) -> tuple[np.ndarray, FloatArray, FloatArray]:
        """One camera's image, the projected mark centres (n, 2) and spurious blobs (k, 2).

        ``cull``: a mark facing away from the camera (its ``normal``), behind it or outside
        its image is not drawn and its centre is NaN (multi-camera cells); otherwise a mark
        behind the camera is a CameraError, as a one-rig cell must see every mark.
        """
        o = self.options
        rng = self._rng if rng is None else rng
        w, h = model.width, model.height
        R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
        eye_obj = -R.T @ t  # the camera centre in the object frame
        theta = np.linspace(0.0, 2 * np.pi, RIM_VERTICES, endpoint=False)
        albedo = np.full((h, w), float(o.background))
        centres = np.full((len(self._circles), 2), np.nan)
        radii_px = []
        for i, f in enumerate(self._circles):
            c_obj = np.asarray(f.xyz_mm)
            normal = np.asarray(f.normal if f.normal is not None else (0.0, 0.0, 1.0))
            if cull and (f.normal is not None and (eye_obj - c_obj) @ normal <= 0
                         or (R @ c_obj + t)[2] <= 0):
                continue
            u, v = _plane_axes(normal)
            unit_rim = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v
            try:
                centre_px = model.project(R @ c_obj + t)[0]
                rim_px = model.project((c_obj + 0.5 * f.diameter_mm * unit_rim) @ R.T + t)
            except VgripError as err:
                if cull:  # the rim reaches behind the camera: not visible
                    continue
                raise CameraError(
                    f"synthetic: mark {f.name!r} in camera {cam_name}: {err}"
                ) from None
            if cull and not (0 <= centre_px[0] < w and 0 <= centre_px[1] < h):
                continue
            centres[i] = centre_px
            radii_px.append(float(np.linalg.norm(rim_px - centre_px, axis=1).mean()))
            if f.name in o.drop_features:
                continue
            level = o.dark_level if f.polarity == "dark" else o.bright_level
            paint_disc(albedo, rim_px, centre_px, level, o.supersample)
        seen = ~np.isnan(centres[:, 0])
        blobs = (self._spurious_blobs(albedo, centres[seen], float(np.mean(radii_px)), rng)
                 if seen.any() else np.zeros((0, 2)))
        if o.black:
            return np.zeros((h, w), np.uint8), centres, blobs
        if o.gradient > 0:
            ramp = (np.arange(w)[None, :] / w + np.arange(h)[:, None] / h) / 2 - 0.5
            albedo *= 1.0 + o.gradient * ramp
        if o.blur_px > 0:
            albedo = cv2.GaussianBlur(albedo, (0, 0), o.blur_px)
        if o.noise_std > 0:
            albedo += rng.normal(0.0, o.noise_std, albedo.shape)
        return np.clip(np.rint(albedo), 0, 255).astype(np.uint8), centres, blobs

    def _spurious_blobs(self, albedo: FloatArray, centres: FloatArray,
                        radius_px: float, rng: np.random.Generator) -> FloatArray:
        """Paint ``extra_blobs`` dark discs near the object, clear of the real marks."""
        o = self.options
        h, w = albedo.shape
        lo = np.maximum(centres.min(axis=0) - 4 * radius_px, 2 * radius_px)
        hi = np.minimum(centres.max(axis=0) + 4 * radius_px, [w - 2 * radius_px, h - 2 * radius_px])
        blobs: list[FloatArray] = []
        theta = np.linspace(0.0, 2 * np.pi, RIM_VERTICES, endpoint=False)
        for _ in range(100 * o.extra_blobs):
            if len(blobs) == o.extra_blobs:
                break
            c = rng.uniform(lo, hi)
            taken = np.vstack([centres, *blobs]) if blobs else centres
            if np.min(np.linalg.norm(taken - c, axis=1)) < 3 * radius_px:
                continue
            r = radius_px * rng.uniform(0.7, 1.3)
            rim = c + r * np.c_[np.cos(theta), np.sin(theta)]
            paint_disc(albedo, rim, c, o.dark_level, o.supersample)
            blobs.append(c)
        return np.array(blobs).reshape(-1, 2)
