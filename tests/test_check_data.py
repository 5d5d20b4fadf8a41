"""``mobileocc check-data`` on a good and on a damaged CODa-layout fixture."""

from __future__ import annotations

import numpy as np
import pytest

from configs.schema import load_config
from flows.cli import main
from flows.commands.check_data import check_data
from tests.coda_fixture import POINTS, make_coda

SIZE = (1224, 1024)


def _check(root, deep=False, **overrides):
    return check_data(load_config(overrides={"dataset.root": str(root), **overrides}), deep=deep)


def _row(text: str, seq: str) -> str:
    """The table row of a sequence (the lines between the header's dashes and the blank line)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("---"))
    table = lines[start + 1 : lines.index("", start)]
    return next(line for line in table if line.split()[0] == seq)


def test_good_download_is_ready(tmp_path, capsys):
    make_coda(tmp_path, seq=0, frames=6, image_size=SIZE)
    make_coda(tmp_path, seq=1, frames=30, present=[*range(0, 8), *range(20, 26)], image_size=SIZE)
    code, text = _check(tmp_path)
    assert code == 0, text
    row0, row1 = _row(text, "0"), _row(text, "1")
    assert "3 of 6/6 (all)" in row0 and "7 of 14/30 (split)" in row1
    for row in (row0, row1):
        assert "5ch" in row and "1224x1024 f731 b0.198 R,P" in row and "rows 0.00px" in row
        assert "ground +0.00m" in row and "ns, <= 99.9 ms" in row and "ok (3 read)" in row
        assert row.endswith("OK") and "day (metadata)" in row
    assert (
        "2 sequence(s): ready to run" in text and "BLOCKING" not in text and "warning" not in text
    )
    assert main(["check-data", "--data", str(tmp_path)]) == 0
    assert "ready to run" in capsys.readouterr().out


def test_damaged_download_is_blocked(tmp_path):
    make_coda(tmp_path, seq=0, frames=8, image_size=SIZE)
    make_coda(tmp_path, seq=1, frames=4, image_size=SIZE, intensity_zero=True, base_file=False)
    make_coda(tmp_path, seq=2, frames=4, image_size=(640, 480))
    bin2 = tmp_path / "3d_comp/os1/0/3d_comp_os1_0_2.bin"
    bin2.write_bytes(bin2.read_bytes()[:5000])  # truncated download
    (tmp_path / "2d_rect/cam1/0/2d_rect_cam1_0_4.jpg").unlink()
    (tmp_path / "calibrations/0/calib_cam0_intrinsics.yaml").unlink()  # sequence 0 cannot be opened
    code, text = _check(tmp_path)
    assert code == 1 and _row(text, "0").endswith("BLOCKED")
    # the reader could not open sequence 0: its calibration is gone; say which file
    assert (
        "0: BLOCKING: cannot be read:" in text
        and "calib_cam0_intrinsics.yaml: calibration file is missing" in text
    )
    (tmp_path / "calibrations/0/calib_cam0_intrinsics.yaml").write_text(
        (tmp_path / "calibrations/1/calib_cam0_intrinsics.yaml").read_text()
    )
    code, text = _check(tmp_path)
    assert code == 1
    assert (
        "0: BLOCKING: 3d_comp sweep truncated or not an OS1-128 sweep: 3d_comp_os1_0_2.bin: 5000 bytes (frame 2)"
        in text
    )
    assert "0: BLOCKING: 2d_rect cam1: 1 of 4 selected frames have no file (first: frame 4)" in text
    assert "2 bad" in _row(text, "0")
    # sequence 1 runs (warnings only): zero intensity and the default base calibration said
    assert _row(text, "1").endswith("warn") and "0 in 2/2" in _row(text, "1")
    assert "1: warning: intensity is 0 for every return in 2 of 2 read sweeps" in text
    assert "1: warning:" in text and "calib_os1_to_base.yaml is missing" in text
    # sequence 2: images are not the calibration's size
    assert "2: BLOCKING:" in text and "image is 640x480, the calibration says 1224x1024" in text
    assert "3 sequence(s): 2 blocked" in text


def test_deep_reads_every_file(tmp_path):
    make_coda(tmp_path, seq=0, frames=10, image_size=SIZE)
    path = (
        tmp_path / "3d_comp/os1/0/3d_comp_os1_0_2.bin"
    )  # not among the 3 sampled sweeps (0, 4, 8)
    raw = np.fromfile(path, np.float32).reshape(POINTS, 5)
    raw[5, 0] = np.nan
    raw.tofile(path)
    (tmp_path / "3d_bbox/os1/0/3d_bbox_os1_0_6.json").write_text('{"3dbbox": [{"classId": "Car"}]}')
    code, text = _check(tmp_path)
    assert code == 0, text
    code, text = _check(tmp_path, deep=True)
    assert code == 1
    assert "3d_comp_os1_0_2.bin (frame 2): 1 points have NaN or inf values" in text
    assert "warning: 1 3d_bbox boxes are malformed or degenerate and are skipped" in text
    assert "ok (4 read)" in _row(text, "0")  # the NaN sweep is not counted as read


def test_no_sequences(tmp_path):
    code, text = _check(tmp_path)
    assert code == 1 and "no sequence found" in text


@pytest.mark.parametrize("lidar", ["3d_raw"])
def test_wrong_lidar_source_names_the_fix(tmp_path, lidar):
    make_coda(tmp_path, seq=0, frames=2, lidar_source=lidar, image_size=SIZE)
    code, text = _check(tmp_path)
    assert code == 1 and "set dataset.lidar_source: 3d_raw" in text
    assert _check(tmp_path, **{"dataset.lidar_source": lidar})[0] == 0


def test_reader_warnings_reach_the_run_summary(tmp_path):
    # a missing calib_os1_to_base.yaml is allowed (dataset.lidar_height_m) but said after the run
    from flows.pipeline.plan import plan_run
    from flows.pipeline.run import RunReport, summary_table
    from storage.manifest import FileHasher, Manifest

    make_coda(tmp_path / "data", seq=0, frames=2, base_file=False)
    cfg = load_config(
        overrides={"dataset.root": str(tmp_path / "data"), "output.root": str(tmp_path / "out")}
    )
    plans = plan_run(cfg, Manifest.load(tmp_path / "out"), FileHasher(None))
    assert not plans[0].error and len(plans[0].warnings) == 1
    text = summary_table(RunReport(tmp_path / "out", plans))
    assert (
        "WARNING 0: " in text
        and "calib_os1_to_base.yaml is missing" in text
        and "0.9 m above the ground" in text
    )


def test_config_lighting_per_sequence_overrides_the_metadata(tmp_path):
    from flows.pipeline.inputs import open_sequence

    make_coda(tmp_path, seq=2, frames=2, metadata={"lighting": "normal"})
    make_coda(tmp_path, seq=3, frames=2, metadata={"lighting": "dark"})
    cfg = load_config(overrides={"dataset.root": str(tmp_path), "dataset.lighting": {2: "night"}})
    assert cfg.dataset.lighting == {"2": "night"}  # YAML's integer keys become sequence ids
    two, three = open_sequence(cfg, "2").info, open_sequence(cfg, "3").info
    assert (two.lighting, two.lighting_source) == ("night", "config")
    assert (three.lighting, three.lighting_source) == ("night", "metadata")
    assert "night (config)" in _row(check_data(cfg)[1], "2")
