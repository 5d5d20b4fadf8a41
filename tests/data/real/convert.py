"""Convert the real frames under tests/data/real/ from their public originals into ROS 2 MCAP logs.

Each log is written with ``rosbags`` alone (not the project's own log writer, so the reader is
tested against bytes it did not produce): ``sensor_msgs/PointCloud2`` (x, y, z, intensity
float32, unorganised), ``sensor_msgs/CompressedImage`` (the original JPEG bytes where the source
is a JPEG, else the PNG re-encoded as JPEG, quality 92), ``sensor_msgs/CameraInfo`` (the raw,
distorted camera: K, plumb_bob D, R = I, P = [K | 0]), and one ``/tf_static`` message with
base_link -> LiDAR -> the camera's optical frame. No poses: the project runs LiDAR odometry.

The base frame is not in the sources: it is put on the ground plane below the LiDAR, found in
the sweep itself (:func:`ground_plane`: a RANSAC plane through the points 3-25 m from the
sensor and below it; the base's z axis is the plane's normal, its x axis the LiDAR's x axis
projected onto the plane, its origin the LiDAR's foot on the plane). PROVENANCE.md of each log
gives the height and tilt found.

Reproduce the committed files (the sources are read from git snapshots of their repositories at
the commits given in SOURCES; fetch them with ``git clone`` + ``git checkout COMMIT``)::

    python tests/data/real/convert.py --repo PJLab-ADG/SensorsCalibration=/path/to/clone \\
        --out tests/data/real

The bytes depend only on the inputs (fixed stamps, seeded RANSAC).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

import numpy as np

#: the first log's first stamp (2024-01-01 00:00:00 UTC; the sources carry no usable time); log i
#: starts i hours later, so that no two logs overlap in time (exports order scenes by time)
START_NS = 1_704_067_200_000_000_000
HOUR_NS = 3_600_000_000_000


@dataclass(frozen=True)
class Source:
    """One log: where its files come from and how its rig is named."""

    name: str
    repo: str
    commit: str
    licence: str
    pcds: tuple[str, ...]
    images: tuple[str, ...]
    calib: str
    lidar_topic: str
    lidar_frame: str
    camera_ns: str
    notes: str = ""
    #: "calibanything": calib.txt with K, D, T; "acfr": a camera_info.yaml (``camera_info``) and
    #: the per-sample extrinsics CSV of acfr/cam_lidar_calibration (``calib``)
    calib_kind: str = "calibanything"
    camera_info: str = ""
    licence_note: str = ""
    licence_file: str = "LICENSE"


SOURCES = (
    Source(
        name="sc_street",
        repo="PJLab-ADG/SensorsCalibration",
        commit="7fe8d46caac040cbcd89cc65e79e5519df01bcd4",
        licence="Apache-2.0",
        pcds=("lidar2camera/auto_calib_v2.0/data/ours/3/calib.pcd",),
        images=("lidar2camera/auto_calib_v2.0/data/ours/3/calib.png",),
        calib="lidar2camera/auto_calib_v2.0/data/ours/3/calib.txt",
        lidar_topic="/hesai/pandar",
        lidar_frame="hesai_lidar",
        camera_ns="/camera/front",
        notes="a street crossing, empty of people; 1920 x 1200 raw (distorted) image",
    ),
    Source(
        name="sc_road",
        repo="PJLab-ADG/SensorsCalibration",
        commit="7fe8d46caac040cbcd89cc65e79e5519df01bcd4",
        licence="Apache-2.0",
        pcds=("lidar2camera/auto_calib_v2.0/data/ours/1/calib.pcd",),
        images=("lidar2camera/auto_calib_v2.0/data/ours/1/calib.jpg",),
        calib="lidar2camera/auto_calib_v2.0/data/ours/1/calib.txt",
        lidar_topic="/hesai/pandar",
        lidar_frame="hesai_lidar",
        camera_ns="/camera/front",
        notes="a road with a truck and a car ahead; 1920 x 1200 raw (distorted) JPEG",
    ),
    Source(
        name="acfr_lab",
        repo="acfr/cam_lidar_calibration",
        commit="65c40c7fc9d4a74907fad2bd295b40922bb7799c",
        licence="BSD (package.xml at this commit); the repository is Apache-2.0 since db09cd8",
        pcds=("data/vlp/pcd/pose2_full.pcd",),
        images=("data/vlp/images/pose2.png",),
        calib="data/vlp/calibration_quickstart.csv",
        camera_info="cfg/camera_info.yaml",
        calib_kind="acfr",
        lidar_topic="/velodyne_points",
        lidar_frame="velodyne",
        camera_ns="/sekonix_camera/port_a_cam_1",
        notes=(
            "a lab with a chessboard on a tripod and a person standing about 4 m ahead-right of a "
            "static VLP-16 + fisheye camera rig; 1920 x 1208 raw fisheye image"
        ),
        licence_note=(
            "The .pcd and the camera_info.yaml are read at commit 65c40c7 (2021-03-11), whose "
            "package.xml declares `<license>BSD</license>` (no licence text or copyright line in "
            "the repository then); the .pcd files were removed in 7297bd8. The repository added an "
            "Apache-2.0 LICENCE in db09cd8 (2024-02-02); the image and the calibration CSV are "
            "byte-identical at its HEAD ecda574 under that licence"
        ),
        licence_file="LICENCE",
    ),
)


# -- reading the originals ---------------------------------------------------------------------
def git_blob(clone: Path, commit: str, path: str) -> bytes:
    """The bytes of ``path`` at ``commit`` in the git repository ``clone`` (work tree or bare)."""
    return subprocess.run(
        ["git", "-C", str(clone), "show", f"{commit}:{path}"], check=True, capture_output=True
    ).stdout


def lzf_decompress(data: bytes, size: int) -> bytes:
    """LZF (liblzf) decompression, as PCL writes ``binary_compressed`` PCD files."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            out += data[i : i + ctrl + 1]
            i += ctrl + 1
            continue
        length = ctrl >> 5
        ref = len(out) - ((ctrl & 0x1F) << 8) - 1
        if length == 7:
            length += data[i]
            i += 1
        ref -= data[i]
        i += 1
        if ref < 0:
            raise ValueError(f"LZF back reference before the start at input byte {i}")
        for k in range(length + 2):  # may overlap itself: byte by byte
            out.append(out[ref + k])
    if len(out) != size:
        raise ValueError(f"LZF: {len(out)} bytes decompressed, the header says {size}")
    return bytes(out)


def read_pcd(raw: bytes, what: str) -> dict[str, np.ndarray]:
    """Fields of a PCD file (ascii, binary or binary_compressed), each (N,) in its own type."""
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.index(b"\n", pos)
        line = raw[pos:end].decode("ascii").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    names, sizes, types = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(names))
    n = int(header["POINTS"][0])
    kinds = {"F": "f", "U": "u", "I": "i"}
    dtypes = [np.dtype(f"<{kinds[t]}{s}") for t, s in zip(types, sizes, strict=True)]
    if any(c != "1" for c in counts):
        raise ValueError(f"{what}: COUNT {counts}: only scalar fields are read")
    mode = header["DATA"][0]
    if mode == "ascii":
        rows = np.loadtxt(BytesIO(raw[pos:]), dtype=np.float64, ndmin=2)[:n]
        return {nm: rows[:, j].astype(dt) for j, (nm, dt) in enumerate(zip(names, dtypes))}
    if mode == "binary":
        rec = np.dtype(list(zip(names, dtypes, strict=True)))
        arr = np.frombuffer(raw, rec, count=n, offset=pos)
        return {nm: np.ascontiguousarray(arr[nm]) for nm in names}
    if mode == "binary_compressed":
        csize, usize = np.frombuffer(raw, "<u4", count=2, offset=pos)
        body = lzf_decompress(raw[pos + 8 : pos + 8 + int(csize)], int(usize))
        out, off = {}, 0
        for nm, dt in zip(names, dtypes, strict=True):  # field after field (SoA)
            out[nm] = np.frombuffer(body, dt, count=n, offset=off).copy()
            off += n * dt.itemsize
        return out
    raise ValueError(f"{what}: DATA {mode!r}: expected ascii, binary or binary_compressed")


def euler_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), radians (ROS / tf convention)."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (np.cos, np.sin))
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def read_acfr_calib(csv: str, camera_info_yaml: str):
    """acfr/cam_lidar_calibration: ``camera_info.yaml`` (K, fisheye D, size) and a CSV of one
    extrinsic estimate per sample set (roll, pitch, yaw rad, x, y, z m): T_lidar_from_cam, the
    camera's pose in the LiDAR frame (its inverse puts the chessboard's returns behind the camera). The tool reports a filtered mean; the per-parameter median of the rows stands
    in for it. Returns K (3, 3), D (4,), model, T_cam_from_lidar (4, 4), (width, height)."""
    import yaml

    info = yaml.safe_load(camera_info_yaml)
    K = np.array(info["K"], np.float64).reshape(3, 3)
    D = np.array(info["D"], np.float64)
    model = {"fisheye": "equidistant"}.get(info["distortion_model"], info["distortion_model"])
    rows = np.loadtxt(BytesIO(csv.encode()), delimiter=",", skiprows=1, ndmin=2)
    r, p, y, *t = np.median(rows[:, :6], axis=0)
    T_lidar_from_cam = np.eye(4)
    T_lidar_from_cam[:3, :3], T_lidar_from_cam[:3, 3] = euler_zyx(r, p, y), t
    return K, D, model, np.linalg.inv(T_lidar_from_cam), (info["width"], info["height"])


def read_calib_txt(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CalibAnything's calib.txt: ``K:`` 9 values, ``D:`` 4 or 5 (OpenCV k1 k2 p1 p2 [k3]),
    ``T:`` 12 (the top 3 x 4 rows of T_cam_from_lidar). Returns K (3, 3), D (5,), T (4, 4)."""
    vals = {}
    for line in text.splitlines():
        if ":" in line:
            key, rest = line.split(":", 1)
            vals[key.strip()] = np.array(rest.split(), dtype=np.float64)
    K = vals["K"].reshape(3, 3)
    D = np.pad(vals["D"], (0, 5 - len(vals["D"])))
    T = np.eye(4)
    T[:3, :] = vals["T"].reshape(3, 4)
    return K, D, T


# -- the base frame ----------------------------------------------------------------------------
def ground_plane(points: np.ndarray, seed: int = 0, iters: int = 400, tol_m: float = 0.08):
    """The ground under the LiDAR: a RANSAC plane through the points 3-25 m away horizontally
    and more than 0.5 m below the sensor, refined by least squares on its inliers.
    Returns (normal (3,) pointing up, d) with normal . p + d = 0 on the plane."""
    p = points.astype(np.float64)
    r = np.hypot(p[:, 0], p[:, 1])
    cand = p[(r > 3) & (r < 25) & (p[:, 2] < -0.5)]
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(iters):
        a, b, c = cand[rng.choice(len(cand), 3, replace=False)]
        nrm = np.cross(b - a, c - a)
        if np.linalg.norm(nrm) < 1e-9:
            continue
        nrm /= np.linalg.norm(nrm)
        if abs(nrm[2]) < 0.9:  # the ground is near level in the LiDAR frame
            continue
        inl = np.abs((cand - a) @ nrm) < tol_m
        if inl.sum() > best_n:
            best, best_n = inl, int(inl.sum())
    q = cand[best]
    centre = q.mean(axis=0)
    nrm = np.linalg.svd(q - centre)[2][-1]
    nrm = nrm if nrm[2] > 0 else -nrm
    return nrm, -float(nrm @ centre)


def base_from_lidar(normal: np.ndarray, d: float) -> np.ndarray:
    """T_base_from_lidar: base z = the ground normal, x = the LiDAR's x on the ground, origin the
    LiDAR's foot on the plane (so the LiDAR is at (0, 0, height) in the base frame)."""
    z = normal / np.linalg.norm(normal)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_lidar_from_base = np.c_[x, y, z]
    height = d  # the LiDAR origin lies `d` above the plane n.p + d = 0
    T = np.eye(4)
    T[:3, :3] = R_lidar_from_base.T
    T[:3, 3] = [0.0, 0.0, height]
    return T


# -- writing -----------------------------------------------------------------------------------
def quat_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method), w >= 0."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q = np.array(q)
    q = q if q[3] >= 0 else -q
    return tuple(float(v) for v in q / np.linalg.norm(q))


@dataclass(frozen=True)
class Frame:
    """One sweep and its image: points (N, 3) float32 and intensity (N,) float32 in the LiDAR
    frame, the encoded image (JPEG bytes), its stamp."""

    stamp_ns: int
    points: np.ndarray
    intensity: np.ndarray
    jpeg: bytes


def write_mcap(
    path: Path,
    src: Source,
    frames: list[Frame],
    K: np.ndarray,
    D: np.ndarray,
    size: tuple[int, int],
    T_cam_from_lidar: np.ndarray,
    T_base_from_lidar: np.ndarray,
    model: str = "plumb_bob",
    P: np.ndarray | None = None,
) -> Path:
    """A ROS 2 MCAP (zstd chunks) of ``frames`` with /tf_static and the camera's CameraInfo."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    optical = src.camera_ns.strip("/").replace("/", "_") + "_optical_frame"

    def header(stamp, frame_id):
        t = T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        return T["std_msgs/msg/Header"](stamp=t, frame_id=frame_id)

    def transform(stamp, parent, child, M):
        x, y, z, w = quat_xyzw(M[:3, :3])
        t = M[:3, 3]
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
            ),
        )  # fmt: skip

    tmp = path.parent / f".{path.stem}.convert"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    writer = Writer(tmp / path.stem, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    conns = {}

    def put(topic, msgtype, msg, stamp):
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        writer.write(conns[topic], stamp, ts.serialize_cdr(msg, msgtype))

    t0 = frames[0].stamp_ns
    T_lidar_from_cam = np.linalg.inv(T_cam_from_lidar)
    tf = T["tf2_msgs/msg/TFMessage"](
        transforms=[
            transform(t0, "base_link", src.lidar_frame, T_base_from_lidar),
            transform(t0, src.lidar_frame, optical, T_lidar_from_cam),
        ]
    )
    put("/tf_static", "tf2_msgs/msg/TFMessage", tf, t0)
    PF = T["sensor_msgs/msg/PointField"]
    names = ("x", "y", "z", "intensity")  # FLOAT32 (datatype 7), 16-byte records
    fields = [PF(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(names)]
    w, h = size
    for fr in frames:
        rec = np.empty((len(fr.points), 4), "<f4")
        rec[:, :3], rec[:, 3] = fr.points, fr.intensity
        cloud = T["sensor_msgs/msg/PointCloud2"](
            header=header(fr.stamp_ns, src.lidar_frame),
            height=1,
            width=len(rec),
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * len(rec),
            data=np.frombuffer(rec.tobytes(), np.uint8),
            is_dense=True,
        )
        put(src.lidar_topic, "sensor_msgs/msg/PointCloud2", cloud, fr.stamp_ns)
        img = T["sensor_msgs/msg/CompressedImage"](
            header=header(fr.stamp_ns, optical),
            format="jpeg",
            data=np.frombuffer(fr.jpeg, np.uint8),
        )
        put(
            src.camera_ns + "/image_raw/compressed",
            "sensor_msgs/msg/CompressedImage",
            img,
            fr.stamp_ns,
        )
        info = T["sensor_msgs/msg/CameraInfo"](
            header=header(fr.stamp_ns, optical),
            height=h,
            width=w,
            distortion_model=model,
            d=np.asarray(D, np.float64),
            k=np.asarray(K, np.float64).reshape(-1),
            r=np.eye(3).reshape(-1),
            p=(np.c_[K, np.zeros(3)] if P is None else P).reshape(-1),
            binning_x=0,
            binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        )
        put(src.camera_ns + "/camera_info", "sensor_msgs/msg/CameraInfo", info, fr.stamp_ns)
    writer.close()
    path.parent.mkdir(parents=True, exist_ok=True)
    (tmp / path.stem / f"{path.stem}.mcap").replace(path)
    shutil.rmtree(tmp)
    return path


def to_jpeg(raw: bytes, name: str) -> tuple[bytes, tuple[int, int], str]:
    """JPEG bytes of an image file (kept as they are when already a JPEG), its size, and what
    was done to it."""
    from PIL import Image

    with Image.open(BytesIO(raw)) as im:
        size = im.size
        if im.format == "JPEG":
            return raw, size, f"{name}: the original JPEG bytes"
        buf = BytesIO()
        im.convert("RGB").save(buf, format="JPEG", quality=92)
    return buf.getvalue(), size, f"{name}: {im.format} re-encoded as JPEG (quality 92)"


def convert(src: Source, clone: Path, out_dir: Path, start_ns: int) -> dict:
    """Write ``out_dir/src.name/src.name.mcap``; returns the facts PROVENANCE.md records."""
    calib = git_blob(clone, src.commit, src.calib).decode()
    if src.calib_kind == "acfr":
        info = git_blob(clone, src.commit, src.camera_info).decode()
        K, D, model, T_cam_from_lidar, _ = read_acfr_calib(calib, info)
    else:
        (K, D, T_cam_from_lidar), model = read_calib_txt(calib), "plumb_bob"
    P = None
    frames, changes, size = [], [], None
    for k, (pcd_path, img_path) in enumerate(zip(src.pcds, src.images, strict=True)):
        pcd = read_pcd(git_blob(clone, src.commit, pcd_path), pcd_path)
        pts = np.c_[pcd["x"], pcd["y"], pcd["z"]].astype(np.float32)
        keep = np.isfinite(pts).all(axis=1) & (np.abs(pts).sum(axis=1) > 0)
        jpeg, size, what = to_jpeg(git_blob(clone, src.commit, img_path), img_path)
        changes.append(what)
        changes.append(
            f"{pcd_path}: {len(pts)} points, {int((~keep).sum())} NaN / zero dropped; "
            "fields x, y, z, intensity kept as float32 ("
            + ", ".join(f for f in pcd if f not in ("x", "y", "z", "intensity"))
            + " dropped)"
        )
        frames.append(
            Frame(start_ns + k * 100_000_000, pts[keep], pcd["intensity"][keep].astype(np.float32), jpeg)
        )  # fmt: skip
    if model == "equidistant":  # P = [K | 0] would crop the fisheye's edges (the person)
        import cv2

        Kp = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            K, D.reshape(1, 4), size, np.eye(3), balance=1.0
        )
        P = np.c_[Kp, np.zeros(3)]
    normal, d = ground_plane(frames[0].points)
    T_base = base_from_lidar(normal, d)
    tilt = float(np.degrees(np.arccos(min(1.0, normal[2]))))
    path = write_mcap(
        out_dir / src.name / f"{src.name}.mcap",
        src, frames, K, D, size, T_cam_from_lidar, T_base, model, P,
    )  # fmt: skip
    return {
        "name": src.name,
        "repo": src.repo,
        "commit": src.commit,
        "licence": src.licence,
        "files": [
            *src.pcds,
            *src.images,
            src.calib,
            *([src.camera_info] if src.camera_info else []),
        ],
        "distortion_model": model,
        "P": None if P is None else [round(float(v), 3) for v in P[:, :3].ravel()],
        "changes": changes,
        "lidar_height_m": round(d, 3),
        "ground_tilt_deg": round(tilt, 2),
        "points": [int(len(f.points)) for f in frames],
        "image_size": list(size),
        "mcap_bytes": path.stat().st_size,
        "start_ns": start_ns,
    }


def write_provenance(path: Path, src: Source, facts: dict) -> None:
    """PROVENANCE.md of one log: source, licence and its notice, what was changed."""
    base = f"https://github.com/{src.repo}/blob/{src.commit}/"
    lines = [
        f"# {src.name}.mcap",
        "",
        f"{src.notes}.",
        "",
        f"- Source: https://github.com/{src.repo}, commit `{src.commit}`",
        *[f"  - [`{f}`]({base}{f})" for f in facts["files"]],
        f"- Licence: {src.licence} (a copy of the repository's {src.licence_file}: "
        f"`../LICENSE-{src.repo.split('/')[1]}`). No NOTICE file in the source repository."
        + (f" {src.licence_note}." if src.licence_note else ""),
        f"- Converted by `tests/data/real/convert.py` (this repository) into a ROS 2 MCAP "
        f"(zstd chunks): `{src.lidar_topic}` PointCloud2 (frame `{src.lidar_frame}`), "
        f"`{src.camera_ns}/image_raw/compressed` CompressedImage, `{src.camera_ns}/camera_info` "
        f"CameraInfo (the raw camera: K and {facts['distortion_model']} D, R = I, "
        + (
            "P = [K | 0]), "
            if facts["P"] is None
            else "P = [K' | 0] with K' from OpenCV's fisheye."
            "estimateNewCameraMatrixForUndistortRectify(K, D, size, I, balance=1): the whole "
            f"fisheye view in the rectified image, K' = {facts['P']}), "
        )
        + "`/tf_static` (base_link -> LiDAR -> camera optical frame). "
        + (
            "K, D and the LiDAR -> camera extrinsic T: the source's calib.txt (its reference "
            "values)."
            if src.calib_kind == "calibanything"
            else "K, D: camera_info.yaml; the extrinsic: the per-parameter median of the 50 "
            "estimates (roll, pitch, yaw, x, y, z: the camera's pose in the LiDAR frame) in "
            "calibration_quickstart.csv (the tool's own figure is a filtered mean)."
        )
        + " No poses.",
        "- Changed:",
        *[f"  - {c}" for c in facts["changes"]],
        f"  - stamps: the sources have none usable; sweep k is at {facts['start_ns']} + k * 100 ms",
        f"  - base_link (not in the source): on the ground plane found in the sweep (RANSAC, "
        f"convert.py `ground_plane`), {facts['lidar_height_m']} m below the LiDAR, its z axis "
        f"the plane normal ({facts['ground_tilt_deg']} deg from the LiDAR's z)",
        f"- Size: {facts['mcap_bytes']} bytes; points per sweep {facts['points']}; image "
        f"{facts['image_size'][0]} x {facts['image_size'][1]}",
        "",
        "Reproduce: `python tests/data/real/convert.py --repo "
        f"{src.repo}=/path/to/a/clone --only {src.name}` (the clone must hold the commit).",
        "",
    ]
    path.write_text("\n".join(lines))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--repo", action="append", default=[], metavar="OWNER/NAME=PATH",
        help="a local git clone (or bare git dir) of a source repository",
    )  # fmt: skip
    ap.add_argument("--out", type=Path, default=Path(__file__).parent)
    ap.add_argument("--only", nargs="*", help="log names to convert (default: all)")
    args = ap.parse_args(argv)
    clones = dict(r.split("=", 1) for r in args.repo)
    facts = []
    for i, src in enumerate(SOURCES):
        if args.only and src.name not in args.only:
            continue
        if src.repo not in clones:
            print(f"skipping {src.name}: no --repo {src.repo}=PATH", file=sys.stderr)
            continue
        facts.append(convert(src, Path(clones[src.repo]), args.out, START_NS + i * HOUR_NS))
        write_provenance(args.out / src.name / "PROVENANCE.md", src, facts[-1])
        print(json.dumps(facts[-1], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
