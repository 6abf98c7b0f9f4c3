"""Siemens S7 client link: vgripd reads and writes a data block of an S7-300/400/1200/1500 PLC.

The PLC serves nothing of vgripd's: vgripd connects to it as a client (python-snap7, the
classic S7 protocol over ISO-on-TCP, port 102, the "PUT/GET" access of S7-1200/1500) and uses
``DB<db>`` bytes ``start .. start + 91`` (``map_version = 4``: ``start + 123``, the conveyor's
latch and belt result) as the register block of ``vgripd.peer.registers``: the same items,
in the same order, with the same handshake as the Modbus links; map register ``n`` is the
16-bit word at byte ``start + 2 n``. S7 is big-endian throughout (16-bit and 32-bit items
alike), which is the map's ``ABCD`` order, so there is no word-order option. ``vgripd s7-udt``
prints the block as an S7 ``UDT`` (SCL source) for the PLC programmer; docs/s7.md has the
table and the TIA Portal settings.

The PLC program writes CMD, REQ_SEQ and RECIPE (bytes 0-5 of the block) and, in map version
4, LATCH_COUNT and LATCH_FRAME (bytes 92-99) before or with REQ_SEQ; vgripd writes the rest
and never those bytes. The link keeps a mirror of the block in a ``RegisterBank`` (the
handshake and image code every register link uses) and copies its changes to the PLC, in the
bank's order:

- every ``poll_ms`` it reads the whole block (one request: 92 bytes, 124 in version 4); a
  change of the command area goes through the bank's handshake: a new request sequence calls
  ``on_trigger`` (with the latch of the same read), a refusal (BUSY, BAD_REQUEST) writes
  REJECT_CODE, then REJECT_SEQ;
- ``image_captured`` / ``publish`` / the heartbeat change the mirror and wake the supervisor,
  which writes what changed: everything between two changes of ACK_SEQ in one write (one on
  each side of the latch in version 4: the PLC's words are never written over), and each
  change of ACK_SEQ in a write of its own at its place in the bank's order (last for a
  publish, first for the retraction of a new job or a CLEAR: ``jobcore.Handshake``), so the
  PLC never pairs an acknowledged sequence with data of another request (``peer.s7_block``);
- after every (re)connect the PLC's block is read and whatever differs from the mirror is
  written (data, then ACK_SEQ), so a result published while the PLC was away reaches it as
  soon as it is back;
- if vgripd's part of the block is not what vgripd last wrote (a DB re-initialised by a
  download from TIA Portal, or a PLC program writing where it should not), the mirror is
  written again (one WARNING line, then at most one a minute while it goes on).

Blocking snap7 calls run on the link's own single-thread executor, never on the event loop;
every call is bounded by ``timeout_s`` on the loop's side, and a call that overruns it is cut
by shutting down its socket (snap7's own connect timeout is a fixed 5 s). One supervisor task
owns the connection and is the only retry loop (snap7's auto-reconnect stays off). After a drop
it reconnects with doubling back-off and logs once per outage (one WARNING line, no
traceback); ``health()`` says DOWN with the reason. A daemon call waiting for the PLC is
released with the outage. Every error is retried, whatever the peer did: a peer that
completes the ISO-on-TCP connect and then answers garbage, or a PLC that refuses the block (the
DB does not exist, is too short, has optimized access, or PUT/GET is not allowed: logged at
ERROR with what to check, since a download from TIA Portal fixes it while vgripd runs). snap7's
own INFO lines (one per connect attempt) are kept out of the log unless the ``snap7`` logger
is configured explicitly.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import socket
import struct
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Literal, TypeVar

from pydantic import Field, field_validator, model_validator
from snap7 import Client
from snap7.error import S7Error, S7ProtocolError, S7TimeoutError

from drivers.links.mirror_client import MirrorClientLink
from vgripd.errors import LinkError
from vgripd.peer.registers import (
    COMMAND_AREA,
    BlockWrite,
    Reg,
    RegisterOptions,
)
from vgripd.peer.s7_block import DB_BYTES, block_bytes, db_bytes, plan_db_writes
from vgripd.registry import S7_CAPABILITIES
from vgripd.service.links.supervisor import BackoffOptions

log = logging.getLogger(__name__)

T = TypeVar("T")

OVERWRITE_LOG_S = 60.0  # at most one line per this long about foreign writes to vgripd's part


def quiet_snap7() -> None:
    """snap7 logs INFO lines for every client it makes, connects and drops; the link reports
    connections itself. Unless the ``snap7`` logger was configured, keep it at WARNING."""
    logger = logging.getLogger("snap7")
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.WARNING)


class S7Options(RegisterOptions, BackoffOptions):
    """Options of ``type = "s7"``; value format, scale and heartbeat as for every register link
    (``RegisterOptions``), back-off as every link that reconnects (``BackoffOptions``);
    ``word_order`` can only be ``ABCD`` (S7 is big-endian).

    ``rack``/``slot``: of the CPU (S7-300: 0/2; S7-400: see the hardware configuration;
    S7-1200/1500: 0/1, or 0/0 for some; docs/s7.md). ``db``: the data block's number;
    ``start``: the block's first byte in it (even: S7 aligns words on even bytes).
    """

    word_order: Literal["ABCD"] = "ABCD"
    host: str = Field(min_length=1)
    port: int = Field(102, ge=1, le=65535)
    rack: int = Field(0, ge=0, le=7)
    slot: int = Field(1, ge=0, le=31)
    db: int = Field(ge=1, le=65535)
    start: int = Field(0, ge=0, le=65536 - DB_BYTES, multiple_of=2)  # and see _fits
    poll_ms: int = Field(20, ge=1, le=10_000)
    timeout_s: float = Field(1.0, gt=0, le=60)  # connect, and each request

    @field_validator("word_order", mode="before")
    @classmethod
    def _big_endian(cls, value: Any) -> Any:
        if value != "ABCD":
            raise ValueError("S7 is big-endian: 32-bit items are always high word first "
                             "(ABCD); leave word_order out")
        return value

    @model_validator(mode="after")
    def _fits(self) -> S7Options:
        size = db_bytes(self.map_version)
        if self.start + size > 65536:
            raise ValueError(f"start {self.start}: the block of map version {self.map_version} "
                             f"({size} bytes) must end within a DB's 65536 bytes; start at most "
                             f"{65536 - size}")
        return self


class S7Refused(LinkError):
    """The PLC answered a request with an error (no such DB, address out of range, access
    denied), as opposed to a lost or silent connection."""


class S7Link(MirrorClientLink[Client]):
    Options = S7Options
    capabilities = S7_CAPABILITIES
    options: S7Options
    peer_kind = "PLC"
    _log = log

    def __init__(self, name: str, options: S7Options) -> None:
        size = db_bytes(options.map_version)
        area = f"DB{options.db} bytes {options.start}..{options.start + size - 1}"
        super().__init__(name, options, f"{options.host}:{options.port} {area}")
        self._area = area
        self._size = size
        self._sent = [0] * (size // 2)  # the block as the PLC has it, as far as vgripd knows
        self._executor: ThreadPoolExecutor | None = None
        self._client: Client | None = None
        self._overwrites = 0  # foreign writes to vgripd's part not yet logged
        self._overwrite_logged: float | None = None  # monotonic s of the last such line

    # -- MirrorClientLink hooks ----------------------------------------------------------------

    def _starting(self) -> None:
        quiet_snap7()
        self._executor = ThreadPoolExecutor(1, thread_name_prefix=f"s7-{self.name}")

    @property
    def _poll_s(self) -> float:
        return self.options.poll_ms / 1000

    def _new_client(self) -> Client:
        client = Client()
        self._client = client
        return client

    async def _connect(self, client: Client) -> None:
        opt = self.options
        try:
            await self._call(
                f"connecting (rack {opt.rack}, slot {opt.slot})",
                functools.partial(client.connect, opt.host, opt.rack, opt.slot, opt.port),
            )
        except S7Refused as err:  # no block asked for yet: a peer that does not speak S7
            raise LinkError(f"{self._peer} is not an S7 PLC as expected ({err})") from None

    def _refusal_hint(self, err: LinkError) -> str | None:
        if not isinstance(err, S7Refused):
            return None
        return (f"{err}; check db and start (the DB must hold {self._area}), that the DB has "
                "optimized block access off and that the CPU allows PUT/GET (docs/s7.md)")

    async def _write_mirror(self, client: Client, words: list[int]) -> None:
        """Write the mirror where the PLC's block differs from it."""
        self._sent = list(words)
        self._journal[:] = [BlockWrite(COMMAND_AREA.stop,
                                       tuple(self.bank.image.words[COMMAND_AREA.stop:]))]
        await self._write_plan(client)  # only vgripd's stretches: the plan skips the PLC's

    async def _exchange(self, client: Client) -> list[int]:
        for _ in range(3):  # what the daemon added meanwhile goes out before the next poll
            await self._flush(client)
            if not (self._journal or self._waiters):
                break
        words = await self._read_block(client)
        self._check_own_part(words)
        return words

    async def _write_changes(self, client: Client) -> None:
        await self._write_plan(client)

    async def _stop(self) -> None:
        await super()._stop()
        executor, self._executor = self._executor, None
        if executor is not None:
            # The supervisor cut any call in progress; once this no-op has run, the thread is
            # idle and shutting the executor down does not block the loop.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(10.0):  # > snap7's fixed 5 s connect timeout
                    await asyncio.wrap_future(executor.submit(lambda: None))
            executor.shutdown(wait=True)

    # -- blocking calls, on the link's own thread --------------------------------------------

    async def _call(self, what: str, fn: Callable[[], T]) -> T:
        """Run ``fn`` on the link's thread, bounded by ``timeout_s``; every way it can fail
        becomes a ``LinkError`` naming ``what`` and the PLC (``S7Refused`` for an error the
        PLC answered with)."""
        assert self._executor is not None
        self.transactions += 1
        fut = asyncio.get_running_loop().run_in_executor(self._executor, fn)
        # a cut call may still fail after nobody waits for it: retrieve that quietly
        fut.add_done_callback(lambda f: f.cancelled() or f.exception())
        timeout_s = self.options.timeout_s
        try:
            done, _ = await asyncio.wait({fut}, timeout=timeout_s)
        except asyncio.CancelledError:
            self._cut()
            raise
        if not done:
            self._cut()
            raise LinkError(f"no answer within {timeout_s:g} s {what} on {self._peer}")
        try:
            return fut.result()
        except S7TimeoutError:
            raise LinkError(f"no answer within {timeout_s:g} s {what} on {self._peer}") from None
        except S7ProtocolError as err:
            raise S7Refused(f"PLC {self._peer} refused {what}: {err}") from None
        except (S7Error, OSError) as err:
            raise LinkError(f"{what} on {self._peer}: {err}") from None
        except Exception as err:  # snap7 choking on an answer that is not S7: the peer's fault
            raise LinkError(f"{what} on {self._peer}: unreadable answer "
                            f"({type(err).__name__}: {err})") from None

    def _cut(self) -> None:
        """Wake the link's thread out of a blocking socket call (the connection is dropped)."""
        conn = getattr(self._client, "connection", None)
        sock: socket.socket | None = getattr(conn, "socket", None)
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def _drop(self, client: Client) -> None:
        """Disconnect ``client`` on the link's thread, after whatever it is doing."""
        self._cut()
        if self._executor is not None:
            self._executor.submit(self._disconnect_quietly, client)

    @staticmethod
    def _disconnect_quietly(client: Client) -> None:
        with contextlib.suppress(Exception):
            client.disconnect()

    # -- polling ------------------------------------------------------------------------------

    def _check_own_part(self, words: list[int]) -> None:
        """vgripd's part of the block must be what vgripd last wrote; if not, write it again.

        Logged at most once per ``OVERWRITE_LOG_S`` (with the count since the last line), so a
        PLC program that keeps writing there does not flood the log.
        """
        changed = [a for seg in self._own for a in seg if words[a] != self._sent[a]]
        if not changed:
            return
        self._overwrites += 1
        now = time.monotonic()
        if self._overwrite_logged is None or now - self._overwrite_logged >= OVERWRITE_LOG_S:
            first = changed[0]
            name = next(r.name for r in reversed(Reg) if r.value <= first)
            theirs = ("CMD, REQ_SEQ and RECIPE (bytes 0-5)" if len(self._peer_areas) == 1 else
                      "CMD, REQ_SEQ, RECIPE (bytes 0-5), LATCH_COUNT and LATCH_FRAME "
                      "(bytes 92-99)")
            log.warning("%s: vgripd's part of %s on %s was changed from the PLC side (first at "
                        "block byte %d, %s; %d time(s) since the last such line): writing it "
                        "again; only %s are the PLC's",
                        self.name, self._area, self._peer, 2 * first, name, self._overwrites,
                        theirs)
            self._overwrite_logged = now
            self._overwrites = 0
        for seg in self._own:
            self._sent[seg.start:seg.stop] = words[seg.start:seg.stop]
            self._journal.append(BlockWrite(seg.start, tuple(self.bank.image.words[seg.start:
                                                                                   seg.stop])))

    async def _write_plan(self, client: Client) -> None:
        plan = plan_db_writes(self._sent, self._journal, self._own)
        self._journal.clear()
        db, start = self.options.db, self.options.start
        for w in plan:
            first = start + 2 * w.address
            await self._call(
                f"writing DB{db} bytes {first}..{first + 2 * len(w.words) - 1}",
                functools.partial(client.db_write, db, first, block_bytes(w.words)),
            )
            self._sent[w.address:w.address + len(w.words)] = w.words

    async def _read_block(self, client: Client) -> list[int]:
        db, start = self.options.db, self.options.start
        raw = await self._call(f"reading {self._area}",
                               functools.partial(client.db_read, db, start, self._size))
        if len(raw) != self._size:
            raise LinkError(f"{self._peer} returned {len(raw)} bytes for {self._area}")
        return list(struct.unpack(f">{self._size // 2}H", raw))
