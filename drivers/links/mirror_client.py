"""What the register client links share: a ``RegisterBank`` mirror pushed to a peer they poll.

``MirrorClientLink`` is the base of the links where vgripd is the client of a peer holding the
register block of ``vgripd.peer.registers`` (``drivers.links.s7``: a PLC data block;
``drivers.links.modbus_client``: the robot's holding registers). It owns the mirror (a
``RegisterBank`` and its journal), the daemon-facing calls that wait until the peer has a change
(``_flushed`` and its waiters, released with an outage), the health and its condition, and the
supervisor: one task that connects, makes the first contact, then polls and pushes until the
connection drops, and reconnects with doubling back-off after any error, logging once per
outage (one line, no traceback). A subclass brings the transport through the hooks below
(connect, read and write the block, disconnect) and explains a refusal of the block.

The block is the link's ``map_version`` (3: 46 words; 4: 62, the conveyor's). The peer owns
its writable areas (``RegisterBank.writable``: the command area, and in map version 4 the
latch area 46-49, which the PLC writes before or with REQ_SEQ); vgripd never writes there.
``own_segments`` are the stretches of the block that are vgripd's: every write of vgripd's
lies inside one of them, so a write never carries a stale copy of the peer's words. A new
request reads the latch from the same poll as its REQ_SEQ and takes it into the ``Trigger``.

No peer error stops the retrying: a peer that answers garbage, a block the peer
refuses (a wrong address, a DB not yet downloaded, access not yet allowed) are outages like a
lost connection, since the peer can be fixed or replaced while vgripd runs. A refusal of the
block is logged at ERROR with what to check (it needs a person), anything else at WARNING.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from abc import abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Generic, TypeVar

from vgripd.errors import LinkError
from vgripd.peer.jobcore import Action
from vgripd.peer.registers import (
    COMMAND_AREA,
    LATCH_AREA,
    BlockWrite,
    Reg,
    RegisterBank,
    ValueCodec,
)
from vgripd.service.links.protocol import CountHandler, LinkState, Trigger, TriggerHandler
from vgripd.service.links.supervisor import (
    Ended,
    OutagePolicy,
    Reconnector,
    SupervisedLink,
    end_task,
)
from vgripd.types import JobResult, Status

C = TypeVar("C")  # the transport's client object, one per connection


def own_segments(size: int, peer: Sequence[range]) -> list[range]:
    """The stretches of a ``size``-word block outside the ``peer`` areas, in address order
    (map version 3: 3-45; version 4: 3-45 and 50-61)."""
    segments: list[range] = []
    start: int | None = None
    for address in range(size + 1):
        ours = address < size and not any(address in area for area in peer)
        if ours and start is None:
            start = address
        elif not ours and start is not None:
            segments.append(range(start, address))
            start = None
    return segments


def without_peer_words(write: BlockWrite, peer: Sequence[range]) -> list[BlockWrite]:
    """The parts of ``write`` that lie outside the ``peer`` areas (the peer's own words
    dropped; a write across an area becomes one write on each side)."""
    end = write.address + len(write.words)
    out: list[BlockWrite] = []
    for seg in own_segments(end, peer):
        lo, hi = max(seg.start, write.address), seg.stop
        if lo < hi:
            out.append(BlockWrite(lo, write.words[lo - write.address:hi - write.address]))
    return out


class MirrorClientLink(SupervisedLink, Generic[C]):
    """A register block mirrored in a ``RegisterBank`` and copied to a polled peer.

    Subclasses set ``peer_kind`` (``"PLC"``, ``"robot"``: it names the peer in messages) and
    ``_log`` (their module's logger, so every line keeps its logger), and implement the hooks.
    Their options have ``host``, ``port``, ``word_order``, ``value_format``, ``scale``,
    ``heartbeat_ms``, ``timeout_s``, ``backoff_initial_s`` and ``backoff_max_s``.
    """

    peer_kind: ClassVar[str]
    _log: ClassVar[logging.Logger]

    def __init__(self, name: str, options: Any, health_peer: str | None = None) -> None:
        super().__init__(name, options, health_peer or f"{options.host}:{options.port}")
        self._peer = f"{options.host}:{options.port}"
        self._journal: list[BlockWrite] = []
        self.bank = RegisterBank(
            ValueCodec(options.word_order, options.value_format, options.scale), self._journal,
            version=options.map_version,
        )
        #: The areas the peer writes (never vgripd) and the block's stretches that are vgripd's.
        self._peer_areas = self.bank.writable()
        self._own = own_segments(self.bank.image.size, self._peer_areas)
        self._on_trigger: TriggerHandler | None = None
        self._on_count: CountHandler | None = None
        self._task: asyncio.Task[None] | None = None
        self._wake: asyncio.Event | None = None
        self._waiters: list[asyncio.Future[None]] = []
        self._primed = False
        self.transactions = 0  # requests sent to the peer (benchmarks, tests)

    # -- hooks -------------------------------------------------------------------------------

    def _starting(self) -> None:
        """At ``open``, before the supervisor starts (quiet a library's logger, make threads)."""

    @abstractmethod
    def _new_client(self) -> C:
        """A client for one connection attempt (no I/O)."""

    @abstractmethod
    async def _connect(self, client: C) -> None:
        """Connect ``client``; ``LinkError`` if that fails."""

    @abstractmethod
    def _drop(self, client: C) -> None:
        """Release ``client`` after a connection ended, however it ended (no waiting)."""

    @abstractmethod
    async def _read_block(self, client: C) -> list[int]:
        """The peer's whole block (map words)."""

    @abstractmethod
    async def _write_mirror(self, client: C, words: list[int]) -> None:
        """After (re)connecting: bring the peer's block (``words``) to the mirror."""

    @abstractmethod
    async def _write_changes(self, client: C) -> None:
        """Write the journal (the mirror's changes since the last write) and clear it."""

    @abstractmethod
    async def _exchange(self, client: C) -> list[int]:
        """One round of the serve loop: push what is pending, poll; the peer's words from
        address 0 at least through its last writable area (one read, so a request's latch
        comes from the same moment as its REQ_SEQ)."""

    @abstractmethod
    def _refusal_hint(self, err: LinkError) -> str | None:
        """``err`` with what to check, if it means the peer refuses the block; else None."""

    def _transport_error(self, err: Exception) -> str | None:
        """The outage's reason for an exception the transport let through; None for a bug."""
        return None

    @property
    @abstractmethod
    def _poll_s(self) -> float:
        """Longest wait between two polls of the command area."""

    # -- RobotLink ---------------------------------------------------------------------------

    async def open(self, on_trigger: TriggerHandler) -> None:
        """Start the supervisor and wait for the outcome of its first contact.

        Neither an unreachable peer nor one that refuses the block is an error here: the
        supervisor keeps retrying (state DOWN, with the reason).
        """
        if self._task is not None:
            raise LinkError(f"link {self.name}: already open")
        self._starting()
        self._on_trigger = on_trigger
        self._wake = asyncio.Event()
        self._task = asyncio.create_task(self._supervise(), name=f"{self.name}-supervisor")
        # connect + one read each take at most timeout_s; a slower first contact stays with
        # the supervisor (CONNECTING) rather than failing the start
        with contextlib.suppress(TimeoutError):
            await self.wait_state({LinkState.UP, LinkState.DOWN, LinkState.FAILED},
                                  2 * self.options.timeout_s + 1.0)
        if self.cell.state is LinkState.FAILED:
            await self._stop()
            raise LinkError(f"link {self.name}: {self.cell.last_error}")

    async def close(self) -> None:
        await self._stop()
        self.cell.set(LinkState.STOPPED)

    async def image_captured(self, seq: int, job_id: int) -> None:
        self.bank.captured(seq, job_id)
        await self._flushed()

    takes_views = True

    async def view_captured(self, seq: int, job_id: int) -> None:
        self.bank.view_captured(seq, job_id)
        await self._flushed()

    async def publish(self, seq: int, result: JobResult) -> Status:
        """Publish into the mirror, then wait until the peer has it; returns the status the
        peer got.

        Raises ``LinkError`` when the peer is not connected; the result stays in the mirror and
        is written (ACK_SEQ last) as soon as the peer is back.
        """
        published = self.bank.publish(seq, result, time.monotonic_ns())
        if published.status is not result.status:
            self._log.warning("%s: request %d published as %s instead of %s: %s", self.name,
                              seq, published.status.name, result.status.name, published.message)
        await self._flushed()
        return published.status

    def refusals(self) -> Mapping[str, int]:
        return dict(self.bank.refusals)

    publishes_count = True

    def watch_count(self, handler: CountHandler | None) -> None:
        self._on_count = handler

    def set_conveyor(self, on: bool) -> None:
        self.bank.handshake.queue = on

    async def set_warnings(self, bits: int) -> None:
        """Set WARNINGS in the mirror; while the peer is connected, wait until it has it.

        Unlike ``publish`` this does not raise while the peer is away: the mirror is written
        at the reconnect, WARNINGS included.
        """
        self.bank.set_warnings(bits)
        if self.cell.state is LinkState.UP:
            await self._flushed()

    # -- helpers for the daemon-facing calls -------------------------------------------------

    async def _flushed(self) -> None:
        if self.cell.state is not LinkState.UP or self._wake is None:
            raise LinkError(
                f"link {self.name}: {self.peer_kind} {self._peer} is {self.cell.state.value}"
                f" ({self.cell.last_error or 'not connected'}); kept for the reconnect"
            )
        done = asyncio.get_running_loop().create_future()
        self._waiters.append(done)
        self._wake.set()
        await done

    def _release_waiters(self, error: Exception) -> None:
        waiters, self._waiters = self._waiters, []
        for w in waiters:
            if not w.done():
                w.set_exception(error)

    async def _stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            await end_task(task)
        self._release_waiters(LinkError(f"link {self.name}: closed"))

    # -- supervisor --------------------------------------------------------------------------

    async def _supervise(self) -> None:
        opt = self.options
        reconnector = Reconnector(self.name, self.cell,
                                  OutagePolicy(opt.backoff_initial_s, opt.backoff_max_s), self._log)
        await reconnector.run(lambda: self._session(reconnector))

    async def _session(self, reconnector: Reconnector) -> Ended:
        """One connection: connect, first contact, serve until it ends; why it ended."""
        self.cell.set(LinkState.CONNECTING, None)  # the last outage's reason stays in view
        client = self._new_client()
        try:
            await self._connect(client)
            await self._first_contact(client)
            if reconnector.up():
                self._log.info("%s: %s %s is back", self.name, self.peer_kind, self._peer)
            await self._serve(client)
        except LinkError as err:
            hint = self._refusal_hint(err)
            ended = Ended(hint or str(err), logging.WARNING if hint is None else logging.ERROR)
        except Exception as err:
            reason = self._transport_error(err)
            if reason is None:  # a bug must not leave a dead link reporting UP
                self._log.exception("%s: unexpected error talking to %s", self.name,
                                    self._peer)
                reason = f"internal error: {err!r}"
            ended = Ended(reason)
        finally:
            self._drop(client)
        self._release_waiters(LinkError(f"link {self.name}: {ended.error}"))
        return ended

    async def _first_contact(self, client: C) -> None:
        """Read the peer's block, adopt its command area (first contact only), write the mirror
        where it has to be."""
        words = await self._read_block(client)
        if not self._primed:
            # A request the peer made before this process ran counts only if it is still
            # unanswered (its ACK_SEQ differs); otherwise it would rerun an old job.
            if words[Reg.ACK_SEQ] == words[Reg.REQ_SEQ]:
                cmd = tuple(words[COMMAND_AREA.start:COMMAND_AREA.stop])
                self.bank.image.apply([BlockWrite(COMMAND_AREA.start, cmd)])
                self.bank.handshake.last_req_seq = words[Reg.REQ_SEQ]
            self._primed = True
        await self._write_mirror(client, words)

    async def _serve(self, client: C) -> None:
        assert self._wake is not None
        period_s = self.options.heartbeat_ms / 1000
        poll_s = self._poll_s
        next_beat = time.monotonic() + period_s
        while True:
            words = await self._exchange(client)
            count = self.bank.published_count(0, words)
            if count is not None and self._on_count is not None:  # the belt's count (travel)
                self._on_count(count, time.monotonic_ns())
            cmd = words[COMMAND_AREA.start:COMMAND_AREA.stop]
            if cmd != self.bank.image.words[COMMAND_AREA.start:COMMAND_AREA.stop]:
                self._on_command(words)
                continue  # write the handshake's answer (if any) before the next poll
            now = time.monotonic()
            if now >= next_beat:
                self.bank.beat()
                age = self.bank.read(Reg.RESULT_AGE_MS, 2, time.monotonic_ns())
                self.bank.image.apply([BlockWrite(Reg.RESULT_AGE_MS, tuple(age))])
                next_beat = max(next_beat + period_s, now)
                continue
            self._wake.clear()
            if self._waiters or self._journal:
                continue
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(min(poll_s, next_beat - now)):
                    await self._wake.wait()

    def _on_command(self, words: list[int]) -> None:
        """The peer changed its command area (``words``: as ``_exchange`` read them). In map
        version 4 the latch read with it goes into the mirror first: the request takes it."""
        if LATCH_AREA in self._peer_areas:
            self.bank.write(LATCH_AREA.start, words[LATCH_AREA.start:LATCH_AREA.stop])
        decision = self.bank.write(COMMAND_AREA.start, words[COMMAND_AREA.start:COMMAND_AREA.stop])
        if decision.action is Action.START:
            assert self._on_trigger is not None
            trigger = Trigger(link=self.name, seq=decision.seq, command=decision.command,
                              t_mono_ns=time.monotonic_ns(), recipe=decision.recipe,
                              view=decision.view, latch_count=decision.count,
                              latch_frame=decision.frame)
            asyncio.get_running_loop().call_soon(self._on_trigger, trigger)
        elif decision.action is Action.REJECT:
            self._log.info("%s: request %d refused: %s", self.name, decision.seq,
                           decision.code.name)

    async def _flush(self, client: C) -> None:
        """Write the mirror's changes since the last flush, then release who waited for them."""
        if not self._journal and not self._waiters:
            return
        waiters, self._waiters = self._waiters, []
        try:
            await self._write_changes(client)
        except BaseException:
            self._waiters = waiters + self._waiters  # released with the outage's reason
            raise
        for w in waiters:
            if not w.done():
                w.set_result(None)
