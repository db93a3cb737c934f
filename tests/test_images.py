"""Image blobs: header sizes of PNG, JPEG and WebP, exact errors, bombs, fuzzed input."""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facewire.protocol.images import (
    MAX_JPEG_SEGMENTS,
    PNG_SIGNATURE,
    ImageError,
    check_image,
    decode_image,
    image_size,
)

W, H = 53, 37


def _pixels(h: int = H, w: int = W, channels: int = 3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, channels), dtype=np.uint8)


def _encode(ext: str, image: np.ndarray, *params: int) -> bytes:
    ok, buf = cv2.imencode(ext, image, list(params))
    assert ok
    return buf.tobytes()


def _chunk(ctype: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", zlib.crc32(ctype + data))


def _ihdr(width: int, height: int, depth: int = 8, colour: int = 2) -> bytes:
    return _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0))


def _png_bomb(side: int = 16384) -> bytes:
    """A valid 8-bit RGB PNG of side x side black pixels in about 0.78 MB.

    The IDAT is one deflate piece of 64 zero rows, flushed with Z_FULL_FLUSH (so it can be
    repeated), repeated side / 64 times; the Adler-32 of n zero bytes is (n mod 65521) << 16 | 1.
    OpenCV decodes it to a (side, side, 3) array: 805 MB, 7 s, 1.6 GB peak RSS.
    """
    row = 1 + 3 * side
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = c.compress(bytes(64 * row)) + c.flush(zlib.Z_FULL_FLUSH)
    end = c.flush()
    adler = ((side * row) % 65521) << 16 | 1
    idat = b"\x78\xda" + piece * (side // 64) + end + struct.pack(">I", adler)
    return PNG_SIGNATURE + _ihdr(side, side) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def _sof_offset(jpeg: bytes) -> int:
    """Offset of the SOF0 marker in a baseline JPEG made by OpenCV."""
    return jpeg.index(b"\xff\xc0")


def _jpeg_with_size(jpeg: bytes, width: int, height: int) -> bytes:
    i = _sof_offset(jpeg)
    return jpeg[: i + 5] + struct.pack(">HH", height, width) + jpeg[i + 9 :]


PNG = _encode(".png", _pixels())
JPEG = _encode(".jpg", _pixels())
JPEG_PROGRESSIVE = _encode(".jpg", _pixels(), cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
WEBP_LOSSY = _encode(".webp", _pixels(), cv2.IMWRITE_WEBP_QUALITY, 80)
WEBP_LOSSLESS = _encode(".webp", _pixels(), cv2.IMWRITE_WEBP_QUALITY, 101)
WEBP_ALPHA = _encode(".webp", _pixels(channels=4), cv2.IMWRITE_WEBP_QUALITY, 80)
GOOD = {
    "png": PNG,
    "png_grey": _encode(".png", _pixels(channels=1)),
    "png_16bit": _encode(".png", _pixels().astype(np.uint16) * 257),
    "jpeg": JPEG,
    "jpeg_progressive": JPEG_PROGRESSIVE,
    "webp_vp8": WEBP_LOSSY,
    "webp_vp8l": WEBP_LOSSLESS,
    "webp_vp8x": WEBP_ALPHA,
}


# --- good images ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(GOOD))
def test_good_images_give_their_size_and_decode(name: str) -> None:
    data = GOOD[name]
    codec = name.split("_")[0]
    assert image_size(data) == (codec, W, H)
    assert check_image(data, "x") == (codec, W, H)
    image = decode_image(data, "x", expected_size=(W, H))
    assert image.shape == (H, W, 3) and image.dtype == np.uint8


def test_import_needs_no_opencv() -> None:
    code = "import sys, protocol.images; sys.exit('cv2' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_webp_chunk_kinds_are_the_ones_tested() -> None:
    assert [GOOD[k][12:16] for k in ("webp_vp8", "webp_vp8l", "webp_vp8x")] == [
        b"VP8 ",
        b"VP8L",
        b"VP8X",
    ]


def test_lossless_codecs_decode_exactly() -> None:
    for data in (PNG, WEBP_LOSSLESS):
        np.testing.assert_array_equal(decode_image(data, "x"), _pixels())


def test_bytearray_and_memoryview_are_accepted() -> None:
    assert image_size(bytearray(PNG)) == ("png", W, H)
    assert decode_image(memoryview(JPEG), "x").shape == (H, W, 3)  # type: ignore[arg-type]


def test_jpeg_walk_skips_fill_bytes_and_standalone_markers() -> None:
    # SOI, then fill bytes, a TEM and an RST marker, a COM segment, then the real segments.
    extra = b"\xff\xff\xff\x01\xff\xd3\xff\xfe\x00\x05abc\xff\xff"
    assert image_size(JPEG[:2] + extra + JPEG[2:]) == ("jpeg", W, H)


@pytest.mark.parametrize("sof", [0xC1, 0xC2, 0xC3, 0xC9, 0xCF])
def test_jpeg_any_frame_header_gives_the_size(sof: int) -> None:
    i = _sof_offset(JPEG)
    assert image_size(JPEG[: i + 1] + bytes([sof]) + JPEG[i + 2 :]) == ("jpeg", W, H)


def test_jpeg_dht_dac_and_jpg_markers_are_not_frame_headers() -> None:
    # DHT/JPG/DAC segments before SOF0 are skipped, not taken for frame headers.
    seg = b"\x00\x08" + bytes([8]) + struct.pack(">HH", 9999, 9999) + b"\x01"
    for marker in (0xC4, 0xC8, 0xCC):
        data = JPEG[:2] + bytes([0xFF, marker]) + seg + JPEG[2:]
        assert image_size(data) == ("jpeg", W, H)


# --- exact errors --------------------------------------------------------------------------------


def test_empty_image() -> None:
    with pytest.raises(ImageError, match=r"^Snapshot.texture: empty image$"):
        decode_image(b"", "Snapshot.texture")
    with pytest.raises(ImageError, match=r"^empty image$"):
        image_size(b"")


def test_garbage_names_its_first_bytes() -> None:
    with pytest.raises(
        ImageError,
        match=r"^Snapshot.background: unknown image format \(starts with 474946383961010a\)$",
    ):
        check_image(b"GIF89a\x01\x0a\x00", "Snapshot.background")


def test_not_bytes() -> None:
    with pytest.raises(ImageError, match=r"^x: expected bytes, got str$"):
        decode_image("\x89PNG", "x")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (PNG[:8], "truncated PNG header (8 bytes, need 33)"),
        (PNG[:20], "truncated PNG header (20 bytes, need 33)"),
        (PNG[:32], "truncated PNG header (32 bytes, need 33)"),
        (
            PNG_SIGNATURE + _chunk(b"IDAT", bytes(13)),
            "PNG first chunk is b'IDAT', expected b'IHDR'",
        ),
        (PNG_SIGNATURE + _chunk(b"IHDR", bytes(14)), "PNG IHDR length 14, expected 13"),
        (PNG[:29] + b"\0\0\0\0" + PNG[33:], "PNG IHDR CRC mismatch"),
        (PNG_SIGNATURE + _ihdr(2**31, 1), "PNG size 2147483648x1 beyond 2^31 - 1"),
        (PNG_SIGNATURE + _ihdr(4, 4, 8, 3 + 4), "PNG colour type 7 with bit depth 8 is invalid"),
        (PNG_SIGNATURE + _ihdr(4, 4, 4, 2), "PNG colour type 2 with bit depth 4 is invalid"),
    ],
)
def test_png_header_errors(data: bytes, message: str) -> None:
    with pytest.raises(ImageError) as info:
        check_image(data, "RemPatch.data")
    assert str(info.value) == f"RemPatch.data: {message}"


def test_truncated_jpeg_headers() -> None:
    sof = _sof_offset(JPEG)
    cases = {
        2: "truncated JPEG: no frame header in 2 bytes",
        3: "truncated JPEG: no frame header in 3 bytes",
        5: "truncated JPEG: segment 0xffe0 at offset 2",
        10: "truncated JPEG: no frame header in 10 bytes",
        sof + 1: f"truncated JPEG: no frame header in {sof + 1} bytes",
        sof + 3: f"truncated JPEG: segment 0xffc0 at offset {sof}",
        sof + 9: f"truncated JPEG frame header 0xffc0 at offset {sof}",
        sof + 18: f"truncated JPEG frame header 0xffc0 at offset {sof}",
    }
    for n, message in cases.items():
        with pytest.raises(ImageError) as info:
            decode_image(JPEG[:n], "Snapshot.texture")
        assert str(info.value) == f"Snapshot.texture: {message}", n
    assert image_size(JPEG[: sof + 19]) == ("jpeg", W, H)  # the frame header is complete


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\xff\xd8\xff\xd9", "JPEG ends (EOI) before the frame header"),
        (b"\xff\xd8\xff\xda\x00\x08", "JPEG scan (SOS) before the frame header"),
        (b"\xff\xd8\xff\x00", "JPEG stuffed byte 0xff00 at offset 2 outside scan data"),
        (b"\xff\xd8\x12\x34", "JPEG marker expected at offset 2, got byte 0x12"),
        (b"\xff\xd8\xff\xe0\x00\x01", "JPEG segment 0xffe0 has length 1 < 2"),
        (b"\xff\xd8\xff\xc0\x00\x07" + bytes(5), "JPEG frame header 0xffc0 has length 7 < 8"),
        (
            b"\xff\xd8\xff\xc0\x00\x0b\x08\x00\x01\x00\x01\x02" + bytes(6),
            "JPEG frame header 0xffc0: length 11 for 2 components",
        ),
        (
            b"\xff\xd8\xff\xc0\x00\x0b\x01\x00\x01\x00\x01\x01" + bytes(3),
            "JPEG sample precision 1 is invalid",
        ),
        (
            b"\xff\xd8" + b"\xff\xfe\x00\x02" * (MAX_JPEG_SEGMENTS + 1),
            f"JPEG has no frame header in its first {MAX_JPEG_SEGMENTS} segments",
        ),
    ],
)
def test_jpeg_header_errors(data: bytes, message: str) -> None:
    with pytest.raises(ImageError) as info:
        check_image(data, "x")
    assert str(info.value) == f"x: {message}"


def _riff(chunk: bytes) -> bytes:
    return b"RIFF" + struct.pack("<I", 4 + len(chunk)) + b"WEBP" + chunk


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (WEBP_LOSSY[:19], "truncated WebP header (19 bytes, need 20)"),
        (WEBP_LOSSY[:100], f"truncated WebP: RIFF size {len(WEBP_LOSSY) - 8} but 92 bytes follow"),
        (b"RIFF\x05\x00\x00\x00WEBPVP8 \x00\x00\x00\x00", "WebP RIFF size 5 is invalid"),
        (
            _riff(b"VP8 \x20\x00\x00\x00" + bytes(8)),
            "WebP chunk b'VP8 ' of 32 bytes overruns the RIFF data",
        ),
        (_riff(b"VP8 \x04\x00\x00\x00" + bytes(4)), "WebP VP8 chunk of 4 bytes, need 10"),
        (
            _riff(b"VP8 \x0a\x00\x00\x00\x01" + bytes(9)),
            "WebP VP8 bitstream does not start with a key frame",
        ),
        (
            _riff(b"VP8 \x0a\x00\x00\x00" + bytes(10)),
            "WebP VP8 start code is 000000, expected 9d012a",
        ),
        (
            _riff(b"VP8L\x06\x00\x00\x00\x2e" + bytes(5)),
            "WebP VP8L signature is 0x2e, expected 0x2f",
        ),
        (_riff(b"VP8L\x06\x00\x00\x00\x2f\0\0\0\x20\0"), "WebP VP8L version 1 is unknown"),
        (_riff(b"VP8X\x0a\x00\x00\x00\x02" + bytes(9)), "animated WebP is not supported"),
        (
            _riff(b"ALPH\x02\x00\x00\x00\x00\x00"),
            "WebP first chunk is b'ALPH', expected VP8, VP8L or VP8X",
        ),
    ],
)
def test_webp_header_errors(data: bytes, message: str) -> None:
    with pytest.raises(ImageError) as info:
        check_image(data, "x")
    assert str(info.value) == f"x: {message}"


def test_webp_sizes_from_each_chunk_kind() -> None:
    vp8 = b"\x10\x02\x00\x9d\x01\x2a" + struct.pack("<HH", 0xC000 | 640, 480)
    assert image_size(_riff(b"VP8 \x0a\x00\x00\x00" + vp8)) == ("webp", 640, 480)
    bits = (640 - 1) | (480 - 1) << 14
    assert image_size(_riff(b"VP8L\x06\x00\x00\x00\x2f" + struct.pack("<I", bits) + b"\0")) == (
        "webp",
        640,
        480,
    )
    vp8x = b"\x10\0\0\0" + (640 - 1).to_bytes(3, "little") + (480 - 1).to_bytes(3, "little")
    assert image_size(_riff(b"VP8X\x0a\x00\x00\x00" + vp8x)) == ("webp", 640, 480)


# --- size limits ---------------------------------------------------------------------------------


def test_png_bomb_is_rejected_by_its_header() -> None:
    bomb = _png_bomb()
    assert len(bomb) < 800_000
    assert image_size(bomb) == ("png", 16384, 16384)
    message = "Snapshot.texture: png image of 16384x16384 pixels, each side must be in [1, 4096]"
    with pytest.raises(ImageError) as info:
        decode_image(bomb, "Snapshot.texture")
    assert str(info.value) == message  # the header check, not OpenCV, rejected it


def _idat_length(png: bytes, length: int) -> bytes:
    """``png`` (IHDR then IDAT) with the IDAT chunk's length field set to ``length``."""
    assert png[37:41] == b"IDAT"
    return png[:33] + length.to_bytes(4, "big") + png[37:]


@given(st.integers(len(PNG) - 33 - 12 + 1, 2**32 - 1))
def test_a_png_chunk_longer_than_the_data_is_refused_by_the_header_check(length: int) -> None:
    # OpenCV allocates what the chunk states before reading it: 0xffffffff took 4 GB and 8 s.
    data = _idat_length(PNG, length)
    follow = len(PNG) - 33 - 12
    with pytest.raises(ImageError) as info:
        decode_image(data, "x")
    assert (
        str(info.value)
        == f"x: PNG chunk b'IDAT' at offset 33 states {length} bytes, {follow} follow"
    )


def test_png_chunk_walk() -> None:
    idat = PNG[33 : 33 + 12 + int.from_bytes(PNG[33:37], "big")]
    assert image_size(PNG + b"trailing bytes after IEND") == ("png", W, H)
    assert image_size(PNG[:33]) == ("png", W, H)  # a header alone is a header
    with pytest.raises(
        ImageError, match=r"^truncated PNG: 5 bytes at offset 33, a chunk needs 12$"
    ):
        image_size(PNG[:38])
    many = PNG[:33] + _chunk(b"tEXt", b"") * 65536 + idat + _chunk(b"IEND", b"")
    with pytest.raises(ImageError, match=r"^PNG has more than 65536 chunks$"):
        image_size(many)
    few = PNG[:33] + _chunk(b"tEXt", b"") * 1000 + idat + _chunk(b"IEND", b"")
    assert decode_image(few, "x").shape == (H, W, 3)


def test_jpeg_claiming_20000_pixels_a_side_is_rejected() -> None:
    data = _jpeg_with_size(JPEG, 20000, 20000)
    assert image_size(data) == ("jpeg", 20000, 20000)
    with pytest.raises(ImageError) as info:
        decode_image(data, "RemPatch.data")
    assert str(info.value) == (
        "RemPatch.data: jpeg image of 20000x20000 pixels, each side must be in [1, 4096]"
    )


def test_zero_sides_and_pixel_count() -> None:
    with pytest.raises(ImageError) as info:
        check_image(_jpeg_with_size(JPEG, W, 0), "x")
    assert str(info.value) == "x: jpeg image of 53x0 pixels, each side must be in [1, 4096]"
    with pytest.raises(ImageError) as info:
        check_image(PNG_SIGNATURE + _ihdr(4096, 4096), "x", max_pixels=4096 * 2048)
    assert str(info.value) == (
        "x: png image of 4096x4096 = 16777216 pixels exceeds the limit of 8388608"
    )
    assert check_image(PNG_SIGNATURE + _ihdr(4096, 4096), "x") == ("png", 4096, 4096)
    with pytest.raises(ImageError, match=r"^x: png image of 53x37 pixels, each side must be in"):
        check_image(PNG, "x", max_side=40)


def test_expected_size() -> None:
    with pytest.raises(ImageError) as info:
        decode_image(PNG, "Snapshot.background", expected_size=(640, 480))
    assert str(info.value) == ("Snapshot.background: png image of 53x37 pixels, expected 640x480")


def test_undecodable_body_and_lying_header() -> None:
    broken = PNG[:33] + _chunk(b"IDAT", b"not zlib") + _chunk(b"IEND", b"")
    with pytest.raises(ImageError) as info:
        decode_image(broken, "x")
    assert str(info.value) == f"x: undecodable png image ({len(broken)} bytes)"
    # WebP whose VP8X canvas disagrees with its VP8 frame: libwebp refuses it.
    lying = WEBP_ALPHA[:24] + (W).to_bytes(3, "little") + WEBP_ALPHA[27:]
    assert image_size(lying) == ("webp", W + 1, H)
    with pytest.raises(ImageError) as info:
        decode_image(lying, "x")
    assert str(info.value) == f"x: undecodable webp image ({len(lying)} bytes)"


# --- fuzzing -------------------------------------------------------------------------------------

bases = st.sampled_from(sorted(GOOD.values()))
edits = st.lists(
    st.tuples(
        st.sampled_from(["flip", "set", "insert", "delete", "truncate"]),
        st.integers(0, 2**16),
        st.integers(0, 255),
    ),
    min_size=1,
    max_size=6,
)


def _mutate(data: bytes, ops: list[tuple[str, int, int]]) -> bytes:
    out = bytearray(data)
    for op, where, value in ops:
        i = where % (len(out) + 1)
        if op == "flip" and i < len(out):
            out[i] ^= 1 << (value % 8)
        elif op == "set" and i < len(out):
            out[i] = value
        elif op == "insert":
            out[i:i] = bytes([value]) * (1 + value % 4)
        elif op == "delete":
            del out[i : i + 1 + value % 16]
        elif op == "truncate":
            del out[i:]
    return bytes(out)


def _only_image_errors(data: bytes) -> None:
    for call in (image_size, lambda d: check_image(d, "x"), lambda d: decode_image(d, "x")):
        try:
            call(data)
        except ImageError:
            pass


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes_raise_only_image_errors(data: bytes) -> None:
    _only_image_errors(data)


@settings(max_examples=300, deadline=None)
@given(bases, edits)
def test_mutated_images_raise_only_image_errors(base: bytes, ops: list) -> None:
    _only_image_errors(_mutate(base, ops))


@settings(max_examples=300, deadline=None)
@given(bases, st.integers(0, 2**16), st.binary(min_size=1, max_size=64))
def test_mutated_image_bodies_raise_only_image_errors(base: bytes, where: int, junk: bytes) -> None:
    # Keep the header so that the decoder itself sees the damage.
    i = 40 + where % max(1, len(base) - 40)
    data = base[:i] + junk + base[i + len(junk) :]
    try:
        image = decode_image(data, "x")
    except ImageError:
        return
    # A JPEG frame header can sit past byte 40: then the junk may rewrite the stated size, and
    # the decoded picture must have the size the header states.
    _, width, height = image_size(data)
    assert image.dtype == np.uint8 and image.shape == (height, width, 3)
