"""``mobileocc show PATH``: a picture of one frame: a bird's-eye view beside the cam0 image with
the LiDAR points projected and coloured by depth.

``PATH`` is one of
- a built dataset (the ``--out`` of ``rebuild``, CODa layout or robot logs): its labels (class
  colours, pedestrians per instance, grey where unobserved) of ``--sequence`` (default: the
  first) at frame index ``--frame`` (default 0); the sensors are read from the recorded raw data;
- a robot log (a .bag / .mcap file or a ROS 2 bag folder): its sweep seen from above (columns
  holding returns coloured by height: nothing is labelled yet) at frame index ``--frame``;
- a ground-truth sequence folder ``ROOT/gt/{SEQ}`` as written by ``mobileocc simulate``: the
  exact occupancy of raw frame ``--frame`` (the raw data are read from the CODa layout under
  ``ROOT``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


class ShowError(ValueError):
    """A path or frame ``show`` cannot draw (one line: what was given, what was expected)."""


def show(path: Path, out_png: Path, frame: int | None = None, sequence: str | None = None) -> Path:
    """Render one frame of ``path`` (a dataset, a robot log or ``ROOT/gt/{SEQ}``) to ``out_png``;
    returns ``out_png``."""
    from storage.sources.log.bag import holds_logs

    path = Path(path)
    if path.is_dir() and (path / "manifest.json").is_file():
        bev, image, K, T = _dataset_frame(path, sequence, frame)
    elif path.name.isdigit() and path.parent.name == "gt":
        bev, image, K, T, points = _truth_frame(path, frame)
        return _write(out_png, bev, image, K, T, points)
    elif path.exists() and holds_logs(path):
        bev, image, K, T, points = _log_frame(path, sequence, frame)
        return _write(out_png, bev, image, K, T, points)
    else:
        raise ShowError(
            f"{path}: expected a dataset built by `mobileocc rebuild` (a folder with "
            "manifest.json), a robot log (.bag / .mcap / ROS 2 bag folder) or a ground-truth "
            "sequence folder ROOT/gt/<SEQ>"
        )
    return _write(out_png, bev, image, K, T[0], T[1])


def _dataset_frame(out: Path, sequence: str | None, frame: int | None):
    from storage.viewer_data import ViewerSource
    from tasks import viz

    src = ViewerSource(out)
    seq = src.check_sequence(sequence) if sequence is not None else src.sequences[0]
    f = src.frame(seq, 0 if frame is None else frame, ground_truth=False)
    visible = f.mask_lidar.astype(bool) | f.mask_camera.astype(bool)
    bev = viz.bev_image(f.semantics, f.instances, visible=visible, scale=10)
    T = np.linalg.inv(f.T_base_from_cam0) @ f.T_base_from_lidar
    image = f.image if f.image is not None else np.zeros((f.height, f.width, 3), np.uint8)
    points = f.points_lidar if f.points_lidar is not None else np.zeros((0, 3), np.float32)
    return bev, image, f.K, (T, points)


def _log_frame(path: Path, sequence: str | None, frame: int | None):
    from configs.schema import load_config
    from flows.pipeline.inputs import open_sequence, source
    from tasks import viz

    config = load_config(overrides={"dataset.root": str(path), "dataset.format": "log"})
    ids = source(config).sequence_ids(path)
    if sequence is not None and sequence not in ids:
        raise ShowError(f"{path}: no log {sequence!r}; logs: {', '.join(ids)}")
    seq = open_sequence(config, sequence or ids[0], with_poses=False)
    i = 0 if frame is None else frame
    if not 0 <= i < len(seq.info.frame_indices):
        raise ShowError(
            f"{path}: log {seq.sequence} has no frame {i}; its frames are "
            f"0..{len(seq.info.frame_indices) - 1} (kept sweeps, not raw sweep numbers)"
        )
    raw = seq.info.frame_indices[i]
    points = seq.frame(i).points_lidar
    calib = seq.info.calibration
    cam = calib.cameras["cam0"]
    grid = config.fuse.grid
    points_base = points @ calib.T_base_from_lidar[:3, :3].T + calib.T_base_from_lidar[:3, 3]
    bev = viz.bev_points(points_base, grid.range_min, grid.range_max, grid.voxel_size_m, 10)
    return bev, seq.image("cam0", raw), cam.K, cam.T_cam_from_lidar, points


def _truth_frame(path: Path, frame: int | None):
    from storage import gt as GT
    from storage.sources.coda import writer as W
    from tasks import viz

    root, seq = path.parent.parent, int(path.name)
    frames = GT.list_gt_frames(root, seq)
    if not frames:
        raise FileNotFoundError(f"{path}: no ground-truth frames")
    if frame is None:
        frame = frames[0]
    elif frame not in frames:
        raise ShowError(f"{path}: no frame {frame}; frames are {frames[0]}..{frames[-1]}")
    gt = GT.read_frame_gt(root, seq, frame)
    bev = viz.bev_image(gt.occupancy, gt.occupancy_instance, scale=10)
    image = W.read_image(root, seq, "cam0", frame)
    K, T = W.read_camera(root, seq, "cam0")
    return bev, image, K, T, W.read_lidar(root, seq, frame)[:, :3]


def _write(out_png: Path, bev, image, K, T_cam_from_lidar, points) -> Path:
    from PIL import Image

    from storage.atomic import write_atomically
    from tasks import viz

    height = min(640, image.shape[0])
    # Draw on the image at the output size, so each point stays one visible pixel.
    small = viz.resize_nearest(image, height)
    K_small = np.array(K, np.float64)
    K_small[:2] *= small.shape[0] / image.shape[0]
    K_small[:2, 2] = (K[:2, 2] + 0.5) * small.shape[0] / image.shape[0] - 0.5
    cam = viz.draw_points(small, points, K_small, T_cam_from_lidar, max_depth=25.0, radius=1)
    picture = viz.side_by_side([bev, cam], height=height)
    with write_atomically(out_png) as tmp:
        fmt = Image.registered_extensions().get(Path(out_png).suffix.lower(), "PNG")
        Image.fromarray(np.ascontiguousarray(picture)).save(tmp, format=fmt, optimize=True)
    return Path(out_png)
