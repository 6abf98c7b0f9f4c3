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
    drop_features = []     # faults: marks not drawn (still in truth, listed as "dropped");
                           # "m3" on every instance, "2/m3" on instance 2 only (from 0)
    extra_blobs = 0        # faults: spurious mark-like blobs
    black = false          # faults: black images (lens cap, flash failed)
    exposure_us = 10000    # brightness scales with exposure / 10000 us (20 .. 1e6; unset: 1)
    gain_db = 0            # and with 10^(gain_db / 20), the noise too (0 .. 24 dB); both can
                           # be changed live (``set_settings``, the web view's camera form)
    recipe = 0             # render the object (and reference) of this recipe ([recipes.N]);
                           # 0 = the top-level [object]. Which plate lies in the cell.
                           # "job": the object of each job's recipe (the grab's hint), so
                           # one daemon shows every recipe's plate in turn (demos, tests)

Several identical objects (pick lists, docs/picklists.md), instead of ``pose``::

    instances = [{ translation_mm = [...], rotvec_rad = [...] }, ...]  # fixed T_base_obj each
    pallet = { count = 6, cols = 3, gap_mm = 0.0, jitter_mm = 2.0, jitter_deg = 3.0 }

The pallet is a grid of ``count`` objects in ``cols`` columns, laid out in the taught
reference's xy plane and centred on it: each object's footprint is the box of its marks (plus
one mark diameter), ``gap_mm`` apart (0: the footprints touch; negative: they overlap, marks
never do; ``pitch_mm = [x, y]`` sets the spacing of the centres instead). Each frame every
object moves by up to ``jitter_mm`` in x and y and turns by up to
``jitter_deg`` about the reference's z axis through its own marks' centroid.

``ImagePair.truth``: ``T_base_obj``, ``T_cam_obj`` (left camera), ``feature_names``,
``pixels_left`` (n, 2) and ``pixels_right`` (n, 2) or None (projected 3D centres, px),
``dropped`` (names) and ``extra_blobs_px`` (k, 2); these describe the first instance.
``instances_T_base_obj``: (k, 4, 4) every instance's pose, ``instances_dropped``: per instance
the names not drawn. Multi-camera cells add ``camera_names`` and ``pixels_views`` (n, N, 2):
each mark's projected centre (first instance) in each camera, NaN where the camera does not see
it (culled, behind it, or outside its image).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import CircleFeature, Config, Model, PoseConfig
from vgripd.errors import CameraError, CameraSettingError, ConfigError, VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
from vgripd.types import CaptureView, FloatArray, ImagePair
from vgripd.vision import scene

#: Vertices of the projected rim; the polygon is within 1e-3 px of the curve for 30 px marks.
RIM_VERTICES = 256
#: The exposure (us) at which the rendered grey levels are the configured ones, and the live
#: settings' ranges (what a device would report).
REFERENCE_EXPOSURE_US = 10000.0
EXPOSURE_US = (20.0, 1_000_000.0)
GAIN_DB = (0.0, 24.0)


class PalletOptions(Model):
    """A grid of identical objects around the taught reference (see the module docstring)."""

    count: int = Field(default=6, ge=1, le=64)
    cols: int = Field(default=3, ge=1, le=64)
    gap_mm: float = Field(default=20.0, ge=-50.0, le=1000.0)
    pitch_mm: tuple[float, float] | None = None  # centre spacing (x, y); instead of gap_mm
    jitter_mm: float = Field(default=2.0, ge=0, le=100)
    jitter_deg: float = Field(default=3.0, ge=0, le=180)

    @model_validator(mode="after")
    def _pitch_or_gap(self) -> PalletOptions:
        if self.pitch_mm is not None:
            if "gap_mm" in self.model_fields_set:
                raise ValueError("give gap_mm or pitch_mm, not both")
            if min(self.pitch_mm) <= 0:
                raise ValueError(f"pitch_mm {list(self.pitch_mm)} must be positive")
        return self


class SyntheticOptions(DriverOptions):
    pose: PoseConfig | None = None
    instances: tuple[PoseConfig, ...] = ()
    pallet: PalletOptions | None = None
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
    exposure_us: float | None = Field(default=None, ge=EXPOSURE_US[0], le=EXPOSURE_US[1])
    gain_db: float | None = Field(default=None, ge=GAIN_DB[0], le=GAIN_DB[1])
    recipe: Annotated[int, Field(ge=0, le=65535)] | Literal["job"] = 0


def checked_settings(exposure_us: float | None, gain_db: float | None) -> dict[str, float]:
    """The live settings as the options take them; ``CameraSettingError`` naming the range."""
    out: dict[str, float] = {}
    for key, value, (lo, hi), unit in (("exposure_us", exposure_us, EXPOSURE_US, "us"),
                                       ("gain_db", gain_db, GAIN_DB, "dB")):
        if value is None:
            continue
        if not lo <= value <= hi:
            raise CameraSettingError(f"synthetic: camera {key} = {value:g} {unit} is out of "
                                     f"the device's range {lo:g} .. {hi:g}")
        out[key] = float(value)
    return out


def brightness(options: SyntheticOptions) -> tuple[float, float]:
    """The factors of the image's grey levels and of its noise (exposure and gain)."""
    gain = 10 ** ((options.gain_db or 0.0) / 20)
    return (options.exposure_us or REFERENCE_EXPOSURE_US) / REFERENCE_EXPOSURE_US * gain, gain


@dataclass
class _Plate:
    """One recipe's object as the renderer needs it: its effective config, the marks, which
    of them are not drawn per instance, and the taught pose (set when the camera opens)."""

    config: Config
    circles: tuple[CircleFeature, ...]
    drop: list[set[str]]
    T_ref: FloatArray | None = None

    @classmethod
    def of(cls, config: Config, recipe: int, drop: list[set[str]]) -> _Plate:
        where = f"recipes.{recipe}.object" if recipe else "object"
        circles = []
        for i, f in enumerate(config.object.features):
            if not isinstance(f, CircleFeature):
                raise ConfigError(f"{where}.features.{i}: the synthetic camera renders circles "
                                  f"only, {f.name!r} is {f.kind!r}")
            circles.append(f)
        names = {f.name for f in circles}
        return cls(config, tuple(circles), [d & names for d in drop])


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

    Only the pixels the rim may cross are sampled: a pixel whose every sample lies closer to
    ``inside_px`` than the polygon's nearest edge is covered (1), one whose samples all lie
    beyond its farthest vertex is not (0); the samples of such a pixel would all have said so,
    so the result is the one sampling every pixel would give, bit for bit.
    """
    rel = rim_px - inside_px
    angles = np.arctan2(rel[:, 1], rel[:, 0])
    order = np.argsort(angles)
    angles, rel = angles[order], rel[order]
    r_in = _nearest_edge(rel)
    r_out = float(np.max(np.hypot(rel[:, 0], rel[:, 1])))
    # Close the fan across the +-pi cut so that every sample angle falls inside one edge.
    angles = np.concatenate(([angles[-1] - 2 * np.pi], angles, [angles[0] + 2 * np.pi]))
    rel = np.concatenate((rel[-1:], rel, rel[:1]))
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    px = np.arange(x0, x0 + w)
    py = np.arange(y0, y0 + h)
    # Farthest sample from its pixel's centre, and a margin far above the rounding of the
    # edge test below: a pixel this near the inscribed or the outer circle is sampled.
    reach = float(np.hypot(offsets[-1], offsets[-1])) + _COVER_MARGIN_PX
    d = np.hypot((px - inside_px[0])[None, :], (py - inside_px[1])[:, None])
    cover = (d + reach < r_in).astype(np.float64)
    ys, xs = np.nonzero((d + reach >= r_in) & (d - reach <= r_out))
    if len(ys):
        # The same sample coordinates as sampling the whole box: (pixel + offset) - centre.
        dx = ((px[xs][:, None] + offsets) - inside_px[0])[:, None, :]
        dy = ((py[ys][:, None] + offsets) - inside_px[1])[:, :, None]
        dx, dy = np.broadcast_arrays(dx, dy)
        k = np.clip(np.searchsorted(angles, np.arctan2(dy, dx)), 1, len(angles) - 1)
        a, b = rel[k - 1], rel[k]
        # Vertices sorted by angle run counter-clockwise: inside is left of edge a -> b.
        cross = ((b[..., 0] - a[..., 0]) * (dy - a[..., 1])
                 - (b[..., 1] - a[..., 1]) * (dx - a[..., 0]))
        inside = (cross >= 0).astype(np.float64)
        cover[ys, xs] = inside.reshape(len(ys), -1).mean(axis=1)
    return cover


#: Pixels within this distance (px) of the inscribed or the outer circle of a rim are sampled
#: (``disc_coverage``); the edge test's rounding is some 1e-12 px.
_COVER_MARGIN_PX = 1e-6


def _nearest_edge(rel: FloatArray) -> float:
    """Distance from the origin to the nearest edge of the closed polygon ``rel`` (vertices in
    order): the radius of the largest circle about the origin inside a star-shaped polygon."""
    a, b = rel, np.roll(rel, -1, axis=0)
    ab = b - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(-np.einsum("ij,ij->i", a, ab) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    nearest = a + t[:, None] * ab
    return float(np.min(np.hypot(nearest[:, 0], nearest[:, 1])))


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
    no_focus = "it renders its images: no lens to focus (blur_px sets their sharpness)"
    options: SyntheticOptions

    def __init__(self, options: SyntheticOptions, config: Config) -> None:
        if options.recipe != "job":  # that recipe's cell as before (vision.views included)
            try:
                super().__init__(options, config.for_recipe(options.recipe))
            except ConfigError as err:
                raise ConfigError(f"camera.recipe: {err}") from None
        else:
            super().__init__(options, config)
        given = [options.pose is not None, bool(options.instances), options.pallet is not None]
        if sum(given) > 1:
            raise ConfigError("camera: give one of pose, instances and pallet")
        self._count = (len(options.instances) if options.instances
                       else options.pallet.count if options.pallet is not None else 1)
        # The plate of each recipe it may render: one with a fixed ``recipe``, every
        # configured recipe with "job". A recipe whose object cannot be rendered is refused
        # here with a fixed recipe, and only when a job asks for it with "job" (the others
        # still render).
        self._plates: dict[int, _Plate | str] = {}
        if options.recipe == "job":
            numbers: tuple[int, ...] = config.recipe_numbers()
            names = set().union(*({f.name for f in config.for_recipe(n).object.features}
                                  for n in numbers))
        else:
            numbers = (options.recipe,)
            try:
                names = {f.name for f in config.for_recipe(options.recipe).object.features}
            except ConfigError as err:
                raise ConfigError(f"camera.recipe: {err}") from None
        unknown = {e.rpartition("/")[2] for e in options.drop_features} - names
        if unknown:
            raise ConfigError(f"camera.drop_features: no such features {sorted(unknown)}")
        drop: list[set[str]] = [set() for _ in range(self._count)]
        for entry in options.drop_features:
            where, _, name = entry.rpartition("/")
            if not where:
                for dropped in drop:
                    dropped.add(name)
            elif where.isdigit() and int(where) < self._count:
                drop[int(where)].add(name)
            else:
                raise ConfigError(f"camera.drop_features: {entry!r}: instance {where!r} is not "
                                  f"one of 0..{self._count - 1}")
        for number in numbers:
            try:
                self._plates[number] = _Plate.of(config.for_recipe(number), number, drop)
            except ConfigError as err:
                if options.recipe != "job":
                    raise
                self._plates[number] = str(err)
        self._use_first()

    def _use_first(self) -> None:
        """Start with the first recipe that can be rendered (the top level, normally)."""
        usable = [n for n, plate in self._plates.items() if not isinstance(plate, str)]
        if not usable:
            raise ConfigError("camera.recipe: no recipe's object can be rendered: "
                              + "; ".join(str(p) for p in self._plates.values()))
        self._use(usable[0])

    def _use(self, recipe: int) -> None:
        """Render ``recipe``'s object from now on (the state the render methods read)."""
        plate = self._plates.get(recipe)
        if plate is None:
            raise CameraError(f"synthetic: no object for recipe {recipe} (camera.recipe = "
                              f"{self.options.recipe!r}; configured: "
                              f"{', '.join(map(str, sorted(self._plates)))})")
        if isinstance(plate, str):
            raise CameraError(f"synthetic: cannot render recipe {recipe}: {plate}")
        self._plate = plate
        self._object_config = plate.config
        self._circles = plate.circles
        self._drop = plate.drop
        self._T_base_obj_ref = plate.T_ref

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
            # Several views per job: each grab renders from the flange pose of its view.
            self._view_poses: list[FloatArray] | None = None
            self._T_base_camera: FloatArray | None = None
            if self.config.vision.views == 1 or self._T_base_flange is not None:
                self._T_base_camera = scene.T_base_camera(self.config, self._T_base_flange)
        except VgripError as err:
            raise CameraError(f"synthetic: cannot set up the scene: {err}") from None
        # Random poses and pallets lie around the taught reference; fixed poses need none.
        # With recipe = "job" an untaught recipe fails only its own grabs.
        fixed = self.options.pose is not None or bool(self.options.instances)
        for number, plate in list(self._plates.items()):
            if isinstance(plate, str):
                continue
            try:
                plate.T_ref = scene.T_base_obj_ref(plate.config)
            except VgripError as err:
                if fixed:
                    continue
                why = f"cannot set up the scene: {err}"
                if self.options.recipe != "job":
                    raise CameraError(f"synthetic: {why}") from None
                self._plates[number] = f"recipes.{number}: {why}" if number else why
        try:
            self._use_first()
        except ConfigError as err:
            raise CameraError(f"synthetic: {err}") from None
        self._rng = np.random.default_rng(self.options.seed)

    def describe(self) -> str:
        return "synthetic renderer"

    def _settings_blocking(self, exposure_us: float | None, gain_db: float | None
                           ) -> dict[str, Any]:
        self.options = self.options.model_copy(update=checked_settings(exposure_us, gain_db))
        return {"camera": {"ExposureTime": self.options.exposure_us, "Gain": self.options.gain_db}}

    def next_pose(self) -> FloatArray:
        """T_base_obj for the next frame: the fixed pose, or a random one around the reference."""
        o = self.options
        if o.pose is not None:
            return scene.matrix_from_pose(o.pose)
        shift = self._rng.uniform(-o.max_shift_mm, o.max_shift_mm, 3)
        tilt = np.radians(self._rng.uniform(-o.max_tilt_deg, o.max_tilt_deg, 3))
        ref = self._T_base_obj_ref
        assert ref is not None  # _open_blocking refused random poses without a reference
        pts = scene.object_points(self._object_config)
        centre = ref[:3, :3] @ pts.mean(axis=0) + ref[:3, 3]
        R = matrix_from_rotvec(tilt)
        # Rotate about the marks' centroid (base frame), then shift.
        delta = make_transform(R, centre - R @ centre + shift)
        return delta @ ref

    def next_poses(self) -> list[FloatArray]:
        """T_base_obj of every instance for the next frame (one, several fixed, or a pallet)."""
        o = self.options
        if o.instances:
            return [scene.matrix_from_pose(p) for p in o.instances]
        if o.pallet is None:
            return [self.next_pose()]
        return self._pallet_poses(o.pallet)

    def _pallet_poses(self, pallet: PalletOptions) -> list[FloatArray]:
        """A grid of objects in the reference's xy plane, centred on it, each jittered.

        The layout is the renderer's own arithmetic on the config's numbers (the truth never
        comes from the code under test). A jitter that would make two marks of different
        objects overlap is drawn again (plates may touch; marks printed on them cannot)."""
        ref = self._T_base_obj_ref
        assert ref is not None  # _open_blocking refused a pallet without a reference
        pts = scene.object_points(self._object_config)
        diameter = max(f.diameter_mm for f in self._circles)
        lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
        pitch = ((hi - lo) + diameter + pallet.gap_mm if pallet.pitch_mm is None
                 else np.asarray(pallet.pitch_mm, dtype=np.float64))
        rows = -(-pallet.count // pallet.cols)
        cols = min(pallet.cols, pallet.count)
        centroid = pts.mean(axis=0)
        axis_z = ref[:3, 2]
        poses: list[FloatArray] = []
        placed: list[FloatArray] = []  # marks of the objects placed so far (base frame)
        for k in range(pallet.count):
            r, c = divmod(k, pallet.cols)
            grid = np.array([(c - (cols - 1) / 2) * pitch[0], (r - (rows - 1) / 2) * pitch[1],
                             0.0])
            for _ in range(100):
                jitter = np.r_[self._rng.uniform(-pallet.jitter_mm, pallet.jitter_mm, 2), 0.0]
                turn = math.radians(self._rng.uniform(-pallet.jitter_deg, pallet.jitter_deg))
                # Move in the reference's object frame, then turn about the base-frame normal
                # of that plane through this object's own marks' centroid.
                T = ref @ make_transform(np.eye(3), grid + jitter)
                centre = T[:3, :3] @ centroid + T[:3, 3]
                R = matrix_from_rotvec(turn * axis_z)
                T = make_transform(R, centre - R @ centre) @ T
                marks = pts @ T[:3, :3].T + T[:3, 3]
                if not placed or np.min(np.linalg.norm(
                        marks[:, None, :] - np.vstack(placed)[None, :, :], axis=2)) > diameter:
                    break
            else:
                raise CameraError("synthetic: camera.pallet: cannot place the objects without "
                                  "overlapping marks (raise gap_mm or lower jitter_mm)")
            placed.append(marks)
            poses.append(T)
        return poses

    def _grab_for(self, timeout_s: float, recipe: int) -> ImagePair:
        """With ``recipe = "job"`` the job's recipe chooses the plate; else the fixed one."""
        if self.options.recipe == "job":
            self._use(recipe)
        return self._grab_blocking(timeout_s)

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        if self.view is not None:
            return self._grab_view(self.view)
        poses = self.next_poses()
        if self._multi is not None:
            return self._grab_views(poses, *self._multi)
        if self._T_base_camera is None:
            raise CameraError(f"synthetic: vision.views = {self.config.vision.views}: a grab "
                              "needs its view's flange pose (or the flange_pose option)")
        inv_base_camera = np.linalg.inv(self._T_base_camera)
        T_cam = [inv_base_camera @ T for T in poses]
        cams: list[tuple[str, CameraModel, list[FloatArray]]] = [("left", self._left, T_cam)]
        if self._right is not None and self._T_right_left is not None:
            cams.append(("right", self._right, [self._T_right_left @ T for T in T_cam]))
        images: dict[str, np.ndarray] = {}
        truth: dict[str, Any] = {
            "T_base_obj": poses[0],
            "T_cam_obj": T_cam[0],
            "feature_names": tuple(f.name for f in self._circles),
            "dropped": tuple(f.name for f in self._circles if f.name in self._drop[0]),
            "pixels_right": None,
            **self._instances_truth(poses),
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

    def _grab_view(self, view: CaptureView) -> ImagePair:
        """View ``view.index`` of a several-view job: the camera at the view's flange pose
        (else ``flange_pose``). The object is placed anew at view 1 and stays put for the
        job's other views, as on a real cell; marks outside the view are not drawn."""
        flange = view.T_base_flange if view.T_base_flange is not None else self._T_base_flange
        if flange is None:
            raise CameraError(f"synthetic: view {view.index} of {view.count}: no flange pose "
                              "to render from (none came with the request and no flange_pose)")
        if view.index == 1 or self._view_poses is None:
            self._view_poses = self.next_poses()
        poses = self._view_poses
        try:
            T_base_camera = scene.T_base_camera(self.config, flange)
        except VgripError as err:
            raise CameraError(f"synthetic: view {view.index}: {err}") from None
        inv_base_camera = np.linalg.inv(T_base_camera)
        T_cam = [inv_base_camera @ T for T in poses]
        image, centres, blobs = self._render(self._left, T_cam, f"view{view.index}",
                                             cull=True)
        truth: dict[str, Any] = {
            "T_base_obj": poses[0], "T_cam_obj": T_cam[0],
            "feature_names": tuple(f.name for f in self._circles),
            "dropped": tuple(f.name for f in self._circles if f.name in self._drop[0]),
            "pixels_left": centres, "pixels_right": None, "extra_blobs_px": blobs,
            "view": view.index,
        }
        return ImagePair(left=image, right=None, t_mono_ns=time.monotonic_ns(),
                         source="synthetic", meta={"seed": self.options.seed,
                                                   "view": view.index},
                         T_base_flange=np.asarray(flange, dtype=np.float64), truth=truth)

    def _instances_truth(self, poses: list[FloatArray]) -> dict[str, Any]:
        """Truth entries of a frame with several instances (none for a single object)."""
        if len(poses) < 2:
            return {}
        return {"instances_T_base_obj": np.array(poses),
                "instances_dropped": tuple(
                    tuple(f.name for f in self._circles if f.name in dropped)
                    for dropped in self._drop)}

    def _grab_views(self, poses: list[FloatArray], models: tuple[CameraModel, ...],
                    T_base_cameras: FloatArray, names: tuple[str, ...]) -> ImagePair:
        """All N cameras of a multi-camera cell, rendered concurrently (one thread each)."""
        # One generator per camera, seeded from the driver's: the same seed gives the same
        # images whatever order the threads run in.
        seeds = self._rng.integers(0, 2**63, len(models))
        jobs = [(models[j], [np.linalg.inv(T_base_cameras[j]) @ T for T in poses], names[j],
                 np.random.default_rng(int(seeds[j]))) for j in range(len(models))]
        rendered = self._per_camera(
            lambda job: self._render(job[0], job[1], job[2], job[3], cull=True), jobs)
        pixels = np.stack([centres for _, centres, _ in rendered], axis=1)
        truth: dict[str, Any] = {
            "T_base_obj": poses[0],
            "T_cam_obj": jobs[0][1][0],
            "feature_names": tuple(f.name for f in self._circles),
            "dropped": tuple(f.name for f in self._circles if f.name in self._drop[0]),
            "camera_names": names,
            "pixels_views": pixels,
            "pixels_left": pixels[:, 0],
            "pixels_right": pixels[:, 1],
            "extra_blobs_px": rendered[0][2],
            **self._instances_truth(poses),
        }
        return ImagePair.of_views(
            [image for image, _, _ in rendered], time.monotonic_ns(), source="synthetic",
            meta={"seed": self.options.seed}, T_base_flange=self._T_base_flange, truth=truth)

    def _render(self, model: CameraModel, T_cam_objs: list[FloatArray], cam_name: str,
                rng: np.random.Generator | None = None, cull: bool = False
                ) -> tuple[np.ndarray, FloatArray, FloatArray]:
        """One camera's image of every instance, the projected mark centres (n, 2) of the
        first instance and the spurious blobs (k, 2).

        ``cull``: a mark facing away from the camera (its ``normal``), behind it or outside
        its image is not drawn and its centre is NaN (multi-camera cells); otherwise a mark
        behind the camera is a CameraError, as a one-rig cell must see every mark.
        """
        o = self.options
        rng = self._rng if rng is None else rng
        w, h = model.width, model.height
        theta = np.linspace(0.0, 2 * np.pi, RIM_VERTICES, endpoint=False)
        albedo = np.full((h, w), float(o.background))
        centres = np.full((len(T_cam_objs), len(self._circles), 2), np.nan)
        radii_px = []
        for k, T_cam_obj in enumerate(T_cam_objs):
            R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
            eye_obj = -R.T @ t  # the camera centre in the object frame
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
                    where = f"mark {f.name!r}" + (f" of instance {k}" if k else "")
                    raise CameraError(f"synthetic: {where} in camera {cam_name}: {err}") from None
                if cull and not (0 <= centre_px[0] < w and 0 <= centre_px[1] < h):
                    continue
                centres[k, i] = centre_px
                radii_px.append(float(np.linalg.norm(rim_px - centre_px, axis=1).mean()))
                if f.name in self._drop[k]:
                    continue
                level = o.dark_level if f.polarity == "dark" else o.bright_level
                paint_disc(albedo, rim_px, centre_px, level, o.supersample)
        flat = centres.reshape(-1, 2)
        seen = ~np.isnan(flat[:, 0])
        blobs = (self._spurious_blobs(albedo, flat[seen], float(np.mean(radii_px)), rng)
                 if seen.any() else np.zeros((0, 2)))
        first = centres[0]
        if o.black:
            return np.zeros((h, w), np.uint8), first, blobs
        if o.gradient > 0:
            ramp = (np.arange(w)[None, :] / w + np.arange(h)[:, None] / h) / 2 - 0.5
            albedo *= 1.0 + o.gradient * ramp
        if o.blur_px > 0:
            albedo = cv2.GaussianBlur(albedo, (0, 0), o.blur_px)
        scale, noise = brightness(o)
        if scale != 1:
            albedo *= scale
        if o.noise_std > 0:
            albedo += rng.normal(0.0, o.noise_std * noise, albedo.shape)
        return np.clip(np.rint(albedo), 0, 255).astype(np.uint8), first, blobs

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
