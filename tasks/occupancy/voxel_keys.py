"""Packed voxel keys: (N, 3) integer voxel keys as sortable int64 (the static map's tables, the
surface fit's moments), in a module of their own so both import them."""

from __future__ import annotations

import numpy as np

KEY_OFFSET = 1 << 20  # 21 bits per axis in a packed key: +-2^20 voxels
KEY_MASK = (1 << 21) - 1


class StaticMapError(ValueError):
    """Bad input to the static-map kernels (shapes, classes, parameters)."""


def pack_keys(keys: np.ndarray) -> np.ndarray:
    """(N, 3) int voxel keys -> (N,) int64 packed keys (sortable, 21 bits per axis)."""
    k = np.asarray(keys, dtype=np.int64).reshape(-1, 3) + KEY_OFFSET
    if len(k) and (k.min() < 0 or k.max() > KEY_MASK):
        lo, hi = k.min() - KEY_OFFSET, k.max() - KEY_OFFSET
        raise StaticMapError(f"voxel keys beyond +-2^20 (got {lo}..{hi})")
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def unpack_keys(packed: np.ndarray) -> np.ndarray:
    """(N,) int64 packed keys -> (N, 3) int64 voxel keys."""
    p = np.asarray(packed, dtype=np.int64)
    return np.stack([(p >> 42) & KEY_MASK, (p >> 21) & KEY_MASK, p & KEY_MASK], axis=1) - KEY_OFFSET


def key_rows(table: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Row of each voxel key in ``table``, the sorted (T,) packed keys; -1 where it is absent or
    beyond the packable range. keys: (N, 3) int voxel keys. Returns (N,) int64."""
    k = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    if not len(table):
        return np.full(len(k), -1, np.int64)
    inside = np.all((k >= -KEY_OFFSET) & (k <= KEY_MASK - KEY_OFFSET), axis=1)
    q = pack_keys(np.where(inside[:, None], k, 0))
    at = np.minimum(np.searchsorted(table, q), len(table) - 1)
    return np.where(inside & (table[at] == q), at, -1)
