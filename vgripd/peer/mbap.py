"""Modbus/TCP framing (the MBAP header), bytes in, frames out, with no I/O.

A frame is a seven-byte header (transaction id, protocol id 0, length = unit id + PDU in bytes,
unit id) then the PDU. ``MbapFramer`` takes what the socket delivered, in any pieces (a frame
split anywhere, several frames in one segment), and hands back complete frames in order. A
header no Modbus client sends (protocol id not 0, length outside 2..254) raises
``MalformedFrame``: after it nothing in the stream can be trusted, so the shell closes the
connection.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

HEADER = 7  # transaction id, protocol id, length (2 bytes each), unit id
MAX_LENGTH = 254  # unit id + the largest PDU (253 bytes)


class MalformedFrame(Exception):
    """Bytes that are not a Modbus request at all: the connection is closed."""


@dataclass(frozen=True)
class MbapFrame:
    """One request: its transaction id (echoed in the answer), unit id and PDU."""

    tid: int
    unit: int
    pdu: bytes


def encode(tid: int, unit: int, pdu: bytes) -> bytes:
    """The frame answering transaction ``tid`` of ``unit`` with ``pdu``."""
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


class MbapFramer:
    """Received bytes in (``feed``), complete frames out (``next_frame``), in order."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._pos = 0  # start of the first frame not yet handed out

    def feed(self, data: bytes) -> None:
        if self._pos:
            del self._buffer[:self._pos]
            self._pos = 0
        self._buffer += data

    def _end(self) -> int | None:
        """End of the complete frame at the read position, None while it is incomplete;
        ``MalformedFrame`` as soon as its header is wrong."""
        if len(self._buffer) - self._pos < 6:
            return None
        _, protocol, length = struct.unpack_from(">HHH", self._buffer, self._pos)
        if protocol != 0:
            raise MalformedFrame(f"MBAP protocol id {protocol} (Modbus is 0)")
        if not 2 <= length <= MAX_LENGTH:
            raise MalformedFrame(f"MBAP length {length} (2..{MAX_LENGTH})")
        end = self._pos + 6 + length
        return end if end <= len(self._buffer) else None

    def has_frame(self) -> bool:
        """A complete frame is waiting (``MalformedFrame`` if the next header is wrong)."""
        return self._end() is not None

    def next_frame(self) -> MbapFrame | None:
        """The next complete frame, None until more bytes arrive."""
        end = self._end()
        if end is None:
            return None
        tid = int.from_bytes(self._buffer[self._pos:self._pos + 2], "big")
        frame = MbapFrame(tid, self._buffer[self._pos + 6],
                          bytes(self._buffer[self._pos + HEADER:end]))
        self._pos = end
        return frame

    @property
    def buffered(self) -> int:
        """Bytes received and not yet handed out as a frame."""
        return len(self._buffer) - self._pos
