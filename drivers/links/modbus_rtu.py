"""Modbus RTU server link on a serial line: the same register map and handshake as the TCP
server (``RegisterServerLink``), over pymodbus' serial server and pyserial.

An RTU slave answers only its own unit id; frames for other units are left unanswered. FC23 is
all or nothing as on TCP (``AllOrNothingReadWrite``, registered by the shared ``open``).
"""

from __future__ import annotations

from typing import Literal

import serial
from pydantic import Field
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer
from pymodbus.server.base import ModbusBaseServer

from drivers.links.modbus_server import RegisterContext, RegisterServerLink
from vgripd.service.protocol import RegisterOptions


class RtuOptions(RegisterOptions):
    """``port``: the serial device (``/dev/ttyUSB0``). ``parity``: N(one), E(ven), O(dd).
    ``unit_id``: this slave's address on the line (1-247)."""

    port: str
    baudrate: int = Field(19200, ge=1200, le=921600)
    parity: Literal["N", "E", "O"] = "E"
    stopbits: Literal[1, 2] = 1
    unit_id: int = Field(1, ge=1, le=247)


class ModbusRtuLink(RegisterServerLink):
    Options = RtuOptions
    options: RtuOptions

    def _make_server(self, context: RegisterContext) -> ModbusBaseServer:
        o = self.options
        return ModbusSerialServer(
            context, framer=FramerType.RTU, port=o.port, baudrate=o.baudrate, parity=o.parity,
            stopbits=o.stopbits, bytesize=8, ignore_missing_devices=True,
        )

    def _describe(self) -> str:
        o = self.options
        return f"{o.port} ({o.baudrate} 8{o.parity}{o.stopbits}, unit {o.unit_id})"

    def _unit_id(self) -> int | None:
        return self.options.unit_id

    def _start_error(self) -> str:
        # pymodbus only logs why the port did not open; open it once more to name the reason.
        reason = "unknown reason"
        try:
            serial.Serial(self.options.port).close()
        except (serial.SerialException, OSError) as err:
            reason = str(err)
        return f"cannot open serial port {self._describe()}: {reason}"

    def peers(self) -> int:
        return 0  # a serial line has no connection to count
