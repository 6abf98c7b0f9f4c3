"""GenICam pixel formats (PFNC names) to the images the pipeline takes: 8-bit grey or BGR.

Shared by the pylon and the aravis drivers, which both hand over the raw payload of a frame
(``bytes`` or a uint8 array) with its width, height and ``PixelFormat``; no SDK converter is
used, so both stacks deliver the same image for the same bytes.

Supported (``FORMATS``):

- ``Mono8``; ``Mono10``/``Mono12``/``Mono16`` unpacked (one little-endian 16-bit word per
  pixel); packed ``Mono10p``/``Mono12p`` (PFNC: pixels LSB first, no gaps) and the older GigE
  Vision ``Mono10Packed``/``Mono12Packed`` (two pixels in three bytes, the high bits of each in
  its own byte). More than 8 bits are reduced to 8 by dropping the low bits.
- ``Bayer{RG,BG,GR,GB}{8,10,12,16}`` and the ``p`` packings: demosaiced with the pattern
  named by the format (its first row starts with the first two letters), then grey; with
  ``grayscale = false`` BGR.
- ``RGB8`` (``RGB8Packed``) and ``BGR8`` (``BGR8Packed``): grey, or BGR.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import numpy.typing as npt

U8 = npt.NDArray[np.uint8]

# GenICam Bayer pattern (first row starts with ..) -> OpenCV's code for that pattern (OpenCV's
# own BayerXY names count from the second row; its RGGB-style aliases are the GenICam names).
_BAYER_GREY = {"RG": cv2.COLOR_BayerRGGB2GRAY, "BG": cv2.COLOR_BayerBGGR2GRAY,
               "GR": cv2.COLOR_BayerGRBG2GRAY, "GB": cv2.COLOR_BayerGBRG2GRAY}
_BAYER_BGR = {"RG": cv2.COLOR_BayerRGGB2BGR, "BG": cv2.COLOR_BayerBGGR2BGR,
              "GR": cv2.COLOR_BayerGRBG2BGR, "GB": cv2.COLOR_BayerGBRG2BGR}

_MONO = re.compile(r"^(Mono|Bayer(RG|BG|GR|GB))(8|10|12|16)(p|Packed)?$")

#: Every pixel format the drivers accept (``pixel_format`` in the config).
FORMATS: tuple[str, ...] = tuple(
    [f"Mono{b}" for b in (8, 10, 12, 16)] + ["Mono10p", "Mono12p", "Mono10Packed", "Mono12Packed"]
    + [f"Bayer{p}{b}" for p in _BAYER_GREY for b in (8, 10, 12, 16)]
    + [f"Bayer{p}{b}p" for p in _BAYER_GREY for b in (10, 12)]
    + [f"Bayer{p}{b}Packed" for p in _BAYER_GREY for b in (10, 12)]
    + ["RGB8", "RGB8Packed", "BGR8", "BGR8Packed"])


class PixelError(ValueError):
    """A payload that does not hold a whole image of its format (or an unknown format)."""


def payload_size(fmt: str, width: int, height: int) -> int:
    """Bytes a whole ``width`` x ``height`` image of ``fmt`` takes (no row padding)."""
    if fmt in ("RGB8", "RGB8Packed", "BGR8", "BGR8Packed"):
        return width * height * 3
    m = _MONO.match(fmt)
    if m is None:
        raise PixelError(f"pixel format {fmt} is not supported (supported: {', '.join(FORMATS)})")
    bits, packing = int(m.group(3)), m.group(4)
    if bits == 8:
        return width * height
    if packing is None:
        return width * height * 2
    if packing == "Packed":  # GigE Vision: two pixels in three bytes, 10 bits or 12
        return (width * height + 1) // 2 * 3
    return (width * height * bits + 7) // 8


def _unpack(raw: U8, n: int, bits: int, packing: str | None) -> npt.NDArray[np.uint16]:
    """``n`` pixel values of ``bits`` bits from ``raw`` (see the module docstring)."""
    if packing is None:
        return raw[: 2 * n].view("<u2").astype(np.uint16)
    if bits == 12 and packing == "p":  # 2 px in 3 bytes, LSB first
        b = raw[: 3 * ((n + 1) // 2)].reshape(-1, 3).astype(np.uint16)
        px = np.empty((b.shape[0], 2), np.uint16)
        px[:, 0] = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
        px[:, 1] = (b[:, 1] >> 4) | (b[:, 2] << 4)
        return px.reshape(-1)[:n]
    if bits == 12:  # GigE Mono12Packed: high 8 bits of each pixel in bytes 0 and 2
        b = raw[: 3 * ((n + 1) // 2)].reshape(-1, 3).astype(np.uint16)
        px = np.empty((b.shape[0], 2), np.uint16)
        px[:, 0] = (b[:, 0] << 4) | (b[:, 1] & 0x0F)
        px[:, 1] = (b[:, 2] << 4) | (b[:, 1] >> 4)
        return px.reshape(-1)[:n]
    if bits == 10 and packing == "p":  # 4 px in 5 bytes, LSB first
        groups = (n + 3) // 4
        b5 = raw[: 5 * groups].reshape(-1, 5).astype(np.uint64)
        shifts = np.array([0, 8, 16, 24, 32], np.uint64)
        word = np.bitwise_or.reduce(b5 << shifts, axis=1)
        px4 = (word[:, None] >> np.array([0, 10, 20, 30], np.uint64)) & np.uint64(0x3FF)
        return px4.astype(np.uint16).reshape(-1)[:n]
    if bits == 10:  # GigE Mono10Packed: 2 px in 3 bytes, low 2 bits of each in byte 1
        b = raw[: 3 * ((n + 1) // 2)].reshape(-1, 3).astype(np.uint16)
        px = np.empty((b.shape[0], 2), np.uint16)
        px[:, 0] = (b[:, 0] << 2) | (b[:, 1] & 0x03)
        px[:, 1] = (b[:, 2] << 2) | ((b[:, 1] >> 4) & 0x03)
        return px.reshape(-1)[:n]
    raise PixelError(f"no {bits}-bit {packing} packing")


def to_image(payload: bytes | npt.NDArray[np.uint8], width: int, height: int, fmt: str,
             grayscale: bool = True) -> U8:
    """The 8-bit image (H, W) grey or (H, W, 3) BGR of one frame's payload.

    ``PixelError`` when the payload is shorter than a whole image of the format (an
    incomplete frame is refused, never returned half filled) or the format is unknown."""
    need = payload_size(fmt, width, height)
    raw = np.frombuffer(payload, np.uint8) if isinstance(payload, bytes | bytearray | memoryview) \
        else np.asarray(payload, np.uint8).reshape(-1)
    if raw.size < need:
        raise PixelError(f"{fmt} {width}x{height} needs {need} bytes, the frame holds {raw.size}")
    if fmt in ("RGB8", "RGB8Packed", "BGR8", "BGR8Packed"):
        image = raw[:need].reshape(height, width, 3)
        code = (cv2.COLOR_RGB2GRAY if grayscale else cv2.COLOR_RGB2BGR) if fmt.startswith("RGB") \
            else (cv2.COLOR_BGR2GRAY if grayscale else None)
        return np.ascontiguousarray(image if code is None else cv2.cvtColor(image, code))
    m = _MONO.match(fmt)
    assert m is not None  # payload_size judged it
    bits, pattern, packing = int(m.group(3)), m.group(2), m.group(4)
    n = width * height
    if bits == 8:
        plane = raw[:n].reshape(height, width)
    else:
        values = _unpack(raw, n, bits, "p" if packing == "p" else packing)
        plane = (values >> (bits - 8)).astype(np.uint8).reshape(height, width)
    if pattern is None:
        return np.array(plane)  # a copy: the SDK's buffer is reused for the next frame
    table = _BAYER_GREY if grayscale else _BAYER_BGR
    return np.ascontiguousarray(cv2.cvtColor(np.ascontiguousarray(plane), table[pattern]))
