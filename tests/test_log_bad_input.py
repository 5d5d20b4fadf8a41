"""Bad robot logs, table-driven: one log of a 2-log dataset damaged at a time.

A clean run of two simulated MCAP logs (``0.mcap``, ``1.mcap``, gt/ beside) is shared. Each case
copies it (hard links: a damage replaces a file, never writes into one), damages log 1, runs
``mobileocc rebuild`` (in-process; when the log cannot even be opened nothing runs, so no Prefect
server) or, where a frame must be decoded, the same run without Prefect
(``flows.pipeline.units.run_units``), and asserts: exit code 1; the error names the file, the
topic and the stamp where there are some, and says what is wrong; log 1's earlier published data
are withdrawn; log 0's published bytes equal the clean run's.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from configs.schema import load_config
from flows import cli
from flows.pipeline.units import run_units, summary_table
from storage.manifest import Manifest
from tests.log_fixture import rewrite_log
from tests.oracle import oracle_yaml

pytestmark = [pytest.mark.slow]

CHEAP = {
    "fit.iterations": 2,
    "fit.min_points": 1000000,
    "dataset.max_range_m": 15.0,
    "map.voxel_size_m": 0.4,
    "map.freespace.voxel_size_m": 0.4,
    "map.freespace.max_range_m": 15.0,
    "fuse.grid.voxel_size_m": 0.4,
    "export.formats": [],
    "detect.max_failed_frame_share": 0.0,
}
LIDAR, CAM0, INFO0 = (
    "/ouster/points",
    "/stereo/left/image_rect_color/compressed",
    "/stereo/left/camera_info",
)


def _link_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link, symlinks=True)
    return dst


def _published(out: Path, seq: str) -> dict[str, bytes]:
    found = {}
    for base in [out / "occupancy" / seq, *(out / "tables").glob(f"*/sequence={seq}")]:
        for p in sorted(base.rglob("*")):
            if p.is_file():
                found[str(p.relative_to(out))] = p.read_bytes()
    return found


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    from flows.commands.simulate import simulate

    work = tmp_path_factory.mktemp("logs")
    data, out = work / "data", work / "out"
    simulate(data, 2, 4, seed=3, pedestrians=2, progress=False, fast=True, fmt="mcap")
    # log 1 again as a ROS 1 bag (the unindexed-bag case)
    simulate(work / "ros1", 1, 4, seed=3, pedestrians=2, progress=False, fast=True, fmt="ros1",
             first_id=1)  # fmt: skip
    config = work / "cheap.yaml"
    nested: dict = {}
    for key, value in CHEAP.items():
        *parents, leaf = key.split(".")
        node = nested
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    config.write_text(yaml.safe_dump(oracle_yaml(nested)))
    report = run_units(
        load_config(config, {"dataset.root": str(data), "output.root": str(out)}), progress=False
    )
    assert report.exit_code == 0, summary_table(report)
    published = {seq: _published(out, seq) for seq in ("0", "1")}
    assert published["0"] and published["1"]
    return SimpleNamespace(work=work, data=data, out=out, config=config, published=published)


# ---- damage ------------------------------------------------------------------------------------


def _cut(keep: float) -> Callable[[Path], Path]:
    def damage(path: Path) -> Path:
        data = path.read_bytes()
        path.unlink()
        path.write_bytes(data[: int(len(data) * keep)])
        return path

    return damage


def _unindexed_ros1(clean) -> Callable[[Path], Path]:
    """Log 1 as a ROS 1 bag whose header has no index position (a recording cut before
    ``rosbag record`` wrote its index)."""

    def damage(path: Path) -> Path:
        path.unlink()
        bag = path.with_suffix(".bag")
        data = bytearray((clean.work / "ros1" / "1.bag").read_bytes())
        at = data.index(b"index_pos=") + len(b"index_pos=")
        data[at : at + 8] = bytes(8)
        bag.write_bytes(bytes(data))
        return bag

    return damage


def _edit(edit, empty=()) -> Callable[[Path], Path]:
    def damage(path: Path) -> Path:
        tmp = path.with_name("rewritten.mcap")
        rewrite_log(path, tmp, edit, empty)
        os.replace(tmp, path)
        return path

    return damage


def _unknown_field_layout(topic, msgtype, msg, log_ns):
    if topic != LIDAR:
        return None
    fields = [dataclasses.replace(f, datatype=9) if f.name == "z" else f for f in msg.fields]
    return [(topic, msgtype, dataclasses.replace(msg, fields=fields), log_ns)]


def _unknown_image_encoding(topic, msgtype, msg, log_ns):
    if topic != CAM0:
        return None
    return [(topic, msgtype, dataclasses.replace(msg, format="h264"), log_ns)]


def _drop(name: str):
    return lambda topic, msgtype, msg, log_ns: [] if topic == name else None


def _tf_gap(topic, msgtype, msg, log_ns):
    if topic != "/tf_static":
        return None
    kept = [t for t in msg.transforms if t.child_frame_id != "stereo_left_optical_frame"]
    return [(topic, msgtype, dataclasses.replace(msg, transforms=kept), log_ns)]


def _stamps_backwards():
    seen = []

    def edit(topic, msgtype, msg, log_ns):
        if topic != LIDAR:
            return None
        seen.append(msg)
        if len(seen) != 3:
            return None
        # sweep 2 stamped 50 ms before sweep 1
        stamp = dataclasses.replace(seen[1].header.stamp)
        stamp = dataclasses.replace(stamp, nanosec=stamp.nanosec - 50_000_000)
        header = dataclasses.replace(msg.header, stamp=stamp)
        return [(topic, msgtype, dataclasses.replace(msg, header=header), log_ns)]

    return edit


def _static_edit(change):
    """An edit of the /tf_static message: ``change(transforms) -> transforms``."""

    def edit(topic, msgtype, msg, log_ns):
        if topic != "/tf_static":
            return None
        return [
            (topic, msgtype, dataclasses.replace(msg, transforms=change(msg.transforms)), log_ns)
        ]

    return edit


def _reparent(t, parent: str):
    return dataclasses.replace(t, header=dataclasses.replace(t.header, frame_id=parent))


def _cycle(ts):  # two extra frames, each the other's parent: rig_a -> rig_b -> rig_a
    a = _reparent(dataclasses.replace(ts[-1], child_frame_id="rig_a"), "rig_b")
    return [*ts, a, _reparent(dataclasses.replace(ts[-1], child_frame_id="rig_b"), "rig_a")]


def _two_parents(ts):
    return [*ts, _reparent(ts[-1], "somewhere_else")]


def _far_camera(ts):  # an os1 -> camera translation of 1e6 m
    def far(t):
        tr = t.transform
        moved = dataclasses.replace(tr.translation, x=1.0e6)
        return dataclasses.replace(t, transform=dataclasses.replace(tr, translation=moved))

    return [far(t) if t.child_frame_id == "stereo_left_optical_frame" else t for t in ts]


def _sweep_xyz(value: float, sweep: int = 2):
    """Sweep ``sweep``'s every x, y, z set to ``value`` (1e30 m, or 0: a sweep of no returns)."""
    seen = []

    def edit(topic, msgtype, msg, log_ns):
        if topic != LIDAR:
            return None
        seen.append(msg)
        if len(seen) != sweep + 1:
            return None
        records = np.frombuffer(bytearray(msg.data), np.uint8).reshape(-1, msg.point_step).copy()
        for f in msg.fields:
            if f.name in "xyz":
                records[:, f.offset : f.offset + 4] = np.full((len(records), 1), value, "<f4").view(
                    np.uint8
                )
        return [(topic, msgtype, dataclasses.replace(msg, data=records.reshape(-1)), log_ns)]

    return edit


def _pose_jump():
    """The robot's /tf pose 100 m away at the third stamp (a picked sweep's) (1 m/s elsewhere)."""
    seen = []

    def edit(topic, msgtype, msg, log_ns):
        if topic != "/tf":
            return None
        seen.append(msg)
        if len(seen) != 3:
            return None

        def far(t):
            tr = t.transform
            moved = dataclasses.replace(tr.translation, x=tr.translation.x + 100.0)
            return dataclasses.replace(t, transform=dataclasses.replace(tr, translation=moved))

        return [
            (
                topic,
                msgtype,
                dataclasses.replace(msg, transforms=[far(t) for t in msg.transforms]),
                log_ns,
            )
        ]

    return edit


def _overlapping_fields(topic, msgtype, msg, log_ns):
    if topic != LIDAR:
        return None
    fields = [dataclasses.replace(f, offset=2) if f.name == "y" else f for f in msg.fields]
    return [(topic, msgtype, dataclasses.replace(msg, fields=fields), log_ns)]


@dataclass(frozen=True)
class Case:
    name: str
    damage: Callable
    #: what the error must say, and the topic it must name ("" where no topic applies)
    says: str
    topic: str = ""
    #: the error names a stamp
    stamp: bool = True
    #: "plan": the log cannot be opened; "frame": a frame's message cannot be decoded
    level: str = "plan"
    #: the file the error names
    names: str = "1.mcap"


CASES = [
    Case("truncated log", _cut(0.6), "truncated", LIDAR),
    Case("unindexed ROS 1 bag", None, "rosbag reindex", "", stamp=False, names="1.bag"),
    Case(
        "unknown point field layout",
        _edit(_unknown_field_layout),
        "datatype 9",
        LIDAR,
        level="frame",
    ),  # fmt: skip
    Case(
        "unknown image encoding",
        _edit(_unknown_image_encoding),
        "format 'h264'",
        CAM0,
        level="frame",
    ),  # fmt: skip
    Case("missing CameraInfo", _edit(_drop(INFO0)), "no sensor_msgs/CameraInfo", INFO0),
    Case("TF chain with a gap", _edit(_tf_gap), "no TF path", "/tf_static"),
    Case("stamps going backwards", _edit(_stamps_backwards()), "go backwards", LIDAR),
    # issue 41: plausibility bounds (tasks/bounds.py)
    Case("a /tf_static cycle", _edit(_static_edit(_cycle)), "has a cycle", "/tf_static", False),
    Case(
        "a frame with two parents", _edit(_static_edit(_two_parents)), "two parents", "/tf_static"
    ),
    Case("a camera 1e6 m away", _edit(_static_edit(_far_camera)), "1e+06 m", "/tf_static", False),
    Case("a pose jump of 100 m", _edit(_pose_jump()), "m/s, more than 20 m/s", "/tf"),
    Case("a sweep at 1e30 m", _edit(_sweep_xyz(1e30)), "beyond 10000 m", LIDAR, level="frame"),
    Case("a sweep of zeros", _edit(_sweep_xyz(0.0)), "at (0, 0, 0)", LIDAR, level="frame"),
    Case(
        "overlapping point fields",
        _edit(_overlapping_fields),
        "overlaps field 'x'",
        LIDAR,
        level="frame",
    ),
    Case(
        "a topic with no messages",
        _edit(_drop(LIDAR), ((LIDAR, "sensor_msgs/msg/PointCloud2"),)),
        "has no messages",
        LIDAR,
        stamp=False,
    ),  # fmt: skip
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_a_bad_log_fails_its_sequence_alone(case: Case, clean, tmp_path, capsys):
    data, out = _link_copy(clean.data, tmp_path / "data"), _link_copy(clean.out, tmp_path / "out")
    damage = case.damage or _unindexed_ros1(clean)
    damage(data / "1.mcap")
    if case.level == "plan":  # through the command line: nothing to run, so no Prefect server
        code = cli.main(
            ["rebuild", "--config", str(clean.config), "--data", str(data), "--out", str(out),
             "--quiet"]
        )  # fmt: skip
        text = capsys.readouterr().out
    else:
        overrides = {"dataset.root": str(data), "output.root": str(out)}
        report = run_units(load_config(clean.config, overrides), progress=False)
        code, text = report.exit_code, summary_table(report)
    assert code == 1, text
    record = Manifest.load(out).get("1", "detect")
    assert record.status == "failed"
    for where in (record.error, text):
        assert case.names in where and case.says in where, (where, case)
        if case.topic:
            assert f"topic {case.topic}" in where, where
        if case.stamp:
            assert "stamp " in where or "log time " in where, where
    assert not (out / "occupancy" / "1").exists()  # withdrawn
    assert _published(out, "0") == clean.published["0"]
    print(f"\nCASE | {case.name} | {case.level} | exit {code} | {record.error[:200]}")
