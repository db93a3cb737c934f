"""Image blobs carried in packets: strict, cheap header validation before any pixel decoding.

A snapshot's texture and background and a REM patch travel as encoded images (PNG, JPEG or
WebP). Decoding an image a peer sent is the one place where a few hundred bytes can cost
gigabytes: a 0.8 MB PNG of one colour can claim 16384 x 16384 pixels (768 MB once decoded).
So :func:`image_size` reads only the header (PNG IHDR, the JPEG frame header, the WebP VP8 /
VP8L / VP8X chunk) and :func:`check_image` bounds the size it claims; :func:`decode_image`
runs both before it lets OpenCV near the pixels, and checks that what OpenCV returns is what
the header promised.

Every failure is an :class:`ImageError` (a ``ValueError``) with a precise message, whatever the
bytes. :mod:`facewire.protocol.packets` runs :func:`check_image` on every image a packet carries,
and turns its ImageError into a ``PacketError``. OpenCV is imported only inside
:func:`decode_image`, so ``import facewire.protocol`` works on a machine without it.
"""

from __future__ import annotations

import logging
import re
import struct
import zlib
from typing import Final, cast

import numpy as np
from numpy.typing import NDArray

from facewire.protocol.constants import MAX_IMAGE_SIDE

logger = logging.getLogger(__name__)

#: Largest image side accepted for decoding, in pixels (a 4K frame is 3840 x 2160).
MAX_IMAGE_SIDE_DECODE: Final = MAX_IMAGE_SIDE
#: Most pixels accepted for decoding (4096 x 4096: 48 MB once decoded as BGR).
MAX_IMAGE_PIXELS_DECODE: Final = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE

PNG_SIGNATURE: Final = b"\x89PNG\r\n\x1a\n"
JPEG_SOI: Final = b"\xff\xd8"
#: Most JPEG marker segments read before the frame header (an ICC profile may take 255).
MAX_JPEG_SEGMENTS: Final = 1024
#: Most PNG chunks walked (16 MiB of image data in libpng's usual 8 KiB IDAT chunks is 2048).
MAX_PNG_CHUNKS: Final = 65536

# PNG colour type -> allowed bit depths (PNG spec, 11.2.2).
_PNG_DEPTHS: Final = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_PNG_MAX_DIM: Final = 2**31 - 1
# JPEG SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF: Final = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length: TEM, RST0..7, SOI.
_JPEG_STANDALONE: Final = frozenset({0x01, *range(0xD0, 0xD8), 0xD8})
_JPEG_FILL: Final = re.compile(rb"\xff+")
_WEBP_MIN_RIFF: Final = 4 + 8  # "WEBP" and one chunk header


class ImageError(ValueError):
    """An image blob is empty, of an unknown format, malformed, oversized or undecodable."""


def image_size(data: bytes) -> tuple[str, int, int]:
    """``(codec, width, height)`` of an encoded image, from its header alone.

    codec is ``"png"``, ``"jpeg"`` or ``"webp"``; width and height are in pixels as the header
    states them (a JPEG may say height 0). Raises :class:`ImageError` for empty, unknown,
    truncated or malformed headers, and a PNG chunk that overruns the data. Reads headers
    only (a few kilobytes, and a PNG's chunk headers); never decodes.
    """
    data = _as_bytes(data)
    if not data:
        raise ImageError("empty image")
    if data.startswith(PNG_SIGNATURE):
        return ("png", *_png_size(data))
    if data.startswith(JPEG_SOI):
        return ("jpeg", *_jpeg_size(data))
    if data.startswith(b"RIFF") and data[8:12] == b"WEBP":
        return ("webp", *_webp_size(data))
    raise ImageError(f"unknown image format (starts with {data[:8].hex()})")


def check_image(
    data: bytes,
    what: str,
    max_side: int = MAX_IMAGE_SIDE_DECODE,
    max_pixels: int = MAX_IMAGE_PIXELS_DECODE,
) -> tuple[str, int, int]:
    """:func:`image_size`, then bound the size: ``(codec, width, height)`` or ImageError.

    ``what`` names the blob in messages ("Snapshot.texture"). Width and height must be in
    ``[1, max_side]`` and ``width * height`` at most ``max_pixels``.
    """
    try:
        codec, width, height = image_size(data)
    except ImageError as exc:
        raise ImageError(f"{what}: {exc}") from None
    if not (1 <= width <= max_side and 1 <= height <= max_side):
        raise ImageError(
            f"{what}: {codec} image of {width}x{height} pixels, "
            f"each side must be in [1, {max_side}]"
        )
    if width * height > max_pixels:
        raise ImageError(
            f"{what}: {codec} image of {width}x{height} = {width * height} pixels "
            f"exceeds the limit of {max_pixels}"
        )
    return codec, width, height


def decode_image(
    data: bytes,
    what: str,
    max_side: int = MAX_IMAGE_SIDE_DECODE,
    expected_size: tuple[int, int] | None = None,
    max_pixels: int = MAX_IMAGE_PIXELS_DECODE,
) -> NDArray[np.uint8]:
    """Decode an image blob to a (height, width, 3) uint8 BGR array, or raise ImageError.

    The header is checked first (:func:`check_image`), and against ``expected_size``
    ``(width, height)`` if given, so an oversized image is rejected before any pixel is
    decoded. EXIF orientation is ignored: the array has the size the header states. Raises
    only :class:`ImageError`, whatever the bytes.
    """
    codec, width, height = check_image(data, what, max_side, max_pixels)
    if expected_size is not None and (width, height) != tuple(expected_size):
        ew, eh = expected_size
        raise ImageError(f"{what}: {codec} image of {width}x{height} pixels, expected {ew}x{eh}")
    import cv2  # OpenCV only where pixels are decoded

    flags = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        image = cv2.imdecode(np.frombuffer(_as_bytes(data), np.uint8), flags)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "cv2.error"
        raise ImageError(f"{what}: undecodable {codec} image ({reason})") from None
    if image is None:
        raise ImageError(f"{what}: undecodable {codec} image ({len(data)} bytes)")
    if image.dtype != np.uint8 or image.shape != (height, width, 3):
        raise ImageError(
            f"{what}: {codec} header says {width}x{height}, decoded a {image.dtype} "
            f"array of shape {image.shape}"
        )
    return cast("NDArray[np.uint8]", image)


# --- header parsers (raise ImageError without the "what" prefix) ------------------------------


def _as_bytes(data: object) -> bytes:
    if isinstance(data, bytes):
        return data
    if isinstance(data, (bytearray, memoryview)):
        return bytes(data)
    raise ImageError(f"expected bytes, got {type(data).__name__}")


def _png_size(data: bytes) -> tuple[int, int]:
    """PNG: the signature, then IHDR must be the first chunk (length 13, valid CRC)."""
    need = len(PNG_SIGNATURE) + 8 + 13 + 4
    if len(data) < need:
        raise ImageError(f"truncated PNG header ({len(data)} bytes, need {need})")
    length, ctype = struct.unpack_from(">I4s", data, 8)
    if ctype != b"IHDR":
        raise ImageError(f"PNG first chunk is {ctype!r}, expected b'IHDR'")
    if length != 13:
        raise ImageError(f"PNG IHDR length {length}, expected 13")
    width, height, depth, colour, compression, filter_, interlace = struct.unpack_from(
        ">IIBBBBB", data, 16
    )
    (crc,) = struct.unpack_from(">I", data, 29)
    if zlib.crc32(data[12:29]) != crc:
        raise ImageError("PNG IHDR CRC mismatch")
    if width > _PNG_MAX_DIM or height > _PNG_MAX_DIM:
        raise ImageError(f"PNG size {width}x{height} beyond 2^31 - 1")
    if depth not in _PNG_DEPTHS.get(colour, ()):
        raise ImageError(f"PNG colour type {colour} with bit depth {depth} is invalid")
    if compression != 0 or filter_ != 0 or interlace > 1:
        raise ImageError(
            f"PNG compression/filter/interlace method {compression}/{filter_}/{interlace} "
            "is invalid"
        )
    _png_chunks(data, need)
    return width, height


def _png_chunks(data: bytes, pos: int) -> None:
    """Walk the chunk headers from ``pos`` to IEND (or the end of the data): every chunk must
    fit in the data. OpenCV allocates the length a chunk states before reading it: a 222-byte
    PNG whose IDAT claimed 4 GB took 4 GB and 8 s to refuse."""
    n = len(data)
    for _ in range(MAX_PNG_CHUNKS):
        if pos == n:
            return
        if pos + 12 > n:
            raise ImageError(f"truncated PNG: {n - pos} bytes at offset {pos}, a chunk needs 12")
        length, ctype = struct.unpack_from(">I4s", data, pos)
        if length > _PNG_MAX_DIM or pos + 12 + length > n:
            raise ImageError(
                f"PNG chunk {ctype!r} at offset {pos} states {length} bytes, {n - pos - 12} follow"
            )
        if ctype == b"IEND":
            return
        pos += 12 + length
    raise ImageError(f"PNG has more than {MAX_PNG_CHUNKS} chunks")


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """JPEG: walk the marker segments after SOI to the first frame header (SOFn)."""
    n = len(data)
    pos = 2
    for _ in range(MAX_JPEG_SEGMENTS):
        if pos >= n:
            raise ImageError(f"truncated JPEG: no frame header in {n} bytes")
        if data[pos] != 0xFF:
            raise ImageError(f"JPEG marker expected at offset {pos}, got byte 0x{data[pos]:02x}")
        fill = _JPEG_FILL.match(data, pos)
        assert fill is not None
        pos = fill.end()  # past the 0xFF fill bytes
        if pos >= n:
            raise ImageError(f"truncated JPEG: no frame header in {n} bytes")
        marker = data[pos]
        pos += 1
        if marker in _JPEG_STANDALONE:
            continue
        if marker == 0x00:
            raise ImageError(f"JPEG stuffed byte 0xff00 at offset {pos - 2} outside scan data")
        if marker == 0xD9:
            raise ImageError("JPEG ends (EOI) before the frame header")
        if marker == 0xDA:
            raise ImageError("JPEG scan (SOS) before the frame header")
        if pos + 2 > n:
            raise ImageError(f"truncated JPEG: segment 0xff{marker:02x} at offset {pos - 2}")
        (length,) = struct.unpack_from(">H", data, pos)
        if length < 2:
            raise ImageError(f"JPEG segment 0xff{marker:02x} has length {length} < 2")
        if marker in _JPEG_SOF:
            return _jpeg_frame(data, marker, pos, length)
        pos += length
    raise ImageError(f"JPEG has no frame header in its first {MAX_JPEG_SEGMENTS} segments")


def _jpeg_frame(data: bytes, marker: int, pos: int, length: int) -> tuple[int, int]:
    """The SOFn segment at ``pos`` (its length field): P, Y, X, Nf and Nf component specs."""
    if length < 8:
        raise ImageError(f"JPEG frame header 0xff{marker:02x} has length {length} < 8")
    if pos + 8 > len(data):
        raise ImageError(f"truncated JPEG frame header 0xff{marker:02x} at offset {pos - 2}")
    precision, height, width, components = struct.unpack_from(">BHHB", data, pos + 2)
    if components == 0 or length != 8 + 3 * components:
        raise ImageError(
            f"JPEG frame header 0xff{marker:02x}: length {length} for {components} components"
        )
    if pos + length > len(data):
        raise ImageError(f"truncated JPEG frame header 0xff{marker:02x} at offset {pos - 2}")
    if not 2 <= precision <= 16:
        raise ImageError(f"JPEG sample precision {precision} is invalid")
    return width, height


def _webp_size(data: bytes) -> tuple[int, int]:
    """WebP: RIFF size, then the first chunk (VP8, VP8L or VP8X) gives the canvas size."""
    n = len(data)
    if n < 8 + _WEBP_MIN_RIFF:
        raise ImageError(f"truncated WebP header ({n} bytes, need {8 + _WEBP_MIN_RIFF})")
    (riff_size,) = struct.unpack_from("<I", data, 4)
    if riff_size < _WEBP_MIN_RIFF or riff_size % 2:
        raise ImageError(f"WebP RIFF size {riff_size} is invalid")
    if riff_size + 8 > n:
        raise ImageError(f"truncated WebP: RIFF size {riff_size} but {n - 8} bytes follow")
    fourcc, size = struct.unpack_from("<4sI", data, 12)
    if size > riff_size - _WEBP_MIN_RIFF:
        raise ImageError(f"WebP chunk {fourcc!r} of {size} bytes overruns the RIFF data")
    body = data[20 : 20 + size]
    if fourcc == b"VP8 ":
        if size < 10:
            raise ImageError(f"WebP VP8 chunk of {size} bytes, need 10")
        tag = body[0] | body[1] << 8 | body[2] << 16
        if tag & 1:
            raise ImageError("WebP VP8 bitstream does not start with a key frame")
        if body[3:6] != b"\x9d\x01\x2a":
            raise ImageError(f"WebP VP8 start code is {body[3:6].hex()}, expected 9d012a")
        width, height = struct.unpack_from("<HH", body, 6)
        return width & 0x3FFF, height & 0x3FFF
    if fourcc == b"VP8L":
        if size < 5:
            raise ImageError(f"WebP VP8L chunk of {size} bytes, need 5")
        if body[0] != 0x2F:
            raise ImageError(f"WebP VP8L signature is 0x{body[0]:02x}, expected 0x2f")
        (bits,) = struct.unpack_from("<I", body, 1)
        if bits >> 29:
            raise ImageError(f"WebP VP8L version {bits >> 29} is unknown")
        return (bits & 0x3FFF) + 1, (bits >> 14 & 0x3FFF) + 1
    if fourcc == b"VP8X":
        if size < 10:
            raise ImageError(f"WebP VP8X chunk of {size} bytes, need 10")
        if body[0] & 0x02:
            raise ImageError("animated WebP is not supported")
        width = int.from_bytes(body[4:7], "little") + 1
        height = int.from_bytes(body[7:10], "little") + 1
        return width, height
    raise ImageError(f"WebP first chunk is {fourcc!r}, expected VP8, VP8L or VP8X")
