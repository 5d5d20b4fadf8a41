"""Reading a frame's raw data back from a frames-table reference ``LOG#TOPIC@INDEX`` (the
nuScenes export copies sweeps and images from the raw data).

A log is opened once per process and indexed without a cache (one header pass). The sweep is
decoded as the reader decodes it; the image is the message's own JPEG / PNG bytes when its topic
is rectified and compressed, else decoded, rectified with the CameraInfo of its namespace
(``<namespace>/camera_info``, the reader's default pairing) and written as PNG.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.sources.log.bag import LogFile, LogFormatError

_REF = re.compile(r"^(?P<log>.+)#(?P<topic>/.*)@(?P<index>\d+)$")


@dataclass(frozen=True)
class MessageRef:
    log: str
    topic: str
    index: int


def parse_ref(ref: str) -> MessageRef | None:
    """``LOG#TOPIC@INDEX`` -> MessageRef; None for anything else (a file path)."""
    m = _REF.match(ref or "")
    return MessageRef(m["log"], m["topic"], int(m["index"])) if m else None


@functools.lru_cache(maxsize=4)
def _open(path: str):
    from storage.sources.log.index import build_index

    log = LogFile(Path(path))
    return log, build_index(log)


def _base(source_root: Path) -> Path:
    return source_root if source_root.is_dir() else source_root.parent


def _message(ref: MessageRef, source_root: Path):
    """(log, index, stream, raw bytes) of a referenced message; LogFormatError naming the log
    when the topic or the index is not there."""
    log, index = _open(str(_base(source_root) / ref.log))
    stream = index.streams.get(ref.topic)
    if stream is None or not 0 <= ref.index < len(stream.log_ns):
        raise LogFormatError(f"{log.path}: no message {ref.index} on topic {ref.topic}", log.path)
    raw = log.raw(
        ref.topic, ref.index, int(stream.log_ns[ref.index]), int(stream.ordinal[ref.index])
    )
    return log, index, stream, raw


def read_ref_sweep(ref: MessageRef, source_root: Path, min_range_m: float) -> np.ndarray:
    """(N, 5) float32 x y z intensity ring of a referenced sweep, LiDAR frame, no-returns and
    returns nearer than ``min_range_m`` dropped."""
    from storage.sources.log.pointcloud import Field, decode_pointcloud2
    from storage.sources.log.positions import pointcloud2_of

    log, index, stream, raw = _message(ref, source_root)
    msg = pointcloud2_of(raw, log.ros1)
    cloud = decode_pointcloud2(
        [Field(*f) for f in msg.fields], msg.data, height=msg.height, width=msg.width,
        point_step=msg.point_step, row_step=msg.row_step, is_bigendian=msg.is_bigendian,
        stamp_ns=msg.stamp_ns, min_range_m=min_range_m,
    )  # fmt: skip
    out = np.empty((len(cloud.points), 5), dtype=np.float32)
    out[:, :3], out[:, 3], out[:, 4] = cloud.points, cloud.intensity, cloud.ring
    return out


def image_suffix(ref: MessageRef, source_root: Path) -> str:
    """The suffix :func:`ref_image` gives the image (".jpg" / ".png"), without decoding it: what
    the Occ3D export's ``img_path`` names, so it matches the nuScenes export's file."""
    from storage.sources.log.index import COMPRESSED_IMAGE
    from storage.sources.log.reader import _strip_transport, camera_namespace

    log, index, stream, raw = _message(ref, source_root)
    info = index.camera_info.get(camera_namespace(ref.topic) + "/camera_info")
    rectified = "rect" in _strip_transport(ref.topic).rsplit("/", 1)[-1]
    needs = not rectified and info is not None and info.needs_rectifying()
    if stream.msgtype != COMPRESSED_IMAGE or needs:
        return ".png"  # decoded (and rectified) here, written as PNG
    fmt = str(log.deserialize(bytes(raw), stream.msgtype, ref.topic).format).lower()
    return ".png" if "png" in fmt else ".jpg"


def ref_image(ref: MessageRef, source_root: Path) -> tuple[bytes, str]:
    """(file bytes, suffix) of a referenced camera image, in the pinhole the pipeline used."""
    from io import BytesIO

    from PIL import Image

    from storage.sources.log.images import Rectifier, decode_compressed, decode_raw
    from storage.sources.log.index import COMPRESSED_IMAGE
    from storage.sources.log.reader import _strip_transport, camera_namespace

    log, index, stream, raw = _message(ref, source_root)
    msg = log.deserialize(bytes(raw), stream.msgtype, ref.topic)
    info = index.camera_info.get(camera_namespace(ref.topic) + "/camera_info")
    rectified = "rect" in _strip_transport(ref.topic).rsplit("/", 1)[-1]
    needs = not rectified and info is not None and info.needs_rectifying()
    if stream.msgtype == COMPRESSED_IMAGE and not needs:
        fmt = str(msg.format).lower()
        return bytes(msg.data), ".png" if "png" in fmt else ".jpg"
    if stream.msgtype == COMPRESSED_IMAGE:
        rgb = decode_compressed(str(msg.format), msg.data)
    else:
        rgb = decode_raw(str(msg.encoding), int(msg.height), int(msg.width), int(msg.step),
                         msg.data, bool(msg.is_bigendian))  # fmt: skip
    if needs:
        rgb = Rectifier(info)(rgb)
    buf = BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG", compress_level=6)
    return buf.getvalue(), ".png"
