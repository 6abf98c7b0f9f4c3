"""The TOML configuration, validated by pydantic.

Every model forbids unknown keys, so a typo is an error naming its field path
(``calibration.left.fx: Input should be greater than 0``). Driver sections carry a ``type``
plus options that the chosen driver validates against its own model (``vgripd.registry``).

Ownership of the sections (one room per job):
- ``camera``, ``calibration``, ``object``, ``vision``, ``output``, ``picking``: the vision
  pipeline (``picking``: pick lists, docs/picklists.md).
- ``daemon``, ``links``, ``limits``, ``record``, ``conveyor``: the service and its robot links
  (``conveyor``: a moving belt, docs/conveyor.md).

Combinations that cannot work are refused here too, when the config is loaded: every link must
be able to carry ``output.vendor`` (each link class declares its ``LinkCapabilities``, looked up
through ``vgripd.registry``, so this module never imports ``drivers/``).

Recipes (docs/recipes.md): ``[recipes.N]`` (N = 1..65535) holds a ``name`` and any of the
per-object sections (``RECIPE_SECTIONS``) as overlays over the top-level ones; recipe 0 is the
top-level config itself. Each recipe's effective config (``Config.for_recipe``) is built and
validated when the config is, so a bad recipe is refused at load with its own field path
(``recipes.2.object.features.3.diameter_mm: ...``).

Size: over 700 lines on purpose: this is the one place that judges a config (house style),
so the section models and the checks across sections (every link carries ``output.vendor``,
each recipe overlaid and validated as a whole) are read together. The section models could
become a package ``vgripd/config/`` (one module per section).
"""

from __future__ import annotations

import ipaddress
import math
import tomllib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from vgripd import registry
from vgripd.configbase import (
    COMBINATION,
    MAX_RECIPE,
    RECIPE_PROBLEMS,
    DriverSection,
    format_validation_error,
)
from vgripd.configsnapshot import include_path
from vgripd.errors import ConfigError, DegenerateInputError
from vgripd.geometry.transforms import check_transform
from vgripd.geometry.vendors import VENDORS
from vgripd.redaction import REDACTED

#: The sections a recipe may overlay (``[recipes.N.<section>]``): what differs from one object
#: to the next. Everything else (camera, calibration, links, daemon, ...) belongs to the cell.
RECIPE_SECTIONS: tuple[str, ...] = ("object", "vision", "reference", "limits", "output",
                                    "picking")
#: Sections a recipe replaces as a whole instead of key by key: another object is another
#: object (its name and definition are not inherited from the top-level one).
RECIPE_WHOLE_SECTIONS: tuple[str, ...] = ("object",)
#: Longest recipe name (characters).
MAX_RECIPE_NAME = 64


class Model(BaseModel):
    """Base of every config model: unknown keys are errors, values are immutable, and numbers
    are finite (TOML can spell ``inf`` and ``nan``; no setting means either)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _allow_entry(entry: str) -> str:
    """One ``allow`` entry: an address (``10.0.0.5``) or a network (``10.0.1.0/24``). Judged
    here, once, so a typo is a config error naming ``...allow.<index>``, not an open door."""
    try:
        ipaddress.ip_network(entry.strip(), strict=False)
    except ValueError:
        raise ValueError(f"{entry!r} is not an IP address or network (e.g. \"10.0.0.5\" or "
                         f"\"10.0.1.0/24\")") from None
    return entry.strip()


#: ``allow = ["10.0.0.5", "10.0.1.0/24"]`` of a server surface (a link or the web view): other
#: client addresses are closed at accept (vgripd.service.gate); unset = every address. An
#: empty list is refused (it would lock every client out).
AllowList = Annotated[list[Annotated[str, AfterValidator(_allow_entry)]], Field(min_length=1)] \
    | None


class OutputConfig(Model):
    """What the robot receives, in one vendor's convention.

    ``mode = "offset"``: the base-frame correction ``T_offset`` (the robot applies it to its
    own taught grip). ``mode = "grip"``: the absolute grip pose ``T_offset @ G`` with ``G`` =
    ``reference.grip`` (taught with ``vgripd teach --grip``; see docs/teach.md).
    """

    vendor: str = "kuka"
    mode: Literal["offset", "grip"] = "offset"

    @field_validator("vendor")
    @classmethod
    def _known_vendor(cls, vendor: str) -> str:
        if vendor not in VENDORS:
            raise ValueError(f"unknown vendor {vendor!r} (known: {', '.join(sorted(VENDORS))})")
        return vendor


class LimitsConfig(Model):
    """Safety gates applied before anything is published (found pose against the taught one).

    ``max_translation_mm``: how far one point P of the object may have moved between the
    taught reference and the found pose (``|T_base_obj @ P - T_base_obj_ref @ P|``), not the
    length of the base-frame offset's translation (which adds the lever arm of any rotation
    about the robot base). P is ``point_mm`` (object frame) when set, else ``point``:
    ``"origin"`` (the object frame's origin), ``"centroid"`` (of the model points) or
    ``"grip"`` (the position of ``reference.grip``); unset = ``"origin"`` for a CAD object,
    ``"centroid"`` for ``object.definition = "reference"`` (whose origin is the robot base's).
    ``max_rotation_deg``: the angle of the object's rotation between reference and found pose.
    ``workspace_min_mm``/``workspace_max_mm``: a box in the robot base frame that every model
    point of the found object must lie in (both or neither; unset = no box check).
    See docs/pipeline.md, "Limits".
    """

    max_translation_mm: float = Field(default=50.0, gt=0)
    max_rotation_deg: float = Field(default=10.0, gt=0)
    point: Literal["origin", "centroid", "grip"] | None = None
    point_mm: tuple[float, float, float] | None = None
    workspace_min_mm: tuple[float, float, float] | None = None
    workspace_max_mm: tuple[float, float, float] | None = None

    @model_validator(mode="after")
    def _box(self) -> LimitsConfig:
        if self.point is not None and self.point_mm is not None:
            raise ValueError("give either point or point_mm (the point whose displacement "
                             "max_translation_mm limits), not both")
        lo, hi = self.workspace_min_mm, self.workspace_max_mm
        if (lo is None) != (hi is None):
            raise ValueError("workspace_min_mm and workspace_max_mm go together")
        if lo is not None and hi is not None and not all(
            a < b for a, b in zip(lo, hi, strict=True)
        ):
            raise ValueError(
                f"workspace_min_mm {list(lo)} must be below workspace_max_mm {list(hi)}"
            )
        return self


class VisionConfig(Model):
    """Feature finding, matching and the residual gates of the pipeline (see docs/pipeline.md).

    Pixel figures are at full image resolution; mm figures in the left camera frame.
    """

    working_distance_mm: tuple[float, float] = (300.0, 2000.0)
    downscale: int = Field(default=2, ge=1, le=8)
    min_contrast: float = Field(default=25.0, gt=0, le=255)
    min_circularity: float = Field(default=0.6, gt=0, le=1)
    template_min_score: float = Field(default=0.7, gt=0, le=1)
    epipolar_tolerance_px: float = Field(default=3.0, gt=0)
    model_tolerance_mm: float = Field(default=3.0, gt=0)
    min_features: int = Field(default=4, ge=3)
    max_fit_rms_mm: float = Field(default=1.0, gt=0)
    max_reprojection_px: float = Field(default=1.5, gt=0)
    epipolar_warn_px: float = Field(default=1.0, gt=0)
    # Multi-camera cells (docs/multicamera.md): a rig whose own pose differs from the pose of
    # the other rigs by more than this at its marks (mm) or in rotation (deg) is named as
    # disagreeing (a camera moved since calibration).
    rig_deviation_mm: float = Field(default=3.0, gt=0)
    rig_deviation_deg: float = Field(default=0.5, gt=0)
    # Several views per job for one robot-mounted camera (docs/multicamera.md, "Several
    # views per job"): the robot takes ``views`` images from as many poses (CAPTURE 1..N),
    # the last one runs one fit over all. ``view_poses``: the taught flange pose of each view,
    # for links that cannot report the robot's pose (Modbus); ``view_timeout_s``: the longest
    # wait for the next view before the job ends CAMERA_ERROR.
    views: int = Field(default=1, ge=1, le=8)
    view_poses: tuple[PoseConfig, ...] = ()
    view_timeout_s: float = Field(default=30.0, gt=0, le=3600)

    @model_validator(mode="after")
    def _ranges(self) -> VisionConfig:
        near, far = self.working_distance_mm
        if not 0 < near < far:
            raise ValueError(
                f"working_distance_mm must be [near, far] with 0 < near < far, got {[near, far]}"
            )
        if self.epipolar_warn_px > self.epipolar_tolerance_px:
            raise ValueError("epipolar_warn_px must not exceed epipolar_tolerance_px")
        if self.view_poses and len(self.view_poses) != self.views:
            raise ValueError(f"view_poses has {len(self.view_poses)} poses for views = "
                             f"{self.views}: give one flange pose per view, or none")
        return self


class PickPointConfig(Model):
    """One grip point of the object (``[[picking.pick_points]]``): ``pose`` is the gripper's
    pose in the object frame (for ``object.definition = "reference"``: in the base frame with
    the object at its reference). ``id`` goes to the robot with the result; ``priority``: a
    smaller number is tried first (1 = first choice). See docs/picklists.md."""

    id: int = Field(ge=1, le=32767)
    priority: int = Field(default=1, ge=0, le=32767)
    pose: PoseConfig


class PickingConfig(Model):
    """Pick lists: several identical objects in one job's images (docs/picklists.md).

    ``max_objects = 1`` (the default) is the single-object job of before: one pose, no
    instance list. Above 1 every instance found is located, gated and ordered, and up to
    ``max_objects`` of them are returned, the pickable ones first in the order ``order``:

    - ``"z"``: highest first (base-frame z of the instance's pick point, or its mark centroid
      without pick points);
    - ``"nearest"``: nearest first to ``point_mm`` (base frame);
    - ``"axis"``: ascending along the direction ``axis`` (base frame; its length is ignored);
    - ``"score"``: best detection score first.

    ``pick_points``: grip points with ids and priorities; for each instance the first one in
    priority order whose target passes the gates is chosen. Empty: the object's own grip
    (``pick_id`` 0).
    """

    max_objects: int = Field(default=1, ge=1, le=64)
    order: Literal["z", "nearest", "axis", "score"] = "z"
    point_mm: Vec3 | None = None
    axis: Vec3 | None = None
    pick_points: tuple[PickPointConfig, ...] = ()

    @model_validator(mode="after")
    def _order_parameters(self) -> PickingConfig:
        if self.order == "nearest" and self.point_mm is None:
            raise ValueError('order = "nearest" needs point_mm (base frame, mm)')
        if self.order == "axis":
            if self.axis is None:
                raise ValueError('order = "axis" needs axis (a direction in the base frame)')
            if sum(a * a for a in self.axis) < 1e-12:
                raise ValueError(f"axis {list(self.axis)} has no direction (zero length)")
        if self.point_mm is not None and self.order != "nearest":
            raise ValueError(f'point_mm is the parameter of order = "nearest", not of '
                             f'order = "{self.order}"')
        if self.axis is not None and self.order != "axis":
            raise ValueError(f'axis is the parameter of order = "axis", not of '
                             f'order = "{self.order}"')
        if self.pick_points and self.max_objects == 1:
            raise ValueError("pick_points need max_objects > 1 (a single-object job has no "
                             "pick list to carry the pick id)")
        ids = [p.id for p in self.pick_points]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            raise ValueError(f"pick_points: id {twice[0]} is used twice")
        return self


class DaemonConfig(Model):
    """The service: one job at a time, each bounded by ``job_timeout_s`` (see docs/daemon.md)."""

    job_timeout_s: float = Field(default=10.0, gt=0)
    # The camera down (no job can get a frame) for longer than this: the systemd watchdog stops
    # pinging, so systemd restarts the service (docs/daemon.md, "systemd integration").
    camera_down_restart_s: float = Field(default=60.0, gt=0)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    # Camera driver, pipeline and recorder in a worker process (docs/daemon.md, "Worker
    # process"); false runs them in the daemon's own interpreter (threads), as before.
    worker: bool = True
    # Cycle-time percentiles in `vgripd status` are taken over this many most recent jobs.
    stats_window: int = Field(default=1000, ge=1)
    # RECALIBRATE warning (docs/daemon.md): over the last `recalibrate_window` stereo jobs, the
    # share whose median epipolar residual exceeds vision.epipolar_warn_px; judged only once
    # `recalibrate_min_jobs` are in the window, raised while the share is above
    # `recalibrate_share`.
    recalibrate_window: int = Field(default=50, ge=1)
    recalibrate_share: float = Field(default=0.2, ge=0, lt=1)
    recalibrate_min_jobs: int = Field(default=10, ge=1)
    # File descriptors kept out of the server surfaces' share of RLIMIT_NOFILE: PLC client
    # links, the worker's pipes, shared-memory segments, recordings, the camera (docs/daemon.md,
    # "File budget").
    fd_reserve: int = Field(default=256, ge=32, le=1_000_000)

    @model_validator(mode="after")
    def _recalibrate_window(self) -> DaemonConfig:
        if self.recalibrate_min_jobs > self.recalibrate_window:
            raise ValueError(
                f"recalibrate_min_jobs ({self.recalibrate_min_jobs}) must not exceed "
                f"recalibrate_window ({self.recalibrate_window})"
            )
        return self


class RecordConfig(Model):
    """Recording of every job (images, metadata, config, result) for offline ``vgripd replay``.

    Off by default; when on, the oldest jobs are deleted beyond ``max_mb`` of the folder.
    """

    enabled: bool = False
    folder: Path = Path("/var/lib/vgripd/record")
    max_mb: float = Field(default=500.0, gt=0)


#: Plausible encoder scales (counts per mm of belt travel): below, the belt's position is
#: coarser than a part's tolerance; above, no encoder input counts that fast at belt speed.
COUNTS_PER_MM_RANGE = (0.05, 5000.0)
#: Largest angle (deg) between ``conveyor.direction`` and the belt plane.
BELT_PLANE_DEG = 0.5


class ConveyorConfig(Model):
    """A moving belt the parts are seen and picked on (docs/conveyor.md). Absent: parts stand
    still between the trigger and the pick.

    ``latch``: where the belt position at the exposure comes from: ``"link"`` (the PLC or robot
    latches the encoder count with the trigger and writes it with the request), ``"frame_id"``
    (the camera is triggered by an encoder divider; the PLC writes the count it latched with
    the frame's id), ``"timestamp"`` (no latch: the count the link last reported, carried to
    the exposure's device timestamp at ``speed_mm_s``; each job states the error this leaves).
    ``direction``: the belt's travel in the base frame (unit, in the plane of ``normal``);
    ``origin_mm``: a point on the belt surface; ``window_mm``: the pick window as
    (upstream, downstream) distances along the belt from ``origin_mm``; ``trigger_distance_mm``:
    belt travel between two images; ``speed_mm_s``: the highest belt speed (for the blur check
    and the timestamp latch); ``max_blur_px``: the largest smear in the image during one
    exposure at that speed; ``sigma_mm``: one sigma of a part's position carried along the belt
    (from ``vgripd calibrate conveyor``), whose ``match_sigmas`` multiple matches the same part
    in two images. ``trigger``: ``"request"`` (each image is a job the PLC or robot asks for)
    or ``"travel"`` (the PLC only publishes the count; the daemon starts a job every
    ``trigger_distance_mm`` of travel, docs/conveyor.md "Triggering by travel").
    """

    latch: Literal["link", "frame_id", "timestamp"] = "link"
    trigger: Literal["request", "travel"] = "request"
    counts_per_mm: float = Field(gt=0)
    encoder_bits: Literal[16, 32] = 32
    direction: tuple[float, float, float]
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    window_mm: tuple[float, float]
    trigger_distance_mm: float = Field(gt=0)
    speed_mm_s: float = Field(gt=0, le=10_000.0)
    max_blur_px: float = Field(default=1.0, gt=0)
    sigma_mm: float = Field(default=0.5, gt=0)
    match_sigmas: float = Field(default=6.0, ge=1.0, le=100.0)
    match_deg: float = Field(default=5.0, gt=0, le=180.0)
    timestamp_error_ms: float = Field(default=2.0, ge=0)

    @model_validator(mode="after")
    def _belt(self) -> ConveyorConfig:
        for name in ("direction", "normal"):
            v = getattr(self, name)
            length = math.sqrt(sum(x * x for x in v))
            if abs(length - 1.0) > 1e-3:
                raise ValueError(f"conveyor.{name} {list(v)} is not a unit vector (length "
                                 f"{length:.6g}): give the belt's {name} normalised")
        dot = sum(a * b for a, b in zip(self.direction, self.normal, strict=True))
        tilt = math.degrees(math.asin(min(1.0, abs(dot))))
        if tilt > BELT_PLANE_DEG:
            raise ValueError(f"conveyor.direction {list(self.direction)} leaves the belt plane "
                             f"(normal {list(self.normal)}) by {tilt:.2f} deg (at most "
                             f"{BELT_PLANE_DEG} deg): the belt runs in its own plane")
        lo, hi = COUNTS_PER_MM_RANGE
        if not lo <= self.counts_per_mm <= hi:
            raise ValueError(f"conveyor.counts_per_mm {self.counts_per_mm:g} is implausible "
                             f"(expected {lo:g} .. {hi:g} counts per mm): mm per count given, "
                             "or counts per metre?")
        up, down = self.window_mm
        if not up < down:
            raise ValueError(f"conveyor.window_mm {list(self.window_mm)}: the upstream limit "
                             "must be below the downstream one (distances along direction)")
        if self.trigger_distance_mm >= down - up:
            raise ValueError(f"conveyor.trigger_distance_mm {self.trigger_distance_mm:g} is "
                             f"not shorter than the pick window ({down - up:g} mm): parts "
                             "would pass between two images")
        if self.trigger == "travel":
            self._travel_fits()
        return self

    def _travel_fits(self) -> None:
        """Triggering by travel: the count is read, not latched at the exposure, and the
        trigger distance is a small part of the counter's range (the wrap stays unambiguous)."""
        if self.latch != "timestamp":
            raise ValueError(f'conveyor.latch = "{self.latch}" with trigger = "travel": the '
                             "link publishes the count now, none is latched at the exposure "
                             'and LATCH_FRAME has no count of its own: set latch = "timestamp" '
                             "(the count carried to the image's time)")
        span = 1 << self.encoder_bits
        if self.trigger_distance_mm * self.counts_per_mm >= span / 4:
            raise ValueError(f"conveyor.trigger_distance_mm {self.trigger_distance_mm:g} is "
                             f"{self.trigger_distance_mm * self.counts_per_mm:.0f} counts, not "
                             f"below a quarter of the {self.encoder_bits}-bit counter "
                             f"({span // 4}): the travel between two counts read is ambiguous")

    def window_points(self) -> list[tuple[float, float, float]]:
        """The pick window's two ends on the belt line, in the base frame."""
        (ox, oy, oz), (dx, dy, dz) = self.origin_mm, self.direction
        return [(ox + s * dx, oy + s * dy, oz + s * dz) for s in self.window_mm]


class CalibrationWalkConfig(Model):
    """How the robot programs move in a walked hand-eye calibration (docs/calibration-handeye.md,
    "Walked calibration"): ``vgripd robot-program`` writes these into each brand's walk routine
    (vgripd commands no motion). The defaults are the UR RTDE routine's (robots/urscript)."""

    speed_mm_s: float = Field(default=50.0, gt=0, le=250.0)  # linear, flange; <= 250: T1 speed
    settle_s: float = Field(default=1.0, ge=0, le=60.0)  # standstill before the image


class StatusConfig(Model):
    """The operator web view, its JSON API (``GET /api/status`` behind ``vgripd status``) and
    ``/metrics`` (port 0: any free). See docs/web.md.

    Read-only unless an action is enabled here; an enabled action also needs a request that
    carries ``token`` (``Authorization: Bearer <token>``). A bind that is not a loopback
    address needs a ``token``, and then every route needs it too (the header, or the cookie
    of ``/login``) unless ``public_read`` opens the read-only routes to anyone who can reach
    the port. ``allowed_hosts``: host names (or addresses) a browser may call the view by,
    besides the bind address (and ``localhost`` on a loopback or wildcard bind); any other
    ``Host:`` is refused (421), which stops DNS rebinding. ``history``: jobs kept for the
    history page; ``bundle_jobs``: recorded jobs put in a support bundle.
    """

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(default=8730, ge=0, le=65535)
    token: str | None = None
    public_read: bool = False
    allowed_hosts: list[str] = Field(default_factory=list, max_length=64)
    allow_trigger: bool = False
    allow_support_bundle: bool = False
    # Commissioning from the page (docs/web.md, "Reload, tuning and audit"): reload the config
    # file, try vision parameters on the last job's images and save them to the config's
    # include (all with the token).
    allow_config_edit: bool = False
    history: int = Field(default=100, ge=1, le=10000)
    bundle_jobs: int = Field(default=5, ge=0, le=100)
    # Connections (docs/web.md, "Connections"): at most `max_connections` at once (ones that
    # never completed a request are evicted first), complete request headers within
    # `header_timeout_s` of connecting or of the previous answer, a body within
    # `body_timeout_s`; `allow` = client addresses/networks (unset: any).
    max_connections: int = Field(default=64, ge=2, le=4096)
    header_timeout_s: float = Field(default=10.0, ge=0.5, le=600.0)
    body_timeout_s: float = Field(default=10.0, ge=0.5, le=600.0)
    allow: AllowList = None
    # Wrong tokens (docs/web.md, "Wrong tokens"), per client address as the OPC UA link's
    # logins: each answered no sooner than 1 / `login_rate_per_s` after the previous one,
    # `login_failures` in a row lock the address's tokens out for `login_lockout_s`.
    login_failures: int = Field(default=10, ge=1, le=1000)
    login_rate_per_s: float = Field(default=10.0, gt=0.0, le=1000.0)
    login_lockout_s: float = Field(default=60.0, ge=0.0, le=86400.0)

    @field_validator("token")
    @classmethod
    def _long_token(cls, token: str | None) -> str | None:
        # The redaction marker: a recorded or bundled config stays loadable (replay); the
        # web view refuses to serve with it.
        if token is not None and token != REDACTED and len(token) < 16:
            raise ValueError("status.token must have at least 16 characters")
        return token

    @field_validator("allowed_hosts")
    @classmethod
    def _host_names(cls, hosts: list[str]) -> list[str]:
        for i, host in enumerate(hosts):
            name = host.strip("[]")
            if not name or any(c in name for c in "/@ ?#") or (":" in name and not _is_ip(name)):
                raise ValueError(f"status.allowed_hosts[{i}] = {host!r}: a host name or address "
                                 f"as a browser puts it in the URL, without scheme, port or path")
        return [h.strip("[]").lower().rstrip(".") for h in hosts]

    @model_validator(mode="after")
    def _token_where_needed(self) -> StatusConfig:
        if self.token is None and not _is_loopback(self.host):
            raise ValueError(
                f"status.host = {self.host!r} is not a loopback address: set status.token "
                f"(at least 16 characters) or bind status.host = \"127.0.0.1\"")
        wanted = [k for k in ("allow_trigger", "allow_support_bundle", "allow_config_edit")
                  if getattr(self, k)]
        if self.token is None and wanted:
            raise ValueError(f"status.{wanted[0]} = true needs status.token (actions are "
                             f"accepted only from requests that carry it)")
        return self

    @property
    def guards_reads(self) -> bool:
        """Whether the read-only routes need the token too (a non-loopback bind, unless
        ``public_read``)."""
        return not _is_loopback(self.host) and not self.public_read


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name other than localhost may resolve to anything
        return False


# --- camera calibration, object model, taught reference (owner: cameras/scene) -------------

Vec3 = tuple[float, float, float]
_Row4 = tuple[float, float, float, float]
_Matrix4 = tuple[_Row4, _Row4, _Row4, _Row4]


class PoseConfig(Model):
    """A rigid transform ``T_a_b`` (pose of frame b in frame a, mm and rad), in exactly one form.

    Either ``translation_mm = [x, y, z]`` with ``rotvec_rad = [rx, ry, rz]`` (axis * angle,
    default no rotation), or ``matrix = [[4 rows of 4]]`` (homogeneous, last row 0 0 0 1).
    """

    translation_mm: Vec3 | None = None
    rotvec_rad: Vec3 | None = None
    matrix: _Matrix4 | None = None

    @field_validator("matrix")
    @classmethod
    def _rigid(cls, m: _Matrix4 | None) -> _Matrix4 | None:
        if m is not None:
            try:
                check_transform(m, "matrix")
            except DegenerateInputError as err:
                raise ValueError(str(err)) from None
        return m

    @model_validator(mode="after")
    def _one_form(self) -> PoseConfig:
        if self.matrix is not None:
            if self.translation_mm is not None or self.rotvec_rad is not None:
                raise ValueError("give either matrix or translation_mm/rotvec_rad, not both")
        elif self.translation_mm is None:
            raise ValueError("pose needs translation_mm (with optional rotvec_rad) or matrix")
        return self


class IntrinsicsConfig(Model):
    """One camera: pinhole + Brown distortion in OpenCV order (= Bouguet ``kc``), pixels.

    ``dist = [k1, k2, p1, p2, k3]``; ``skew`` is the x-axis shear in px (Bouguet
    ``alpha_c * fc[0]``), 0 for square-pixel sensors.
    """

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    skew: float = 0.0
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = Field(gt=0)
    height: int = Field(gt=0)

    @model_validator(mode="after")
    def _principal_point_inside(self) -> IntrinsicsConfig:
        if not (0 <= self.cx < self.width and 0 <= self.cy < self.height):
            raise ValueError(
                f"principal point ({self.cx}, {self.cy}) lies outside the "
                f"{self.width}x{self.height} image"
            )
        return self


class StereoConfig(Model):
    """The rig: ``T_right_left`` = pose of the left camera in the right camera frame
    (Bouguet/OpenCV ``stereoCalibrate``: ``X_R = R X_L + T``)."""

    T_right_left: PoseConfig


class HandEyeConfig(Model):
    """Where the (left) camera is: fixed in the cell or carried by the robot.

    ``mounting = "fixed"`` needs ``T_base_camera`` (camera in the robot base frame);
    ``mounting = "robot"`` needs ``T_flange_camera`` (camera in the flange frame; the flange pose
    at capture then comes with each image).
    """

    mounting: Literal["fixed", "robot"] = "fixed"
    T_base_camera: PoseConfig | None = None
    T_flange_camera: PoseConfig | None = None

    @model_validator(mode="after")
    def _pose_matches_mounting(self) -> HandEyeConfig:
        need, other = (
            ("T_base_camera", "T_flange_camera")
            if self.mounting == "fixed"
            else ("T_flange_camera", "T_base_camera")
        )
        if getattr(self, need) is None:
            raise ValueError(f'mounting = "{self.mounting}" needs {need}')
        if getattr(self, other) is not None:
            raise ValueError(f'mounting = "{self.mounting}" takes {need}, not {other}')
        return self


#: Names of cameras and rigs: they become keys of residuals (``rig.<name>.reprojection_px``)
#: and of messages, so plain lower-case words.
NAME_PATTERN = r"^[a-z0-9_]+$"

#: How many cameras one cell may have (``calibration.cameras``).
MAX_CAMERAS = 8


class CameraEntryConfig(Model):
    """One camera of a multi-camera cell: its intrinsics and where it is.

    ``mounting = "fixed"`` needs ``T_base_camera`` (the camera in the robot base frame);
    ``mounting = "robot"`` needs ``T_flange_camera`` (the camera on the flange; the flange pose
    comes with each acquisition). Same meaning as ``calibration.hand_eye``, per camera.
    """

    name: str = Field(pattern=NAME_PATTERN, max_length=32)
    intrinsics: IntrinsicsConfig
    mounting: Literal["fixed", "robot"] = "fixed"
    T_base_camera: PoseConfig | None = None
    T_flange_camera: PoseConfig | None = None

    @model_validator(mode="after")
    def _pose_matches_mounting(self) -> CameraEntryConfig:
        HandEyeConfig(mounting=self.mounting, T_base_camera=self.T_base_camera,
                      T_flange_camera=self.T_flange_camera)
        return self

    def hand_eye(self) -> HandEyeConfig:
        """This camera's pose as the single-camera ``calibration.hand_eye`` section."""
        return HandEyeConfig(mounting=self.mounting, T_base_camera=self.T_base_camera,
                             T_flange_camera=self.T_flange_camera)


class RigConfig(Model):
    """A named group of cameras (usually a stereo pair on one side of the object).

    Rigs do not change the fit (one pose over all marks of all cameras); they name the groups
    whose residuals are reported apart and which the consistency check can blame (a camera
    moved, a rig knocked). A camera belongs to at most one rig; one in no rig is a group of
    its own, named after the camera.
    """

    name: str = Field(pattern=NAME_PATTERN, max_length=32)
    cameras: tuple[str, ...] = Field(min_length=1)


_PLACEHOLDER_INTRINSICS = IntrinsicsConfig(fx=1, fy=1, cx=0, cy=0, width=1, height=1)
_PLACEHOLDER_HAND_EYE = HandEyeConfig(T_base_camera=PoseConfig(translation_mm=(0, 0, 0)))


class CalibrationConfig(Model):
    """Intrinsics of one or two cameras, the stereo rig and the hand-eye pose; or N cameras.

    Without ``right`` (and ``stereo``) the job runs in single-camera (PnP) mode.

    ``cameras`` (2..8 entries) makes a multi-camera cell (docs/multicamera.md): every camera
    has its own pose in the base frame or on the flange, ``rigs`` group them. Then ``right``,
    ``stereo`` and ``hand_eye`` must not be given, and ``left`` / ``hand_eye`` are filled in
    from the first camera, so that single-camera tools (commissioning, teach) see camera 0 as
    "the" camera. (A ``left`` / ``hand_eye`` equal to camera 0 is accepted, so that a dumped
    config loads again.)
    """

    left: IntrinsicsConfig
    right: IntrinsicsConfig | None = None
    stereo: StereoConfig | None = None
    hand_eye: HandEyeConfig
    cameras: tuple[CameraEntryConfig, ...] | None = None
    rigs: tuple[RigConfig, ...] = ()

    @model_validator(mode="before")
    @classmethod
    def _left_from_first_camera(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not data.get("cameras"):
            return data
        data = dict(data)
        first = data["cameras"][0] if isinstance(data["cameras"], list | tuple) else None
        try:
            first = CameraEntryConfig.model_validate(first)
        except ValidationError:
            # The field validation reports calibration.cameras.0 and fails the whole config;
            # placeholders keep it from also calling left and hand_eye missing.
            data.setdefault("left", _PLACEHOLDER_INTRINSICS)
            data.setdefault("hand_eye", _PLACEHOLDER_HAND_EYE)
            return data
        for key in ("right", "stereo"):
            if data.get(key) is not None:
                raise ValueError(f"calibration.{key} is not used with calibration.cameras: "
                                 f"remove it (a pair is two entries of calibration.cameras)")
        derived = {"left": first.intrinsics, "hand_eye": first.hand_eye()}
        for key, value in derived.items():
            given = data.get(key)
            if given is None:
                data[key] = value
                continue
            given_model = type(value).model_validate(given) if isinstance(given, dict) else given
            if given_model != value:
                raise ValueError(
                    f"calibration.{key} is not used with calibration.cameras and differs from "
                    f"the first camera ({first.name!r}): remove calibration.{key}")
        return data

    @model_validator(mode="after")
    def _stereo_complete(self) -> CalibrationConfig:
        if (self.right is None) != (self.stereo is None):
            raise ValueError("calibration.right and calibration.stereo go together")
        return self

    @model_validator(mode="after")
    def _cameras_and_rigs(self) -> CalibrationConfig:
        if self.cameras is None:
            if self.rigs:
                raise ValueError("calibration.rigs needs calibration.cameras")
            return self
        n = len(self.cameras)
        if not 2 <= n <= MAX_CAMERAS:
            raise ValueError(f"calibration.cameras: a multi-camera cell has 2 to {MAX_CAMERAS} "
                             f"cameras, got {n} (one or two cameras: use calibration.left/right)")
        names: dict[str, int] = {}
        for i, cam in enumerate(self.cameras):
            if cam.name in names:
                raise ValueError(f"calibration.cameras.{i}.name: {cam.name!r} is already the "
                                 f"name of calibration.cameras.{names[cam.name]}")
            names[cam.name] = i
        owner: dict[str, str] = {}
        rig_names: set[str] = set()
        for i, rig in enumerate(self.rigs):
            where = f"calibration.rigs.{i}"
            if rig.name in rig_names:
                raise ValueError(f"{where}.name: duplicate rig name {rig.name!r}")
            if rig.name in names:
                raise ValueError(f"{where}.name: {rig.name!r} is also a camera's name (a camera "
                                 "outside every rig is reported under its own name)")
            rig_names.add(rig.name)
            for j, cam_name in enumerate(rig.cameras):
                if cam_name not in names:
                    raise ValueError(f"{where}.cameras.{j}: no camera named {cam_name!r} in "
                                     f"calibration.cameras (known: {', '.join(names)})")
                if cam_name in owner:
                    raise ValueError(f"{where}.cameras.{j}: camera {cam_name!r} is already in "
                                     f"rig {owner[cam_name]!r} (a camera is in one rig at most)")
                owner[cam_name] = rig.name
        return self

    def camera_groups(self) -> tuple[tuple[str, tuple[int, ...]], ...]:
        """``(group name, camera indices)`` of a multi-camera cell: the rigs in config order,
        then every camera outside all rigs as a group of its own; () without cameras."""
        if self.cameras is None:
            return ()
        index = {cam.name: i for i, cam in enumerate(self.cameras)}
        groups = [(rig.name, tuple(index[c] for c in rig.cameras)) for rig in self.rigs]
        grouped = {i for _, members in groups for i in members}
        groups += [(cam.name, (i,)) for i, cam in enumerate(self.cameras) if i not in grouped]
        return tuple(groups)


class _FeatureBase(Model):
    """``normal``: optional outward normal of the mark's face (object frame, any length > 0).

    A mark is seen only from the side its normal points to (a frame with marks on both sides:
    each camera sees its own side). Unset: the object's z axis, and the mark counts as seen
    from both sides (the single-rig cells that predate it look at the object from one side).
    """

    name: str = Field(min_length=1)
    xyz_mm: Vec3
    normal: Vec3 | None = None

    @field_validator("normal")
    @classmethod
    def _nonzero_normal(cls, normal: Vec3 | None) -> Vec3 | None:
        if normal is not None and not math.hypot(*normal) > 1e-9:
            raise ValueError(f"normal must be a non-zero vector, got {list(normal)}")
        return normal


class CircleFeature(_FeatureBase):
    """A circular mark; its centre is the feature point."""

    kind: Literal["circle"]
    diameter_mm: float = Field(gt=0)
    polarity: Literal["dark", "bright"] = "dark"


class ArucoFeature(_FeatureBase):
    """An ArUco marker; its centre is the feature point."""

    kind: Literal["aruco"]
    marker_id: int = Field(ge=0)
    dictionary: str = Field(default="DICT_4X4_50", pattern=r"^DICT_[A-Z0-9_]+$")
    size_mm: float = Field(gt=0)


class TemplateFeature(_FeatureBase):
    """A grey-level template (image file) whose centre is the feature point."""

    kind: Literal["template"]
    template: str = Field(min_length=1)
    size_px: int = Field(gt=0)


FeatureConfig = Annotated[
    CircleFeature | ArucoFeature | TemplateFeature, Field(discriminator="kind")
]


class ObjectConfig(Model):
    """The object's features and how their coordinates are defined.

    ``definition = "cad"``: ``xyz_mm`` are model points in the object frame (from CAD).
    ``definition = "reference"``: ``xyz_mm`` are the points as measured in the robot base frame
    with the object at its taught reference position (relative orientation, no CAD needed).
    """

    name: str = Field(default="object", min_length=1)
    definition: Literal["cad", "reference"] = "cad"
    features: tuple[FeatureConfig, ...]

    @field_validator("features")
    @classmethod
    def _enough_unique(cls, feats: tuple[Any, ...]) -> tuple[Any, ...]:
        if len(feats) < 3:
            raise ValueError(f"needs at least 3 features for a 6-DOF pose, got {len(feats)}")
        seen: set[str] = set()
        for i, f in enumerate(feats):
            if f.name in seen:
                raise ValueError(f"feature {i}: duplicate name {f.name!r}")
            seen.add(f.name)
        return feats


class ReferenceConfig(Model):
    """The taught reference: ``T_base_obj`` = object pose in the base frame at teach time.

    The gripping offset of a job is the base-frame correction
    ``T_offset = T_base_obj @ inv(T_base_obj_ref)``: a grip pose ``G`` taught on the reference
    object (in the base frame) becomes ``T_offset @ G`` for the object as found.
    Only for ``object.definition = "cad"``; with ``"reference"`` the object frame *is* the base
    frame at teach time (``T_base_obj_ref`` = identity) and this pose must not be set.
    Unset for a CAD object means "not taught yet": jobs end with NOT_CALIBRATED.

    ``points_mm`` (``"reference"`` only): the feature points measured in the base frame at the
    reference by ``vgripd teach``, one per feature name. When set, the pipeline fits these
    instead of the features' ``xyz_mm`` (which then only need to be a nominal layout).
    ``grip``: the robot's grip pose taught on the reference object (base frame); the absolute
    grip for a found object is ``T_offset @ grip`` (``output.mode = "grip"``).
    """

    T_base_obj: PoseConfig | None = None
    points_mm: dict[str, Vec3] | None = None
    grip: PoseConfig | None = None


# The embedded demo cell: two 1280x1024 cameras with 16 mm lenses (fx ~ 1800 px), 150 mm
# baseline, each toed in by 6 deg, ~690 mm above a 160 x 120 mm plate with six dark 10 mm marks
# (two on bosses 12 and 20 mm high; all pairwise distances differ by > 4 mm, so no symmetry).
DEMO_CALIBRATION = CalibrationConfig(
    left=IntrinsicsConfig(
        fx=1805.2, fy=1804.6, cx=641.3, cy=508.9, dist=(-0.08, 0.11, 0.0004, -0.0003, 0.0),
        width=1280, height=1024,
    ),
    right=IntrinsicsConfig(
        fx=1798.7, fy=1799.5, cx=636.8, cy=514.2, dist=(-0.075, 0.095, -0.0002, 0.0005, 0.0),
        width=1280, height=1024,
    ),
    stereo=StereoConfig(
        T_right_left=PoseConfig(
            translation_mm=(-149.18, 0.35, 15.68), rotvec_rad=(0.0021, 0.20944, -0.0032)
        )
    ),
    hand_eye=HandEyeConfig(
        mounting="fixed",
        T_base_camera=PoseConfig(
            translation_mm=(525.0, 100.0, 700.0), rotvec_rad=(3.13729, 0.0, 0.16442)
        ),
    ),
)
DEMO_OBJECT = ObjectConfig(
    name="demo_plate",
    definition="cad",
    features=tuple(
        CircleFeature(name=f"m{i + 1}", xyz_mm=xyz, kind="circle", diameter_mm=10.0)
        for i, xyz in enumerate(
            [
                (-62.0, 29.0, 0.0),
                (-65.0, -44.0, 0.0),
                (-16.0, 46.0, 0.0),
                (-32.0, -15.0, 0.0),
                (48.0, -41.0, 20.0),
                (58.0, 16.0, 12.0),
            ]
        )
    ),
)
DEMO_REFERENCE = ReferenceConfig(
    T_base_obj=PoseConfig(translation_mm=(600.0, 100.0, 10.0), rotvec_rad=(0.0, 0.0, 0.05))
)


RecipeNumber = Annotated[int, Field(ge=1, le=MAX_RECIPE)]


class RecipeConfig(BaseModel):
    """``[recipes.N]``: a ``name`` and overlays of the ``RECIPE_SECTIONS`` (raw tables here;
    they are judged as part of the recipe's effective config, ``Config.for_recipe``).

    Overlay rule, per section: the keys a recipe gives replace the same keys of the top-level
    section, the others are inherited (one level deep: a list or a table such as
    ``reference.T_base_obj`` is replaced as a whole). ``[recipes.N.object]`` replaces the
    top-level object as a whole (``RECIPE_WHOLE_SECTIONS``), and a recipe with its own object
    inherits no reference: its ``[recipes.N.reference]`` is all it has (none = not taught yet,
    its jobs answer NOT_CALIBRATED), since the top-level reference was taught on another
    object; for the same reason it inherits no ``picking.pick_points`` (grip points of the
    other object), while ``max_objects`` and ``order`` are inherited.
    """

    model_config = ConfigDict(extra="allow", frozen=True)
    # Shown in every log line of its jobs, the status line, the web view's header and a
    # metric label: one short line.
    name: str = Field(min_length=1, max_length=MAX_RECIPE_NAME)

    @field_validator("name")
    @classmethod
    def _one_line(cls, value: str) -> str:
        if any(ord(c) < 32 or ord(c) == 127 for c in value):
            raise ValueError(f"{value!r}: a recipe name is one line without control "
                             "characters (it appears in log lines and the status)")
        return value

    @model_validator(mode="after")
    def _known_sections(self) -> RecipeConfig:
        for key, value in (self.model_extra or {}).items():
            if key not in RECIPE_SECTIONS:
                raise ValueError(f"{key!r} cannot be set per recipe (a recipe may set name and "
                                 f"{', '.join(RECIPE_SECTIONS)}; the rest belongs to the cell)")
            if not isinstance(value, dict):
                raise ValueError(f"{key} must be a table ([recipes.N.{key}])")
        return self

    def sections(self) -> dict[str, dict[str, Any]]:
        """The overlaid sections, by name."""
        return {k: v for k, v in (self.model_extra or {}).items() if k in RECIPE_SECTIONS}


class Config(Model):
    """The whole file. Sections are filled in by their owners (see module docstring)."""

    camera: DriverSection = DriverSection(type="synthetic")
    output: OutputConfig = OutputConfig()
    limits: LimitsConfig = LimitsConfig()
    vision: VisionConfig = VisionConfig()
    picking: PickingConfig = PickingConfig()
    daemon: DaemonConfig = DaemonConfig()
    record: RecordConfig = RecordConfig()
    status: StatusConfig = StatusConfig()
    calibration_walk: CalibrationWalkConfig = CalibrationWalkConfig()
    # A moving belt (docs/conveyor.md); None: parts stand still until picked.
    conveyor: ConveyorConfig | None = None
    links: tuple[DriverSection, ...] = ()
    # Free-form notes on where a file came from (result files of `vgripd calibrate` carry one).
    about: dict[str, Any] = Field(default_factory=dict)
    # The demo cell applies only where a file does not say otherwise: a real camera without a
    # [calibration] is uncalibrated, a custom [object] without a [reference] is untaught.
    calibration: CalibrationConfig | None = DEMO_CALIBRATION
    object: ObjectConfig = DEMO_OBJECT
    reference: ReferenceConfig = DEMO_REFERENCE
    # Recipes selected by number with the trigger (docs/recipes.md); 0 is this config itself.
    recipes: dict[RecipeNumber, RecipeConfig] = Field(default_factory=dict)
    # Effective config of each recipe, built and validated with this one.
    _recipe_configs: dict[int, Config] = PrivateAttr(default_factory=dict)
    # What load_config found questionable in the files but accepted (check_calibration_files).
    _load_warnings: list[str] = PrivateAttr(default_factory=list)

    @property
    def load_warnings(self) -> list[str]:
        """Warnings about the files this config was loaded from (an included hand-eye or
        taught reference without a camera-model fingerprint)."""
        return list(self._load_warnings)

    @model_validator(mode="before")
    @classmethod
    def _demo_defaults_only_for_demo(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        data = dict(data)
        camera = data.get("camera")
        camera_type = camera.get("type") if isinstance(camera, dict) else None
        if "calibration" not in data and camera_type not in (None, "synthetic"):
            data["calibration"] = None
        if "object" in data and "reference" not in data:
            data["reference"] = {}
        return data

    @model_validator(mode="after")
    def _reference_matches_definition(self) -> Config:
        if self.object.definition == "reference" and self.reference.T_base_obj is not None:
            raise ValueError(
                'reference.T_base_obj must be unset when object.definition = "reference" '
                "(the object frame is the base frame at teach time)"
            )
        points = self.reference.points_mm
        if points is not None:
            if self.object.definition != "reference":
                raise ValueError(
                    'reference.points_mm is only for object.definition = "reference" '
                    "(a CAD object takes reference.T_base_obj)"
                )
            names = [f.name for f in self.object.features]
            missing = [n for n in names if n not in points]
            unknown = sorted(set(points) - set(names))
            if missing or unknown:
                raise ValueError(
                    f"reference.points_mm must name every feature of object {self.object.name!r}"
                    f" exactly once: missing {missing}, unknown {unknown}"
                )
        return self

    @model_validator(mode="after")
    def _views_need_one_robot_camera(self) -> Config:
        """``vision.views`` > 1 is one robot-mounted camera moved through the views."""
        if self.vision.views == 1:
            return self
        cal = self.calibration
        why = ("no [calibration]" if cal is None else
               "calibration.cameras is set (a multi-camera cell takes its views at once)"
               if cal.cameras is not None else
               "calibration.right is set (one camera only)" if cal.right is not None else
               'calibration.hand_eye.mounting is "fixed" (the camera must ride on the robot)'
               if cal.hand_eye.mounting != "robot" else
               "picking.max_objects > 1 (pick lists take one view)"
               if self.picking.max_objects > 1 else "")
        if why:
            raise ValueError(f"vision.views = {self.vision.views} needs one robot-mounted "
                             f"camera: {why}")
        problems = registry.views_problems(self.links, self.vision.views)
        if problems:
            raise PydanticCustomError(COMBINATION, "{problems}",
                                      {"problems": "\n".join(problems)})
        return self

    @model_validator(mode="after")
    def _window_in_workspace(self) -> Config:
        """The conveyor's pick window lies in ``limits.workspace_*`` (when a box is set)."""
        belt, lo, hi = self.conveyor, self.limits.workspace_min_mm, self.limits.workspace_max_mm
        if belt is None or lo is None or hi is None:
            return self
        for which, point in zip(("upstream", "downstream"), belt.window_points(), strict=True):
            if not all(a <= p <= b for a, p, b in zip(lo, point, hi, strict=True)):
                raise ValueError(
                    f"conveyor.window_mm: the {which} end {[round(p, 1) for p in point]} mm "
                    f"lies outside the workspace limits.workspace_min_mm {list(lo)} .. "
                    f"workspace_max_mm {list(hi)}: no part there could be picked")
        return self

    @model_validator(mode="after")
    def _links_carry_the_latch(self) -> Config:
        """A conveyor's jobs need the encoder count with each request: every register link
        serves map version 4 (the latch area)."""
        if self.conveyor is None:
            return self
        problems = registry.travel_problems(self.links, self.vision.views) \
            if self.conveyor.trigger == "travel" else []
        if not self.links and not problems:
            return self
        problems += registry.latch_problems(self.links)
        if problems:
            raise PydanticCustomError(COMBINATION, "{problems}",
                                      {"problems": "\n".join(problems)})
        return self

    @model_validator(mode="after")
    def _links_carry_output(self) -> Config:
        """Every link must be able to carry ``output.vendor`` (its class's capabilities)."""
        if not self.links:
            return self
        default = "vendor" not in self.output.model_fields_set
        problems = registry.link_problems(self.links, self.output.vendor, default)
        if problems:
            raise PydanticCustomError(COMBINATION, "{problems}",
                                      {"problems": "\n".join(problems)})
        return self


    @model_validator(mode="after")
    def _recipes_valid(self) -> Config:
        """Build and validate every recipe's effective config; all problems at once, each with
        its ``recipes.N.`` path."""
        lines: list[str] = []
        for number in sorted(self.recipes):
            try:
                self._recipe_configs[number] = Config.model_validate(self._recipe_data(number))
            except ValidationError as err:
                lines += [f"recipes.{number}.{line}" if not line.startswith("<root>") else
                          f"recipes.{number}{line.removeprefix('<root>')}"
                          for line in _problem_lines(err)]
        if lines:
            raise PydanticCustomError(RECIPE_PROBLEMS, "{lines}", {"lines": "\n".join(lines)})
        return self

    def _recipe_data(self, number: int) -> dict[str, Any]:
        """The effective config data of recipe ``number`` (the overlay rule: RecipeConfig)."""
        data = self.model_dump(exclude_unset=True, exclude={"recipes"})
        overlays = self.recipes[number].sections()
        for section, overlay in overlays.items():
            top = getattr(self, section).model_dump(exclude_unset=True)
            if section in RECIPE_WHOLE_SECTIONS or (section == "reference"
                                                    and "object" in overlays):
                top = {}  # another object; a reference taught on the top-level object
            if section == "picking" and "object" in overlays:
                top.pop("pick_points", None)  # grip points of the top-level object
            data[section] = {**top, **overlay}
        if "object" in overlays and "reference" not in overlays:
            data["reference"] = {}
        if "object" in overlays and "picking" not in overlays and "picking" in data:
            data["picking"] = {k: v for k, v in data["picking"].items() if k != "pick_points"}
        return data

    def recipe_numbers(self) -> tuple[int, ...]:
        """Every recipe a trigger may select: 0 (this config) and the configured ones."""
        return (0, *sorted(self.recipes))

    def recipe_name(self, number: int) -> str:
        """The recipe's ``name``; recipe 0 is ``"default"``."""
        return "default" if number == 0 else self.recipes[number].name

    def for_recipe(self, number: int) -> Config:
        """The full effective config of recipe ``number`` (0: this one). ``ConfigError`` for a
        number that is not configured, naming the configured ones.

        Built when this config was validated: a ``model_copy(update=...)`` of it keeps the
        recipes of the original (validate a new config to change the top level under them)."""
        if number == 0:
            return self
        if number not in self.recipes:
            raise ConfigError(unknown_recipe(number, self.recipe_numbers()))
        if number not in self._recipe_configs:  # a copy made without validation
            self._recipe_configs[number] = Config.model_validate(self._recipe_data(number))
        return self._recipe_configs[number]


def unknown_recipe(number: int, known: tuple[int, ...]) -> str:
    """The message for a recipe number that is not configured."""
    return (f"recipe {number} is not configured (configured: "
            f"{', '.join(str(n) for n in known)}; 0 = the top-level config)")


def _problem_lines(err: ValidationError) -> list[str]:
    """``path: message`` per problem (``<root>: message`` for whole-config ones)."""
    lines = []
    for e in err.errors():
        if e["type"] in (COMBINATION, RECIPE_PROBLEMS):
            lines += [f"<root>: {line}" for line in e["msg"].splitlines()]
        else:
            lines.append(f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}")
    return lines


def config_from_dict(
    data: dict[str, Any], source: str = "<config>", owner: dict[str, str] | None = None
) -> Config:
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, source, owner)) from None


def _read_toml(p: Path, what: str, files: Mapping[str, bytes] | None = None) -> dict[str, Any]:
    try:
        if files is None:
            text = p.read_text(encoding="utf-8")
        elif str(p) in files:
            text = files[str(p)].decode("utf-8")
        else:
            raise ConfigError(f"{p}: {what}: not in the snapshot judged (read before it "
                              f"was named)")
    except OSError as err:
        raise ConfigError(f"{p}: cannot read {what}: {err.strerror}") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{p}: {what}: not UTF-8 text: {err}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from None


def _merge(into: dict[str, Any], owner: dict[str, str], data: dict[str, Any],
           source: str, prefix: str = "") -> None:
    """Deep-merge ``data`` into ``into``; a leaf set by two files is an error naming both."""
    for key, value in data.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and isinstance(into.get(key, {}), dict):
            _merge(into.setdefault(key, {}), owner, value, source, path + ".")
        elif key in into:
            raise ConfigError(f"{source}: {path} is already set in {owner.get(path, '?')}")
        else:
            into[key] = value
            owner[path] = source


def read_config_data(
    path: str | Path, owner: dict[str, str] | None = None,
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] | None = None,
    files: Mapping[str, bytes] | None = None,
) -> dict[str, Any]:
    """The config file as a dict, with its ``include = [...]`` files merged in.

    Included files (calibration results, the taught reference) are resolved relative to the
    including file, may not include further files, and may not set what another file sets.
    Their ``[about]`` tables (how a calibration was made) are dropped from the result; with
    ``included`` given, each included file is appended to it as (path, its tables, its
    ``[about]``), for the consistency check of :func:`check_calibration_files`. With ``files``
    (``vgripd.configsnapshot.Snapshot.files``) the bytes come from there, not from disk.
    """
    p = Path(path)
    data = _read_toml(p, "config", files)
    includes = data.pop("include", [])
    if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
        raise ConfigError(f"{p}: include: must be a list of file names")
    merged: dict[str, Any] = {}
    owner = {} if owner is None else owner
    _merge(merged, owner, data, str(p))
    for name in includes:
        inc = include_path(p, name)
        part = _read_toml(inc, f"included file (from {p}: include)", files)
        about = part.pop("about", None)
        if included is not None:
            included.append((str(inc), part, about if isinstance(about, dict) else {}))
        if "include" in part:
            raise ConfigError(f"{inc}: include: included files may not include others")
        _merge(merged, owner, part, str(inc))
    return merged


#: The calibrations in the order they build on each other (cameras -> hand-eye -> teach).
REDO_STEPS = ("hand_eye", "reference")


def load_config(path: str | Path, files: Mapping[str, bytes] | None = None,
                redo: str | None = None) -> Config:
    """Read and validate a TOML config file (with its includes); every failure is a
    ``ConfigError``. ``files``: the bytes to read instead of the disk (a judged snapshot).
    ``redo``: the step a command measures again (``hand_eye``: the walked hand-eye's plan and
    walk; ``reference``: teaching). The included files of that step and of the steps after it
    may then belong to another camera model or hand-eye (a warning, not an error): they are
    what the command replaces, and the hand-eye's plan needs only a rough one."""
    owner: dict[str, str] = {}
    included: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    data = read_config_data(path, owner, included, files)
    config = config_from_dict(data, str(path), owner)
    config._load_warnings = check_calibration_files(data, owner, included, redo)
    return config


def _holder(owner: dict[str, str], prefixes: tuple[str, ...], default: str) -> str:
    """The file that set the first key under one of ``prefixes``."""
    for key, source in owner.items():
        if key.startswith(prefixes):
            return source
    return default


#: The keys of a taught reference that are its measurement (what ``vgripd teach`` measures).
MEASURED_REFERENCE_KEYS = ("T_base_obj", "points_mm")


def measured_references(part: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """The reference tables (``[reference]``, ``[recipes.N.reference]``) of one file's tables
    that hold a measurement; one set aside (``grip`` alone) is not taught."""
    tables = [part.get("reference")]
    recipes = part.get("recipes")
    if isinstance(recipes, dict):
        tables += [r.get("reference") for r in recipes.values() if isinstance(r, dict)]
    for table in tables:
        if isinstance(table, dict) and any(k in table for k in MEASURED_REFERENCE_KEYS):
            yield table


def check_calibration_files(
    data: dict[str, Any], owner: dict[str, str],
    included: list[tuple[str, dict[str, Any], dict[str, Any]]], redo: str | None = None,
) -> list[str]:
    """Whether the included hand-eye and taught-reference files were made with this config's
    camera model (and the reference with its hand-eye): the fingerprints their ``[about]``
    recorded (``vgripd.geometry.fingerprint``) against the config's own sections.

    A mismatch is a ConfigError naming both files; a file without a fingerprint (made before
    they were recorded) is a warning, returned, so that existing configs still load. A
    mismatch of a file that ``redo`` measures again (``load_config``) is a warning too.
    """
    from vgripd.geometry.fingerprint import camera_fingerprint, hand_eye_fingerprint

    if redo is not None and redo not in REDO_STEPS:
        raise ValueError(f"redo {redo!r}: one of {REDO_STEPS}")
    redone = set(REDO_STEPS[REDO_STEPS.index(redo):]) if redo else set()

    calibration = data.get("calibration")
    if not isinstance(calibration, dict):
        return []
    camera_parts = ("calibration.left", "calibration.right", "calibration.stereo",
                    "calibration.cameras")
    camera_file = _holder(owner, camera_parts, "the config")
    hand_eye_file = _holder(owner, ("calibration.hand_eye", "calibration.cameras"),
                            "the config")
    warnings: list[str] = []
    problems: list[str] = []
    order = "(the order is: cameras/rig -> hand-eye -> teach)"
    for path, part, about in included:
        cal_value = part.get("calibration")
        cal: dict[str, Any] = cal_value if isinstance(cal_value, dict) else {}
        holds_camera = any(k in cal for k in ("left", "right", "stereo", "cameras"))
        taught = any(True for _ in measured_references(part))
        holds_hand_eye = "hand_eye" in cal and not holds_camera
        if not (holds_hand_eye or taught):
            continue
        what = "taught reference" if taught else "hand-eye"
        found = warnings if ("reference" if taught else "hand_eye") in redone else problems
        recorded = about.get("camera_model")
        if recorded is None:
            warnings.append(f"{path}: the {what} records no camera model fingerprint ([about] "
                            f"camera_model; made before vgripd recorded one): cannot check that "
                            f"it was made with the camera model of {camera_file} {order}")
        else:
            parts = about.get("camera_model_parts") or ["left"]
            try:
                now = camera_fingerprint(calibration, parts)
            except (KeyError, TypeError, ValueError) as err:
                problems.append(f"{path}: [about] camera_model_parts {parts!r}: {err}")
                continue
            if now != recorded:
                again = ("teach it again" if taught else "calibrate the hand-eye again (then "
                         "teach again)")
                found.append(
                    f"{path}: the {what} was made with camera model {recorded}, but the camera "
                    f"model of this config ({camera_file}) is {now}: they do not belong "
                    f"together; {again} with {camera_file} {order}")
                continue
        if taught:
            recorded_he = about.get("hand_eye")
            if recorded_he is None:
                if recorded is not None:
                    warnings.append(f"{path}: the taught reference records no hand-eye "
                                    f"fingerprint ([about] hand_eye)")
            elif recorded_he != hand_eye_fingerprint(calibration):
                found.append(
                    f"{path}: the taught reference was measured with hand-eye {recorded_he}, "
                    f"but the hand-eye of this config ({hand_eye_file}) is "
                    f"{hand_eye_fingerprint(calibration)}: teach it again {order}")
    if problems:
        raise ConfigError("\n".join(problems))
    return warnings
