"""``reprocess --set K=V`` after a rebuild publishes the same bytes as a clean ``rebuild --set K=V``.

A stage whose key did not change is reused; if it read a setting its key does not cover, the
reused output would differ from a clean run's. One setting per stage family, including the one the
old hand-written key table missed (the map stage reads track.person_points.assoc_min_iou).
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from configs.schema import ORACLE_CONFIG, load_config
from flows.pipeline.run import rebuild_dataset

pytestmark = [
    pytest.mark.usefixtures("prefect_harness"),
    pytest.mark.xdist_group("prefect"),
    pytest.mark.slow,
]


def _config(data: Path, out: Path, **overrides):
    return load_config(
        ORACLE_CONFIG,
        overrides={
            "dataset.root": str(data),
            "output.root": str(out),
            "dataset.sequences": ["0"],
            "fit.iterations": 5,
            "export.formats": [],
            **overrides,
        },
    )


def _published(out: Path) -> dict[str, str]:
    """sha256 of every published file (Zarr stores and table partitions), by relative path."""
    files = [
        p for d in ("occupancy", "tables") for p in sorted((out / d).rglob("*")) if p.is_file()
    ]
    return {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


@pytest.mark.parametrize(
    "setting",
    [
        {"track.person_points.assoc_min_iou": 0.9},  # read by track and map
        {"fuse.camera_pixel_stride": 3},
        {"fit.iterations": 3},
        {"map.freespace.prob_hit": 0.75},  # read by map and (the state threshold's map) fuse
    ],
)
def test_reprocess_publishes_what_a_clean_rebuild_does(synthetic_root, tmp_path, setting):
    base = tmp_path / "base"
    assert not rebuild_dataset(_config(synthetic_root, base), progress=False).failed
    before = _published(base)
    report = rebuild_dataset(_config(synthetic_root, base, **setting), progress=False)
    assert not report.failed
    assert any(o.ran and o.status == "done" for o in report.outcomes.values())
    clean = tmp_path / "clean"
    assert not rebuild_dataset(_config(synthetic_root, clean, **setting), progress=False).failed
    assert _published(base) == _published(clean)
    assert _published(base) != before  # the setting does change the dataset
    shutil.rmtree(tmp_path, ignore_errors=True)
