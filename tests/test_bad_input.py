"""Bad input, table-driven: a fixture damaged in many ways, one sequence at a time.

One clean run of a 2-sequence synthetic dataset is shared. Each case copies it (hard links: a
damage replaces a file, never writes into one), damages sequence 1 (or adds a stray one), runs
``mobileocc rebuild`` (in-process; with nothing to run it starts no Prefect server) or, where
detect must run, the same run without Prefect (``flows.pipeline.units.run_units``), then ``mobileocc
status``, and asserts: the exit codes are 1; the manifest and the status output show the failure
with the file (and frame) named; the damaged sequence's earlier published data are withdrawn and
the sequences table marks it failed; sequence 0's published bytes equal the clean run's.

The clean run takes ``detect.max_failed_frame_share: 0``, so a bad frame fails its sequence here;
leaving a bad frame out while the rest goes on is tested on its own below, as are the edges of
the command line (``--data``, ``--out``, config numbers) and the run lock.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
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
from storage.tables import read_table
from tests.oracle import oracle_yaml

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
BAD = "1"
#: cheap settings: these tests are about what happens to bad input, not about the products
CHEAP = {
    "fit": {"iterations": 2, "min_points": 1000000},
    "dataset": {"max_range_m": 15.0},
    "map": {"voxel_size_m": 0.4, "freespace": {"voxel_size_m": 0.4, "max_range_m": 15.0}},
    "fuse": {"grid": {"voxel_size_m": 0.4}},
    "export": {"formats": []},
    "detect": {"max_failed_frame_share": 0.0},
}
BIN = "3d_comp/os1/1/3d_comp_os1_1_{}.bin"
CAM0 = "2d_rect/cam0/1/2d_rect_cam0_1_{}.jpg"
CALIB = "calibrations/1/{}.yaml"


def _link_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link, symlinks=True)
    return dst


def _published(out: Path, seq: str) -> dict[str, bytes]:
    """Every published byte of one sequence: its arrays and its table partitions."""
    found = {}
    for base in [out / "occupancy" / seq, *(out / "tables").glob(f"*/sequence={seq}")]:
        for p in sorted(base.rglob("*")):
            if p.is_file():
                found[str(p.relative_to(out))] = p.read_bytes()
    return found


@pytest.fixture(scope="module")
def clean(synthetic_root, tmp_path_factory):
    """The session's 2-sequence dataset (never written to: cases copy it) and one clean run."""
    data = synthetic_root
    work = tmp_path_factory.mktemp("clean")
    config = work / "faults.yaml"
    config.write_text(yaml.safe_dump(oracle_yaml(CHEAP)))
    out = work / "out"
    report = run_units(
        load_config(config, {"dataset.root": str(data), "output.root": str(out)}), progress=False
    )
    assert report.exit_code == 0, summary_table(report)
    published = {seq: _published(out, seq) for seq in ("0", "1")}
    assert published["0"] and published["1"]
    return SimpleNamespace(data=data, out=out, config=config, published=published)


# ---- damage ------------------------------------------------------------------------------------


def _put(path: Path, data: bytes | str) -> None:
    """Replace a file (never write into it: the dataset is a hard-linked copy)."""
    if os.path.lexists(path):
        path.unlink() if not path.is_dir() or path.is_symlink() else shutil.rmtree(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data if isinstance(data, bytes) else data.encode())


def _remove(path: Path) -> None:
    path.unlink()


def _fifo(path: Path) -> None:
    path.unlink()
    os.mkfifo(path)


def _symlink_loop(path: Path) -> None:
    path.unlink()
    os.symlink(path.name + ".loop", path)
    os.symlink(path.name, path.with_name(path.name + ".loop"))


def _symlink(target: str) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        path.unlink()
        os.symlink(target, path)

    return damage


def _directory(path: Path) -> None:
    path.unlink()
    path.mkdir()


def _cut(n: int | None = None, keep: float | None = None) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        data = path.read_bytes()
        _put(path, data[: n if n is not None else int(len(data) * keep)])

    return damage


def _nan_points(path: Path) -> None:
    raw = np.fromfile(path, dtype="<f4").copy()
    raw[100:110] = np.nan
    _put(path, raw.tobytes())


def _text(edit: Callable[[str], str]) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        _put(path, edit(path.read_text()))

    return damage


def _lines(edit: Callable[[list[list[str]]], None]) -> Callable[[Path], None]:
    """Edit a whitespace table (timestamps, poses) row by row."""

    def damage(path: Path) -> None:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
        edit(rows)
        _put(path, "".join(" ".join(r) + "\n" for r in rows))

    return damage


def _yaml(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        data = yaml.safe_load(path.read_text())
        edit(data)
        _put(path, yaml.safe_dump(data))

    return damage


def _matrix(key: str, change: Callable[[np.ndarray], np.ndarray]) -> Callable[[dict], None]:
    def edit(data: dict) -> None:
        node = data[key]
        rows, cols = node["rows"], node["cols"]
        node["data"] = [
            float(v) for v in change(np.array(node["data"], float).reshape(rows, cols)).reshape(-1)
        ]

    return edit


def _rotation(change: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    def edit(T: np.ndarray) -> np.ndarray:
        T = T.copy()
        T[:3, :3] = change(T[:3, :3])
        return T

    return edit


def _json(value) -> Callable[[Path], None]:
    return lambda path: _put(path, json.dumps(value))


def _image(size: tuple[int, int]) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        from PIL import Image

        path.unlink()
        Image.new("RGB", size).save(path, format="JPEG")

    return damage


def _huge_header(path: Path) -> None:
    """A valid small JPEG whose frame header claims 60000 x 60000 px."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (16, 16)).save(buffer, format="JPEG")
    data = bytearray(buffer.getvalue())
    at = data.index(b"\xff\xc0")  # SOF0: length (2), precision (1), height (2), width (2)
    data[at + 5 : at + 9] = (60000).to_bytes(2, "big") * 2
    _put(path, bytes(data))


def _exif_rotated(path: Path) -> None:
    """The same image, saved with an EXIF orientation of 6 (viewers turn it 90 degrees)."""
    from PIL import Image

    with Image.open(path) as im:
        rgb = im.convert("RGB")
    exif = rgb.getexif()
    exif[0x0112] = 6
    path.unlink()
    rgb.save(path, format="JPEG", exif=exif)


def _npz_garbage(path: Path) -> None:
    _put(path, b"PK\x03\x04 this is not a zip archive")


def _stray_sequence(data: Path) -> None:
    shutil.copytree(data / "3d_comp/os1/1", data / "3d_comp/os1/7", copy_function=os.link)
    # its truth too: the oracle config would refuse the whole run for a sequence without gt/
    # (issue 38) before the plan finds the missing timestamps this case is about
    shutil.copytree(data / "gt/1", data / "gt/7", copy_function=os.link)


def _frame_beyond(data: Path) -> None:
    os.link(data / BIN.format(2), data / BIN.format(9))


def _no_sweeps(data: Path) -> None:
    for p in (data / "3d_comp/os1/1").iterdir():
        p.unlink()


def _calibration_folder_is_a_file(data: Path) -> None:
    shutil.rmtree(data / "calibrations/1")
    (data / "calibrations/1").write_text("not a folder")


@dataclass(frozen=True)
class Case:
    name: str
    #: the damaged path relative to the dataset root ("" when ``damage`` takes the root)
    path: str
    damage: Callable[[Path], None]
    #: what the error must say (besides the file)
    says: str
    #: "plan": the sequence cannot be read at all; "frame": one frame's input is bad (frame 2)
    level: str = "plan"
    #: the file the error names (default: ``path``)
    names: str = ""
    sequence: str = BAD


CASES = [
    # files that are not regular files: fingerprinting and reading fail the sequence, never hang
    Case("sweep is a symlink loop", BIN.format(2), _symlink_loop, "symlink loop"),
    Case("sweep is a FIFO", BIN.format(2), _fifo, "FIFO"),
    Case("sweep is a folder", BIN.format(2), _directory, "is a directory"),
    Case("sweep is a device", BIN.format(2), _symlink("/dev/zero"), "character device"),
    Case("sweep is a dangling link", BIN.format(2), _symlink("/nonexistent/x.bin"), "is missing"),
    Case("image is a folder", CAM0.format(2), _directory, "is a directory"),
    Case("timestamps is a FIFO", "timestamps/1.txt", _fifo, "FIFO"),
    Case("calibration is a FIFO", CALIB.format("calib_os1_to_cam0"), _fifo, "FIFO"),
    Case("metadata is a symlink loop", "metadata/1.json", _symlink_loop, "symlink loop"),
    # sweeps of one frame
    Case("sweep truncated", BIN.format(2), _cut(1000), "truncated", "frame"),
    Case(
        "5-channel sweep cut to the 4-channel size",
        BIN.format(2),
        _cut(128 * 1024 * 16),
        "5 float32 channels",
        "frame",
    ),
    Case("sweep empty", BIN.format(2), _cut(0), "0 bytes", "frame"),
    Case("sweep with NaN points", BIN.format(2), _nan_points, "NaN or inf", "frame"),
    Case(
        "sweep too long",
        BIN.format(2),
        lambda p: _put(p, p.read_bytes() + b"\0" * 4096),
        "bytes but",
        "frame",
    ),
    # images of one frame: decoded and size-checked before anything (or an export) uses them
    Case(
        "image missing",
        CAM0.format(2),
        _remove,
        "image is missing",
        "frame",
        names="2d_rect_cam0_1_2",
    ),
    Case(
        "image corrupt",
        CAM0.format(2),
        lambda p: _put(p, b"\xff\xd8\xff garbage"),
        "cannot be decoded",
        "frame",
    ),
    Case("image cut in half", CAM0.format(2), _cut(keep=0.5), "cannot be decoded", "frame"),
    Case("image of the wrong size", CAM0.format(2), _image((640, 480)), "640 x 480 px", "frame"),
    Case(
        "image header claims 60000 x 60000 px",
        CAM0.format(2),
        _huge_header,
        "image header claims an implausible size",
        "frame",
    ),
    Case(
        "image with an EXIF rotation", CAM0.format(2), _exif_rotated, "EXIF orientation 6", "frame"
    ),
    Case(
        "cam1 image corrupt",
        "2d_rect/cam1/1/2d_rect_cam1_1_2.jpg",
        lambda p: _put(p, b"not an image"),
        "cannot be decoded",
        "frame",
    ),
    # labels and ground truth of one frame
    Case(
        "semantic labels of the wrong size",
        "3d_semantic/os1/1/3d_semantic_os1_1_2.bin",
        _cut(5000),
        "labels, expected 131072",
        "frame",
    ),
    Case(
        "box file not JSON",
        "3d_bbox/os1/1/3d_bbox_os1_1_2.json",
        lambda p: _put(p, "{oops"),
        "invalid JSON",
        "frame",
    ),
    Case(
        "box file without a 3dbbox list",
        "3d_bbox/os1/1/3d_bbox_os1_1_2.json",
        _json([1, 2]),
        "'3dbbox' list",
        "frame",
    ),
    Case(
        "ground-truth frame corrupt",
        "gt/1/gt_1_2.npz",
        _npz_garbage,
        "not a readable ground-truth npz",
        "frame",
    ),
    Case(
        "ground-truth frame missing",
        "gt/1/gt_1_2.npz",
        _remove,
        "no ground truth for sequence 1 frame 2",
        "frame",
    ),
    # timestamps
    Case("timestamps missing", "timestamps/1.txt", _remove, "timestamps file is missing"),
    Case(
        "timestamps not numbers",
        "timestamps/1.txt",
        _text(lambda t: t.replace("1700003600.1", "noon", 1)),
        "not a list of Unix seconds",
    ),
    Case(
        "timestamps not increasing",
        "timestamps/1.txt",
        _lines(lambda r: r.__setitem__(2, r[0])),
        "not strictly increasing",
    ),
    Case("timestamps empty", "timestamps/1.txt", lambda p: _put(p, ""), "no timestamps"),
    Case(
        "timestamps not text",
        "timestamps/1.txt",
        lambda p: _put(p, b"\xff\xfe\x00\x81"),
        "not UTF-8",
    ),
    # poses
    Case(
        "poses missing",
        "poses/dense_global/1.txt",
        _remove,
        "poses file is missing",
        names="poses/dense/1.txt",
    ),  # the fallback named last
    Case(
        "a pose line missing",
        "poses/dense_global/1.txt",
        _lines(lambda r: r.pop()),
        "pose lines but",
    ),
    Case(
        "pose not finite",
        "poses/dense_global/1.txt",
        _lines(lambda r: r[1].__setitem__(2, "nan")),
        "8 finite values",
    ),
    Case(
        "pose not numbers",
        "poses/dense_global/1.txt",
        _lines(lambda r: r[1].__setitem__(2, "x")),
        "is not numeric",
    ),
    Case(
        "pose quaternion not unit",
        "poses/dense_global/1.txt",
        _lines(lambda r: r[1].__setitem__(4, "2.0")),
        "quaternion norm",
    ),
    Case(
        "pose times a day off",
        "poses/dense_global/1.txt",
        _lines(lambda r: [row.__setitem__(0, f"{float(row[0]) + 86400:.6f}") for row in r]),
        "pose time",
    ),
    Case(
        "pose at x = 1e9",
        "poses/dense_global/1.txt",
        _lines(lambda r: r[2].__setitem__(1, "1e9")),
        "from the map origin",
    ),
    Case(
        "pose jumps 50 m in a frame",
        "poses/dense_global/1.txt",
        _lines(lambda r: r[2].__setitem__(1, "50")),
        "m/s",
    ),
    # calibration
    Case(
        "intrinsics missing",
        CALIB.format("calib_cam0_intrinsics"),
        _remove,
        "calibration file is missing",
    ),
    Case(
        "intrinsics not YAML",
        CALIB.format("calib_cam0_intrinsics"),
        lambda p: _put(p, "a: [1, 2\n"),
        "invalid YAML",
    ),
    Case(
        "image_width: wide",
        CALIB.format("calib_cam0_intrinsics"),
        _yaml(lambda d: d.__setitem__("image_width", "wide")),
        "image_width is 'wide'",
    ),
    Case(
        "zero camera matrix",
        CALIB.format("calib_cam0_intrinsics"),
        _yaml(_matrix("camera_matrix", lambda m: m * 0)),
        "not a camera matrix",
    ),
    Case(
        "negative focal length",
        CALIB.format("calib_cam0_intrinsics"),
        _yaml(_matrix("projection_matrix", lambda m: m * np.array([[-1], [1], [1]]))),
        "not a camera matrix",
    ),
    Case(
        "calibration NaN",
        CALIB.format("calib_cam0_intrinsics"),
        _text(lambda t: t.replace("730.27", ".nan", 1)),
        "non-finite",
    ),
    Case(
        "rectification not a rotation",
        CALIB.format("calib_cam0_intrinsics"),
        _yaml(_matrix("rectification_matrix", lambda m: m * 1.5)),
        "rectification_matrix is not orthonormal",
    ),
    Case(
        "extrinsic scaled",
        CALIB.format("calib_os1_to_cam0"),
        _yaml(_matrix("extrinsic_matrix", _rotation(lambda r: r * 2))),
        "not orthonormal",
    ),
    Case(
        "extrinsic sheared",
        CALIB.format("calib_os1_to_cam0"),
        _yaml(
            _matrix(
                "extrinsic_matrix",
                _rotation(lambda r: r @ np.array([[1, 0.3, 0], [0, 1, 0], [0, 0, 1]])),
            )
        ),
        "not orthonormal",
    ),
    Case(
        "extrinsic a reflection",
        CALIB.format("calib_os1_to_cam0"),
        _yaml(_matrix("extrinsic_matrix", _rotation(lambda r: r * np.array([1, 1, -1])))),
        "determinant",
    ),
    Case(
        "extrinsic zero",
        CALIB.format("calib_os1_to_cam0"),
        _yaml(_matrix("extrinsic_matrix", lambda m: m * 0)),
        "last row",
    ),
    Case(
        "base extrinsic singular",
        CALIB.format("calib_os1_to_base"),
        _yaml(_matrix("extrinsic_matrix", _rotation(lambda r: r * 0))),
        "not orthonormal",
    ),
    Case(
        "calibration folder is a file",
        "",
        _calibration_folder_is_a_file,
        "Not a directory",
        names="calibrations/1/calib_cam0_intrinsics.yaml",
    ),
    # metadata
    Case("metadata a JSON list", "metadata/1.json", _json([1, 2]), "expected a JSON object"),
    Case("metadata not JSON", "metadata/1.json", lambda p: _put(p, "{"), "invalid JSON"),
    Case(
        "metadata lighting a number", "metadata/1.json", _json({"lighting": 3}), "'lighting' is 3"
    ),
    Case(
        "metadata frame lists of the wrong type",
        "metadata/1.json",
        _json({"ObjectTracking": [1]}),
        "expected an object of file lists",
    ),
    # what a sequence is
    Case(
        "a sequence without timestamps is reported",
        "",
        _stray_sequence,
        "timestamps file is missing",
        names="timestamps/7.txt",
        sequence="7",
    ),
    Case("no sweeps", "", _no_sweeps, "no 3d_comp sweeps", names="3d_comp/os1/1"),
    Case(
        "a sweep beyond the timestamps",
        "",
        _frame_beyond,
        "frame number beyond",
        names=BIN.format(9),
    ),
]


def _ids(case: Case) -> str:
    return case.name.replace(" ", "-")


def _status(data: Path, out: Path, config: Path, capsys) -> tuple[int, str]:
    capsys.readouterr()
    code = cli.main(["status", "--config", str(config), "--data", str(data), "--out", str(out)])
    return code, capsys.readouterr().out


@pytest.mark.parametrize("case", CASES, ids=_ids)
def test_bad_input_fails_its_sequence_alone(case: Case, clean, tmp_path, capsys):
    data, out = _link_copy(clean.data, tmp_path / "data"), _link_copy(clean.out, tmp_path / "out")
    case.damage(data / case.path if case.path else data)
    names = case.names or case.path
    if case.level == "plan":  # through the command line: nothing to run, so no Prefect server
        code = cli.main(
            [
                "rebuild",
                "--config",
                str(clean.config),
                "--data",
                str(data),
                "--out",
                str(out),
                "--quiet",
            ]
        )
        text = capsys.readouterr().out
    else:
        report = run_units(
            load_config(clean.config, {"dataset.root": str(data), "output.root": str(out)}),
            progress=False,
        )
        code, text = report.exit_code, summary_table(report)
    assert code == 1, text
    error = Manifest.load(out).get(case.sequence, "detect").error
    assert Manifest.load(out).get(case.sequence, "detect").status == "failed"
    for where in (error, text):
        assert names in where and case.says in where, (where, names, case.says)
        if case.level == "frame":
            assert f"{names.rsplit('/', 1)[-1].split('.')[0]}" in where and "(frame 2)" in where
    status_code, status = _status(data, out, clean.config, capsys)
    assert status_code == 1 and names in status and case.says in status, status
    # the damaged sequence: withdrawn, marked failed; the other: the clean run's bytes
    assert not (out / "occupancy" / case.sequence).exists()
    row = read_table(out, "sequences", case.sequence).to_pylist()
    assert [r["status"] for r in row] == ["failed"] and case.says in row[0]["error"]
    for seq in {"0", "1"} - {case.sequence}:
        assert _published(out, seq) == clean.published[seq], seq
    print(
        f"\nCASE | {case.name} | {case.level} | exit {code} / status {status_code} | {error[:160]}"
    )


def test_the_table_is_large_enough():
    assert len(CASES) >= 40 and len({c.name for c in CASES}) == len(CASES)


# ---- one bad frame: left out, the rest of the sequence goes on ------------------------------------


def test_a_bad_frame_is_left_out_and_the_sequence_goes_on(clean, tmp_path, capsys):
    from storage.dataset import open_dataset
    from storage.products import FusedFrames

    data, out = _link_copy(clean.data, tmp_path / "data"), _link_copy(clean.out, tmp_path / "out")
    _cut(1000)(data / BIN.format(2))
    over = {
        "detect.max_failed_frame_share": 0.5,
        "dataset.sequences": [BAD],
    }  # 1 of 2 frames may go
    cfg = load_config(clean.config, {"dataset.root": str(data), "output.root": str(out), **over})
    report = run_units(cfg, progress=False)
    assert {o.status for o in report.outcomes.values()} == {"done"}, summary_table(report)
    assert report.exit_code == 1  # a frame was lost: the run says so
    [bad] = report.failed_frames()[BAD]
    assert (
        bad["frame"] == 2
        and "3d_comp_os1_1_2.bin (frame 2)" in bad["error"]
        and "bytes but" in bad["error"]
    )
    assert "FRAME FAILED 1/frame 2: " in summary_table(report)
    # the store's frame axis, the fuse product and the frames table agree: only raw frame 0
    ds = open_dataset(out)
    assert ds.arrays(BAD, lazy="zarr")["semantics"].shape[0] == 1
    fused = FusedFrames.read(out / Manifest.load(out).get(BAD, "fuse").location)
    frames = read_table(out, "frames", BAD).to_pylist()
    assert fused.frame.tolist() == [0] and [(r["frame"], r["raw_frame"]) for r in frames] == [
        (0, 0)
    ]
    pose0 = np.loadtxt(data / "poses/dense_global/1.txt")[0]
    assert np.allclose(np.reshape(frames[0]["T_world_from_lidar"], (4, 4))[:3, 3], pose0[1:4])
    assert Manifest.load(out).get(BAD, "detect").summary["failed_frames"] == [bad]
    capsys.readouterr()
    code = cli.main(
        [
            "status",
            "--config",
            str(clean.config),
            "--data",
            str(data),
            "--out",
            str(out),
            "--set",
            "detect.max_failed_frame_share=0.5",
            "--set",
            "dataset.sequences=['1']",
        ]
    )
    status = capsys.readouterr().out
    assert (
        code == 1
        and "fresh, frame 2 left out:" in status
        and "3d_comp_os1_1_2.bin (frame 2)" in status
    )
    assert _published(out, "0") == clean.published["0"]


# ---- the command line's edges --------------------------------------------------------------------


def _edge_args(kind: str, clean, tmp_path: Path) -> tuple[list[str], str]:
    """(rebuild arguments, what stderr must say) for one edge of the command line."""
    out, data = tmp_path / "out", str(clean.data)
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "empty").mkdir()
    return {
        "data missing": (
            ["--data", str(tmp_path / "nowhere"), "--out", str(out)],
            "does not exist",
        ),
        "data is a file": (
            ["--data", str(tmp_path / "a-file"), "--out", str(out)],
            "is not a folder",
        ),
        "data empty": (["--data", str(tmp_path / "empty"), "--out", str(out)], "holds no sequence"),
        "out is a file": (["--data", data, "--out", str(tmp_path / "a-file")], "is not a folder"),
        "out not writable": (["--data", data, "--out", "/proc/mobileocc-out"], "is not writable"),
        "config inf": (
            ["--data", data, "--out", str(out), "--set", "fuse.grid.range_max=[.inf, 4.8, 3.8]"],
            "fuse.grid.range_max.0: Input should be a finite number",
        ),
        "config nan": (
            ["--data", data, "--out", str(out), "--set", "fuse.grid.voxel_size_m=.nan"],
            "fuse.grid.voxel_size_m: Input should be a finite number",
        ),
        "config boolean for a number": (
            ["--data", data, "--out", str(out), "--set", "map.min_votes=true"],
            "map.min_votes: Value error, expected a number, got True",
        ),
        "config string for a number": (
            ["--data", data, "--out", str(out), "--set", "dataset.max_range_m='9'"],
            "expected a number, got '9'",
        ),
        "config grid too large": (
            [
                "--data",
                data,
                "--out",
                str(out),
                "--set",
                "fuse.grid.range_min=[-1000, -4.8, -1]",
                "--set",
                "fuse.grid.range_max=[1000, 4.8, 3.8]",
            ],
            "at most 4096",
        ),
    }[kind]


@pytest.mark.parametrize(
    "kind",
    [
        "data missing",
        "data is a file",
        "data empty",
        "out is a file",
        "out not writable",
        "config inf",
        "config nan",
        "config boolean for a number",
        "config string for a number",
        "config grid too large",
    ],
)
def test_command_line_edges_are_one_clear_error(kind, clean, tmp_path, capsys):
    args, says = _edge_args(kind, clean, tmp_path)
    capsys.readouterr()
    code = cli.main(["rebuild", "--config", str(clean.config), "--quiet", *args])
    err = capsys.readouterr().err
    assert code == cli.EXIT_USAGE and says in err, err
    assert (
        len(err.strip().splitlines()) <= 2 and "Traceback" not in err
    )  # config errors: file + key line
    assert not (tmp_path / "out" / "manifest.json").exists()  # no work started
    print(f"\nCASE | {kind} | cli | exit {code} | {err.strip().splitlines()[-1][:160]}")


def test_config_validate_rejects_non_finite_and_boolean_numbers(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(
        "fuse:\n  grid:\n    range_max: [.inf, 4.8, 3.8]\nmap:\n  min_votes: true\n"
        "fit:\n  learning_rate: .nan\n"
    )
    assert cli.main(["config", "validate", str(path)]) == 1
    err = capsys.readouterr().err
    assert "3 error(s)" in err and "fuse.grid.range_max.0" in err and "map.min_votes" in err
    assert "fit.learning_rate" in err and "Traceback" not in err


# ---- the run lock, leftovers, disk errors, withdrawn exports ---------------------------------------

HOLD_LOCK = textwrap.dedent("""
    import sys
    from storage.manifest import run_lock
    with run_lock(sys.argv[1]):
        print("holding", flush=True)
        sys.stdin.read()
""")


def test_a_refused_run_prints_one_line(clean, tmp_path, capsys):
    out = _link_copy(clean.out, tmp_path / "out")
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(out)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "holding"
        capsys.readouterr()
        code = cli.main(
            ["rebuild", "--config", str(clean.config), "--data", str(clean.data), "--out", str(out)]
        )
        err = capsys.readouterr().err.strip()
        assert code == cli.EXIT_BUSY and len(err.splitlines()) == 1, err
        assert "is in use by another run" in err and f"pid {holder.pid}" in err
    finally:
        holder.communicate("", timeout=60)
    # the holder is gone: the lock is free again
    assert (
        cli.main(
            ["rebuild", "--config", str(clean.config), "--data", str(clean.data), "--out", str(out)]
        )
        == 0
    )


@pytest.mark.parametrize(
    "content", ['{"host": "%s", "pid": 999999999}', ""], ids=["dead pid", "empty"]
)
def test_a_lock_file_left_behind_is_taken_over(content, clean, tmp_path):
    import socket

    out = _link_copy(clean.out, tmp_path / "out")
    (out / ".lock").write_text(content.replace("%s", socket.gethostname()))
    code = cli.main(
        ["rebuild", "--config", str(clean.config), "--data", str(clean.data), "--out", str(out)]
    )
    assert code == 0 and not (out / ".lock").exists()


def test_leftovers_of_killed_runs_are_swept(clean, tmp_path):
    out = _link_copy(clean.out, tmp_path / "out")
    leftovers = [
        ".tmp-0-abc-123",
        ".cache/.tmp-procedural_smpl_v1.npz-1a2b",
        ".cache/sequences/.tmp-0.json-9",
        "stages/detect/0/.tmp-deadbeef-1",
        "occupancy/0/.tmp-old-x",
        "tables/frames/sequence=0/.tmp-1.parquet",
        "exports/.tmp-occ3d-1",
        ".tmp-manifest.json-77",
    ]
    for rel in leftovers:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).mkdir() if "." not in rel.rsplit("/", 1)[-1][5:] else (out / rel).write_bytes(
            b"x" * 10
        )
    assert (
        cli.main(
            ["rebuild", "--config", str(clean.config), "--data", str(clean.data), "--out", str(out)]
        )
        == 0
    )
    assert [rel for rel in leftovers if os.path.lexists(out / rel)] == []
    assert _published(out, "0") == clean.published["0"]


DISK_FULL = textwrap.dedent("""
    import resource, signal, sys
    from configs.schema import load_config
    from flows.pipeline.units import run_units, summary_table
    cfg = load_config(sys.argv[1], {"dataset.root": sys.argv[2], "output.root": sys.argv[3]})
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))  # every file written stops at 4 KiB
    report = run_units(cfg, progress=False)
    print(summary_table(report))
    sys.exit(report.exit_code)
""")


def test_a_disk_error_names_the_file(clean, tmp_path, capsys):
    data, out = _link_copy(clean.data, tmp_path / "data"), _link_copy(clean.out, tmp_path / "out")
    path = data / BIN.format(0)  # a valid edit: sequence 1 must run again
    raw = bytearray(path.read_bytes())
    raw[-8:-4] = bytes([0, 0, 192, 63])
    _put(path, bytes(raw))
    run = subprocess.run(
        [sys.executable, "-c", DISK_FULL, str(clean.config), str(data), str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=600,
    )
    assert run.returncode == 1, run.stdout + run.stderr
    assert (
        "FAILED 1/detect: OSError: [Errno 27] File too large:" in run.stdout
        and "stages/detect/1/" in run.stdout
    )
    error = Manifest.load(out).get(BAD, "detect").error  # the journal kept it
    assert "File too large" in error and f"{out}/stages/detect/1/" in error and ".npz" in error
    capsys.readouterr()
    code = cli.main(
        ["status", "--config", str(clean.config), "--data", str(data), "--out", str(out)]
    )
    assert code == 1 and "File too large" in capsys.readouterr().out
    assert _published(out, "0") == clean.published["0"]
    print(f"\nCASE | file size limit (a full disk) | run | exit {run.returncode} | {error[:160]}")


def test_a_failed_sequence_leaves_the_dataset_exports(clean, tmp_path):
    data, out = _link_copy(clean.data, tmp_path / "data"), _link_copy(clean.out, tmp_path / "out")
    args = [
        "rebuild",
        "--config",
        str(clean.config),
        "--data",
        str(data),
        "--out",
        str(out),
        "--set",
        "export.formats=['occ3d']",
    ]
    assert cli.main(args) == 0
    scenes = json.loads((out / "exports/occ3d/annotations.json").read_text())["scene_infos"]
    assert sorted(scenes) == ["coda-0", "coda-1"] and (out / "exports/occ3d/gts/coda-1").is_dir()
    _yaml(_matrix("extrinsic_matrix", _rotation(lambda r: r * 2)))(
        data / CALIB.format("calib_os1_to_cam0")
    )
    assert cli.main(args) == 1
    scenes = json.loads((out / "exports/occ3d/annotations.json").read_text())["scene_infos"]
    assert sorted(scenes) == ["coda-0"] and not (out / "exports/occ3d/gts/coda-1").exists()
    assert _published(out, "0") == clean.published["0"] and not (out / "occupancy/1").exists()


def test_the_temporary_prefect_server_dies_with_its_cli(clean, tmp_path):
    """Regression: after a SIGKILL of the CLI its temporary Prefect server kept running."""
    import psutil

    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(PYTHONPATH=str(ROOT), PREFECT_HOME=str(tmp_path / "prefect-home"))
    cli_proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "rebuild",
            "--config",
            str(clean.config),
            "--data",
            str(clean.data),
            "--out",
            str(tmp_path / "out"),
            "--quiet",
            "--set",
            "dask.prefect=always",  # a run with no Prefect API starts no server by default
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    server, deadline = None, time.time() + 300
    try:
        while (
            server is None and time.time() < deadline and cli_proc.poll() is None
        ):  # a start-up timeout
            kids = psutil.Process(cli_proc.pid).children(recursive=True)
            server = next((k for k in kids if "uvicorn" in " ".join(k.cmdline())), None)
            time.sleep(0.1)
        assert server is not None, "the CLI started no Prefect server"
        os.kill(cli_proc.pid, signal.SIGKILL)
        cli_proc.wait()
        gone, alive = psutil.wait_procs([server], timeout=60)
        assert gone and not alive
    finally:
        if server is not None and server.is_running():
            server.kill()
