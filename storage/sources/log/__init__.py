"""Robot logs as sequences: ROS 1 bags, ROS 2 bag folders and MCAP files (read with rosbags).

- :mod:`.bag`: which paths are logs, opening one, its topics and messages;
- :mod:`.positions`: where each message lies, read back by position; in-place message layouts;
- :mod:`.index`: the per-log index (stamps, positions, TF, poses, CameraInfo), cached;
- :mod:`.pointcloud`, :mod:`.images`: PointCloud2 and image decoding, rectification;
- :mod:`.reader`: :class:`LogSequence`, the sequence source;
- :mod:`.check`: the log side of check-data; :mod:`.writer`: writing logs (the simulator).
"""
