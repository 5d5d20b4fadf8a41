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
            rgb = np.array(im.convert("RGB"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: image file not found") from None
    except (UnidentifiedImageError, OSError) as error:
        raise ValueError(f"{path}: not a readable image ({error})") from error
    if expect_size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(expect_size):
        raise ValueError(
            f"{path}: image is {rgb.shape[1]} x {rgb.shape[0]} px, the camera calibration "
            f"says {expect_size[0]} x {expect_size[1]}"
        )
    return rgb
