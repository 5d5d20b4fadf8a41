"""Intermediate stage products: typed bundles of arrays, checked on write and on read.

A stage's key-named output folder holds its products as ``<name>.npz`` files (deterministic zip:
the same arrays give the same bytes) and a ``summary.json``. Each product is a frozen dataclass
whose fields are numpy arrays; every field declares its dtype and its shape, with symbolic
dimensions shared between fields (``("R", 4)``: as many rows as every other ``R`` field;
``("R+1",)``: one more). :meth:`Product.write` and :meth:`Product.read` check every field and
fail with :class:`ProductError` naming the file, the field, what was expected and what was found.
Fields are documented in storage/SCHEMA.md ("Stage products"), which a test keeps in agreement
with the declarations below. These products are internal to the pipeline; the published dataset is
the Zarr store and the Parquet tables.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np

from storage.atomic import atomic_write_text
from storage.npzio import NPZ_ERRORS, load_npz, save_npz_deterministic
from tasks.conventions import FREE, NUM_CLASSES

#: columns of the static map's vote counts: one per occupied class 0..9 (9: returns with no class)
NUM_OCCUPIED = FREE

P = TypeVar("P", bound="Product")


class ProductError(ValueError):
    """A stage product is missing, or a field has the wrong dtype or shape."""


@dataclasses.dataclass(frozen=True)
class ArraySpec:
    dtype: np.dtype
    shape: tuple[int | str, ...]
    doc: str


def array(dtype: Any, shape: tuple[int | str, ...], doc: str) -> Any:
    """Declare a product field: its dtype, its (symbolic) shape and one line of documentation."""
    return dataclasses.field(metadata={"spec": ArraySpec(np.dtype(dtype), tuple(shape), doc)})


def _dim(symbol: int | str, sizes: dict[str, int]) -> tuple[str, int] | None:
    """(base symbol, offset) of a symbolic dimension, e.g. "R+1" -> ("R", 1); None for a literal."""
    if isinstance(symbol, int):
        return None
    base, _, plus = symbol.partition("+")
    return base, int(plus or 0)


def check_arrays(
    kind: str, where: str, arrays: dict[str, np.ndarray], specs: dict[str, ArraySpec]
) -> dict[str, int]:
    """Check ``arrays`` against ``specs`` (all present, dtype, ndim, consistent symbolic sizes).

    Returns the sizes found for each symbol; raises ProductError naming ``where`` and the field.
    """
    missing = sorted(set(specs) - set(arrays))
    extra = sorted(set(arrays) - set(specs))
    if missing or extra:
        raise ProductError(
            f"{where}: {kind} has missing field(s) {missing} / unknown field(s) {extra}"
        )
    sizes: dict[str, int] = {}
    for name, spec in specs.items():
        a = arrays[name]
        if not isinstance(a, np.ndarray) or a.dtype != spec.dtype:
            raise ProductError(
                f"{where}: {kind}.{name} must be a {spec.dtype} array, got "
                f"{getattr(a, 'dtype', type(a).__name__)}"
            )
        if a.ndim != len(spec.shape):
            raise ProductError(
                f"{where}: {kind}.{name} must have shape {spec.shape}, got {a.shape}"
            )
        for axis, (symbol, size) in enumerate(zip(spec.shape, a.shape)):
            dim = _dim(symbol, sizes)
            if dim is None:
                if size != symbol:
                    raise ProductError(
                        f"{where}: {kind}.{name} must have shape {spec.shape}, "
                        f"got {a.shape} (axis {axis})"
                    )
                continue
            base, offset = dim
            if base not in sizes:
                sizes[base] = size - offset
            elif sizes[base] + offset != size:
                raise ProductError(
                    f"{where}: {kind}.{name} has {size} along axis {axis}, expected "
                    f"{symbol} = {sizes[base] + offset} as in the other fields"
                )
    return sizes


@dataclasses.dataclass(frozen=True)
class Product:
    """Base of every stage product (subclasses add array fields made with :func:`array`)."""

    #: file name without ``.npz`` (per-frame products take theirs at write / read time)
    NAME: ClassVar[str] = ""

    def __post_init__(self) -> None:
        check_arrays(type(self).__name__, "new product", self.arrays(), self.specs())

    @classmethod
    def specs(cls) -> dict[str, ArraySpec]:
        return {f.name: f.metadata["spec"] for f in dataclasses.fields(cls)}

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def empty(cls: type[P], **sizes: int) -> P:
        """A product whose row dimensions are 0 (other symbols from ``sizes``, e.g. H=480)."""

        def size(symbol):
            if isinstance(symbol, int):
                return symbol
            base, offset = _dim(symbol, {})
            return sizes.get(base, 0) + offset

        return cls(
            **{
                name: np.zeros(tuple(size(s) for s in spec.shape), spec.dtype)
                for name, spec in cls.specs().items()
            }
        )

    def take(self: P, rows: np.ndarray) -> P:
        """The given rows of a row-indexed product."""
        return type(self)(**{name: value[rows] for name, value in self.arrays().items()})

    def write(self, folder: Path, name: str | None = None) -> Path:
        """Store as ``folder/<name>.npz`` (written aside and renamed: never half a file)."""
        return save_npz_deterministic(
            product_path(folder, name or self.NAME), compressed=True, **self.arrays()
        )

    @classmethod
    def read(cls: type[P], folder: Path, name: str | None = None) -> P:
        path = product_path(folder, name or cls.NAME)
        if not path.exists():
            raise ProductError(f"{path}: stage product is missing (was the stage output deleted?)")
        try:
            arrays = load_npz(path)
        except NPZ_ERRORS as exc:
            raise ProductError(f"{path}: cannot read stage product ({exc})") from None
        check_arrays(cls.__name__, str(path), arrays, cls.specs())
        return cls(**arrays)


def product_path(folder: Path, name: str) -> Path:
    return Path(folder) / f"{name}.npz"


# ---- the products, stage by stage -----------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Detections(Product):
    """detect, one per frame (``frame_<raw frame>.npz``): the perception of one frame. D image
    detections, M LiDAR boxes, H x W the camera image."""

    boxes_xyxy: np.ndarray = array(np.float32, ("D", 4), "2D person boxes (u0, v0, u1, v1), pixels")
    scores: np.ndarray = array(np.float32, ("D",), "detection scores in [0, 1]")
    keypoints: np.ndarray = array(np.float32, ("D", 17, 3), "COCO-17 (u, v) pixels and confidence")
    mask_labels: np.ndarray = array(
        np.uint16, ("H", "W"), "instance masks: detection k is label k + 1, 0 none"
    )
    semantic: np.ndarray = array(np.uint8, ("H", "W"), "Cityscapes train ids, 255 ignore")
    lidar_centers: np.ndarray = array(
        np.float32, ("M", 3), "LiDAR pedestrian box centres, LiDAR frame, m"
    )
    lidar_sizes: np.ndarray = array(
        np.float32, ("M", 3), "box (l, w, h), l along the box x axis, m"
    )
    lidar_yaws: np.ndarray = array(np.float32, ("M",), "box yaw about LiDAR z, rad")
    lidar_scores: np.ndarray = array(np.float32, ("M",), "LiDAR box scores")
    gt_index: np.ndarray = array(
        np.int64, ("D",), "oracle only: ground-truth row, -1 false positive; -2 unknown"
    )

    @staticmethod
    def file_name(raw_frame: int) -> str:
        return f"frame_{int(raw_frame)}"


@dataclasses.dataclass(frozen=True)
class Tracks(Product):
    """track: one row per tracked detection, frames ascending. A person's LiDAR points are
    ``points_index[points_offsets[r]:points_offsets[r + 1]]`` (indices into the frame's
    ``points_lidar`` as the reader returns it); the first ``points_in_image[r]`` of them project
    into the image, the rest were found past its left / right side on LiDAR geometry."""

    NAME: ClassVar[str] = "tracks"
    frame: np.ndarray = array(np.int64, ("R",), "raw frame number")
    det_index: np.ndarray = array(np.int64, ("R",), "row in that frame's Detections")
    track_id: np.ndarray = array(np.int64, ("R",), "track id (>= 1)")
    boxes_xyxy: np.ndarray = array(np.float32, ("R", 4), "2D box, pixels")
    scores: np.ndarray = array(np.float32, ("R",), "detection score")
    keypoints: np.ndarray = array(np.float32, ("R", 17, 3), "COCO-17 (u, v, confidence)")
    lidar_box: np.ndarray = array(np.int64, ("R",), "matched LiDAR box row of the frame, -1 none")
    gt_index: np.ndarray = array(np.int64, ("R",), "the detection's gt_index")
    points_in_image: np.ndarray = array(
        np.int64, ("R",), "how many of the person's points are in the image"
    )
    points_offsets: np.ndarray = array(
        np.int64, ("R+1",), "row r's points start at points_offsets[r]"
    )
    points_index: np.ndarray = array(np.int64, ("P",), "point indices into the frame's sweep")

    def points_of(self, row: int, in_image_only: bool = False) -> np.ndarray:
        """Indices of row ``row``'s points in its frame's sweep."""
        lo = int(self.points_offsets[row])
        hi = (
            lo + int(self.points_in_image[row])
            if in_image_only
            else int(self.points_offsets[row + 1])
        )
        return self.points_index[lo:hi]


@dataclasses.dataclass(frozen=True)
class Bodies(Product):
    """fit: one row per fitted person and frame; body parameters in the LiDAR frame of the frame.
    Rows with ``gap_filled`` are bodies interpolated for a frame the track coasted over (no
    detection: det_index -1, no loss terms: NaN)."""

    NAME: ClassVar[str] = "bodies"
    frame: np.ndarray = array(np.int64, ("R",), "raw frame number")
    track_id: np.ndarray = array(np.int64, ("R",), "track id")
    det_index: np.ndarray = array(np.int64, ("R",), "row in that frame's Detections, -1 none")
    betas: np.ndarray = array(np.float32, ("R", 10), "SMPL shape")
    global_orient: np.ndarray = array(np.float32, ("R", 3), "root axis-angle, LiDAR frame, rad")
    body_pose: np.ndarray = array(np.float32, ("R", 69), "23 joint axis-angles, rad")
    transl: np.ndarray = array(np.float32, ("R", 3), "SMPL translation, LiDAR frame, m")
    velocity_base: np.ndarray = array(
        np.float32, ("R", 2), "pelvis velocity (vx, vy), base frame, m/s"
    )
    loss_j: np.ndarray = array(np.float32, ("R",), "final L_J")
    loss_3d: np.ndarray = array(np.float32, ("R",), "final L_3D")
    loss_total: np.ndarray = array(np.float32, ("R",), "final objective")
    chamfer_m: np.ndarray = array(
        np.float32, ("R",), "mean distance of the person's points to the fitted mesh's vertices, m"
    )
    reproj_px: np.ndarray = array(
        np.float32, ("R",), "mean reprojection error of the confident keypoints, px (NaN: none)"
    )
    num_points: np.ndarray = array(np.int64, ("R",), "LiDAR points the fit used")
    shift_m: np.ndarray = array(
        np.float32, ("R",), "how far the fit moved the root from its initial estimate, m"
    )
    mirrored: np.ndarray = array(
        np.bool_, ("R",), "the fit used the detection's keypoints mirrored left / right"
    )
    gap_filled: np.ndarray = array(
        np.bool_, ("R",), "interpolated for a frame without a detection (tasks/fit/gaps.py)"
    )


#: the map stage's folder of tile products (StaticMapProduct, OccupancyMapProduct)
TILES = "tiles"


def _tile_name(kind: str, tile) -> str:
    return f"{kind}_{int(tile[0])}_{int(tile[1])}"


@dataclasses.dataclass(frozen=True)
class StaticMapProduct(Product):
    """map, one per tile (``tiles/static_<tx>_<ty>.npz``): the human-free static semantic map
    (world frame) inside tile (tx, ty) (MapTiles). Voxel k covers ``[keys[k], keys[k] + 1) *
    voxel_size_m``; keys ascending (x, then y, then z); the tiles together are the sequence's map."""

    voxel_size_m: np.ndarray = array(np.float64, (), "voxel edge, m")
    keys: np.ndarray = array(np.int64, ("K", 3), "integer voxel keys")
    labels: np.ndarray = array(np.uint8, ("K",), "class id (max voting)")
    counts: np.ndarray = array(
        np.uint16, ("K", NUM_OCCUPIED), "votes per occupied class 0..9 (9: returns with no class)"
    )
    surface: np.ndarray = array(
        np.float32,
        ("K", 6),
        "centroid of the voxel's points relative to its corner (m), unit normal of their plane "
        "towards the sensor (zeros: no plane)",
    )

    @staticmethod
    def file_name(tile) -> str:
        return _tile_name("static", tile)


@dataclasses.dataclass(frozen=True)
class OccupancyMapProduct(Product):
    """map, one per tile (``tiles/occupancy_<tx>_<ty>.npz``): the free / unknown map (OctoMap
    semantics, world frame) inside tile (tx, ty); unknown voxels are absent; keys ascending."""

    voxel_size_m: np.ndarray = array(np.float64, (), "voxel edge, m")
    keys: np.ndarray = array(np.int64, ("M", 3), "integer voxel keys")
    logodds: np.ndarray = array(np.float32, ("M",), "OctoMap log-odds")

    @staticmethod
    def file_name(tile) -> str:
        return _tile_name("occupancy", tile)


@dataclasses.dataclass(frozen=True)
class MapTiles(Product):
    """map (``map_tiles.npz``): the index of the map's tiles. Tile (tx, ty) covers world x in
    ``[tx, tx + 1) * tile_m`` and y in ``[ty, ty + 1) * tile_m`` (any z); a voxel key k of a map
    of voxel v lies in tile ``floor(k / (tile_m / v))``. Tiles not listed hold no voxel."""

    NAME: ClassVar[str] = "map_tiles"
    tile_m: np.ndarray = array(np.float64, (), "tile edge, m")
    static_voxel_size_m: np.ndarray = array(np.float64, (), "the static map's voxel edge, m")
    occupancy_voxel_size_m: np.ndarray = array(np.float64, (), "the occupancy map's voxel edge, m")
    static_tiles: np.ndarray = array(
        np.int64, ("S", 2), "(tx, ty) of every StaticMapProduct tile, ascending"
    )
    static_voxels: np.ndarray = array(np.int64, ("S",), "voxels in that tile")
    occupancy_tiles: np.ndarray = array(
        np.int64, ("O", 2), "(tx, ty) of every OccupancyMapProduct tile, ascending"
    )
    occupancy_voxels: np.ndarray = array(np.int64, ("O",), "voxels in that tile")

    @classmethod
    def of(
        cls,
        tile_m: float,
        static_voxel_size_m: float,
        occupancy_voxel_size_m: float,
        static: list[tuple[tuple[int, int], int]],
        occupancy: list[tuple[tuple[int, int], int]],
    ) -> MapTiles:
        """The index of (tile, voxels) lists (any order; tiles of no voxel are left out)."""
        s, o = sorted(t for t in static if t[1]), sorted(t for t in occupancy if t[1])
        return cls(
            np.array(tile_m, np.float64),
            np.array(static_voxel_size_m, np.float64),
            np.array(occupancy_voxel_size_m, np.float64),
            np.array([t for t, _ in s], np.int64).reshape(-1, 2),
            np.array([n for _, n in s], np.int64),
            np.array([t for t, _ in o], np.int64).reshape(-1, 2),
            np.array([n for _, n in o], np.int64),
        )

    def has(self, kind: str, tile) -> bool:
        tiles = self.static_tiles if kind == "static" else self.occupancy_tiles
        return bool(np.any(np.all(tiles == np.asarray(tile, np.int64), axis=1)))


@dataclasses.dataclass(frozen=True)
class KeepMasks(Product):
    """map, scratch (``work/keep_<window>.npz``, deleted when the stage ends): which points of each
    sweep of a window of frames are kept (not a person), handed from the window pass to the
    occupancy pass. Sweep r's mask is bits ``offsets[r]:offsets[r + 1]`` of ``unpackbits(bits)``."""

    frame: np.ndarray = array(np.int64, ("W",), "raw frame number")
    offsets: np.ndarray = array(np.int64, ("W+1",), "first bit of each sweep's mask")
    bits: np.ndarray = array(np.uint8, ("B",), "np.packbits of the concatenated masks (1 = kept)")

    @staticmethod
    def file_name(window: int) -> str:
        return f"keep_{int(window)}"

    @classmethod
    def of(cls, frames: list[int], masks: list[np.ndarray]) -> KeepMasks:
        sizes = [len(m) for m in masks]
        bits = np.concatenate(masks).astype(bool) if masks else np.zeros(0, bool)
        return cls(
            np.asarray(frames, np.int64).reshape(-1),
            np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            np.packbits(bits),
        )

    def mask(self, row: int) -> np.ndarray:
        a, b = int(self.offsets[row]), int(self.offsets[row + 1])
        return np.unpackbits(self.bits, count=b)[a:b].astype(bool)


@dataclasses.dataclass(frozen=True)
class WindowVotesProduct(Product):
    """map, scratch (``work/votes_<window>_<tx>_<ty>.npz``, deleted when the stage ends): the raw
    static-map votes of one window of frames inside one tile, camera-seen and not (summed over
    windows, then voted per tile). Packed keys: 21 bits per axis, offset 2^20
    (tasks.occupancy.static_map.pack_keys), ascending."""

    seen_keys: np.ndarray = array(np.int64, ("A",), "packed voxel keys with camera votes")
    seen_counts: np.ndarray = array(np.uint16, ("A", NUM_OCCUPIED), "camera votes per class 0..9")
    seen_moments: np.ndarray = array(
        np.int64, ("A", 13), "point moments (tasks/occupancy/surface.py), fixed point"
    )
    unseen_keys: np.ndarray = array(np.int64, ("U",), "packed voxel keys with fallback votes")
    unseen_counts: np.ndarray = array(
        np.uint16, ("U", NUM_OCCUPIED), "fallback votes per class 0..9"
    )
    unseen_moments: np.ndarray = array(
        np.int64, ("U", 13), "point moments (tasks/occupancy/surface.py), fixed point"
    )

    @staticmethod
    def file_name(window: int, tile) -> str:
        return f"votes_{int(window)}_{int(tile[0])}_{int(tile[1])}"


@dataclasses.dataclass(frozen=True)
class FusedFrames(Product):
    """fuse: per-frame facts beside the fused Zarr store ``occupancy.zarr``."""

    NAME: ClassVar[str] = "frames"
    frame: np.ndarray = array(np.int64, ("F",), "raw frame number")
    stamp_ns: np.ndarray = array(np.int64, ("F",), "Unix time of the sweep, ns")
    class_counts: np.ndarray = array(
        np.int64, ("F", NUM_CLASSES), "voxels per class id among voxels with mask_lidar = 1"
    )
    T_world_from_base: np.ndarray = array(np.float64, ("F", 4, 4), "robot pose, m")


@dataclasses.dataclass(frozen=True)
class PersonVoxels(Product):
    """fuse: per tracked detection (a Tracks row) the voxels of its LiDAR points that the labels
    call unclassified, or pedestrian with no instance (no fitted body near the returns)."""

    NAME: ClassVar[str] = "person_voxels"
    frame: np.ndarray = array(np.int64, ("R",), "raw frame number")
    det_index: np.ndarray = array(np.int64, ("R",), "row in that frame's Detections")
    unclassified_voxels: np.ndarray = array(
        np.int64, ("R",), "voxels of the person's points labelled unclassified"
    )
    pedestrian_voxels_without_body: np.ndarray = array(
        np.int64, ("R",), "voxels of the person's points labelled pedestrian, instance 0"
    )


#: every product type, for the schema documentation test
PRODUCTS: tuple[type[Product], ...] = (
    Detections,
    Tracks,
    Bodies,
    StaticMapProduct,
    OccupancyMapProduct,
    MapTiles,
    KeepMasks,
    WindowVotesProduct,
    FusedFrames,
    PersonVoxels,
)


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


#: a stage's JSON-able summary, beside its products
SUMMARY = "summary.json"


def write_summary(folder: Path, summary: dict) -> None:
    atomic_write_text(Path(folder) / SUMMARY, json.dumps(summary, sort_keys=True, indent=1))


def read_summary(folder: Path) -> dict:
    return json.loads((Path(folder) / SUMMARY).read_text())


def remove_scratch(folder: Path) -> None:
    """Remove a folder of scratch products (a stage's work files, not part of its output)."""
    shutil.rmtree(folder, ignore_errors=True)
