"""The robot-link contract, with no I/O.

Every link driver (``drivers/links/*``) implements ``RobotLink``; the daemon talks to links only
through it. A link turns its peer's trigger into a ``Trigger`` and hands it to the daemon's
handler; the daemon answers through ``image_captured`` and ``publish``. The rules a link's
peer relies on are ``vgripd.peer`` (``jobcore``: the handshake; ``registers``: the register
map of register-based links).
"""

from __future__ import annotations

import asyncio
import enum
import hashlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from pydantic import BaseModel

from vgripd.errors import LinkError
from vgripd.peer.registers import checked_warnings
from vgripd.registry import LinkCapabilities
from vgripd.types import FloatArray, JobResult, Status


class LinkState(enum.Enum):
    STOPPED = "stopped"
    CONNECTING = "connecting"
    UP = "up"
    DOWN = "down"  # lost; the supervisor is retrying with doubling back-off
    FAILED = "failed"  # cannot start (bad address, port in use, register IN_USE): not retried


@dataclass(frozen=True)
class LinkHealth:
    """``peers``: connected clients for server links (0 when not applicable)."""

    state: LinkState
    peer: str = ""
    last_error: str = ""
    reconnects: int = 0
    since_mono_ns: int = 0
    peers: int = 0


@dataclass(frozen=True)
class Trigger:
    """A request from the robot side. ``seq`` is the peer's request sequence number.

    ``T_base_flange`` is the robot's flange/TCP pose at trigger time (mm) when the link can read
    it (RTDE), for robot-mounted cameras. ``recipe`` is the peer's job parameter (0 = default).
    ``peer`` names where the request came from when the link can tell (robot socket: the
    connection's address:port; RTDE: the controller's), "" otherwise.
    """

    link: str
    seq: int
    command: int
    t_mono_ns: int
    T_base_flange: FloatArray | None = None
    recipe: int = 0
    #: ``Command.CAPTURE``: the 1-based view of a several-view job (0 = not a view).
    view: int = 0
    peer: str = ""
    #: A conveyor recipe (docs/conveyor.md): the encoder count the peer latched with the
    #: request (PREDICT: the count N to predict for), and the camera frame it belongs to
    #: (``latch = "frame_id"``); None when the link carries none.
    latch_count: int | None = None
    latch_frame: int | None = None


TriggerHandler = Callable[[Trigger], None]
#: ``conveyor.trigger = "travel"``: the belt's encoder count as a link read it, and when
#: (``time.monotonic_ns()``): ``handler(count, t_mono_ns)``.
CountHandler = Callable[[int, int], None]


def config_identity(config: Any) -> tuple[str, bytes]:
    """``(id, SHA-256)`` of a loaded config: the digest of its canonical JSON (the values
    as judged, not the file's bytes), the id ``config-`` and its first 12 hex digits."""
    digest = hashlib.sha256(config.model_dump_json().encode()).digest()
    return f"config-{digest.hex()[:12]}", digest


def _no_one_listens() -> None:
    pass


class RobotLink(ABC):
    """Base of every link driver. ``__init__`` does no I/O.

    ``capabilities`` says which vendor conventions the link can carry; the config is checked
    against it at load time, so ``publish`` never meets a pose it cannot write (it still answers
    such a result with a failure status rather than a wrong number).
    """

    Options: ClassVar[type[BaseModel]]
    capabilities: ClassVar[LinkCapabilities]
    #: The link can send CAPTURE requests and implements ``view_captured`` (``vision.views``).
    takes_views: ClassVar[bool] = False
    #: The link reads the belt's encoder count its peer publishes (map version 4: LATCH_COUNT)
    #: and hands each reading to ``watch_count``'s handler (``conveyor.trigger = "travel"``).
    publishes_count: ClassVar[bool] = False

    def __init__(self, name: str, options: Any) -> None:
        self.name = name
        self.options = options
        #: ``output.vendor``: the convention of poses the peer sends (``set_vendor``)
        self.vendor: str | None = None
        #: Called whenever what ``health()`` reports changes (state, error, reconnects, peers);
        #: the link supervisor points it at the daemon's change hook, which pushes the status
        #: to the web view.
        self.health_changed: Callable[[], None] = _no_one_listens

    @abstractmethod
    async def open(self, on_trigger: TriggerHandler) -> None:
        """Start serving; raise ``LinkError`` saying exactly why if it cannot start."""

    @abstractmethod
    async def close(self) -> None:
        """Stop serving and release sockets/ports/threads/processes."""

    @abstractmethod
    def health(self) -> LinkHealth: ...

    @abstractmethod
    async def image_captured(self, seq: int, job_id: int) -> None:
        """The job for ``seq`` has its images: the robot may move on."""

    @abstractmethod
    async def publish(self, seq: int, result: JobResult) -> Status:
        """Publish a finished job atomically (data first, acknowledged sequence last).

        Returns the status the peer was given: ``result.status``, or the failure the link had
        to put in its place (a register link answers a value that does not fit its register
        format with ``OUT_OF_LIMITS``). Raises ``LinkError`` when the peer could not be given
        the answer now (a link may still hand it over when the peer is back).
        """

    async def view_captured(self, seq: int, job_id: int) -> None:
        """The image of view request ``seq`` (not the job's last view) is taken: the robot
        may move on to the next view. This answers the request (register links: CAPTURED_SEQ
        and STATE 4 VIEWS, no ACK_SEQ); the job's result follows under the last view's
        request. Links that cannot send CAPTURE never get here; the default refuses."""
        raise LinkError(f"link {self.name}: cannot take several views per job")

    def refusals(self) -> Mapping[str, int]:
        """Requests this link refused on its own, without the daemon, by status name.

        Register links refuse on their handshake (``REJECT_SEQ``/``REJECT_CODE``: ``BUSY``,
        ``BAD_REQUEST``); the daemon adds these to its counters. Default: none.
        """
        return {}

    def set_recipes(self, recipes: Mapping[int, str]) -> None:  # noqa: B027 - optional
        """The recipes a trigger may name (number -> name, 0 = the top-level config), told by
        the daemon before ``open``. A link whose peer selects the recipe apart from the
        trigger (OPC UA ``SelectRecipe``) refuses any other number at once, where the peer
        can see why; a link that carries the number with each trigger leaves it to the
        daemon, whose job answers ``BAD_REQUEST``. Default: ignored."""

    def set_configuration(self, name: str, digest: bytes) -> None:  # noqa: B027 - optional
        """The loaded config's id and SHA-256 (``config_identity``), told before ``open`` and
        after a reload: a link that shows its peer which configuration runs (OPC 40100's
        ActiveConfiguration) overrides this. Default: ignored."""

    def set_vendor(self, vendor: str) -> None:
        """The ``output.vendor`` convention, told before ``open``: the one a link whose peer
        sends poses (robot_socket CAPTURE_AT) reads them in."""
        self.vendor = vendor

    def set_conveyor(self, on: bool) -> None:  # noqa: B027 - optional
        """A recipe has a conveyor: the part queue answers NEXT and PREDICT, so a link that
        refuses NEXT without a pick list itself lets them through (``Handshake.queue``).
        Default: ignored."""

    def watch_count(self, handler: CountHandler | None) -> None:  # noqa: B027 - optional
        """Hand every encoder count the peer publishes to ``handler`` (None: stop), with the
        time it was read; called on the event loop, never raising into the link. Only links
        with ``publishes_count`` have counts to hand. Default: ignored."""

    def set_walking(self, walking: bool) -> None:  # noqa: B027 - optional
        """A walked hand-eye calibration is served (``vgripd.service.links.handeye_walk``): a link
        that refuses NEXT without a pick list itself lets every NEXT through while ``walking``.
        Default: ignored."""

    async def robot_pose(self) -> Any | None:
        """The robot's flange pose now (``T_base_flange``, 4x4, mm), read from the peer at
        this call; None when this link cannot read it now (not up, or its peer sends poses
        only with a request, as the robot socket's CAPTURE_AT does). A link that reads the
        controller's actual pose (UR RTDE ``actual_TCP_pose``) overrides this; it raises
        ``LinkError`` when the peer does not answer. Default: None."""
        return None

    async def set_warnings(self, bits: int) -> None:
        """Show the daemon's current ``Warnings`` bits to the peer (live, not tied to a job).

        Called whenever a warning rises or clears; a link starts with 0 and writes the last
        bits again after a reconnect. A link that can hold the bits somewhere overrides this;
        the default only checks them (the warning still shows in the status and the log).
        """
        checked_warnings(bits)




async def robot_pose_now(links: Mapping[str, RobotLink],
                         timeout_s: float = 2.0) -> tuple[str, Any] | None:
    """The robot's flange pose now from the first link (in config order) that reads one:
    ``(link name, T_base_flange)``; None when no link has one. A link that fails or takes
    longer than ``timeout_s`` is skipped (a capture never waits on a silent controller)."""
    for name, link in links.items():
        try:
            async with asyncio.timeout(timeout_s):
                T = await link.robot_pose()
        except (LinkError, TimeoutError):
            continue
        if T is not None:
            return name, T
    return None


def tell_links(links: Iterable[RobotLink], config: Any) -> None:
    """What every link learns from the config, at the start and after each reload: the recipes'
    names, the config's identity, the pose convention (``output.vendor``) and whether a
    recipe has a conveyor (NEXT and PREDICT served from its part queue)."""
    recipes = {number: config.recipe_name(number) for number in config.recipe_numbers()}
    identity = config_identity(config)
    belt = any(config.for_recipe(n).conveyor is not None for n in config.recipe_numbers())
    for link in links:
        link.set_recipes(recipes)
        link.set_configuration(*identity)
        link.set_vendor(config.output.vendor)
        link.set_conveyor(belt)
