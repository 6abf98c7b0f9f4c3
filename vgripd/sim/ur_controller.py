"""Mock Universal Robots controller: the robot side of RTDE (protocol version 2) on TCP 30004.

The real ``ur_rtde`` client connects to it unchanged (see ``shared/reference/RTDE.md``): framing,
``V v O I S P U M`` packages, the trailing comma ur_rtde puts after names, input recipe ids
1, 2, 3, ... per connection, ``IN_USE`` / ``NOT_FOUND`` replies, standard types, streaming at the
requested rate with the first ``U`` at once after ``S``.

Why a separate OS process: the ur_rtde constructors hold the GIL while they wait for replies, so a
socket server living in the same interpreter could never answer them. ``URController`` is the
in-process handle: it spawns the server process and drives it over a pipe (set outputs, read the
inputs the client wrote, run the simulated robot program, switch faults on and off).

The simulated robot program (``start_program`` / ``program_result``) is the Python twin of
``robots/urscript/vgripd.script``, including what it does when vgripd does not answer (asks again,
``attempts`` requests in all, then gives up as the script's popup does) and when it answers BUSY
(waits ``busy_wait_s``, asks again). Both take their registers from ``peer.ur_registers``.

Input registers can also be named in an output recipe (the controller's "input read back"), as
on a real controller; ``set_inputs`` presets them (values left by an earlier client).

Faults for tests: ``set_silent`` (accept connections, answer nothing), ``drop`` (close every
connection, optionally stop listening so connects are refused), ``set_in_use`` (input names owned
by "a fieldbus adapter": I replies say ``IN_USE``), ``pause_stream`` (no ``U`` packages).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import multiprocessing
import struct
import time
from collections.abc import Iterable, Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from vgripd.errors import VgripError
from vgripd.geometry.vendors import transform_from_vendor, vendor_from_transform
from vgripd.peer.jobcore import capture_word
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.sim.ur_belt import BeltProgram
from vgripd.types import Status

RTDE_PORT = 30004
PROTOCOL_VERSION = 2
DEFAULT_CONTROLLER_VERSION = (5, 15, 0, 0)

# ------------------------------------------------------------------------------------ codec
#: RTDE type name -> struct code (big-endian, no padding), RTDE.md section 2.
TYPE_CODES = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_VECTOR_LEN = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _table(spec: dict[str, str]) -> dict[str, str]:
    return {name: kind for kind, names in spec.items() for name in names.split()}


OUTPUT_TYPES: dict[str, str] = _table({
    "DOUBLE": "timestamp actual_execution_time target_execution_time speed_scaling "
    "target_speed_fraction actual_momentum actual_main_voltage actual_robot_voltage "
    "actual_robot_current standard_analog_input0 standard_analog_input1 standard_analog_output0 "
    "standard_analog_output1 io_current euromap67_24V_voltage euromap67_24V_current "
    "tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature tcp_force_scalar "
    "payload actual_robot_energy_consumed actual_robot_braking_energy_dissipated "
    "joint_position_deviation_ratio collision_detection_ratio",
    "VECTOR6D": "target_q target_qd target_qdd target_current target_moment actual_q actual_qd "
    "actual_current actual_current_window actual_current_as_torque joint_control_output "
    "actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed tcp_offset "
    "actual_TCP_acceleration target_TCP_acceleration joint_temperatures actual_joint_voltage "
    "ft_raw_wrench payload_inertia wrench_calc_from_currents target_base_acceleration "
    "target_base_wrench",
    "VECTOR3D": "actual_tool_accelerometer elbow_position elbow_velocity payload_cog "
    "target_gravity",
    "VECTOR6INT32": "joint_mode",
    "UINT64": "actual_digital_input_bits actual_digital_output_bits "
    "actual_configurable_digital_input_bits actual_configurable_digital_output_bits control_step",
    "UINT32": "runtime_state robot_status_bits safety_status_bits analog_io_types "
    "euromap67_input_bits euromap67_output_bits tool_mode tool_analog_input_types "
    "script_control_line output_bit_registers0_to_31 output_bit_registers32_to_63",
    "INT32": "robot_mode safety_mode safety_status tool_output_voltage encoder0_raw encoder1_raw "
    "time_scale_source",
    "UINT8": "tool_output_mode tool_digital_output0_mode tool_digital_output1_mode",
    "BOOL": " ".join(f"output_bit_register_{i}" for i in range(64, 128)),
})
INPUT_TYPES: dict[str, str] = _table({
    "UINT32": "speed_slider_mask input_bit_registers0_to_31 input_bit_registers32_to_63",
    "DOUBLE": "speed_slider_fraction standard_analog_output_0 standard_analog_output_1",
    "UINT8": "standard_digital_output_mask standard_digital_output "
    "configurable_digital_output_mask configurable_digital_output tool_digital_output_mask "
    "tool_digital_output "
    "standard_analog_output_mask standard_analog_output_type",
    "VECTOR6D": "external_force_torque",
    "BOOL": " ".join(f"input_bit_register_{i}" for i in range(64, 128)),
})
for _i in range(48):
    OUTPUT_TYPES[f"output_int_register_{_i}"] = "INT32"
    OUTPUT_TYPES[f"output_double_register_{_i}"] = "DOUBLE"
    INPUT_TYPES[f"input_int_register_{_i}"] = "INT32"
    INPUT_TYPES[f"input_double_register_{_i}"] = "DOUBLE"
#: Input registers an output recipe may name (the RTDE guide's "input read back").
READ_BACK_TYPES: dict[str, str] = {
    name: kind for name, kind in INPUT_TYPES.items() if name.startswith("input_")}


def frame(letter: str, payload: bytes = b"") -> bytes:
    """One RTDE package: uint16 size (header included), uint8 type letter, payload."""
    return struct.pack(">HB", 3 + len(payload), ord(letter)) + payload


def struct_format(types: Iterable[str]) -> str:
    """Big-endian struct format of a data package body (after the recipe id byte)."""
    return ">" + "".join(TYPE_CODES[t] for t in types)


def encode_values(types: Sequence[str], values: Sequence[Any]) -> bytes:
    flat: list[Any] = []
    for kind, value in zip(types, values, strict=True):
        flat.extend(value if kind in _VECTOR_LEN else [value])
    return struct.pack(struct_format(types), *flat)


def decode_values(types: Sequence[str], body: bytes) -> list[Any]:
    flat = list(struct.unpack(struct_format(types), body))
    out: list[Any] = []
    for kind in types:
        n = _VECTOR_LEN.get(kind, 1)
        out.append(tuple(flat[:n]) if n > 1 else flat[0])
        del flat[:n]
    return out


def split_names(text: bytes) -> list[str]:
    """Names of an O/I request; ur_rtde ends the list with a comma, so drop empty names."""
    return [n for n in text.decode("ascii").split(",") if n]


def default_value(kind: str) -> Any:
    n = _VECTOR_LEN.get(kind)
    if n is None:
        return 0.0 if kind == "DOUBLE" else (False if kind == "BOOL" else 0)
    return (0.0 if kind in ("VECTOR3D", "VECTOR6D") else 0,) * n


#: Status codes under which the robot program reads a pose.
POSE_VALID_STATUS = tuple(int(s) for s in Status if s.pose_valid)
SEQ_MAX = 2**31 - 1
#: The script's VGRIPD_ATTEMPTS and VGRIPD_BUSY_WAIT_S (a unit test keeps them equal).
ATTEMPTS = 3
BUSY_WAIT_S = 0.25
NO_ANSWER = -1  # vgripd_request()'s "no answer within timeout_s"


def pose_trans(p_from: Sequence[float], p_from_to: Sequence[float]) -> tuple[float, ...]:
    """URScript ``pose_trans``: compose two UR poses [x, y, z (m), rx, ry, rz (rotvec, rad)]."""
    T = transform_from_vendor("ur", p_from) @ transform_from_vendor("ur", p_from_to)
    return vendor_from_transform("ur", T)


# ---------------------------------------------------------------------- server (child process)
class _Session:
    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        host, port = writer.get_extra_info("peername")[:2]
        self.peer = f"{host}:{port}"
        self.output_names: list[str] = []
        self.output_types: list[str] = []
        self.frequency_hz = 125.0
        self.input_recipes: dict[int, tuple[list[str], list[str]]] = {}
        self.stream_task: asyncio.Task[None] | None = None
        self.sent = 0


class _Server(BeltProgram):
    """Runs in the mock's own process: the RTDE socket server plus the pipe command handler
    (the conveyor's part of the robot program: ``BeltProgram``)."""

    default_attempts = ATTEMPTS
    default_busy_wait_s = BUSY_WAIT_S

    def __init__(self, host: str, port: int, version: tuple[int, int, int, int],
                 conn: Connection) -> None:
        self.host, self.port, self.version, self.conn = host, port, version, conn
        self.t0 = time.monotonic()
        self.outputs: dict[str, Any] = {}
        self.inputs: dict[str, Any] = {}
        self.input_log: list[tuple[str, Any]] = []
        self.owner: dict[str, _Session] = {}
        self.in_use: set[str] = set()
        self.silent = False
        self.paused = False
        self.sessions: set[_Session] = set()
        self.server: asyncio.Server | None = None
        self.changed = asyncio.Event()
        self.programs: dict[int, asyncio.Task[dict[str, Any]]] = {}
        self.done = asyncio.Event()
        self.tasks: set[asyncio.Task[Any]] = set()

    # ---- RTDE side
    async def listen(self) -> None:
        if self.server is None:
            self.server = await asyncio.start_server(self.serve_client, self.host, self.port)

    async def serve_client(self, reader: asyncio.StreamReader,
                           writer: asyncio.StreamWriter) -> None:
        session = _Session(writer)
        self.sessions.add(session)
        try:
            while True:
                size, letter = struct.unpack(">HB", await reader.readexactly(3))
                payload = await reader.readexactly(size - 3)
                if not self.silent:
                    self.handle(session, chr(letter), payload)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self.end_session(session)

    def end_session(self, session: _Session) -> None:
        if session.stream_task is not None:
            session.stream_task.cancel()
        for name in [n for n, s in self.owner.items() if s is session]:
            del self.owner[name]
        self.sessions.discard(session)
        session.writer.close()

    def handle(self, s: _Session, letter: str, payload: bytes) -> None:
        w = s.writer
        if letter == "V":
            (version,) = struct.unpack(">H", payload)
            w.write(frame("V", bytes([version == PROTOCOL_VERSION])))
        elif letter == "v":
            w.write(frame("v", struct.pack(">4I", *self.version)))
        elif letter == "O":
            (s.frequency_hz,) = struct.unpack(">d", payload[:8])
            names = split_names(payload[8:])
            types = [OUTPUT_TYPES.get(n, READ_BACK_TYPES.get(n, "NOT_FOUND")) for n in names]
            ok = "NOT_FOUND" not in types and bool(names) and s.frequency_hz > 0
            s.output_names, s.output_types = (names, types) if ok else ([], [])
            w.write(frame("O", bytes([1 if ok else 0]) + ",".join(types).encode()))
        elif letter == "I":
            names = split_names(payload)
            types = [self.input_type(s, n) for n in names]
            ok = bool(names) and not {"NOT_FOUND", "IN_USE"} & set(types)
            recipe_id = 0
            if ok:
                recipe_id = len(s.input_recipes) + 1
                s.input_recipes[recipe_id] = (names, types)
                for n in names:
                    self.owner[n] = s
            w.write(frame("I", bytes([recipe_id]) + ",".join(types).encode()))
        elif letter == "S":
            ok = bool(s.output_names)
            if ok and s.stream_task is None:
                s.stream_task = self.spawn(self.stream(s))
            w.write(frame("S", bytes([ok])))
        elif letter == "P":
            if s.stream_task is not None:
                s.stream_task.cancel()
                s.stream_task = None
            w.write(frame("P", b"\x01"))
        elif letter == "U":
            recipe = s.input_recipes.get(payload[0])
            if recipe is not None:
                names, types = recipe
                for name, value in zip(names, decode_values(types, payload[1:]), strict=True):
                    self.inputs[name] = value
                    self.input_log.append((name, value))
                self.notify()
        # M (text message) and unknown letters need no reply.

    def input_type(self, s: _Session, name: str) -> str:
        kind = INPUT_TYPES.get(name, "NOT_FOUND")
        owner = self.owner.get(name)
        if kind != "NOT_FOUND" and (name in self.in_use or (owner is not None and owner is not s)):
            return "IN_USE"
        return kind

    def output_value(self, name: str, kind: str) -> Any:
        if name == "timestamp":
            return time.monotonic() - self.t0
        if name in READ_BACK_TYPES:
            return self.inputs.get(name, default_value(kind))
        return self.outputs.get(name, default_value(kind))

    async def stream(self, s: _Session) -> None:
        period = 1.0 / s.frequency_hz
        fmt_types = s.output_types
        next_t = time.monotonic()
        while True:
            # Like a loaded controller, skip packages rather than queue them for a slow reader.
            backlog = s.writer.transport.get_write_buffer_size()
            if not (self.paused or self.silent) and backlog < 1 << 20:
                values = [self.output_value(n, k) for n, k in zip(s.output_names, fmt_types,
                                                                  strict=True)]
                s.writer.write(frame("U", b"\x01" + encode_values(fmt_types, values)))
                s.sent += 1
            next_t += period
            now = time.monotonic()
            if next_t < now - period:
                next_t = now
            await asyncio.sleep(max(0.0, next_t - now))

    def notify(self) -> None:
        self.changed.set()
        self.changed = asyncio.Event()

    def spawn(self, coro: Any) -> asyncio.Task[Any]:
        task = asyncio.get_running_loop().create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    # ---- simulated robot program (twin of robots/urscript/vgripd.script)
    async def wait_input(self, name: str, value: int, deadline: float) -> bool:
        while self.inputs.get(name) != value:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.changed.wait(), remaining)
        return True

    def trigger(self, command: int, regs: URRegisterMap, recipe: int = 0) -> int:
        """A new request as the script's ``vgripd_request`` makes it; returns its sequence."""
        previous = max(int(self.outputs.get(f"output_int_register_{regs.seq}", 0)),
                       int(self.inputs.get(f"input_int_register_{regs.ack}", 0)))
        seq = previous + 1 if previous < SEQ_MAX else 1
        # Command, recipe, latch and seq change in one data package; the seq is the trigger.
        self.write_latch(command, regs)
        self.outputs[f"output_int_register_{regs.command}"] = command
        self.outputs[f"output_int_register_{regs.recipe}"] = recipe
        self.outputs[f"output_int_register_{regs.seq}"] = seq
        return seq

    async def request(self, seq: int, regs: URRegisterMap, timeout_s: float,
                      result: dict[str, Any]) -> int:
        """``vgripd_request`` after its trigger: the status, or ``NO_ANSWER`` (``error`` says
        which wait ran out). Fills ``result`` with what the robot read."""
        def in_int(n: int) -> int:
            return int(self.inputs.get(f"input_int_register_{n}", 0))

        def in_page() -> list[float]:
            return [float(self.inputs.get(f"input_double_register_{n}", 0.0)) for n in regs.page]

        deadline = time.monotonic() + timeout_s
        ack_name = f"input_int_register_{regs.ack}"
        if not await self.wait_input(ack_name, seq, deadline):
            result["error"] = f"timeout waiting for {ack_name} == {seq}"
            return NO_ANSWER
        result["ack_log_index"] = len(self.input_log) - 1
        status = in_int(regs.status)
        result.update(status=status, job_id=in_int(regs.job_id), captured=in_int(regs.captured))
        # The pick list word, decoded as the script's vgripd_pick_count/vgripd_pick_index do.
        pick = float(self.inputs.get(f"input_double_register_{regs.pick}", 0.0))
        count = math.floor(pick / regs.PICK_BASE + 1e-9)
        result.update(pick=pick, count=count, index=round(pick - regs.PICK_BASE * count))
        if regs.conveyor and not await self.read_belt(seq, regs, deadline, result):
            return NO_ANSWER
        if status not in POSE_VALID_STATUS:
            return status
        translation = in_page()
        self.outputs[f"output_int_register_{regs.page_request}"] = seq
        page_ack_name = f"input_int_register_{regs.page_ack}"
        if not await self.wait_input(page_ack_name, seq, deadline):
            result["error"] = f"timeout waiting for {page_ack_name} == {seq}"
            return NO_ANSWER
        result["offset"] = (*translation, *in_page())
        return status

    async def program(self, command: int, seq: int, regs: URRegisterMap, timeout_s: float,
                      taught_pose: Sequence[float] | None, t_start: float, attempts: int,
                      busy_wait_s: float, recipe: int = 0) -> dict[str, Any]:
        """``vgripd_locate``: ask until answered (``attempts`` requests without an answer, then
        give up: the script's popup and halt), waiting ``busy_wait_s`` after each BUSY (at most
        ``ceil(timeout_s / busy_wait_s)`` times, then BUSY is the answer)."""
        result: dict[str, Any] = {"seq": seq, "error": None, "offset": None, "target": None,
                                  "requests": [seq], "unanswered": 0, "busy": 0}
        busy_max = math.ceil(timeout_s / busy_wait_s)
        while True:
            result.update(error=None, offset=None, status=None)
            status = await self.request(seq, regs, timeout_s, result)
            if status == NO_ANSWER:
                result["unanswered"] += 1
                if result["unanswered"] >= attempts:
                    result["error"] = (f"no answer to {attempts} requests (popup, halt): "
                                       f"{result['error']}")
                    result["elapsed_s"] = time.monotonic() - t_start
                    return result
            elif status == Status.BUSY and result["busy"] < busy_max:
                result["busy"] += 1
                await asyncio.sleep(busy_wait_s)
            else:
                break
            seq = self.trigger(command, regs, recipe)
            result["seq"] = seq
            result["requests"].append(seq)
        result["elapsed_s"] = time.monotonic() - t_start
        if taught_pose is not None and result["offset"] is not None:
            # vgripd's offset is T_base_obj @ inv(T_base_obj_ref), in the base frame: it is
            # applied on the left of the taught grip pose.
            result["target"] = pose_trans(result["offset"], taught_pose)
        return result

    def start_program(self, command: int, timeout_s: float, upper: bool,
                      taught_pose: Sequence[float] | None, attempts: int = ATTEMPTS,
                      busy_wait_s: float = BUSY_WAIT_S, recipe: int = 0,
                      conveyor: bool = False) -> int:
        regs = URRegisterMap(upper, conveyor)
        seq = self.trigger(command, regs, recipe)
        self.programs[seq] = self.spawn(self.program(command, seq, regs, timeout_s, taught_pose,
                                                     time.monotonic(), attempts, busy_wait_s,
                                                     recipe))
        return seq

    # ---- pipe commands from the handle
    async def command(self, req: int, method: str, args: tuple[Any, ...]) -> None:
        try:
            result = await getattr(self, "cmd_" + method)(*args)
            reply: tuple[Any, ...] = (req, True, result)
        except Exception as err:  # report every failure to the handle, keep serving
            reply = (req, False, f"{type(err).__name__}: {err}")
        self.conn.send(reply)

    def on_pipe(self) -> None:
        try:
            while self.conn.poll():
                req, method, args = self.conn.recv()
                self.spawn(self.command(req, method, args))
        except (EOFError, OSError):  # the handle's process is gone: stop
            self.done.set()

    async def cmd_set_outputs(self, values: dict[str, Any]) -> None:
        unknown = sorted(set(values) - set(OUTPUT_TYPES))
        if unknown:
            raise KeyError(f"unknown RTDE output name(s) {unknown}")
        self.outputs.update(values)

    async def cmd_set_inputs(self, values: dict[str, Any]) -> None:
        unknown = sorted(set(values) - set(INPUT_TYPES))
        if unknown:
            raise KeyError(f"unknown RTDE input name(s) {unknown}")
        self.inputs.update(values)
        self.notify()

    async def cmd_wait_input(self, name: str, value: Any, timeout_s: float) -> bool:
        return await self.wait_input(name, value, time.monotonic() + timeout_s)

    async def cmd_inputs(self, names: Sequence[str]) -> dict[str, Any]:
        return {n: self.inputs.get(n, default_value(INPUT_TYPES.get(n, "INT32"))) for n in names}

    async def cmd_input_log(self, start: int) -> list[tuple[str, Any]]:
        return self.input_log[start:]

    async def cmd_set_in_use(self, names: Sequence[str]) -> None:
        self.in_use = set(names)

    async def cmd_set_silent(self, on: bool) -> None:
        self.silent = on

    async def cmd_pause_stream(self, on: bool) -> None:
        self.paused = on

    async def cmd_drop(self, refuse: bool) -> None:
        if refuse and self.server is not None:
            self.server.close()
            await self.server.wait_closed()
            self.server = None
        for s in list(self.sessions):
            self.end_session(s)

    async def cmd_listen(self) -> None:
        await self.listen()

    async def cmd_sessions(self) -> list[dict[str, Any]]:
        return [{"peer": s.peer, "outputs": s.output_names, "frequency_hz": s.frequency_hz,
                 "input_recipes": len(s.input_recipes), "streaming": s.stream_task is not None,
                 "sent": s.sent} for s in self.sessions]

    async def cmd_start_program(self, command: int, timeout_s: float, upper: bool,
                                taught_pose: Sequence[float] | None, attempts: int,
                                busy_wait_s: float, recipe: int = 0,
                                conveyor: bool = False) -> int:
        return self.start_program(command, timeout_s, upper, taught_pose, attempts, busy_wait_s,
                                  recipe, conveyor)

    async def cmd_capture_view(self, view: int, tcp_pose: Sequence[float], last: bool,
                               timeout_s: float, upper: bool) -> dict[str, Any]:
        """One view of a several-view job, as a robot program does it: the robot stands at
        ``tcp_pose`` (m, rotation vector), requests CAPTURE of ``view``, and waits until the
        view is taken (``captured`` = seq: it may move on; not for its ``last`` view) or the
        request is answered (``ack``: the job's result, or the status that ended it)."""
        regs = URRegisterMap(upper)
        self.outputs["actual_TCP_pose"] = tuple(float(v) for v in tcp_pose)
        seq = self.trigger(capture_word(view), regs)
        result: dict[str, Any] = {"seq": seq, "error": None, "offset": None, "status": None}
        deadline = time.monotonic() + timeout_s
        ack, captured = (f"input_int_register_{n}" for n in (regs.ack, regs.captured))
        while self.inputs.get(ack) != seq and (last or self.inputs.get(captured) != seq):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                result["error"] = f"view {view} (request {seq}) neither taken nor answered"
                return result
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.changed.wait(), remaining)
        if self.inputs.get(ack) == seq:
            await self.request(seq, regs, timeout_s, result)
        else:
            result["captured"] = seq
        return result

    async def cmd_program_result(self, seq: int) -> dict[str, Any]:
        task = self.programs.pop(seq)
        return await task

    async def cmd_stop(self) -> None:
        self.done.set()

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            await self.listen()
        except OSError as err:
            self.conn.send((0, False, f"cannot listen on {self.host}:{self.port}: {err}"))
            return
        self.conn.send((0, True, None))
        loop.add_reader(self.conn.fileno(), self.on_pipe)
        await self.done.wait()
        loop.remove_reader(self.conn.fileno())
        await self.cmd_drop(refuse=True)
        for task in list(self.tasks):
            task.cancel()


def _serve(host: str, port: int, version: tuple[int, int, int, int], conn: Connection) -> None:
    asyncio.run(_Server(host, port, version, conn).run())


# ------------------------------------------------------------------------ in-process handle
class MockControllerError(VgripError):
    """The mock controller could not start or rejected a command."""


class URController:
    """Handle of a mock UR controller process listening on ``host:port`` (RTDE).

    Use as a context manager. Every method is a quick request over a pipe, except
    ``program_result``, which waits for the simulated robot program to finish.

    Parameters
    ----------
    host : str
        Loopback address such as ``"127.0.0.7"`` (ur_rtde has no port argument: tests differ by it).
    version : tuple of 4 int
        Controller version reported in the ``v`` reply (it changes ur_rtde's default recipe).
    timeout_s : float
        A call's wait for its reply, the process's start's too: a bound, not a target.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = RTDE_PORT,
                 version: tuple[int, int, int, int] = DEFAULT_CONTROLLER_VERSION,
                 timeout_s: float = 30.0) -> None:
        self.host, self.port, self.version, self.timeout_s = host, port, version, timeout_s
        self._ids = itertools.count(1)
        self._conn: Connection | None = None
        self._process: Any = None

    def __enter__(self) -> URController:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve, name=f"mock-ur-{self.host}", daemon=True,
                                    args=(self.host, self.port, self.version, child))
        self._process.start()
        child.close()
        try:
            self._reply(0, self.timeout_s)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        if self._process is None:
            return
        if self._conn is not None:
            with contextlib.suppress(OSError, BrokenPipeError):
                self._conn.send((next(self._ids), "stop", ()))
        self._process.join(5.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        if self._conn is not None:
            self._conn.close()
        self._process = self._conn = None

    def _reply(self, req: int, timeout_s: float) -> Any:
        assert self._conn is not None, "mock controller not started"
        while True:
            if not self._conn.poll(timeout_s):
                raise MockControllerError(
                    f"mock controller {self.host}:{self.port} gave no reply within {timeout_s} s")
            try:
                rid, ok, value = self._conn.recv()
            except EOFError:
                raise MockControllerError(
                    f"mock controller {self.host}:{self.port} process ended") from None
            if rid != req:
                continue  # reply to an earlier call that timed out
            if not ok:
                raise MockControllerError(f"mock controller {self.host}:{self.port}: {value}")
            return value

    def _call(self, method: str, *args: Any, timeout_s: float | None = None) -> Any:
        assert self._conn is not None, "mock controller not started"
        req = next(self._ids)
        self._conn.send((req, method, args))
        return self._reply(req, self.timeout_s if timeout_s is None else timeout_s)

    # ---- robot state
    def set_outputs(self, **values: Any) -> None:
        """Set streamed output values by RTDE name (e.g. ``output_int_register_12=5``)."""
        self._call("set_outputs", values)

    def set_tcp_pose(self, pose: Sequence[float]) -> None:
        """``actual_TCP_pose`` = [x, y, z (m), rx, ry, rz (rotation vector, rad)] in base."""
        values = tuple(float(v) for v in pose)
        if len(values) != 6 or not np.isfinite(values).all():
            raise ValueError(f"TCP pose needs 6 finite numbers, got {list(pose)}")
        self._call("set_outputs", {"actual_TCP_pose": values})

    def set_inputs(self, **values: Any) -> None:
        """Preset input registers by RTDE name, as an earlier client (a vgripd that ran
        before) left them; the controller keeps them across connections."""
        self._call("set_inputs", values)

    def inputs(self, *names: str) -> dict[str, Any]:
        """Current values of input names as the client last wrote them (type default if never)."""
        result: dict[str, Any] = self._call("inputs", names)
        return result

    def wait_input(self, name: str, value: Any, timeout_s: float = 5.0) -> bool:
        """Wait until a client has written ``value`` to input ``name``; False after timeout_s."""
        ok: bool = self._call("wait_input", name, value, timeout_s, timeout_s=timeout_s + 5.0)
        return ok

    def input_log(self, start: int = 0) -> list[tuple[str, Any]]:
        """Every input value written by clients, in arrival order, from index ``start``."""
        result: list[tuple[str, Any]] = self._call("input_log", start)
        return result

    def sessions(self) -> list[dict[str, Any]]:
        """Open client connections: peer, output recipe, frequency, input recipes, sent count."""
        result: list[dict[str, Any]] = self._call("sessions")
        return result

    # ---- simulated robot program
    def start_program(self, command: int = 1, *, timeout_s: float = 10.0, upper: bool = False,
                      taught_pose: Sequence[float] | None = None, attempts: int = ATTEMPTS,
                      busy_wait_s: float = BUSY_WAIT_S, recipe: int = 0,
                      conveyor: bool = False) -> int:
        """Run ``vgripd_locate(command, timeout_s)`` the way robots/urscript/vgripd.script does
        (with ``VGRIPD_RECIPE = recipe``; ``conveyor``: ``VGRIPD_CONVEYOR = True``, the latch
        written with each request and the belt block read with each answer, ``belt``);
        returns the sequence of its first request (the key for ``program_result``)."""
        seq: int = self._call("start_program", command, timeout_s, upper,
                              None if taught_pose is None else tuple(taught_pose), attempts,
                              busy_wait_s, recipe, conveyor)
        return seq

    # ---- the conveyor (vgripd/sim/ur_belt.py)
    def set_encoder(self, count: int) -> None:
        """The belt's encoder count now (``encoder_get_tick_count(.., opt="raw")``; 32 bits)."""
        self._call("set_encoder", count)

    def set_predict_count(self, count: int) -> None:
        """The count N of the next PREDICT (the script's ``vgripd_predict_count``)."""
        self._call("set_predict_count", count)

    def belt_track(self, taught_pose: Sequence[float], direction: Sequence[float],
                   ticks_per_m: float, *, bits: int = 32, timeout_s: float = 15.0,
                   upper: bool = False, recipe: int = 0) -> dict[str, Any]:
        """``vgripd_belt_track``: as ``program_result`` plus ``belt``, ``start_count`` and
        ``start_grip`` (the grip where tracking starts; ``ur_belt.tracked`` moves it on)."""
        result: dict[str, Any] = self._call(
            "belt_track", tuple(taught_pose), tuple(direction), ticks_per_m, bits, timeout_s,
            upper, recipe, timeout_s=3 * timeout_s + 5.0)
        return result

    def belt_intercept(self, taught_pose: Sequence[float], lead: int, *,
                       timeout_s: float = 15.0, upper: bool = False,
                       recipe: int = 0) -> dict[str, Any]:
        """``vgripd_belt_intercept``: NEXT (``next``), then PREDICT for the encoder + ``lead``
        ticks (``predict_count``); the PREDICT's answer as ``program_result`` has it."""
        result: dict[str, Any] = self._call(
            "belt_intercept", tuple(taught_pose), lead, timeout_s, upper, recipe,
            timeout_s=6 * timeout_s + 5.0)
        return result

    def capture_view(self, view: int, tcp_pose: Sequence[float], *, last: bool = False,
                     timeout_s: float = 15.0, upper: bool = False) -> dict[str, Any]:
        """A robot program's CAPTURE of ``view`` at ``tcp_pose`` (``cmd_capture_view``):
        ``captured`` = seq when the view was taken without an answer, else ``status``,
        ``job_id``, ``offset`` as ``program_result`` has them. ``last``: the job's last view,
        whose answer the robot waits for."""
        result: dict[str, Any] = self._call("capture_view", view, tuple(tcp_pose), last,
                                            timeout_s, upper, timeout_s=timeout_s + 5.0)
        return result

    def program_result(self, seq: int, timeout_s: float = 15.0) -> dict[str, Any]:
        """Wait for the program started as ``seq``: ``status``, ``job_id``, ``captured``,
        ``offset`` (UR pose read from the registers), ``target`` (``pose_trans(offset,
        taught)``), ``seq`` (the request that was answered), ``requests`` (every sequence
        sent), ``unanswered`` / ``busy`` (requests that timed out / were answered BUSY),
        ``ack_log_index`` (index in ``input_log`` of the last ack write), ``pick`` / ``count`` /
        ``index`` (the pick list register and its decoding), ``elapsed_s``
        (first trigger to the last value read, on the mock's clock) or ``error`` (given up)."""
        result: dict[str, Any] = self._call("program_result", seq, timeout_s=timeout_s)
        return result

    # ---- faults
    def set_silent(self, on: bool = True) -> None:
        """Accept connections but answer nothing and stream nothing."""
        self._call("set_silent", on)

    def set_in_use(self, *names: str) -> None:
        """Input names owned by "a fieldbus adapter": I requests get ``IN_USE`` for them."""
        self._call("set_in_use", names)

    def pause_stream(self, on: bool = True) -> None:
        """Stop (or resume) sending U packages on every connection."""
        self._call("pause_stream", on)

    def drop(self, refuse: bool = False) -> None:
        """Close every client connection; with ``refuse`` also stop listening (until ``listen``)."""
        self._call("drop", refuse)

    def listen(self) -> None:
        self._call("listen")
