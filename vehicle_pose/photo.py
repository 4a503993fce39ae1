"""Reading photos into RGB arrays (EXIF orientation applied, any mode converted, bombs refused),
and the lens's focal length from their EXIF.

Phones' own formats are read as well as JPEG: HEIC/HEIF (an iPhone camera's default) through
pillow-heif's plugin, AVIF through Pillow's."""

from __future__ import annotations

import io
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pillow_heif
from PIL import ExifTags, Image, ImageOps, UnidentifiedImageError

from vehicle_pose.errors import PhotoError, PhotoTooLargeError

__all__ = ["load_photo", "load_photo_focal", "decode_photo", "verify_photo", "read_focal", "ExifFocal", "is_gray",
           "resized", "resized_within", "resized_mask", "MAX_PIXELS", "EQUIVALENT_RANGE", "FULL_FRAME_DIAGONAL"]

MAX_PIXELS = 50_000_000

# HEIC/HEIF photos open as any other (only the primary image: a phone's depth maps and
# thumbnails are not decoded). The decoder applies the file's own rotation and mirroring, so
# the image it gives is upright and its EXIF orientation reads 1 (the one written is kept in
# ``info["original_orientation"]``; :func:`_as_written`).
pillow_heif.register_heif_opener(thumbnails=False, depth_images=False, aux_images=False)

FORMATS = "JPEG, PNG, HEIC/HEIF, AVIF, WebP, TIFF, BMP, GIF"
"""The photo formats read, as messages name them."""


@contextmanager
def _opened(data: bytes, max_pixels: int) -> Iterator[Image.Image]:
    """The opened image, its size checked from the header; everything PIL raises while the
    caller decodes it is a PhotoError (PhotoTooLargeError for a decompression bomb)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(data))
            if img.width * img.height > max_pixels:
                raise PhotoTooLargeError(f"photo has {img.width}x{img.height} pixels, more than {max_pixels}")
            yield img
    except PhotoError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise PhotoTooLargeError(
            f"photo declares too many pixels (more than {max_pixels} are refused): {exc}") from None
    except UnidentifiedImageError:
        # PIL's message names its in-memory buffer (an address), which tells a client nothing.
        raise PhotoError("not a readable image: its bytes are in no image format the reader knows "
                         f"({FORMATS})") from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise PhotoError(f"image data is damaged or truncated: {exc}") from None


def decode_photo(data: bytes, *, max_pixels: int = MAX_PIXELS, reduce_to: int | None = None) -> npt.NDArray[np.uint8]:
    """Decode image bytes to an (H, W, 3) uint8 RGB array.

    EXIF orientation is applied; CMYK, 16-bit, palette, gray and alpha images are converted
    (alpha is composited over mid-gray). Raises PhotoError for anything that is not a complete
    image, and PhotoTooLargeError (a PhotoError) for one with more than ``max_pixels`` pixels;
    the size is checked from the header, before anything is decoded. With ``reduce_to``, a JPEG
    whose longer side is more than twice that is decoded at a half, a quarter or an eighth of
    its size (in the compressed domain), its longer side still at least ``reduce_to``: the
    array is then smaller than the photo (:func:`verify_photo` gives the photo's size).
    """
    with _opened(data, max_pixels) as img:
        longer = max(img.width, img.height)
        if reduce_to is not None and img.format == "JPEG" and longer >= 2 * reduce_to:
            k = reduce_to / longer
            img.draft(img.mode, (max(1, int(np.ceil(img.width * k))), max(1, int(np.ceil(img.height * k)))))
        img.load()
    img = ImageOps.exif_transpose(img)
    if img.mode in ("I;16", "I;16B", "I;16L", "I", "F"):  # 16- and 32-bit integers, 32-bit floats (a TIFF)
        arr = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        top = max(float(arr.max()), 1.0 if img.mode != "F" else 1e-12)
        img = Image.fromarray(np.clip(arr / top * 255.0, 0, 255).astype(np.uint8), "L")
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        rgba = img.convert("RGBA")
        base = Image.new("RGBA", rgba.size, (128, 128, 128, 255))
        img = Image.alpha_composite(base, rgba)
    rgb = np.asarray(img.convert("RGB"), dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[0] < 8 or rgb.shape[1] < 8:
        raise PhotoError(f"photo of size {rgb.shape[1]}x{rgb.shape[0]} is too small")
    return np.ascontiguousarray(rgb)


def _quarter_turned(exif: Image.Exif) -> bool:
    """Whether the EXIF orientation turns the stored image by a quarter (values 5-8)."""
    return exif.get(0x0112, 1) in (5, 6, 7, 8)


def _as_written(img: Image.Image) -> tuple[int, int, bool]:
    """The width and height of the image as the camera wrote it (before any orientation), and
    whether the photo as seen is that image turned by a quarter.

    A JPEG (or AVIF, TIFF, ...) is stored as written and its EXIF orientation turns it. A HEIF
    decoder has already turned it by the file's own transforms and reset the EXIF orientation
    to 1, keeping the one written as ``info["original_orientation"]``: its size is then the
    photo as seen, and the camera's was that size turned back."""
    original = img.info.get("original_orientation")
    if original is not None:
        turned = original in (5, 6, 7, 8)
        return (img.height, img.width, True) if turned else (img.width, img.height, False)
    return img.width, img.height, _quarter_turned(img.getexif())


def verify_photo(data: bytes, *, max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """Width and height (EXIF orientation applied) of a photo :func:`decode_photo` would accept,
    found without building its RGB array: a JPEG is decoded at an eighth of its size (every
    byte of the stream is still read, so a truncated or damaged one fails), other formats once
    in their own mode. Raises what :func:`decode_photo` raises."""
    with _opened(data, max_pixels) as img:
        width, height, turned = _as_written(img)
        if img.format == "JPEG":
            img.draft(img.mode, (max(1, img.width // 8), max(1, img.height // 8)))
        img.load()
    if turned:  # the photo's sides swap
        width, height = height, width
    if width < 8 or height < 8:
        raise PhotoError(f"photo of size {width}x{height} is too small")
    return width, height


def _file(path: str | Path) -> bytes:
    p = Path(path)
    try:
        return p.read_bytes()
    except OSError as exc:
        raise PhotoError(f"cannot read photo {p}: {exc.strerror}") from None


def load_photo(path: str | Path, *, max_pixels: int = MAX_PIXELS) -> npt.NDArray[np.uint8]:
    """Read a photo file into an (H, W, 3) uint8 RGB array; PhotoError if it cannot be used."""
    return decode_photo(_file(path), max_pixels=max_pixels)


def load_photo_focal(path: str | Path, *, max_pixels: int = MAX_PIXELS) -> tuple[npt.NDArray[np.uint8], ExifFocal]:
    """:func:`load_photo` and :func:`read_focal` of one file, read once."""
    data = _file(path)
    return decode_photo(data, max_pixels=max_pixels), read_focal(data, max_pixels=max_pixels)


FULL_FRAME_DIAGONAL = float(np.hypot(36.0, 24.0))
"""Diagonal (mm) of the 36 x 24 mm frame that 35 mm equivalent focal lengths refer to."""

EQUIVALENT_RANGE = (10.0, 600.0)
"""35 mm equivalent focal lengths (mm) a photo's lens may have: horizontal fields of view of a
3:2 frame from 122 to 3.4 degrees (phones' widest lenses are 13 mm, their longest 240 mm).
EXIF outside it (0, 1000 mm, a sensor size off by a factor of ten) is taken for an error."""

# EXIF tags (Exif IFD) of the lens and of the image size the camera wrote.
_FOCAL_LENGTH, _FOCAL_35MM = 0x920A, 0xA405
_PLANE_X, _PLANE_UNIT = 0xA20E, 0xA210
_PIXEL_X, _PIXEL_Y = 0xA002, 0xA003
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit: inch, cm, mm, um


@dataclass(frozen=True)
class ExifFocal:
    """The focal length a photo's EXIF gives, as a registration can use it.

    ``widths`` is the focal length over the photo's width (the width as the photo is seen, after
    its EXIF orientation), so that it holds at any reduction: :meth:`pixels`. It is None when
    the EXIF gives none, or one that cannot be right (then ``warning`` says why). ``form`` is
    the EXIF form it was read from: ``35mm`` (FocalLengthIn35mmFilm) or ``focal_plane``
    (FocalLength and FocalPlaneXResolution); ``equivalent_mm`` its 35 mm equivalent and
    ``focal_mm`` the FocalLength as written.
    """

    widths: float | None = None
    form: str | None = None
    equivalent_mm: float | None = None
    focal_mm: float | None = None
    warning: str | None = None

    def pixels(self, width: float) -> float | None:
        """The focal length in pixels of the photo at ``width`` pixels wide."""
        return None if self.widths is None else self.widths * width

    def to_dict(self) -> dict[str, float | str | None]:
        return {"widths": self.widths, "form": self.form, "equivalent_mm": self.equivalent_mm,
                "focal_mm": self.focal_mm, "warning": self.warning}


def _number(value: object) -> float | None:
    """An EXIF rational or integer as a float; None when absent, zero-divided or not a number."""
    if value is None:
        return None
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return out if np.isfinite(out) else None


def read_focal(data: bytes, *, max_pixels: int = MAX_PIXELS) -> ExifFocal:
    """The focal length in the EXIF of the photo ``data`` (only its header is read).

    The 35 mm equivalent (FocalLengthIn35mmFilm) is converted across the diagonal (a lens of
    ``e`` mm equivalent has a focal length of ``e`` / 43.27 diagonals); else the focal length
    and the sensor's pixels per unit (FocalLength, FocalPlaneXResolution and its unit) give it
    in pixels of the image the camera wrote (PixelXDimension wide where written), scaled to the
    photo. A 35 mm equivalent outside :data:`EQUIVALENT_RANGE`, or a photo whose shape is no
    longer the one the camera wrote (cropped since), gives none, with a warning. Raises what
    :func:`decode_photo` raises for data that is not a photo.
    """
    with _opened(data, max_pixels) as img:
        width, height, turned = _as_written(img)
        exif = img.getexif()
    tags = exif.get_ifd(ExifTags.IFD.Exif)
    focal_mm = _number(tags.get(_FOCAL_LENGTH))
    written = _number(tags.get(_FOCAL_35MM))
    plane = _number(tags.get(_PLANE_X))
    if written is None and (focal_mm is None or plane is None):
        return ExifFocal(focal_mm=focal_mm)
    # The image size the camera wrote, in its stored orientation (as the photo's own).
    shot_w, shot_h = _number(tags.get(_PIXEL_X)), _number(tags.get(_PIXEL_Y))
    shape = width / height
    if shot_w and shot_h and shot_w > 0 and shot_h > 0 and abs(shot_w / shot_h - shape) > 0.01 * shape:
        return ExifFocal(focal_mm=focal_mm, warning=(
            f"the EXIF focal length is for a {shot_w:.0f}x{shot_h:.0f} picture and the photo is "
            f"{width}x{height} (cropped since it was taken): the focal length is searched"))
    diagonal = float(np.hypot(width, height))
    seen_width = height if turned else width
    found: list[tuple[str, float, float]] = []  # form, focal in pixels of the stored image, 35 mm equivalent
    if written is not None:
        found.append(("35mm", written / FULL_FRAME_DIAGONAL * diagonal, written))
    if focal_mm is not None and plane is not None:
        unit = _UNIT_MM.get(int(_number(tags.get(_PLANE_UNIT)) or 2))
        if unit is not None:
            pixels = focal_mm * plane / unit * (width / shot_w if shot_w and shot_w > 0 else 1.0)
            found.append(("focal_plane", pixels, pixels / diagonal * FULL_FRAME_DIAGONAL))
    lo, hi = EQUIVALENT_RANGE
    for form, pixels, equivalent in found:
        if lo <= equivalent <= hi:
            return ExifFocal(pixels / seen_width, form, equivalent, focal_mm)
    form, _, equivalent = found[0]
    return ExifFocal(focal_mm=focal_mm, equivalent_mm=equivalent, form=form, warning=(
        f"the EXIF focal length ({equivalent:.4g} mm, 35 mm equivalent, from its {form} form) is outside "
        f"{lo:.0f}-{hi:.0f} mm and cannot be the lens's: the focal length is searched"))


def is_gray(rgb: npt.NDArray[np.uint8]) -> bool:
    """True when all three channels are equal (a gray photo stored as RGB)."""
    return bool(np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]))


def resized(rgb: npt.NDArray[np.uint8], width: int, height: int) -> npt.NDArray[np.uint8]:
    """The photo (H, W, 3) at ``width`` x ``height`` (area interpolation); itself at its own size."""
    if (rgb.shape[1], rgb.shape[0]) == (width, height):
        return rgb
    import cv2

    out: npt.NDArray[np.uint8] = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    return out


def resized_within(rgb: npt.NDArray[np.uint8], max_size: int) -> npt.NDArray[np.uint8]:
    """The photo (H, W, 3) reduced to at most ``max_size`` pixels on its longer side; itself when
    it is no larger."""
    h, w = rgb.shape[:2]
    s = max_size / max(h, w)
    if s >= 1.0:
        return rgb
    return resized(rgb, max(1, round(w * s)), max(1, round(h * s)))


def resized_mask(mask: npt.NDArray[np.bool_], width: int, height: int) -> npt.NDArray[np.bool_]:
    """The mask (H, W) at ``width`` x ``height`` (nearest neighbour); itself at its own size."""
    if (mask.shape[1], mask.shape[0]) == (width, height):
        return mask
    import cv2

    out: npt.NDArray[np.bool_] = cv2.resize(mask.astype(np.uint8), (width, height),
                                            interpolation=cv2.INTER_NEAREST) > 0
    return out
