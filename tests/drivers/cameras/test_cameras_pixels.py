"""GenICam pixel formats to 8-bit images (drivers/cameras/pixels.py), against packers written
here from the format definitions (PFNC for ``p``, GigE Vision 2.0 for ``Packed``) and against
OpenCV's colour conversion of the scene a Bayer sensor saw."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivers.cameras.pixels import FORMATS, PixelError, payload_size, to_image

W, H = 64, 48
RNG = np.random.default_rng(21)


def pack_lsb(values: np.ndarray, bits: int) -> bytes:
    """PFNC ``p`` packing: the values' bits one after the other, least significant first."""
    stream = 0
    for i, v in enumerate(values.reshape(-1).tolist()):
        stream |= int(v) << (bits * i)
    return stream.to_bytes((values.size * bits + 7) // 8, "little")


def pack_gige(values: np.ndarray, bits: int) -> bytes:
    """GigE Vision ``Mono10Packed`` / ``Mono12Packed``: two pixels in three bytes, the high 8
    bits of each in bytes 0 and 2, the low bits in byte 1 (pixel 0 low nibble, pixel 1 high)."""
    out = bytearray()
    low = bits - 8
    flat = values.reshape(-1).tolist()
    for a, b in zip(flat[0::2], flat[1::2], strict=True):
        out += bytes([a >> low, (a & ((1 << low) - 1)) | ((b & ((1 << low) - 1)) << 4), b >> low])
    return bytes(out)


@pytest.mark.parametrize(("fmt", "bits"), [("Mono10", 10), ("Mono12", 12), ("Mono16", 16),
                                           ("Mono10p", 10), ("Mono12p", 12),
                                           ("Mono10Packed", 10), ("Mono12Packed", 12)])
def test_deep_mono_formats_keep_the_high_eight_bits(fmt: str, bits: int) -> None:
    values = RNG.integers(0, 1 << bits, size=(H, W), dtype=np.uint16)
    if fmt.endswith("Packed"):
        payload = pack_gige(values, bits)
    elif fmt.endswith("p"):
        payload = pack_lsb(values, bits)
    else:
        payload = values.astype("<u2").tobytes()
    assert len(payload) == payload_size(fmt, W, H)
    image = to_image(payload, W, H, fmt)
    assert image.dtype == np.uint8
    np.testing.assert_array_equal(image, (values >> (bits - 8)).astype(np.uint8))


def test_mono8_is_copied_out_of_the_sdk_buffer() -> None:
    buffer = bytearray(RNG.integers(0, 256, size=W * H, dtype=np.uint8).tobytes())
    image = to_image(np.frombuffer(buffer, np.uint8), W, H, "Mono8")
    expected = image.copy()
    buffer[:] = bytes(len(buffer))  # the SDK reuses the buffer for the next frame
    np.testing.assert_array_equal(image, expected)


def _scene() -> np.ndarray:
    """A smooth colour scene (BGR) with a red and a blue region, so a Bayer image demosaiced
    with the wrong pattern differs clearly from the scene's grey."""
    y, x = np.mgrid[0:H, 0:W]
    scene = np.zeros((H, W, 3), np.uint8)
    scene[..., 0] = np.where(x < W // 2, 220, 20)  # blue on the left
    scene[..., 1] = 60 + y
    scene[..., 2] = np.where(x < W // 2, 20, 230)  # red on the right
    return cv2.GaussianBlur(scene, (0, 0), 2.0)


def mosaic(scene: np.ndarray, pattern: str) -> np.ndarray:
    """What a sensor with the GenICam pattern (first row starts with pattern[0:2]) records."""
    channel = {"B": 0, "G": 1, "R": 2}
    raw = np.empty(scene.shape[:2], np.uint8)
    cells = [[pattern[0], pattern[1]], [pattern[2], pattern[3]]]
    for dy in (0, 1):
        for dx in (0, 1):
            raw[dy::2, dx::2] = scene[dy::2, dx::2, channel[cells[dy][dx]]]
    return raw


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_bayer_is_demosaiced_with_the_pattern_the_format_names(pattern: str) -> None:
    scene = _scene()
    grey = cv2.cvtColor(scene, cv2.COLOR_BGR2GRAY).astype(float)
    raw = mosaic(scene, pattern).tobytes()
    inner = (slice(4, -4), slice(4, -4))  # demosaicing borders differ by method
    right = np.abs(to_image(raw, W, H, f"Bayer{pattern[:2]}8")[inner] - grey[inner]).mean()
    assert right < 3.0
    others = {"RGGB": "BG", "BGGR": "RG", "GRBG": "GB", "GBRG": "GR"}  # R and B swapped
    wrong = np.abs(to_image(raw, W, H, f"Bayer{others[pattern]}8")[inner] - grey[inner]).mean()
    assert wrong > 4 * right + 5
    bgr = to_image(raw, W, H, f"Bayer{pattern[:2]}8", grayscale=False)
    assert bgr.shape == (H, W, 3)
    assert np.abs(bgr[inner].astype(float) - scene[inner]).mean() < 6.0


def test_bayer12_packed_is_unpacked_then_demosaiced() -> None:
    raw8 = mosaic(_scene(), "RGGB")
    values = raw8.astype(np.uint16) << 4
    np.testing.assert_array_equal(to_image(pack_lsb(values, 12), W, H, "BayerRG12p"),
                                  to_image(raw8.tobytes(), W, H, "BayerRG8"))


def test_rgb8_and_bgr8_arrive_as_bgr_or_grey() -> None:
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB order
    bgr = to_image(rgb.tobytes(), W, H, "RGB8", grayscale=False)
    assert (bgr[..., 2] == 200).all()
    assert (bgr[..., 0] == 0).all()
    grey = to_image(rgb.tobytes(), W, H, "RGB8Packed")
    np.testing.assert_array_equal(grey, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    np.testing.assert_array_equal(to_image(rgb[..., ::-1].tobytes(), W, H, "BGR8"), grey)


@pytest.mark.parametrize("fmt", ["Mono8", "Mono12p", "BayerGR8", "RGB8"])
def test_a_short_payload_is_refused_never_returned_half_filled(fmt: str) -> None:
    whole = payload_size(fmt, W, H)
    with pytest.raises(PixelError, match=f"{fmt} {W}x{H} needs {whole} bytes, the frame holds"):
        to_image(bytes(whole - 1), W, H, fmt)


def test_an_unknown_format_names_the_supported_ones() -> None:
    with pytest.raises(PixelError, match="YUV422_8 is not supported .*Mono12p"):
        to_image(bytes(W * H * 2), W, H, "YUV422_8")
    assert "BayerBG10p" in FORMATS
