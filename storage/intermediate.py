"""Intermediate stage products: named array bundles inside a stage's key-named output folder.

A stage folder holds ``<name>.npz`` files (deterministic zip, so the same inputs give the same
bytes) and a ``summary.json``. These products are internal to the pipeline (the published dataset is
the Zarr store and the Parquet tables); their fields are documented where each stage writes them
(flows/stages.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.npzio import save_npz_deterministic


def product_path(folder: Path, name: str) -> Path:
    return Path(folder) / f"{name}.npz"


def write_product(folder: Path, name: str, arrays: dict[str, np.ndarray]) -> Path:
    return save_npz_deterministic(product_path(folder, name), compressed=True, **arrays)


def read_product(folder: Path, name: str, keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """A stage product's arrays; ``keys`` reads only those (the rest is not decompressed)."""
    path = product_path(folder, name)
    if not path.exists():
        raise FileNotFoundError(f"{path}: stage product is missing (was the stage output deleted?)")
    with np.load(path, allow_pickle=False) as z:
        missing = sorted(set(keys or ()) - set(z.files))
        if missing:
            raise KeyError(f"{path}: no array(s) {missing} (has {sorted(z.files)})")
        return {k: z[k] for k in (z.files if keys is None else keys)}


def masks_to_labels(masks: np.ndarray) -> np.ndarray:
    """(D, H, W) bool instance masks -> (H, W) uint16 label image (1..D, later masks win overlaps)."""
    d = masks.shape[0]
    labels = np.zeros(masks.shape[1:], np.uint16)
    for k in range(d):
        labels[masks[k]] = k + 1
    return labels


def labels_to_masks(labels: np.ndarray, count: int) -> np.ndarray:
    """(H, W) uint16 label image -> (count, H, W) bool masks."""
    return labels[None, :, :] == np.arange(1, count + 1, dtype=np.uint16)[:, None, None]
