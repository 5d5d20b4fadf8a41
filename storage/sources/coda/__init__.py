"""The CODa raw layout as a sequence source (real downloads and the simulator's output).

- :mod:`.layout`: where a sequence's files are, the sequences of a root, the errors;
- :mod:`.calibration`: the calibration files and the rectified pinhole of each camera;
- :mod:`.reader`: :class:`CodaSequence`, the sequence source, and the per-file readers;
- :mod:`.check`: the CODa side of check-data; :mod:`.writer`: writing the layout (the simulator).
"""

from storage.sources.coda.calibration import (
    quat_wxyz_to_matrix,
    read_calibration,
    read_extrinsic,
    read_intrinsics,
    rectified_camera,
)
from storage.sources.coda.layout import (
    IMAGE_EXTENSIONS,
    POINTS_PER_SWEEP,
    READER_VERSION,
    CodaFormatError,
    CodaFrameError,
    check_dataset_root,
    frame_number,
    list_sequences,
    sequence_ids,
    sequence_layout,
    stride_frames,
)
from storage.sources.coda.reader import (
    CodaSequence,
    LidarSweep,
    box_rotation,
    decode_image,
    image_size,
    lidar_channels,
    read_boxes,
    read_lidar_bin,
    read_lidar_raw,
    read_pose_stamps,
    read_semantic,
)

__all__ = [
    "IMAGE_EXTENSIONS",
    "POINTS_PER_SWEEP",
    "READER_VERSION",
    "CodaFormatError",
    "CodaFrameError",
    "CodaSequence",
    "LidarSweep",
    "box_rotation",
    "check_dataset_root",
    "decode_image",
    "frame_number",
    "image_size",
    "lidar_channels",
    "list_sequences",
    "quat_wxyz_to_matrix",
    "read_boxes",
    "read_calibration",
    "read_extrinsic",
    "read_intrinsics",
    "read_lidar_bin",
    "read_lidar_raw",
    "read_pose_stamps",
    "read_semantic",
    "rectified_camera",
    "sequence_ids",
    "sequence_layout",
    "stride_frames",
]
