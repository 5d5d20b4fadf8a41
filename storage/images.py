"""Camera images as arrays (the model providers read the frames' images through here)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError


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
            rgb = np.array(im.convert("RGB"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: image file not found") from None
    except Image.DecompressionBombError as error:
        raise ValueError(f"{path}: image header claims an implausible size ({error})") from None
    except (UnidentifiedImageError, OSError) as error:
        raise ValueError(f"{path}: not a readable image ({error})") from error
    return rgb
