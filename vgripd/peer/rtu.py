"""Modbus RTU framing, bytes and their arrival times in, frames out, with no I/O.

A frame is unit id, PDU, CRC-16. Its length follows from the function code (a byte count where
the request has one); a function code without a known layout is a frame once the whole buffer
carries a valid CRC. A CRC error, or bytes that start no frame, cost only themselves: the
framer looks for the next valid frame one byte further on. Silence ends a frame (Modbus over
serial line, 2.5.1.1): when at least 3.5 character times (1.75 ms above 19200 baud) pass with
nothing on the line, a partial frame left in the buffer is dropped, so one stray byte never
spoils the next request. The silence is judged from when data arrives (the time is passed in)
minus the time the new bytes took on the wire; a USB adapter that hands over a frame in pieces
therefore does not lose it, and a piece that completes a valid frame is always kept.
"""

from __future__ import annotations

from collections.abc import Iterator

MAX_ADU = 256  # the longest RTU frame: unit id + 253-byte PDU + CRC
# Frame lengths by function code (unit id and CRC included), from the Modbus application
# protocol. An int is a fixed length; (at, fixed) a byte count at index ``at``: fixed + count.
# Requests are what this slave answers; responses are other slaves' answers on a shared line
# (and an adapter's echo of our own), recognised so that they are skipped whole, never answered.
Layout = int | tuple[int, int]
_REQUEST: dict[int, Layout] = {
    1: 8, 2: 8, 3: 8, 4: 8, 5: 8, 6: 8, 7: 4, 8: 8, 11: 4, 12: 4, 17: 4, 22: 10, 24: 6, 43: 7,
    15: (6, 9), 16: (6, 9), 20: (2, 5), 21: (2, 5), 23: (10, 13),
}
_RESPONSE: dict[int, Layout] = {
    1: (2, 5), 2: (2, 5), 3: (2, 5), 4: (2, 5), 23: (2, 5), 5: 8, 6: 8, 15: 8, 16: 8, 22: 10,
}
_EXCEPTION_LENGTH = 5  # unit, function | 0x80, exception code, CRC


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """Modbus CRC-16 (polynomial 0xA001 reflected, start 0xFFFF); sent low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return crc


def with_crc(body: bytes) -> bytes:
    """``body`` (unit id + PDU) with its CRC appended."""
    return body + crc16(body).to_bytes(2, "little")


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and crc16(frame[:-2]) == int.from_bytes(frame[-2:], "little")


def char_time_s(baudrate: int, parity: str, stopbits: int) -> float:
    """Time one character takes on the line: start bit, 8 data bits, parity bit, stop bits."""
    return (1 + 8 + (parity != "N") + stopbits) / baudrate


def silence_s(baudrate: int, parity: str, stopbits: int) -> float:
    """The 3.5-character inter-frame silence; fixed at 1.75 ms above 19200 baud (the spec)."""
    if baudrate > 19200:
        return 0.00175
    return 3.5 * char_time_s(baudrate, parity, stopbits)


def _length(buffer: bytes, start: int, layout: Layout) -> int | None:
    if isinstance(layout, int):
        return layout
    at, fixed = layout
    if len(buffer) - start <= at:
        return None
    return fixed + buffer[start + at]


class RtuFramer:
    """Bytes from the line in, complete frames with a valid CRC out (any unit id).

    ``feed(data, t)`` takes what one read returned and when (monotonic seconds) and returns the
    requests it completed, in order (other slaves' responses are skipped). Counters:
    ``garbage`` bytes skipped (CRC errors, noise, partial frames dropped at a silence),
    ``frames`` requests returned, ``responses`` responses skipped.
    """

    def __init__(self, char_s: float, silence: float) -> None:
        self.char_s = char_s
        self.silence = silence
        self.buffer = b""
        self.garbage = 0
        self.frames = 0
        self.responses = 0
        self._t_last: float | None = None

    def feed(self, data: bytes, t: float) -> list[bytes]:
        if self.buffer and self._t_last is not None:
            quiet = (t - self._t_last) - len(data) * self.char_s
            if quiet >= self.silence and self._frame_at(self.buffer + data, 0) is None:
                # The line was silent after these bytes: they were a partial frame or noise.
                self.garbage += len(self.buffer)
                self.buffer = b""
        self._t_last = t
        self.buffer += data
        return list(self._requests())

    def _requests(self) -> Iterator[bytes]:
        while self.buffer:
            found = self._first_frame()
            if found is None:
                if len(self.buffer) > MAX_ADU:  # no frame can start this early any more
                    self.garbage += len(self.buffer) - MAX_ADU
                    self.buffer = self.buffer[-MAX_ADU:]
                return
            start, length, is_request = found
            self.garbage += start
            frame = self.buffer[start:start + length]
            self.buffer = self.buffer[start + length:]
            if is_request:
                self.frames += 1
                yield frame
            else:
                self.responses += 1

    def _first_frame(self) -> tuple[int, int, bool] | None:
        for start in range(len(self.buffer) - 3):
            found = self._frame_at(self.buffer, start)
            if found is not None:
                return (start, *found)
        return None

    @staticmethod
    def _frame_at(buffer: bytes, start: int) -> tuple[int, bool] | None:
        """(length, is a request) of a complete, CRC-valid frame at ``start``, or None."""
        rest = len(buffer) - start
        if rest < 4:
            return None
        function = buffer[start + 1]
        candidates: list[tuple[Layout, bool]] = []
        if function & 0x80:
            candidates.append((_EXCEPTION_LENGTH, False))
        else:
            if function in _REQUEST:
                candidates.append((_REQUEST[function], True))
            if function in _RESPONSE:
                candidates.append((_RESPONSE[function], False))
            if not candidates and start == 0 and rest <= MAX_ADU:
                # A function without a known layout: a request if the whole buffer is one.
                candidates.append((rest, True))
        for layout, is_request in candidates:
            length = _length(buffer, start, layout)
            if length is not None and 4 <= length <= rest and crc_ok(
                    buffer[start:start + length]):
                return length, is_request
        return None
