"""The mock UR controller's RTDE protocol, checked byte by byte with a raw socket client (the
expected bytes are the ones RTDE.md recorded from the real ur_rtde 1.6.5 and UR's own clients)."""

from __future__ import annotations

import re
import socket
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import lo
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.sim.ur_controller import MockControllerError, URController, pose_trans

pytestmark = pytest.mark.timeout(30)
HOST = lo("127.0.5.30")


@pytest.fixture(scope="module")
def robot() -> Iterator[URController]:
    with URController(HOST) as controller:
        yield controller


@pytest.fixture
def client(robot: URController) -> Iterator[socket.socket]:
    robot.set_in_use()
    with socket.create_connection((HOST, 30004), timeout=5) as sock:
        yield sock


def send(sock: socket.socket, letter: str, payload: bytes = b"") -> None:
    sock.sendall(struct.pack(">HB", 3 + len(payload), ord(letter)) + payload)


def recv(sock: socket.socket) -> tuple[str, bytes]:
    def exactly(n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            assert chunk, "connection closed"
            buf += chunk
        return buf

    size, letter = struct.unpack(">HB", exactly(3))
    return chr(letter), exactly(size - 3)


def test_version_requests(client: socket.socket) -> None:
    client.sendall(bytes.fromhex("00055600 02"))
    assert client.recv(16) == bytes.fromhex("00045601")
    send(client, "v")
    letter, payload = recv(client)
    assert letter == "v"
    assert struct.unpack(">4I", payload) == (5, 15, 0, 0)
    send(client, "V", struct.pack(">H", 3))  # only version 2 is spoken
    assert recv(client) == ("V", b"\x00")


def test_output_recipe_and_stream(robot: URController, client: socket.socket) -> None:
    robot.set_outputs(output_int_register_12=-7, actual_TCP_pose=(0.1, 0.2, 0.3, 1.0, 2.0, 3.0))
    send(client, "V", struct.pack(">H", 2))
    recv(client)
    names = b"timestamp,actual_TCP_pose,output_int_register_12,joint_mode,"  # trailing comma
    send(client, "O", struct.pack(">d", 500.0) + names)
    assert recv(client) == ("O", b"\x01DOUBLE,VECTOR6D,INT32,VECTOR6INT32")
    send(client, "S")
    assert recv(client) == ("S", b"\x01")
    stamps = []
    for _ in range(5):
        letter, payload = recv(client)
        assert letter == "U"
        fields = struct.unpack(">B d 6d i 6i", payload)
        assert fields[0] == 1
        assert fields[2:8] == (0.1, 0.2, 0.3, 1.0, 2.0, 3.0)
        assert fields[8] == -7
        stamps.append(fields[1])
    assert stamps == sorted(stamps)
    assert len(set(stamps)) == 5
    session = robot.sessions()[0]
    assert session["frequency_hz"] == 500.0
    assert session["streaming"]
    send(client, "P")
    while (reply := recv(client))[0] == "U":
        pass
    assert reply == ("P", b"\x01")
    assert not robot.sessions()[0]["streaming"]


def test_unknown_output_is_not_found_and_start_refused(client: socket.socket) -> None:
    send(client, "O", struct.pack(">d", 125.0) + b"timestamp,no_such_thing,")
    assert recv(client) == ("O", b"\x00DOUBLE,NOT_FOUND")
    send(client, "S")
    assert recv(client) == ("S", b"\x00")


def test_input_recipes_numbered_and_applied(robot: URController, client: socket.socket) -> None:
    start = len(robot.input_log())
    send(client, "I", b"input_int_register_23,input_int_register_19,")
    assert recv(client) == ("I", b"\x01INT32,INT32")
    send(client, "I", b"input_int_register_23,input_double_register_18,")
    assert recv(client) == ("I", b"\x02INT32,DOUBLE")
    send(client, "I", b"input_int_register_99,")
    assert recv(client) == ("I", b"\x00NOT_FOUND")
    send(client, "M", b"\x02hi\x01x\x03")  # text messages need no reply
    # The bytes ur_rtde sends for setInputDoubleRegister(18, 1.5) (its recipe 12 here is our 2).
    send(client, "U", bytes.fromhex("02 00000032 3ff8000000000000"))
    send(client, "U", b"\x01" + struct.pack(">ii", 49, -42))
    send(client, "V", struct.pack(">H", 2))  # a reply proves the U packages were processed
    recv(client)
    assert robot.inputs("input_double_register_18", "input_int_register_19") == {
        "input_double_register_18": 1.5, "input_int_register_19": -42}
    assert robot.input_log(start) == [
        ("input_int_register_23", 50), ("input_double_register_18", 1.5),
        ("input_int_register_23", 49), ("input_int_register_19", -42)]


def test_in_use_by_fieldbus_and_by_another_client(robot: URController, client: socket.socket) -> None:
    robot.set_in_use("input_int_register_20")
    send(client, "I", b"input_int_register_19,input_int_register_20,")
    assert recv(client) == ("I", b"\x00INT32,IN_USE")
    send(client, "I", b"input_int_register_19,")
    assert recv(client) == ("I", b"\x01INT32")  # ids count accepted recipes only
    with socket.create_connection((HOST, 30004), timeout=5) as other:
        send(other, "I", b"input_int_register_19,")
        assert recv(other) == ("I", b"\x00IN_USE")
    client.close()  # the owner leaves: the register is free again
    with socket.create_connection((HOST, 30004), timeout=5) as other:
        for _ in range(100):
            send(other, "I", b"input_int_register_19,")
            if recv(other)[1] != b"\x00IN_USE":
                break
        else:
            pytest.fail("register never released")


def test_program_times_out_naming_the_register(robot: URController) -> None:
    seq = robot.start_program(1, timeout_s=0.2, upper=True, attempts=1)
    result = robot.program_result(seq)
    assert result["error"] == ("no answer to 1 requests (popup, halt): "
                               f"timeout waiting for input_int_register_42 == {seq}")
    assert (result["requests"], result["status"]) == ([seq], None)


def test_program_asks_again_with_a_new_sequence_each_time(robot: URController) -> None:
    seq = robot.start_program(1, timeout_s=0.1, attempts=3)
    result = robot.program_result(seq)
    assert result["requests"] == [seq, seq + 1, seq + 2]
    assert result["unanswered"] == 3
    assert result["error"].endswith(f"input_int_register_18 == {seq + 2}")


def test_input_registers_read_back_in_an_output_recipe(robot: URController,
                                                       client: socket.socket) -> None:
    """A real controller offers input registers as outputs ("input read back"): the link reads
    vgripd's own acknowledge register that way at the first connect."""
    robot.set_inputs(input_int_register_18=77)
    robot.set_outputs(output_int_register_12=78)
    send(client, "O", struct.pack(">d", 125.0) + b"output_int_register_12,input_int_register_18,")
    assert recv(client) == ("O", b"\x01INT32,INT32")
    send(client, "S")
    assert recv(client) == ("S", b"\x01")
    letter, payload = recv(client)
    assert (letter, struct.unpack(">Bii", payload)) == ("U", (1, 78, 77))
    send(client, "P")
    while (reply := recv(client))[0] == "U":
        pass
    assert reply == ("P", b"\x01")
    robot.set_inputs(input_int_register_18=0)
    robot.set_outputs(output_int_register_12=0)


def test_handle_rejects_unknown_output(robot: URController) -> None:
    with pytest.raises(MockControllerError, match="no_such_output"):
        robot.set_outputs(no_such_output=1)


def test_address_in_use_is_reported(robot: URController) -> None:
    with pytest.raises(MockControllerError, match=f"cannot listen on {HOST}:30004"), URController(HOST):
        pass


def test_pose_trans_matches_scipy() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        a, b = rng.normal(size=6), rng.normal(size=6)
        got = pose_trans(a, b)
        Ra, Rb = Rotation.from_rotvec(a[3:]), Rotation.from_rotvec(b[3:])
        np.testing.assert_allclose(got[:3], a[:3] + Ra.apply(b[:3]), atol=1e-12)
        R = (Ra * Rb).as_matrix()
        np.testing.assert_allclose(Rotation.from_rotvec(got[3:]).as_matrix(), R, atol=1e-12)


def _script_code() -> str:
    text = (Path(__file__).resolve().parents[3] / "robots" / "urscript" / "vgripd.script").read_text()
    return "\n".join(line.split("#", 1)[0] for line in text.splitlines())


def test_script_and_twin_retry_alike() -> None:
    """The script's retry constants and codes are the twin's (vgripd/sim/ur_controller.py)."""
    from vgripd.sim import ur_controller as twin
    from vgripd.types import Status

    code = _script_code()
    assert f"global VGRIPD_ATTEMPTS = {twin.ATTEMPTS}" in code
    assert f"global VGRIPD_BUSY_WAIT_S = {twin.BUSY_WAIT_S}" in code
    assert f"vgripd_status == {int(Status.BUSY)} and busy < busy_max" in code
    assert "busy_max = ceil(timeout_s / VGRIPD_BUSY_WAIT_S)" in code
    assert f"return {twin.NO_ANSWER}" in code
    assert f"vgripd_status == {twin.NO_ANSWER}" in code
    assert "popup(" in code
    assert "halt" in code


def test_urscript_uses_the_register_map() -> None:
    """robots/urscript/vgripd.script and the simulated program must use the same registers."""
    text = (Path(__file__).resolve().parents[3] / "robots" / "urscript" / "vgripd.script").read_text()
    code = "\n".join(line.split("#", 1)[0] for line in text.splitlines())

    def used(function: str) -> set[int]:
        return {int(n) for n in re.findall(rf"{function}\((\d+) \+ o", code)}

    regs = URRegisterMap()
    assert used("write_output_integer_register") == {regs.seq, regs.command, regs.page_request,
                                                     regs.recipe, regs.latch}
    assert used("read_output_integer_register") == {regs.seq}
    assert used("vgripd_wait_int") == {regs.ack, regs.page_ack}
    # vgripd_capture (several views per job) also watches ``captured``.
    assert used("read_input_integer_register") == {regs.ack, regs.status, regs.captured}
    assert used("read_input_float_register") == {*regs.page, regs.warnings}
    assert URRegisterMap(upper=True).ack - regs.ack == 24
    assert "global VGRIPD_OFFSET = 0" in code
