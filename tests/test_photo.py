"""Reading photos: every mode, EXIF orientation, bad bytes, verification without decoding, bombs."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from vehicle_pose.errors import PhotoError, PhotoTooLargeError
from vehicle_pose.photo import decode_photo, verify_photo


def _encode(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def test_decodes_every_mode():
    rgb = Image.fromarray(np.random.default_rng(0).integers(0, 255, (20, 30, 3), dtype=np.uint8))
    for img, fmt in [(rgb, "PNG"), (rgb.convert("L"), "PNG"), (rgb.convert("RGBA"), "PNG"),
                     (rgb.convert("CMYK"), "JPEG"),
                     (rgb.convert("P"), "PNG"), (Image.fromarray(np.full((20, 30), 40000, np.uint16)), "PNG")]:
        arr = decode_photo(_encode(img, fmt))
        assert arr.shape == (20, 30, 3) and arr.dtype == np.uint8


def test_exif_orientation_is_applied():
    img = Image.new("RGB", (40, 20))
    exif = img.getexif()
    exif[0x0112] = 6
    arr = decode_photo(_encode(img, "JPEG", exif=exif))
    assert arr.shape[:2] == (40, 20)


@pytest.mark.parametrize("data", [b"not an image", _encode(Image.new("RGB", (64, 64)), "JPEG")[:200]])
def test_bad_bytes_are_photo_errors(data):
    with pytest.raises(PhotoError):
        decode_photo(data)


def _photos() -> list[bytes]:
    rng = np.random.default_rng(1)
    rgb = Image.fromarray(rng.integers(0, 255, (120, 200, 3), dtype=np.uint8))
    turned = Image.new("RGB", (40, 20))
    exif = turned.getexif()
    exif[0x0112] = 6
    return [_encode(rgb, "JPEG", quality=90), _encode(rgb, "PNG"), _encode(rgb.convert("CMYK"), "JPEG"),
            _encode(rgb, "WEBP"), _encode(turned, "JPEG", exif=exif), _encode(rgb.convert("L"), "TIFF")]


@pytest.mark.parametrize("index", range(6))
def test_verification_sees_the_size_decoding_gives(index):
    data = _photos()[index]
    assert verify_photo(data) == decode_photo(data).shape[1::-1]


@pytest.mark.parametrize("cut", [0.3, 0.6, 0.9])
def test_verification_refuses_what_decoding_refuses(cut):
    big = Image.fromarray(np.random.default_rng(2).integers(0, 255, (600, 800, 3), dtype=np.uint8))
    for data in (_encode(big, "JPEG", quality=92), _encode(big, "PNG")):
        short = data[: int(len(data) * cut)]
        with pytest.raises(PhotoError):
            decode_photo(short)
        with pytest.raises(PhotoError):
            verify_photo(short)
    with pytest.raises(PhotoTooLargeError):
        verify_photo(_encode(Image.new("L", (5000, 5000)), "PNG"), max_pixels=1_000_000)
    with pytest.raises(PhotoError, match="too small"):
        verify_photo(_encode(Image.new("RGB", (4, 30)), "PNG"))


def test_decompression_bomb_is_refused():
    with pytest.raises(PhotoTooLargeError):
        decode_photo(_encode(Image.new("L", (5000, 5000)), "PNG"), max_pixels=1_000_000)


def test_a_large_jpeg_can_be_decoded_reduced_to_at_least_the_size_asked():
    rng = np.random.default_rng(0)
    img = Image.fromarray((rng.random((60, 80, 3)) * 255).astype(np.uint8)).resize((3200, 2400))
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=90)
    data = buf.getvalue()
    assert decode_photo(data).shape == (2400, 3200, 3)
    reduced = decode_photo(data, reduce_to=800)
    assert reduced.shape == (600, 800, 3) and verify_photo(data) == (3200, 2400)
    assert decode_photo(data, reduce_to=1700).shape == (2400, 3200, 3)  # under twice the size asked: whole
    png = io.BytesIO()
    img.save(png, format="PNG")
    assert decode_photo(png.getvalue(), reduce_to=800).shape == (2400, 3200, 3)  # only JPEG reduces while decoding
