"""Universal Robots RTDE link: the robot program triggers jobs and reads results through RTDE
general-purpose registers (port 30004), with the ``ur_rtde`` client.

The register map and handshake are ``vgripd.peer.ur_registers.URRegisterMap`` (docs/ur_rtde.md);
the robot side is ``robots/urscript/vgripd.script``. The pose goes to the robot in two pages
(translation, then rotation vector) because ur_rtde can write only 5 input double registers; each
page is written data first, acknowledge last. The robot program uses the six numbers as
``p[x, y, z, rx, ry, rz]``, so the link carries only the ``ur`` convention (``capabilities``;
a config with another ``output.vendor`` is refused when it is loaded).

ur_rtde runs in a child process (``ur_rtde_worker``): its constructors hold the GIL with no
timeout and it aborts the process when it destroys an IO interface on a dead socket. The asyncio
side reads the child's pipe with ``add_reader`` (no threads) and one supervisor task owns the
child: it starts it, waits for ``up`` at most ``connect_timeout_s``, serves, and on any failure
(silent controller, refused connection, dropped socket, data stream older than
``stale_after_s``, child crash) kills it and starts a new one after a doubling back-off, logging
once per outage. No error of the controller stops the retrying: a register
``IN_USE`` or a variable the controller does not know is a configuration problem of the robot,
fixed on the robot while vgripd runs, so it is an outage too, logged once at ERROR naming it.

After every reconnect the warning bits (``set_warnings``, input_double_register 21) and the last
``image_captured``/``publish`` are written again, so a robot whose acknowledge was lost with the
connection still gets its answer, and a stale warning from an earlier run is overwritten. A
request already pending when the link first connects (the robot's sequence differs from the
acknowledge register, read back once at the first connect) is served, as is one that arrives
while the link is down (at the reconnect); an answered one is never run again.

The request rules are ``jobcore.Handshake``'s, as on every link, decided here in the parent:
the child is the RTDE I/O shell, reporting each change of the robot's sequence register with
its data package and carrying out the register writes the handshake's plans become
(``ur_wire.writes``, one pipe message per plan, as before). The decision costs no extra
round trip: the child sent every new sequence to this side before as well. The rotation page
stays in the child (answered at the polling rate, no trip through the pipe).

A request whose command is not one of ``URRegisterMap.COMMANDS`` (1 = locate, 3 = next), a
capture or (map version 4) a predict, a next without a pick list, or a request while this
link's own one runs is answered by the link itself (``BAD_REQUEST`` 32, ``BUSY`` 40) with job
id 0, without a job; ``refusals()`` counts it. A next with a list goes to the daemon like a
locate; the daemon answers it from the last job's pick list.
Every answer carries the pick list position in input_double_register ``regs.pick``
(``1000 * COUNT + INDEX``, written before the ack; 0 for refusals).

Conveyor (``map_version = 4``, docs/ur_rtde.md "Conveyor"): the robot writes the encoder count
it latched with each request into output_int_register ``regs.latch`` (read from the trigger's
data package: ``Trigger.latch_count``); PREDICT (5) is a request; every answer carries the belt
block (``URRegisterMap.belt_values``: its sequence, RESULT_COUNT, LATCH_SOURCE, QUEUED,
LATCH_ERR_MM, ALONG, ACROSS, THETA), written by the child before the acknowledge.

The child's stdout/stderr (ur_rtde prints its own errors there) is a pipe read on the loop:
each line is logged through ``vgripd.link.ur_rtde`` (``link <name>: ur_rtde: <line>``, INFO),
at most ``OUTPUT_LINES`` lines per ``OUTPUT_WINDOW_S`` and link, then a count of the held ones.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import time
from collections import Counter
from collections.abc import Callable, Mapping
from multiprocessing.connection import Connection
from typing import Any, Literal

from pydantic import ConfigDict, Field

from drivers.links import ur_rtde_worker
from vgripd.errors import ConversionError, LinkError
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.peer import ur_wire
from vgripd.peer.jobcore import Action, Command, Step, split_command
from vgripd.peer.registers import checked_warnings
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.registry import UR_CAPABILITIES
from vgripd.service.host import children
from vgripd.service.links.protocol import LinkState, Trigger, TriggerHandler
from vgripd.service.links.supervisor import (
    BackoffOptions,
    Ended,
    OutagePolicy,
    Reconnector,
    SupervisedLink,
    backoff_initial,
    backoff_max,
    end_task,
)
from vgripd.types import JobResult, Status

log = logging.getLogger("vgripd.link.ur_rtde")

# The child's output lines logged per link and window; more are counted and reported once.
OUTPUT_LINES = 20
#: How long the link's helper process may take to start (an interpreter and ur_rtde loaded)
#: before the RTDE setup's own time (``connect_timeout_s``) begins.
CHILD_START_S = 60.0
OUTPUT_WINDOW_S = 60.0
OUTPUT_LINE_CHARS = 400


class OutputLog:
    """Logs the child's output one line per record, at most ``lines`` per ``window_s``."""

    def __init__(self, link: str, lines: int = OUTPUT_LINES, window_s: float = OUTPUT_WINDOW_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.link, self.lines, self.window_s, self.clock = link, lines, window_s, clock
        self._window_start = -float("inf")
        self._in_window = 0
        self.held = 0
        self._partial = b""

    def feed(self, data: bytes) -> None:
        """Bytes from the pipe; b"" at its end (a last line without newline is logged too)."""
        if not data:
            rest, self._partial = self._partial, b""
            self.line(rest.decode("utf-8", "replace"))
            return
        lines = (self._partial + data).split(b"\n")
        self._partial = lines.pop()
        if len(self._partial) > OUTPUT_LINE_CHARS:  # no newline coming: log what there is
            lines.append(self._partial)
            self._partial = b""
        for raw in lines:
            self.line(raw.decode("utf-8", "replace"))

    def line(self, text: str) -> None:
        text = text.strip()
        if not text:
            return
        now = self.clock()
        if now - self._window_start >= self.window_s:
            if self.held:
                log.info("link %s: ur_rtde: %d more output lines held back in the last %.0f s",
                         self.link, self.held, now - self._window_start)
            self._window_start, self._in_window, self.held = now, 0, 0
        if self._in_window >= self.lines:
            self.held += 1
            return
        self._in_window += 1
        if len(text) > OUTPUT_LINE_CHARS:
            text = text[:OUTPUT_LINE_CHARS] + " ..."
        log.info("link %s: ur_rtde: %s", self.link, text)


class URRtdeOptions(BackoffOptions):
    """Options of ``type = "ur_rtde"`` (TOML ``[links.<name>]``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    host: str = Field(min_length=1)
    #: Use registers 36..47 instead of 12..23 (leaves the lower range to a PLC/fieldbus).
    use_upper_range_registers: bool = False
    #: Output stream rate asked from the controller; also the child's polling rate.
    frequency_hz: float = Field(500.0, gt=0, le=500)
    #: Child start + RTDE setup must finish within this (a silent controller is killed after it).
    connect_timeout_s: float = Field(6.0, gt=0, le=120)
    #: No new data package for this long = connection lost (ur_rtde itself gives up at 2.5 s).
    stale_after_s: float = Field(1.0, gt=0, lt=2.5)
    #: Longest wait for the child to confirm a register write.
    write_timeout_s: float = Field(2.0, gt=0, le=60)
    backoff_initial_s: float = backoff_initial(0.2)
    backoff_max_s: float = backoff_max(10.0)
    #: 4: the conveyor's registers (the latch count with each request, PREDICT, the belt
    #: block with each answer; docs/ur_rtde.md "Conveyor"), as the Modbus links' version 4.
    map_version: Literal[3, 4] = 3


class _Child:
    """One worker process and the asyncio side of its pipes (messages; stdout/stderr)."""

    def __init__(self, opts: URRtdeOptions, last_seq: int | None, output: OutputLog) -> None:
        ctx = children.context()
        self.conn, child_conn = ctx.Pipe()
        self._output_r, output_w = os.pipe()
        os.set_blocking(self._output_r, False)
        # A Connection only to hand the pipe's write end to the spawned child (it dup2s it
        # onto its fds 1 and 2); nothing is ever sent through it as a Connection.
        child_output = Connection(output_w, readable=False)
        self.output = output
        self.process = ctx.Process(
            target=ur_rtde_worker.main, name=f"ur_rtde {opts.host}", daemon=True,
            args=(child_conn, child_output, opts.host, opts.use_upper_range_registers,
                  opts.frequency_hz, opts.stale_after_s, opts.connect_timeout_s, last_seq,
                  ur_rtde_worker.link_child_setup(), opts.map_version == 4))
        self._child_conns: list[Connection] = [child_conn, child_output]
        self.messages: asyncio.Queue[tuple[Any, ...]] = asyncio.Queue()
        self.exited: asyncio.Future[int] = asyncio.get_running_loop().create_future()

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.process.start()
        for conn in self._child_conns:
            conn.close()
        self._child_conns = []
        loop.add_reader(self.conn.fileno(), self._on_readable)
        loop.add_reader(self.process.sentinel, self._on_exit)
        loop.add_reader(self._output_r, self._on_output)

    def _on_output(self) -> None:
        try:
            data = os.read(self._output_r, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._close_output()
        self.output.feed(data)

    def _close_output(self) -> None:
        if self._output_r >= 0:
            asyncio.get_running_loop().remove_reader(self._output_r)
            os.close(self._output_r)
            self._output_r = -1

    def _on_readable(self) -> None:
        try:
            while self.conn.poll():
                self.messages.put_nowait(self.conn.recv())
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(self.conn.fileno())

    def _on_exit(self) -> None:
        asyncio.get_running_loop().remove_reader(self.process.sentinel)
        self.process.join()
        if not self.exited.done():
            code = self.process.exitcode
            self.exited.set_result(-1 if code is None else code)

    async def next_message(self) -> tuple[Any, ...]:
        """The next message, or ``("exit", code)`` once the process is gone and nothing is left."""
        get: asyncio.Future[Any] = asyncio.ensure_future(self.messages.get())
        try:
            await asyncio.wait({get, self.exited}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            if not get.done():
                get.cancel()
        if get.done() and not get.cancelled():
            return get.result()
        self._on_readable()  # anything written just before the exit
        if not self.messages.empty():
            return self.messages.get_nowait()
        return ("exit", self.exited.result())

    def send(self, message: tuple[Any, ...]) -> None:
        self.conn.send(message)

    async def stop(self, grace_s: float) -> None:
        """Ask the child to leave, kill it after ``grace_s``, reap it, close the pipe."""
        if self.process.pid is not None and not self.exited.done():
            with contextlib.suppress(OSError):
                self.send((0, "close", ()))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self.exited), grace_s)
            if not self.exited.done():
                self.process.kill()
                await self.exited
        loop = asyncio.get_running_loop()
        loop.remove_reader(self.conn.fileno())
        self.conn.close()
        for conn in self._child_conns:
            conn.close()
        self._child_conns = []
        if self._output_r >= 0:  # the child is gone: log what it left
            with contextlib.suppress(OSError):
                while data := os.read(self._output_r, 65536):
                    self.output.feed(data)
            self.output.feed(b"")
            self._close_output()


def _describe_exit(code: int | None) -> str:
    if code is not None and code < 0:
        return f"worker process killed by signal {-code}"
    return f"worker process ended with code {code}"


class URRtdeLink(SupervisedLink):
    """RobotLink over UR RTDE registers (see module docstring and docs/ur_rtde.md)."""

    Options = URRtdeOptions
    capabilities = UR_CAPABILITIES
    options: URRtdeOptions

    def __init__(self, name: str, options: URRtdeOptions) -> None:
        super().__init__(name, options, f"{options.host}:{ur_rtde_worker.RTDE_PORT}")
        self.regs = URRegisterMap(options.use_upper_range_registers, options.map_version == 4)
        #: The link's request rules (``jobcore.Handshake``); the child reports the sequence.
        self.handshake = ur_wire.handshake(self.regs)
        self._peer = self.cell.peer
        self._task: asyncio.Task[None] | None = None
        self._child: _Child | None = None
        self._on_trigger: TriggerHandler | None = None
        #: The robot's sequence at the first connect is known (``handshake.last_req_seq``).
        self._baseline = False
        #: The writes since the last request, written again at a reconnect.
        self._replay: list[ur_wire.Write] = []
        self._warnings = 0
        self._walking = False
        self._pending: dict[int, asyncio.Future[None]] = {}
        self._ids = itertools.count(1)
        self._refused: Counter[str] = Counter()
        self._output = OutputLog(name)

    # -- RobotLink ----------------------------------------------------------------------------

    async def open(self, on_trigger: TriggerHandler) -> None:
        """Start the supervisor and wait for the first attempt's outcome.

        Nothing the controller does is an error here: unreachable, silent, or refusing a
        register (IN_USE, NOT_FOUND), the link is DOWN with the reason and keeps retrying.
        """
        if self._task is not None:
            raise LinkError(f"link {self.name}: already open")
        self._on_trigger = on_trigger
        self._task = asyncio.create_task(self._supervise(), name=f"link {self.name} supervisor")
        try:
            health = await self.wait_state({LinkState.UP, LinkState.DOWN, LinkState.FAILED},
                                           timeout_s=self.options.connect_timeout_s + 5.0)
        except TimeoutError:  # the first attempt still running (a busy machine): it goes on
            health = self.health()
        if health.state is LinkState.FAILED:
            await self.close()
            self.cell.set(LinkState.FAILED, health.last_error)
            raise LinkError(f"link {self.name}: {health.last_error}")

    async def close(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            await end_task(task)
        self.cell.set(LinkState.STOPPED, None)

    def refusals(self) -> Mapping[str, int]:
        return dict(self._refused)

    async def image_captured(self, seq: int, job_id: int) -> None:
        self._check_open()
        await self._write(f"image_captured seq {seq}", self.handshake.on_captured(seq, job_id))

    takes_views = True

    async def view_captured(self, seq: int, job_id: int) -> None:
        """A view before the last is taken: ``captured`` = seq, the robot moves to the next
        view (it knows which view is its last; only that one gets ``ack``)."""
        self._check_open()
        await self._write(f"view_captured seq {seq}",
                          self.handshake.on_view_captured(seq, job_id))

    async def publish(self, seq: int, result: JobResult) -> Status:
        """Write status, job id and (for a valid pose) the translation page, then the ack;
        returns the status the robot got.

        The rotation page follows when the robot asks for it (``page_request`` = seq). A valid
        status whose target is not a UR pose of 6 finite values is answered INTERNAL without a
        pose and logged as an error: the config check (``capabilities``) refuses any
        ``output.vendor`` but ``ur``, so only a bug gets here.
        """
        self._check_open()
        answer, why = ur_wire.ur_answer(result)
        if why:
            log.error("link %s: %s; answered INTERNAL", self.name, why)
        await self._write(f"publish seq {seq}", self.handshake.publish(seq, answer))
        return answer.status

    def set_conveyor(self, on: bool) -> None:
        """A recipe has a conveyor: NEXT and PREDICT go to the daemon (its part queue)."""
        self.handshake.queue = on and self.regs.conveyor

    def set_walking(self, walking: bool) -> None:
        """A walked hand-eye calibration is served: every NEXT goes on (the walk answers it,
        the first one asks for a target). After the walk there is no pick list."""
        self._walking = walking
        if not walking:
            self.handshake.listed = False

    async def set_warnings(self, bits: int) -> None:
        """Write the bits to input_double_register ``regs.warnings``; while the link is down
        they are kept and written at the reconnect (no error: they are state, not an answer)."""
        self._warnings = checked_warnings(bits)
        child = self._child
        if child is not None and self.cell.state is LinkState.UP:
            await self._send(child, "write", (self._warnings_writes(),))

    async def robot_pose(self) -> Any | None:
        """``actual_TCP_pose`` read now by the child from the newest data package, as
        ``T_base_flange`` (mm); None while the link is not up."""
        child = self._child
        if child is None or self.cell.state is not LinkState.UP:
            return None
        values = await self._send(child, "pose", ())
        try:
            return transform_from_vendor("ur", values)
        except ConversionError as err:
            raise LinkError(f"link {self.name}: unusable actual_TCP_pose {values}: {err}") from None

    # -- requests to the child ----------------------------------------------------------------

    def _check_open(self) -> None:
        if self._task is None or self.cell.state is LinkState.FAILED:
            raise LinkError(f"link {self.name} to {self._peer} is {self.cell.state.value}")

    def _warnings_writes(self) -> tuple[ur_wire.Write, ...]:
        return (("double", self.regs.warnings, float(self._warnings)),)

    async def _write(self, what: str, plan: tuple[Step, ...]) -> None:
        """Carry out a handshake plan: kept for the reconnect, written now when the link is up
        (``LinkError`` when it is not: the writes wait for the reconnect)."""
        writes = ur_wire.writes(self.regs, plan)
        self._replay += writes
        child = self._child
        if child is None or self.cell.state is not LinkState.UP:
            raise LinkError(f"link {self.name} to {self._peer} is {self.cell.state.value} "
                            f"({self.cell.last_error}); {what} will be written at the "
                            "reconnect")
        await self._send(child, "write", (writes,))

    async def _send(self, child: _Child, kind: str, args: tuple[Any, ...]) -> Any:
        """Send one request to the child and wait for its "done"; its value (a pose), if any."""
        req = next(self._ids)
        done = asyncio.get_running_loop().create_future()
        self._pending[req] = done
        try:
            child.send((req, kind, args))
            return await asyncio.wait_for(done, self.options.write_timeout_s)
        except (OSError, TimeoutError):
            what = f"{kind} {args[0]}" if args else kind
            raise LinkError(f"link {self.name} to {self._peer}: {what} not "
                            f"confirmed within {self.options.write_timeout_s} s") from None
        finally:
            self._pending.pop(req, None)

    # -- supervisor ---------------------------------------------------------------------------

    async def _supervise(self) -> None:
        o = self.options
        reconnector = Reconnector(
            self.name, self.cell, OutagePolicy(o.backoff_initial_s, o.backoff_max_s), log,
            down_line="link %s down: %s (retrying with back-off up to %.0f s)",
            still_line="link %s still down (attempt %d): %s")
        ever_up = False

        async def session() -> Ended:
            nonlocal ever_up
            known = self.handshake.last_req_seq if self._baseline else None
            if not ever_up and self.cell.state is LinkState.STOPPED:
                self.cell.set(LinkState.CONNECTING, None)  # the helper's start counts too
            # the fork server ready off the event loop: the child's start then takes ms
            await asyncio.to_thread(children.start_server)
            child = _Child(self.options, known, self._output)
            self._child = child
            try:
                child.start()
                fatal, error = await self._serve(child, reconnector, ever_up)
            finally:
                self._child = None
                for fut in self._pending.values():
                    if not fut.done():
                        fut.set_exception(LinkError(f"link {self.name}: connection lost"))
                await child.stop(grace_s=1.0)
            ever_up = ever_up or self.cell.state is LinkState.UP
            # a refused register needs a person: ERROR, else WARNING
            return Ended(error, logging.ERROR if fatal else logging.WARNING)

        await reconnector.run(session)

    async def _serve(self, child: _Child, reconnector: Reconnector,
                     ever_up: bool) -> tuple[bool, str]:
        """Run one child until it fails; return (fatal, reason). ``ever_up``: an earlier child
        was up (only reconnections after that count)."""
        # The child's own start (an interpreter and ur_rtde loaded) is not the controller's
        # time: a busy cell PC takes seconds for it. connect_timeout_s runs from "started".
        try:
            first = await asyncio.wait_for(child.next_message(), CHILD_START_S)
        except TimeoutError:
            return False, (f"link {self.name}: its helper process did not start within "
                           f"{CHILD_START_S:g} s (the computer is overloaded?)")
        if first[0] == "started":
            try:
                first = await asyncio.wait_for(child.next_message(),
                                               self.options.connect_timeout_s)
            except TimeoutError:
                return False, (f"{self._peer} did not complete the RTDE setup within "
                               f"{self.options.connect_timeout_s} s (controller silent?)")
        if first[0] == "error":
            return bool(first[1]), str(first[2])
        if first[0] == "exit":
            return False, f"{self._peer}: {_describe_exit(first[1])} during setup"
        if not self._baseline:  # the baseline: later connects serve anything newer
            self._baseline = True
            self.handshake.last_req_seq = first[2]
            if first[3]:
                log.info("link %s: %s", self.name, first[3])
        if reconnector.up(reconnect=ever_up):
            log.info("link %s up again (%s)", self.name, self._peer)
        try:
            # nobody waits for these: no "done" is expected
            child.send((0, "write", (self._warnings_writes() + tuple(self._replay),)))
        except OSError as err:
            return False, f"{self._peer}: {err}"
        while True:
            msg = await child.next_message()
            if msg[0] == "request":
                if not self._on_request(child, *msg[1:]):
                    return False, f"{self._peer}: the worker process pipe closed"
            elif msg[0] == "done":
                fut = self._pending.get(msg[1])
                if fut is not None and not fut.done():
                    fut.set_result(msg[2] if len(msg) > 2 else None)
            elif msg[0] == "error":
                return bool(msg[1]), str(msg[2])
            else:
                return False, f"{self._peer}: {_describe_exit(msg[1])}"

    def _on_request(self, child: _Child, seq: int, command: int, tcp_pose: list[float],
                    recipe: int = 0, latch: int | None = None) -> bool:
        """The robot's sequence changed: the handshake decides; a refusal is written here (no
        job), a request goes to the daemon. False when the pipe broke."""
        if self._walking and split_command(command)[0] == Command.NEXT:
            self.handshake.listed = True  # a walk answers every NEXT
        decision = self.handshake.on_request(command, seq, recipe)
        if decision.action is Action.IGNORE:
            return True
        self._replay.clear()  # a new request: earlier answers are no longer wanted
        if decision.action is Action.REJECT:
            writes = ur_wire.writes(self.regs, decision.steps)
            self._replay += writes
            self._refused[decision.code.name] += 1
            if decision.code is Status.BUSY:
                why = f"request {self.handshake.running_seq} still runs"
            else:
                why = "the robot program may send " + " or ".join(str(c) for c in sorted(
                    self.handshake.commands or ()) if c != Command.CAPTURE) + " or a capture"
            log.info("link %s: request %d refused: %s (command %d; %s)", self.name, seq,
                     decision.code.name, command, why)
            try:
                child.send((0, "write", (writes,)))  # nobody waits: no "done" is expected
            except OSError:
                return False
            return True
        if self._deliver(seq, command, tcp_pose, recipe, latch):
            return True
        # the handler failed: the request still ends, with INTERNAL, so the next one is no BUSY
        plan = self.handshake.publish(seq, JobResult(0, Status.INTERNAL,
                                                     "the trigger handler failed"))
        writes = ur_wire.writes(self.regs, plan)
        self._replay += writes
        try:
            child.send((0, "write", (writes,)))
        except OSError:
            return False
        return True

    def _deliver(self, seq: int, command: int, tcp_pose: list[float], recipe: int = 0,
                 latch: int | None = None) -> bool:
        """Hand the request to the daemon; False when its handler raised."""
        t_mono_ns = time.monotonic_ns()
        try:
            T_base_flange = transform_from_vendor("ur", tcp_pose)
        except ConversionError as err:
            log.warning("link %s: trigger seq %d with unusable TCP pose %s: %s",
                        self.name, seq, tcp_pose, err)
            T_base_flange = None
        command, view = split_command(command)
        trigger = Trigger(self.name, seq, command, t_mono_ns, T_base_flange, recipe=recipe,
                          view=view, peer=self._peer, latch_count=latch)
        assert self._on_trigger is not None
        try:
            self._on_trigger(trigger)
        except Exception:  # the handler's bug must not take the link down
            log.exception("link %s: trigger handler failed for seq %d", self.name, seq)
            return False
        return True
