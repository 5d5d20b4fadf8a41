"""Camera images as arrays (the model providers read the frames' images through here)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

#: Pillow modes that convert to 8-bit RGB as they are (bit depth 8 or less per channel)
_EIGHT_BIT_MODES = ("1", "L", "LA", "La", "P", "PA", "RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr")


def rgb8(im) -> np.ndarray:
    """A decoded Pillow image as (H, W, 3) uint8 RGB. A 16-bit grey image (PNG ``I;16*``, or
    ``I`` holding 0..65535) is scaled to 8 bits (v / 257: 65535 -> 255), never clipped (clipping
    reads most of a 16-bit image as white); any other mode (float, 32-bit) is a ValueError naming
    the mode (tasks/bounds.py: image bit depths)."""
    if im.mode in _EIGHT_BIT_MODES:
        return np.array(im.convert("RGB"))
    if im.mode.startswith("I;16") or im.mode == "I":
        grey = np.array(im).astype(np.int64)
        if grey.size and (grey.min() < 0 or grey.max() > 65535):
            raise ValueError(
                f"image mode {im.mode} holds values {grey.min()}..{grey.max()}, expected 16-bit "
                "0..65535"
            )
        grey8 = ((grey * 255 + 32767) // 65535).astype(np.uint8)
        return np.repeat(grey8[..., None], 3, axis=2)
    raise ValueError(f"image mode {im.mode!r} is not an 8- or 16-bit colour or grey image")


def read_rgb(path: str | os.PathLike, expect_size: tuple[int, int] | None = None) -> np.ndarray:
    """An image file as (H, W, 3) uint8 RGB; ``expect_size`` (width, height) is checked (the
    camera's calibrated size), with an error naming the file and both sizes."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            size = im.size  # from the header: a wrong size is refused before decoding
            if expect_size is not None and tuple(size) != tuple(expect_size):
                raise ValueError(
                    f"{path}: image is {size[0]} x {size[1]} px, the camera calibration "
                    f"says {expect_size[0]} x {expect_size[1]}"
                )
            try:
                rgb = rgb8(im)
            except ValueError as error:
                raise ValueError(f"{path}: {error}") from None
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: image file not found") from None
    except Image.DecompressionBombError as error:
        raise ValueError(f"{path}: image header claims an implausible size ({error})") from None
    except (UnidentifiedImageError, OSError) as error:
        raise ValueError(f"{path}: not a readable image ({error})") from error
    return rgb
