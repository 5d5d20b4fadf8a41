"""``mobileocc show``: a picture of one frame: bird's-eye view of the occupancy grid beside the
cam0 image with the LiDAR points projected and coloured by depth.

``path`` is a ground-truth sequence folder ``ROOT/gt/{SEQ}`` as written by ``mobileocc simulate``
(the raw data are read from the CODa layout under ``ROOT``).
"""

from __future__ import annotations

from pathlib import Path


def show(path: Path, out_png: Path, frame: int | None = None) -> Path:
    """Render frame ``frame`` (default: the first) of the sequence at ``path`` (``ROOT/gt/{SEQ}``)
    to ``out_png``; returns ``out_png``."""
    import numpy as np
    from PIL import Image

    from storage import coda_writer as W
    from storage import gt as GT
    from storage.atomic import write_atomically
    from tasks import viz

    path = Path(path)
    if not path.name.isdigit() or path.parent.name != "gt":
        raise ValueError(f"{path}: expected a ground-truth sequence folder ROOT/gt/<SEQ>")
    root, seq = path.parent.parent, int(path.name)
    frames = GT.list_gt_frames(root, seq)
    if not frames:
        raise FileNotFoundError(f"{path}: no ground-truth frames")
    if frame is None:
        frame = frames[0]
    elif frame not in frames:
        raise ValueError(f"{path}: no frame {frame}; frames are {frames[0]}..{frames[-1]}")
    gt = GT.read_frame_gt(root, seq, frame)
    bev = viz.bev_image(gt.occupancy, gt.occupancy_instance, scale=10)
    image = W.read_image(root, seq, "cam0", frame)
    K, T = W.read_camera(root, seq, "cam0")
    points = W.read_lidar(root, seq, frame)[:, :3]
    height = min(640, image.shape[0])
    # Draw on the image at the output size, so each point stays one visible pixel.
    small = viz.resize_nearest(image, height)
    K_small = K.copy()
    K_small[:2] *= small.shape[0] / image.shape[0]
    K_small[:2, 2] = (K[:2, 2] + 0.5) * small.shape[0] / image.shape[0] - 0.5
    cam = viz.draw_points(small, points, K_small, T, max_depth=25.0, radius=1)
    picture = viz.side_by_side([bev, cam], height=height)
    with write_atomically(out_png) as tmp:
        fmt = Image.registered_extensions().get(Path(out_png).suffix.lower(), "PNG")
        Image.fromarray(np.ascontiguousarray(picture)).save(tmp, format=fmt, optimize=True)
    return Path(out_png)
