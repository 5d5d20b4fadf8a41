"""Explicit, versioned Parquet schemas of the dataset tables; field by field in SCHEMA.md.

Rules: a schema change only adds columns (nullable) or widens types, and bumps
``SCHEMA_VERSIONS[name]``; the version travels in each file's schema metadata
(``mobileocc.schema`` / ``mobileocc.schema_version``). Tables are partitioned by sequence
(``<table>/sequence=<seq>/data.parquet``); the ``sequence`` column comes from the partition
directory and is not stored inside the files (pyarrow refuses a field that is both).

Poses are 4x4 float64 flattened row-major to 16 values (``T[i, j]`` at ``4 * i + j``).
"""

from __future__ import annotations

import pyarrow as pa


def _vec(n: int, t: pa.DataType = pa.float64()) -> pa.DataType:
    return pa.list_(t, n)


def _f(name: str, t: pa.DataType, doc: str, nullable: bool = True) -> pa.Field:
    return pa.field(name, t, nullable=nullable, metadata={"doc": doc})


PARTITION_FIELD = pa.field(
    "sequence", pa.string(), nullable=False, metadata={"doc": "sequence name"}
)

FRAMES = pa.schema(
    [
        _f(
            "frame",
            pa.int32(),
            "frame index within the sequence (0..F-1), the zarr frame axis",
            False,
        ),
        _f("raw_frame", pa.int32(), "CODa frame number (before the 5 Hz stride)", False),
        _f("stamp_ns", pa.int64(), "Unix time of the LiDAR sweep, integer ns", False),
        _f("T_world_from_lidar", _vec(16), "4x4 float64 row-major, m"),
        _f("T_world_from_base", _vec(16), "4x4 float64 row-major, m"),
        _f("lidar_path", pa.string(), "source LiDAR .bin, absolute or relative to the CODa root"),
        _f("cam0_path", pa.string(), "source cam0 image"),
        _f("cam1_path", pa.string(), "source cam1 image (null if absent)"),
        _f(
            "class_counts",
            # variable length: version 1's 10 values (free at 9) still read beside version 2's 11
            pa.list_(pa.int64()),
            "voxels per class id 0..10 among voxels with mask_lidar = 1 (9 unclassified, 10 free)",
        ),
        _f(
            "unclassified_voxels",
            pa.int64(),
            "occupied voxels with no class (class 9) among voxels with mask_lidar = 1",
        ),
        _f("is_night", pa.bool_(), "frame recorded at night"),
    ]
)

INSTANCES = pa.schema(
    [
        _f(
            "track_id",
            pa.int32(),
            "pedestrian track id (the per-voxel id in zarr `instances`)",
            False,
        ),
        _f("frame", pa.int32(), "frame index within the sequence", False),
        _f("box2d_xyxy", _vec(4, pa.float32()), "cam0 box x0 y0 x1 y1, pixels"),
        _f("box3d_center", _vec(3), "box centre, base frame, m"),
        _f("box3d_size", _vec(3), "box size l (along box x), w, h, m"),
        _f("box3d_yaw", pa.float64(), "box yaw about base z, rad"),
        _f("keypoints", _vec(51, pa.float32()), "COCO-17 (u, v, confidence) x 17, pixels"),
        _f("betas", _vec(10, pa.float32()), "SMPL shape"),
        _f("global_orient", _vec(3, pa.float32()), "SMPL root axis-angle, base frame, rad"),
        _f("body_pose", _vec(69, pa.float32()), "SMPL 23 joint axis-angles, rad"),
        _f("transl", _vec(3, pa.float32()), "SMPL translation, base frame, m"),
        _f("chamfer_m", pa.float32(), "fit residual: mean LiDAR-to-mesh distance, m"),
        _f("reproj_px", pa.float32(), "fit residual: mean keypoint reprojection error, px"),
        _f("vx", pa.float32(), "velocity x, base frame, m/s"),
        _f("vy", pa.float32(), "velocity y, base frame, m/s"),
        _f("keypoints_mirrored", pa.bool_(), "the fit used the keypoints mirrored left / right"),
        _f(
            "gap_filled",
            pa.bool_(),
            "a body interpolated for a frame the track coasted over (no detection)",
        ),
        _f(
            "unclassified_voxels",
            pa.int64(),
            "voxels of the person's LiDAR points labelled unclassified (null: gap-filled row)",
        ),
        _f(
            "pedestrian_voxels_without_body",
            pa.int64(),
            "voxels of the person's LiDAR points labelled pedestrian with instance 0 (no body)",
        ),
    ]
)

SEQUENCES = pa.schema(
    [
        _f("fingerprint", pa.string(), "content hash of the sequence's input files", False),
        _f("config_hash", pa.string(), "hash of the resolved config", False),
        _f("code_version", pa.string(), "package / stage code version", False),
        _f("status", pa.string(), "ok | failed", False),
        _f("error", pa.string(), "error message when status = failed"),
        _f("num_frames", pa.int32(), "frames in the sequence (zarr frame axis length)", False),
        _f("occupancy_version", pa.string(), "published zarr version (occupancy/<seq>/<v>.zarr)"),
        _f("K", _vec(9), "cam0 intrinsics 3x3 row-major, pixels"),
        _f("T_cam0_from_lidar", _vec(16), "4x4 row-major, m"),
        _f("T_base_from_lidar", _vec(16), "4x4 row-major, m"),
        _f("image_width", pa.int32(), "cam0 width, pixels"),
        _f("image_height", pa.int32(), "cam0 height, pixels"),
    ]
)

SCHEMA_VERSIONS: dict[str, int] = {
    "frames": 2,
    "instances": 3,
    "sequences": 1,
}  # instances 2: keypoints_mirrored, gap_filled; 3: unclassified_voxels,
#    pedestrian_voxels_without_body; frames 2: class 9 unclassified (free 10, 11
#    class_counts), unclassified_voxels
_BASE: dict[str, pa.Schema] = {"frames": FRAMES, "instances": INSTANCES, "sequences": SEQUENCES}
TABLE_NAMES: tuple[str, ...] = tuple(_BASE)


def file_schema(name: str) -> pa.Schema:
    """The schema of one partition file (no ``sequence`` column), with version metadata."""
    if name not in _BASE:
        raise ValueError(f"unknown table {name!r}, expected one of {TABLE_NAMES}")
    return _BASE[name].with_metadata(
        {"mobileocc.schema": name, "mobileocc.schema_version": str(SCHEMA_VERSIONS[name])}
    )


def dataset_schema(name: str) -> pa.Schema:
    """The schema of the whole partitioned table: the file schema plus ``sequence``."""
    schema = file_schema(name)
    return schema.insert(0, PARTITION_FIELD)
