"""Reading photos: every mode, EXIF orientation, bad bytes, verification without decoding, bombs, the
EXIF focal length."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import ExifTags, Image

from vehicle_pose.errors import PhotoError, PhotoTooLargeError
from vehicle_pose.photo import FULL_FRAME_DIAGONAL, decode_photo, read_focal, verify_photo


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
    # A 32-bit float TIFF of values in [0, 1] keeps its gradient (not all black).
    ramp = np.tile(np.linspace(0.0, 1.0, 30, dtype=np.float32), (20, 1))
    arr = decode_photo(_encode(Image.fromarray(ramp), "TIFF"))
    assert arr[0, 0, 0] == 0 and arr[0, -1, 0] == 255 and np.all(np.diff(arr[0, :, 0].astype(int)) >= 0)


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


def test_bytes_in_no_image_format_are_named_so_without_the_reader_s_internals():
    with pytest.raises(PhotoError, match="not a readable image: its bytes are in no image format") as caught:
        decode_photo(b"%PDF-1.4 not a photo")
    assert "BytesIO" not in str(caught.value) and " at 0x" not in str(caught.value)


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


def _with_lens(size: tuple[int, int], tags: dict[int, object], orientation: int = 1, fmt: str = "JPEG") -> bytes:
    """A photo of ``size`` (as stored) whose Exif IFD holds ``tags``, written by Pillow."""
    img = Image.new("RGB", size, (90, 100, 110))
    exif = Image.Exif()
    exif[0x0112] = orientation
    exif.get_ifd(ExifTags.IFD.Exif).update(tags)
    return _encode(img, fmt, exif=exif.tobytes())  # bytes: pillow-heif reads the orientation from them


def test_the_35mm_equivalent_is_converted_across_the_diagonal():
    lens = read_focal(_with_lens((800, 600), {0xA405: 26}))
    assert lens.form == "35mm" and lens.warning is None and lens.equivalent_mm == 26
    assert lens.pixels(800) == pytest.approx(26 / FULL_FRAME_DIAGONAL * 1000.0)
    # A reduced copy of the photo has the focal length reduced with it.
    assert lens.pixels(400) == pytest.approx(0.5 * lens.pixels(800))


@pytest.mark.parametrize("fmt", ["JPEG", "PNG", "WEBP"])
def test_the_focal_plane_form_gives_the_focal_length_in_pixels(fmt):
    # 4.2 mm on a sensor of 1000 pixels per 5.6 mm, written for the 1000-pixel image it is.
    tags = {0x920A: 4.2, 0xA20E: 1000 / 5.6 * 25.4, 0xA210: 2, 0xA002: 1000, 0xA003: 750}
    lens = read_focal(_with_lens((1000, 750), tags, fmt=fmt))
    assert lens.form == "focal_plane" and lens.focal_mm == pytest.approx(4.2)
    assert lens.pixels(1000) == pytest.approx(4.2 / 5.6 * 1000, rel=1e-3)
    # In millimetres per unit, and for a photo resized since: the same field of view.
    tags = {0x920A: 4.2, 0xA20E: 1000 / 5.6, 0xA210: 4, 0xA002: 2000, 0xA003: 1500}
    assert read_focal(_with_lens((1000, 750), tags)).pixels(1000) == pytest.approx(0.5 * 4.2 / 5.6 * 1000, rel=1e-3)


def test_the_focal_length_is_in_widths_of_the_photo_as_seen():
    # Stored 800x600 and turned a quarter by its orientation: seen 600 wide, same pixels.
    lens = read_focal(_with_lens((800, 600), {0xA405: 26}, orientation=6))
    assert lens.pixels(600) == pytest.approx(26 / FULL_FRAME_DIAGONAL * 1000.0)
    assert decode_photo(_with_lens((800, 600), {0xA405: 26}, orientation=6)).shape[1] == 600


@pytest.mark.parametrize("tags", [{0xA405: 0}, {0xA405: 1000}, {0x920A: 4.2, 0xA20E: 1000 / 0.056 * 25.4},
                                  {0x920A: 0.0, 0xA20E: 300.0}])
def test_absurd_exif_is_none_with_a_warning(tags):
    lens = read_focal(_with_lens((800, 600), tags))
    assert lens.widths is None and lens.pixels(800) is None
    assert "cannot be the lens's" in lens.warning


def test_a_photo_cropped_since_it_was_taken_has_no_focal_length():
    lens = read_focal(_with_lens((800, 800), {0xA405: 26, 0xA002: 4032, 0xA003: 3024}))
    assert lens.widths is None and "cropped" in lens.warning


def test_a_photo_without_a_usable_focal_length_has_none_and_no_warning():
    assert read_focal(_encode(Image.new("RGB", (64, 48)), "JPEG")).widths is None
    # A focal length without the sensor's size says nothing of the field of view.
    lens = read_focal(_with_lens((800, 600), {0x920A: 4.2}))
    assert lens.widths is None and lens.warning is None and lens.focal_mm == pytest.approx(4.2)


_PHONE_FORMATS = ["HEIF", "AVIF"]  # an iPhone's HEIC (pillow-heif), AVIF (Pillow)


@pytest.mark.parametrize("fmt", _PHONE_FORMATS)
def test_phone_formats_are_decoded_upright_as_a_jpeg_is(fmt):
    # A picture with a marked corner stored turned by its EXIF orientation, as phones store a
    # portrait photo: HEIF turns it while decoding, JPEG and AVIF by the orientation.
    img = np.full((60, 80, 3), (200, 40, 40), np.uint8)
    img[:20, :20] = (30, 30, 220)
    exif = Image.Exif()
    exif[0x0112] = 6
    data = _encode(Image.fromarray(img), fmt, exif=exif.tobytes(), quality=95)
    arr, ref = decode_photo(data), decode_photo(_encode(Image.fromarray(img), "JPEG", exif=exif.tobytes(), quality=95))
    assert arr.shape == ref.shape == (80, 60, 3)
    assert verify_photo(data) == (60, 80)
    assert np.abs(arr.astype(int) - ref.astype(int)).mean() < 6
    assert arr[:20, -20:, 2].mean() > 180 and arr[:20, :20, 2].mean() < 80  # the marked corner turned right


@pytest.mark.parametrize("fmt", _PHONE_FORMATS)
@pytest.mark.parametrize("orientation", [1, 6])
def test_a_phone_format_s_exif_gives_the_focal_length_a_jpeg_s_does(fmt, orientation):
    for tags in ({0x920A: 4.2, 0xA20E: 1000 / 5.6 * 25.4, 0xA210: 2, 0xA002: 1000, 0xA003: 750},
                 {0xA405: 26, 0xA002: 1000, 0xA003: 750}):
        lens = read_focal(_with_lens((1000, 750), tags, orientation, fmt))
        ref = read_focal(_with_lens((1000, 750), tags, orientation))
        assert lens.warning is None and ref.warning is None and lens.form == ref.form
        assert lens.widths == pytest.approx(ref.widths)
        seen = 750 if orientation == 6 else 1000
        assert decode_photo(_with_lens((1000, 750), tags, orientation, fmt)).shape[1] == seen


@pytest.mark.parametrize("cut", [0.3, 0.9])
def test_a_truncated_heic_is_refused(cut):
    img = Image.fromarray(np.random.default_rng(3).integers(0, 255, (240, 320, 3), dtype=np.uint8))
    data = _encode(img, "HEIF")
    assert decode_photo(data).shape == (240, 320, 3)
    short = data[: int(len(data) * cut)]
    with pytest.raises(PhotoError):
        decode_photo(short)
    with pytest.raises(PhotoError):
        verify_photo(short)


def test_the_focal_length_of_bad_bytes_is_a_photo_error():
    with pytest.raises(PhotoError):
        read_focal(b"not an image")
