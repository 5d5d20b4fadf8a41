"""Files of the ``precomputed`` perception provider: readers, writers, validation.

The layout of one sequence's directory is documented field by field in
``storage/PERCEPTION_FORMAT.md``. Readers return plain dicts whose keys are the fields of
``tasks.perception.types.ImagePerception`` / ``LidarDetections`` (storage does not import tasks
beyond conventions): ``ImagePerception(**reader.image(i))``. Writers take any object with those
attributes. Every problem raises :class:`PerceptionFileError` naming the file, the frame and the
value.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from storage.atomic import atomic_write_text, staged_folder
from tasks.conventions import CITYSCAPES_IGNORE

FORMAT_NAME = "mobileocc-perception"
FORMAT_VERSION = 1
META_FILE = "perception.json"
DETECTIONS_FILE = "detections.parquet"
LIDAR_FILE = "lidar_boxes.parquet"
SEMANTIC_DIR = "semantic"
NUM_KEYPOINTS = 17

DETECTION_SCHEMA = pa.schema(
    [
        ("frame", pa.int64()),
        ("bbox", pa.list_(pa.float32(), 4)),
        ("score", pa.float32()),
        ("keypoints", pa.list_(pa.float32(), 3 * NUM_KEYPOINTS)),
        ("mask_counts", pa.string()),
    ]
)
LIDAR_SCHEMA = pa.schema(
    [("frame", pa.int64())]
    + [
        (name, pa.float32())
        for name in (
            "center_x",
            "center_y",
            "center_z",
            "length",
            "width",
            "height",
            "yaw",
            "score",
        )
    ]
)


class PerceptionFileError(ValueError):
    """A precomputed perception file is missing, malformed or inconsistent."""


# --- COCO run-length encoding (column-major), our own numpy implementation -------------------


def rle_encode(mask: np.ndarray) -> np.ndarray:
    """COCO uncompressed RLE counts of a (H, W) bool mask.

    Runs alternate 0, 1, 0, ... over the pixels in column-major order (down each column, then the
    next column), starting with a (possibly empty) run of zeros. Returns (R,) int64.
    """
    flat = np.asarray(mask, bool).ravel(order="F")
    if flat.size == 0:
        return np.zeros(0, np.int64)
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    counts = np.diff(np.concatenate([[0], change, [flat.size]]))
    if flat[0]:
        counts = np.concatenate([[0], counts])
    return counts.astype(np.int64)


def rle_decode(counts: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) bool mask from COCO uncompressed RLE counts (column-major); raises on a bad sum."""
    counts = np.asarray(counts, np.int64)
    if (counts < 0).any() or int(counts.sum()) != height * width:
        raise ValueError(
            f"RLE counts sum to {int(counts.sum())}, expected {height} x {width} = {height * width}"
        )
    values = np.arange(counts.size) % 2 == 1
    flat = np.repeat(values, counts)
    return flat.reshape((width, height)).T.copy()


def rle_to_string(counts: np.ndarray) -> str:
    """COCO compressed RLE string (the ``counts`` string of pycocotools' ``encode``).

    Each count (after the first two, minus the count two places back) is written as 5-bit groups,
    least significant first, in characters offset by 48; bit 0x20 marks "more groups follow".
    """
    out = []
    counts = [int(c) for c in np.asarray(counts, np.int64)]
    for i, count in enumerate(counts):
        x = count - counts[i - 2] if i > 2 else count
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = (x != -1) if (c & 0x10) else (x != 0)
            if more:
                c |= 0x20
            out.append(chr(c + 48))
    return "".join(out)


def rle_from_string(text: str) -> np.ndarray:
    """Counts (R,) int64 from a COCO compressed RLE string (inverse of :func:`rle_to_string`)."""
    counts: list[int] = []
    pos = 0
    while pos < len(text):
        x, shift, more = 0, 0, True
        while more:
            if pos >= len(text):
                raise ValueError(f"RLE string ends inside a number at character {pos}")
            c = ord(text[pos]) - 48
            if not 0 <= c < 64:
                raise ValueError(f"RLE string has an invalid character {text[pos]!r} at {pos}")
            x |= (c & 0x1F) << (5 * shift)
            more = bool(c & 0x20)
            pos += 1
            shift += 1
            if not more and (c & 0x10):
                x |= -1 << (5 * shift)
        if len(counts) > 2:
            x += counts[-2]
        counts.append(x)
    return np.asarray(counts, np.int64)


# --- writing ------------------------------------------------------------------------------------


def write_perception(
    root: str | os.PathLike,
    image_width: int,
    image_height: int,
    images: Iterable[tuple[int, Any]],
    lidar: Iterable[tuple[int, Any]] | None = None,
) -> Path:
    """Write one sequence's perception files; the directory appears complete or not at all.

    images: (frame_index, ImagePerception-like) pairs, every frame of the sequence (a frame with no
    detections is still listed). lidar: (frame_index, LidarDetections-like) pairs or None.
    Boxes are stored COCO-style (x, y, w, h), keypoints as 17 x (u, v, confidence) flattened,
    masks as COCO compressed RLE, semantics as one 8-bit PNG per frame.
    """
    root = Path(root)
    with staged_folder(root) as tmp:
        _write_perception(tmp, root, image_width, image_height, images, lidar)
    return root


def _write_perception(tmp: Path, root: Path, image_width, image_height, images, lidar) -> None:
    (tmp / SEMANTIC_DIR).mkdir()
    columns: dict[str, list] = {name: [] for name in DETECTION_SCHEMA.names}
    frames: list[int] = []
    for frame, det in images:
        frame = int(frame)
        if frames and frame <= frames[-1]:
            raise PerceptionFileError(
                f"{root}: frames must be written in increasing order, got {frame} after {frames[-1]}"
            )
        frames.append(frame)
        semantic = np.asarray(det.semantic)
        if semantic.shape != (image_height, image_width) or semantic.dtype != np.uint8:
            raise PerceptionFileError(
                f"{root}: frame {frame}: semantic is {semantic.shape} {semantic.dtype}, expected "
                f"({image_height}, {image_width}) uint8"
            )
        Image.fromarray(semantic, mode="L").save(tmp / SEMANTIC_DIR / f"{frame:06d}.png")
        boxes = np.asarray(det.boxes_xyxy, np.float32).reshape(-1, 4)
        for d in range(boxes.shape[0]):
            x0, y0, x1, y1 = boxes[d]
            mask = np.asarray(det.masks[d], bool)
            columns["frame"].append(frame)
            columns["bbox"].append([x0, y0, x1 - x0, y1 - y0])
            columns["score"].append(float(det.scores[d]))
            columns["keypoints"].append(
                np.asarray(det.keypoints[d], np.float32).reshape(-1).tolist()
            )
            columns["mask_counts"].append(rle_to_string(rle_encode(mask)) if mask.any() else "")
    pq.write_table(pa.table(columns, schema=DETECTION_SCHEMA), tmp / DETECTIONS_FILE)
    has_lidar = lidar is not None
    if has_lidar:
        rows: dict[str, list] = {name: [] for name in LIDAR_SCHEMA.names}
        for frame, boxes3d in lidar:
            for m in range(len(boxes3d.scores)):
                rows["frame"].append(int(frame))
                for name, value in zip(LIDAR_SCHEMA.names[1:4], boxes3d.centers[m]):
                    rows[name].append(float(value))
                for name, value in zip(LIDAR_SCHEMA.names[4:7], boxes3d.sizes[m]):
                    rows[name].append(float(value))
                rows["yaw"].append(float(boxes3d.yaws[m]))
                rows["score"].append(float(boxes3d.scores[m]))
        pq.write_table(pa.table(rows, schema=LIDAR_SCHEMA), tmp / LIDAR_FILE)
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "image_width": int(image_width),
        "image_height": int(image_height),
        "frames": frames,
        "semantic": True,
        "lidar": has_lidar,
    }
    atomic_write_text(tmp / META_FILE, json.dumps(meta, indent=1))


# --- reading ------------------------------------------------------------------------------------


def _fail(path: Path, frame: int | None, message: str) -> PerceptionFileError:
    where = f"{path}" + (f": frame {frame}" if frame is not None else "")
    return PerceptionFileError(f"{where}: {message}")


def _read_table(path: Path, schema: pa.Schema) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise _fail(path, None, "file is missing")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as error:
        raise _fail(path, None, f"not a readable Parquet file ({error})") from error
    missing = [name for name in schema.names if name not in table.column_names]
    if missing:
        raise _fail(path, None, f"missing columns {missing}; expected {schema.names}")
    out = {}
    for field in schema:
        column = table.column(field.name)
        if pa.types.is_fixed_size_list(field.type) or pa.types.is_list(field.type):
            size = field.type.list_size
            values = column.to_pylist()
            bad = [i for i, item in enumerate(values) if item is None or len(item) != size]
            if bad:
                raise _fail(
                    path, None, f"row {bad[0]}: column {field.name!r} must hold {size} numbers"
                )
            out[field.name] = np.asarray(values, np.float64).reshape(len(values), size)
        elif field.name == "mask_counts":
            out[field.name] = np.asarray([s or "" for s in column.to_pylist()], dtype=object)
        else:
            values = column.to_numpy(zero_copy_only=False)
            out[field.name] = np.asarray(values, np.int64 if field.name == "frame" else np.float64)
    return out


class PrecomputedPerception:
    """Reader of one sequence's precomputed perception (the ``precomputed`` provider).

    Opening validates the metadata and the tables (shapes, NaN, ranges, frame keys, image size);
    masks and semantic PNGs are validated when their frame is read.
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        meta_path = self.root / META_FILE
        if not meta_path.is_file():
            raise _fail(
                meta_path, None, "file is missing (not a precomputed perception directory?)"
            )
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as error:
            raise _fail(meta_path, None, f"invalid JSON ({error})") from error
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            raise _fail(meta_path, None, f"'format' must be {FORMAT_NAME!r}")
        if meta.get("version") != FORMAT_VERSION:
            version = meta.get("version")
            raise _fail(
                meta_path, None, f"version {version!r} unsupported, expected {FORMAT_VERSION}"
            )
        for key in ("image_width", "image_height"):
            if not isinstance(meta.get(key), int) or meta[key] <= 0:
                raise _fail(
                    meta_path, None, f"{key} must be a positive integer, got {meta.get(key)!r}"
                )
        frames = meta.get("frames")
        if not isinstance(frames, list) or not all(isinstance(f, int) and f >= 0 for f in frames):
            raise _fail(meta_path, None, "'frames' must be a list of non-negative integers")
        if len(set(frames)) != len(frames):
            raise _fail(meta_path, None, "'frames' has duplicates")
        self.width, self.height = meta["image_width"], meta["image_height"]
        self.frames = tuple(frames)
        self.has_semantic = bool(meta.get("semantic", False))
        self.has_lidar = bool(meta.get("lidar", False))
        self._detections = self._load_detections(self.root / DETECTIONS_FILE)
        self._lidar = self._load_lidar(self.root / LIDAR_FILE) if self.has_lidar else None

    def _check_frames(self, path: Path, frame_column: np.ndarray) -> None:
        unknown = np.setdiff1d(frame_column, np.asarray(self.frames, np.int64))
        if unknown.size:
            raise _fail(path, int(unknown[0]), f"frame key not listed in {META_FILE} 'frames'")

    def _load_detections(self, path: Path) -> dict[str, np.ndarray]:
        table = _read_table(path, DETECTION_SCHEMA)
        self._check_frames(path, table["frame"])
        frame = table["frame"]
        for name in ("bbox", "score", "keypoints"):
            values = table[name] if table[name].ndim == 2 else table[name][:, None]
            bad = ~np.isfinite(values).all(axis=1)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise _fail(
                    path, int(frame[i]), f"row {i}: {name} has NaN/inf: {table[name][i].tolist()}"
                )
        bbox, tol = table["bbox"], 1.0
        bad = (bbox[:, 2] <= 0) | (bbox[:, 3] <= 0) | (bbox[:, 0] < -tol) | (bbox[:, 1] < -tol)
        bad |= (bbox[:, 0] + bbox[:, 2] > self.width + tol) | (
            bbox[:, 1] + bbox[:, 3] > self.height + tol
        )
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise _fail(
                path,
                int(frame[i]),
                f"row {i}: bbox [x, y, w, h] = {bbox[i].tolist()} must have w, h > 0 and lie in the "
                f"{self.width} x {self.height} image",
            )
        bad = (table["score"] < 0) | (table["score"] > 1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise _fail(path, int(frame[i]), f"row {i}: score {table['score'][i]} outside [0, 1]")
        conf = table["keypoints"].reshape(-1, NUM_KEYPOINTS, 3)[:, :, 2]
        bad = ((conf < 0) | (conf > 1)).any(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            message = f"row {i}: keypoint confidences {conf[i].tolist()} outside [0, 1]"
            raise _fail(path, int(frame[i]), message)
        return table

    def _load_lidar(self, path: Path) -> dict[str, np.ndarray]:
        table = _read_table(path, LIDAR_SCHEMA)
        self._check_frames(path, table["frame"])
        names = LIDAR_SCHEMA.names[1:]
        values = np.stack([table[name] for name in names], axis=1).reshape(-1, len(names))
        bad = ~np.isfinite(values).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            message = f"row {i}: NaN/inf in {dict(zip(names, values[i].tolist()))}"
            raise _fail(path, int(table["frame"][i]), message)
        bad = (values[:, 3:6] <= 0).any(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            message = f"row {i}: box size (l, w, h) = {values[i, 3:6].tolist()} must be > 0"
            raise _fail(path, int(table["frame"][i]), message)
        bad = (values[:, 7] < 0) | (values[:, 7] > 1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise _fail(
                path, int(table["frame"][i]), f"row {i}: score {values[i, 7]} outside [0, 1]"
            )
        return table

    def _require_frame(self, frame_index: int) -> None:
        if frame_index not in self.frames:
            raise _fail(
                self.root / META_FILE, frame_index, "frame not in this sequence's perception files"
            )

    def semantic(self, frame_index: int) -> np.ndarray:
        """(H, W) uint8 Cityscapes train ids of a frame (all 255 when the files have none)."""
        self._require_frame(frame_index)
        if not self.has_semantic:
            return np.full((self.height, self.width), CITYSCAPES_IGNORE, np.uint8)
        path = self.root / SEMANTIC_DIR / f"{frame_index:06d}.png"
        if not path.is_file():
            raise _fail(path, frame_index, "semantic PNG is missing")
        try:
            with Image.open(path) as image:
                mode = image.mode
                semantic = np.asarray(image)
        except OSError as error:
            raise _fail(path, frame_index, f"not a readable PNG ({error})") from error
        if mode != "L" or semantic.dtype != np.uint8:
            raise _fail(
                path, frame_index, f"PNG mode {mode!r}, expected 8-bit grayscale 'L' of train ids"
            )
        if semantic.shape != (self.height, self.width):
            got = f"{semantic.shape[1]} x {semantic.shape[0]}"
            raise _fail(path, frame_index, f"image is {got}, expected {self.width} x {self.height}")
        bad = (semantic > 18) & (semantic != CITYSCAPES_IGNORE)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            message = (
                f"pixel (u={c}, v={r}) = {semantic[r, c]}: not a Cityscapes train id (0-18 or 255)"
            )
            raise _fail(path, frame_index, message)
        return semantic

    def image(self, frame_index: int) -> dict[str, np.ndarray]:
        """A frame's 2D perception as the fields of ImagePerception (see the module docstring)."""
        self._require_frame(frame_index)
        table, path = self._detections, self.root / DETECTIONS_FILE
        rows = np.flatnonzero(table["frame"] == frame_index)
        bbox = table["bbox"][rows]
        masks = np.zeros((rows.size, self.height, self.width), bool)
        for k, row in enumerate(rows):
            text = table["mask_counts"][row]
            if not text:
                continue
            try:
                masks[k] = rle_decode(rle_from_string(text), self.height, self.width)
            except ValueError as error:
                raise _fail(path, frame_index, f"row {row}: mask_counts: {error}") from error
        return {
            "boxes_xyxy": np.concatenate([bbox[:, :2], bbox[:, :2] + bbox[:, 2:]], axis=1).astype(
                np.float32
            ),
            "scores": table["score"][rows].astype(np.float32),
            "keypoints": table["keypoints"][rows].reshape(-1, NUM_KEYPOINTS, 3).astype(np.float32),
            "masks": masks,
            "semantic": self.semantic(frame_index),
        }

    def lidar(self, frame_index: int) -> dict[str, np.ndarray]:
        """A frame's LiDAR boxes as the fields of LidarDetections (empty when the files have none)."""
        self._require_frame(frame_index)
        if self._lidar is None:
            return {
                "centers": np.zeros((0, 3), np.float32),
                "sizes": np.zeros((0, 3), np.float32),
                "yaws": np.zeros(0, np.float32),
                "scores": np.zeros(0, np.float32),
            }
        t = self._lidar
        rows = np.flatnonzero(t["frame"] == frame_index)

        def stack(names: tuple[str, ...]) -> np.ndarray:
            return (
                np.stack([t[n][rows] for n in names], axis=1)
                .astype(np.float32)
                .reshape(-1, len(names))
            )

        return {
            "centers": stack(("center_x", "center_y", "center_z")),
            "sizes": stack(("length", "width", "height")),
            "yaws": t["yaw"][rows].astype(np.float32),
            "scores": t["score"][rows].astype(np.float32),
        }
