"""Link supervision: the robot links the daemon serves, built from the config, opened at once,
split the file budget between, called with a bound time, and closed.

- Start-up opens every link at once (a silent controller delays no other link and not the
  status endpoint); a link that cannot start is shown FAILED while the others serve.
  ``LinkError`` only when no link could start.
- The file limit (RLIMIT_NOFILE) is split between the server surfaces (the web view, each
  listening link) and ``daemon.fd_reserve`` (docs/daemon.md, "File budget").
- A link call (``image_captured``, ``view_captured``, ``publish``, ``set_warnings``) that fails
  or takes longer than ``LINK_CALL_TIMEOUT_S`` is logged and abandoned; it never fails a job.
  ``publish`` returns the status the link actually gave its peer (None: not delivered).
- Warning bits go to every link: the one about to publish is waited for, the others are set in
  the background so that a slow link never delays another's result.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable
from typing import Any

from vgripd.config import Config
from vgripd.errors import LinkError
from vgripd.registry import LINKS, load_class, validate_options
from vgripd.service.host.tasks import Background
from vgripd.service.links.gate import WEB_SURFACE, Budget, Gate, file_limit, open_files, plan_budget
from vgripd.service.links.protocol import RobotLink, TriggerHandler, tell_links
from vgripd.service.links.webtrigger import WEB_LINK, WebTriggerLink
from vgripd.types import JobResult, Status

log = logging.getLogger("vgripd")

# A link call (image_captured/publish) that takes longer is abandoned and logged.
LINK_CALL_TIMEOUT_S = 2.0


def link_names(config: Config) -> list[str]:
    types = [s.type for s in config.links]
    return [t if types.count(t) == 1 else f"{t}.{i}" for i, t in enumerate(types)]


class LinkSupervisor:
    """The daemon's links by name. Construction validates the drivers and does no I/O
    (``ConfigError`` for a bad link type or options). ``changed`` is called whenever a link's
    health changes (its state, last error, reconnects or connected peers)."""

    def __init__(self, config: Config, background: Background,
                 changed: Callable[[], None] | None = None) -> None:
        self.config = config
        self._background = background
        self._changed = changed
        self.links: dict[str, RobotLink] = {}
        for i, (name, section) in enumerate(zip(link_names(config), config.links, strict=True)):
            link_cls = load_class(LINKS, "link", section.type)
            self.links[name] = link_cls(name, validate_options(link_cls, section, f"links.{i}"))
        if config.status.enabled and config.status.allow_trigger:  # the web view's test trigger
            self.links[WEB_LINK] = WebTriggerLink()
        tell_links(self.links.values(), config)
        for link in self.links.values():
            self.watch(link)
        #: How RLIMIT_NOFILE is split between the server surfaces and the reserve (at start).
        self.fd_budget: Budget | None = None

    def watch(self, link: RobotLink) -> None:
        """Report ``link``'s health changes (and its server gate's connection count) to the
        ``changed`` hook."""
        if self._changed is None:
            return
        link.health_changed = self._changed
        gate = getattr(link, "gate", None)
        if isinstance(gate, Gate):
            gate.count_changed = self._changed

    # --- start and stop -----------------------------------------------------------------

    def plan_files(self) -> Budget:
        """Split the file limit between the server surfaces (web view, each listening link)
        and ``daemon.fd_reserve`` (docs/daemon.md, "File budget"); set each gate's cap and
        log the split once."""
        gates: dict[str, Gate] = {}
        for name, link in self.links.items():
            gate = getattr(link, "gate", None)
            if isinstance(gate, Gate) and getattr(link.options, "mode", "server") == "server":
                gates[name] = gate
        wanted = [(name, gate.configured_cap) for name, gate in gates.items()]
        if self.config.status.enabled:
            wanted.insert(0, (WEB_SURFACE, self.config.status.max_connections))
        budget = plan_budget(file_limit(), open_files(), self.config.daemon.fd_reserve, wanted)
        for name, gate in gates.items():
            gate.cap = budget.caps[name]
        log.info("%s", budget.describe())
        if budget.scaled:
            log.warning("the configured max_connections do not fit the file limit %d: lowered "
                        "to %s (raise LimitNOFILE= in the unit, or lower max_connections or "
                        "daemon.fd_reserve)", budget.limit,
                        ", ".join(f"{n} {c}" for n, c in budget.caps.items()))
        self.fd_budget = budget
        return budget

    def begin_opening(self, on_trigger: TriggerHandler) -> list[asyncio.Task[str | None]]:
        """One task per link opening it (``judge_opened`` reads their outcomes)."""
        return [asyncio.create_task(self.open_link(name, link, on_trigger),
                                    name=f"vgripd-open-link-{name}")
                for name, link in self.links.items()]

    def judge_opened(self, results: list[Any]) -> None:
        """The links' first outcomes (``open_link``'s): a link that cannot start is logged and
        shown FAILED while the others serve; ``LinkError`` only when no link could start."""
        failed = [r for r in results if isinstance(r, str)]
        if self.links and len(failed) == len(self.links):
            raise LinkError(failed[0] if len(failed) == 1 else
                            "no link could start: " + "; ".join(failed))
        for why in failed:
            log.error("%s; the other links serve without it", why)

    async def open_link(self, name: str, link: RobotLink,
                        on_trigger: TriggerHandler) -> str | None:
        """``link.open``; the error text when it cannot start (the link is FAILED)."""
        try:
            await link.open(on_trigger)
        except LinkError as err:
            return str(err)
        log.info("link %s open (%s)", name, link.health().state.value)
        return None

    async def close(self) -> None:
        for name, link in self.links.items():
            try:
                await link.close()
            except Exception:
                log.exception("link %s: close failed", name)

    # --- calls --------------------------------------------------------------------------

    async def show_warnings(self, first: str, bits: int) -> None:
        """Hand the warning bits to every link: ``first`` (about to publish) is waited for,
        the others run in the background so a slow link never delays another's result. Each
        link applies the bits in call order, so a later change cannot be overtaken."""
        for name in self.links:
            if name != first:
                self._background.spawn(self._warnings_call(name, bits))
        await self._warnings_call(first, bits)

    async def _warnings_call(self, name: str, bits: int) -> None:
        try:
            async with asyncio.timeout(LINK_CALL_TIMEOUT_S):
                await self.links[name].set_warnings(bits)
        except Exception as err:
            log.error("link %s: set_warnings(%#x) failed: %r", name, bits, err)

    async def call(self, name: str, method: str, seq: int, arg: Any) -> Any:
        """Call a link and return its answer; a failing or hanging link is logged (None) and
        never fails the job."""
        try:
            async with asyncio.timeout(LINK_CALL_TIMEOUT_S):
                return await getattr(self.links[name], method)(seq, arg)
        except Exception as err:
            log.error("link %s: %s(seq %d) failed: %r", name, method, seq, err)
            return None

    async def publish(self, name: str, seq: int, result: JobResult) -> Status | None:
        """Publish through a link: the status its peer was told, None when it was not."""
        told = await self.call(name, "publish", seq, result)
        if told is None:  # failed, logged by call()
            return None
        if not isinstance(told, Status):
            log.error("link %s: publish(seq %d) returned %r, not a Status", name, seq, told)
            return None
        if told is not result.status:
            log.warning("link %s: seq %d: %s published as %s", name, seq, result.status.name,
                        told.name)
        return told

    def refusals(self) -> dict[str, Counter[str]]:
        """Per link, the requests it refused on its own handshake, by status name."""
        return {name: Counter(link.refusals()) for name, link in self.links.items()}
