"""Reading photos into RGB arrays: EXIF orientation applied, any mode converted, bombs refused."""

from __future__ import annotations

import io
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageOps, UnidentifiedImageError

from vehicle_pose.errors import PhotoError, PhotoTooLargeError

__all__ = ["load_photo", "decode_photo", "verify_photo", "is_gray", "resized", "resized_mask", "MAX_PIXELS"]

MAX_PIXELS = 50_000_000


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
    except UnidentifiedImageError as exc:
        raise PhotoError(f"not a readable image: {exc}") from None
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
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        top = max(float(arr.max()), 1.0)
        img = Image.fromarray(np.clip(arr / top * 255.0, 0, 255).astype(np.uint8), "L")
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        rgba = img.convert("RGBA")
        base = Image.new("RGBA", rgba.size, (128, 128, 128, 255))
        img = Image.alpha_composite(base, rgba)
    rgb = np.asarray(img.convert("RGB"), dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[0] < 8 or rgb.shape[1] < 8:
        raise PhotoError(f"photo of size {rgb.shape[1]}x{rgb.shape[0]} is too small")
    return np.ascontiguousarray(rgb)


def verify_photo(data: bytes, *, max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """Width and height (EXIF orientation applied) of a photo :func:`decode_photo` would accept,
    found without building its RGB array: a JPEG is decoded at an eighth of its size (every
    byte of the stream is still read, so a truncated or damaged one fails), other formats once
    in their own mode. Raises what :func:`decode_photo` raises."""
    with _opened(data, max_pixels) as img:
        width, height = img.width, img.height
        if img.format == "JPEG":
            img.draft(img.mode, (max(1, width // 8), max(1, height // 8)))
        img.load()
        orientation = img.getexif().get(0x0112, 1)
    if orientation in (5, 6, 7, 8):  # turned by a quarter: the photo's sides swap
        width, height = height, width
    if width < 8 or height < 8:
        raise PhotoError(f"photo of size {width}x{height} is too small")
    return width, height


def load_photo(path: str | Path, *, max_pixels: int = MAX_PIXELS) -> npt.NDArray[np.uint8]:
    """Read a photo file into an (H, W, 3) uint8 RGB array; PhotoError if it cannot be used."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise PhotoError(f"cannot read photo {p}: {exc.strerror}") from None
    return decode_photo(data, max_pixels=max_pixels)


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


def resized_mask(mask: npt.NDArray[np.bool_], width: int, height: int) -> npt.NDArray[np.bool_]:
    """The mask (H, W) at ``width`` x ``height`` (nearest neighbour); itself at its own size."""
    if (mask.shape[1], mask.shape[0]) == (width, height):
        return mask
    import cv2

    out: npt.NDArray[np.bool_] = cv2.resize(mask.astype(np.uint8), (width, height),
                                            interpolation=cv2.INTER_NEAREST) > 0
    return out
