"""The scale benchmark's own arithmetic and dataset plumbing (flows/bench/scale.py, planning.py):
Amdahl's fit on exact speed-ups, the projection's critical-path floor, sequences cut and copied
by hard links."""

from __future__ import annotations

import pytest

from flows.bench.planning import replicate_sequence
from flows.bench.scale import amdahl_serial_fraction, link_sequence, project

STAGES = ("detect", "track", "fit", "map", "fuse", "export")


@pytest.mark.parametrize("f", [0.0, 0.05, 0.3])
def test_amdahl_fit_recovers_the_serial_fraction(f):
    speedups = {n: 1.0 / (f + (1 - f) / n) for n in (1, 2, 4)}
    assert amdahl_serial_fraction(speedups) == pytest.approx(f, abs=1e-12)


def _cost(cpu: dict) -> dict:
    return {
        s: {"cpu_s_per_frame": cpu.get(s, 0.0), "wall_s_per_frame": 2 * cpu.get(s, 0.0)}
        for s in STAGES
    }


def test_projection_scales_throughput_and_stops_at_the_critical_path():
    cost = _cost({"fit": 9.0, "map": 0.5, "track": 0.5})  # 10 CPU s per frame
    long = {100: _cost({"map": 0.5, "track": 0.5})}  # serial stages: 2 wall s per frame
    cluster = {"runs": {1: {"speedup_dedicated": 1.0}, 2: {"speedup_dedicated": 2.0}}}
    p = project(cost, long, cluster, frames=36_000, sequence_frames=3_600, workers=(1, 2, 128))
    rows = p["workers"]
    assert rows[1]["hours"] == pytest.approx(100.0) and rows[1]["bound"] == "throughput"
    assert p["serial_fraction"] == pytest.approx(0.0)
    assert rows[2]["hours"] == pytest.approx(50.0)
    # 128 workers: throughput 100 / 128 h, but one sequence's track + map take 3,600 x 2 s = 2 h
    assert rows[128]["hours"] == pytest.approx(2.0) and rows[128]["bound"] == "critical path"


def _tree(root, sid: int, frames: int) -> None:
    for f in range(frames):
        for rel in (
            f"3d_comp/os1/{sid}/3d_comp_os1_{sid}_{f}.bin",
            f"2d_rect/cam0/{sid}/2d_rect_cam0_{sid}_{f}.jpg",
            f"gt/{sid}/gt_{sid}_{f}.npz",
        ):
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(bytes([f]))
    (root / f"calibrations/{sid}").mkdir(parents=True)
    (root / f"calibrations/{sid}/calib_os1_to_base.yaml").write_text("x")
    (root / f"gt/{sid}/sequence.npz").write_bytes(b"s")
    for rel in (f"timestamps/{sid}.txt", f"poses/dense_global/{sid}.txt"):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text("".join(f"{f}\n" for f in range(frames)))
    (root / "metadata").mkdir()
    (root / f"metadata/{sid}.json").write_text(
        f'{{"a": ["3d_comp/os1/{sid}/3d_comp_os1_{sid}_0.bin"]}}'
    )


def test_link_sequence_cuts_frames_and_renames(tmp_path):
    src, dst = tmp_path / "src", tmp_path / "dst"
    _tree(src, 987654, 6)
    link_sequence(src, 987654, dst, 3, raw_frames=4)
    names = sorted(str(p.relative_to(dst)) for p in dst.rglob("*") if p.is_file())
    assert (
        "3d_comp/os1/3/3d_comp_os1_3_3.bin" in names
        and "3d_comp/os1/3/3d_comp_os1_3_4.bin" not in names
    )
    assert (
        "gt/3/gt_3_3.npz" in names
        and "gt/3/gt_3_4.npz" not in names
        and "gt/3/sequence.npz" in names
    )
    assert "calibrations/3/calib_os1_to_base.yaml" in names
    assert not any("987654" in n for n in names)
    assert (dst / "timestamps/3.txt").read_text().splitlines() == ["0", "1", "2", "3"]
    assert (dst / "poses/dense_global/3.txt").read_text().splitlines() == ["0", "1", "2", "3"]
    assert "3d_comp_os1_3_0" in (dst / "metadata/3.json").read_text()
    # hard links: the same inode as the source
    assert (dst / "3d_comp/os1/3/3d_comp_os1_3_2.bin").stat().st_ino == (
        src / "3d_comp/os1/987654/3d_comp_os1_987654_2.bin"
    ).stat().st_ino


def test_replicated_sequences_are_hard_links_under_new_ids(tmp_path):
    src, dst = tmp_path / "src", tmp_path / "dst"
    _tree(src, 987654, 2)
    replicate_sequence(src, dst, 987654, [0, 1, 12])
    for sid in (0, 1, 12):
        assert (dst / f"3d_comp/os1/{sid}/3d_comp_os1_{sid}_1.bin").read_bytes() == bytes([1])
        assert (dst / f"timestamps/{sid}.txt").exists()
    inodes = {
        (dst / f"2d_rect/cam0/{sid}/2d_rect_cam0_{sid}_0.jpg").stat().st_ino for sid in (0, 1, 12)
    }
    assert len(inodes) == 1 and not (dst / "metadata/987654.json").exists()
