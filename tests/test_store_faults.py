"""Faults of the store, the exports, the data root and the process, table-driven (issue 28).

tests/test_bad_input.py damages the *input*; this module damages what the pipeline wrote (stage
products, the published arrays, tables and ``current.json``, the dataset-level exports), changes
the data under a built dataset, kills runs at exact steps of a publication, and stops runs with
signals. One clean run of the session's 2-sequence dataset is shared (``built``); each case copies
it (hard links: every damage replaces a file, never writes into one), damages it, runs the
command a user would run, and asserts: the exit code; the one line that says what is wrong (and
no traceback); sequence 0's published bytes untouched; and that the repair the message points to
(usually a plain ``rebuild``) gives back the clean run's bytes, the dataset-level export included.

Runs go through ``flows.cli.main`` in this process; the flow itself runs inline (the CLI's
``_run_flow`` is replaced by the Prefect-free runner it wraps, which test_flows / test_faults test
under Prefect), except the signal tests, which start the real CLI.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from configs.schema import load_config
from flows import cli
from flows.pipeline.units import run_units, summary_table
from storage.manifest import Manifest

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
#: cheap settings: these tests are about faults, not products; one dataset-level export
CHEAP = {
    "fit": {"iterations": 2, "min_points": 1000000},
    "dataset": {"max_range_m": 15.0},
    "map": {"voxel_size_m": 0.4, "freespace": {"voxel_size_m": 0.4, "max_range_m": 15.0}},
    "fuse": {"grid": {"voxel_size_m": 0.4}},
    "export": {"formats": ["occ3d"]},
    "detect": {"max_failed_frame_share": 0.0},
}
CALIB = "calibrations/1/calib_os1_to_cam0.yaml"


def _link_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link, symlinks=True)
    return dst


def _files(base: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(base)): p.read_bytes() for p in sorted(base.rglob("*")) if p.is_file()
    }


def _published(out: Path, seq: str) -> dict[str, bytes]:
    """Every published byte of one sequence: its arrays, current.json and table partitions."""
    found = {}
    for base in [out / "occupancy" / seq, *(out / "tables").glob(f"*/sequence={seq}")]:
        for rel, data in _files(base).items():
            found[str((base / rel).relative_to(out))] = data
    return found


def _exports(out: Path) -> dict[str, bytes]:
    return _files(out / "exports") if (out / "exports").is_dir() else {}


def _put(path: Path, data: bytes | str) -> None:
    """Replace a file (never write into it: the store is a hard-linked copy)."""
    if os.path.lexists(path):
        path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data if isinstance(data, bytes) else data.encode())


def _break_calibration(data: Path) -> None:
    path = data / CALIB
    _put(path, path.read_text().replace("extrinsic_matrix", "extrinsic_matrixx"))


def _inline_flow(monkeypatch) -> None:
    """The CLI's flow, without Prefect: the runner it wraps, under the lock the CLI holds."""

    def run_flow(cfg, force, progress, verify, **kw):
        return run_units(cfg, force=force, progress=False, verify=verify, lock_held=True, **kw)

    monkeypatch.setattr(cli, "_run_flow", run_flow)


@pytest.fixture(scope="module")
def built(synthetic_root, tmp_path_factory):
    """The session's dataset (never written to: cases copy it), one clean run, and the store after
    a run with sequence 1's calibration broken (sequence 1 withdrawn)."""
    work = tmp_path_factory.mktemp("built")
    config = work / "faults.yaml"
    config.write_text(yaml.safe_dump(CHEAP))
    out = work / "out"
    cfg = load_config(config, {"dataset.root": str(synthetic_root), "output.root": str(out)})
    report = run_units(cfg, progress=False)
    assert report.exit_code == 0, summary_table(report)
    published = {seq: _published(out, seq) for seq in ("0", "1")}
    assert published["0"] and published["1"] and _exports(out)
    # withdrawn: the same store after a run with sequence 1's calibration broken
    broken = _link_copy(synthetic_root, work / "broken-data")
    _break_calibration(broken)
    withdrawn = _link_copy(out, work / "withdrawn")
    report = run_units(
        load_config(config, {"dataset.root": str(broken), "output.root": str(withdrawn)}),
        progress=False,
    )
    assert report.exit_code == 1 and report.withdrawn == ["1"], summary_table(report)
    return SimpleNamespace(
        data=synthetic_root,
        broken=broken,
        out=out,
        withdrawn=withdrawn,
        config=config,
        published=published,
        exports=_exports(out),
    )


@dataclass
class Env:
    data: Path
    out: Path
    config: Path

    def args(self, command: str, *more: str) -> list[str]:
        words = command.split()
        if words[0] in ("rebuild", "reprocess", "status", "export"):
            words += ["--config", str(self.config), "--data", str(self.data)]
            words += ["--out", str(self.out)]
        if words[0] in ("rebuild", "reprocess", "status"):
            words.append("--quiet")
        return words + list(more)

    def stage(self, stage: str, seq: str = "1") -> Path:
        return self.out / Manifest.load(self.out).get(seq, stage).location

    def current(self, seq: str = "1") -> Path:
        return self.out / "occupancy" / seq / "current.json"

    def store(self, seq: str = "1") -> Path:
        version = json.loads(self.current(seq).read_text())["version"]
        return self.out / "occupancy" / seq / f"{version}.zarr"


def _env(built, tmp_path: Path, out: Path | None = None, data: Path | None = None) -> Env:
    return Env(
        _link_copy(data or built.data, tmp_path / "data"),
        _link_copy(out or built.out, tmp_path / "out"),
        built.config,
    )


def _cli(env: Env, command: str, capsys, *more: str) -> tuple[int, str]:
    """Run one command in this process; (exit code, stdout + stderr)."""
    capsys.readouterr()
    code = cli.main(env.args(command, *more))
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def _assert_one_clear_line(text: str) -> None:
    assert "Traceback" not in text and "Error:" not in text.split("\n", 1)[0][:0], text


# ---- damage of the store ----------------------------------------------------------------------


def _cut_half(path: Path) -> None:
    _put(path, path.read_bytes()[: len(path.read_bytes()) // 2])


def _same_size_garbage(path: Path) -> None:
    data = path.read_bytes()
    _put(path, bytes((b + 1) % 256 for b in data))


def _first(folder: Path, pattern: str) -> Path:
    return sorted(p for p in folder.rglob(pattern) if p.is_file())[0]


@dataclass(frozen=True)
class Fault:
    name: str
    damage: Callable[[Env], None]
    #: the command that must notice it, its exit code and what it must say
    check: str = "status"
    code: int = 1
    says: str = ""
    #: the command that repairs it (and must then give the clean bytes), and what it says
    repair: str = "rebuild"
    repair_says: str = ""
    #: the repair with --verify (content damage that keeps sizes is found by hashing)
    more: tuple[str, ...] = field(default=())


def _chunk(env: Env) -> Path:
    return _first(env.store() / "semantics" / "c", "*")


STORE_FAULTS = [
    # root cause 1: a unit whose folder exists is not done unless its completion record verifies
    Fault(
        "stage product truncated",
        lambda e: _cut_half(_first(e.stage("track"), "*.npz")),
        says="output damaged",
    ),
    Fault(
        "stage product deleted",
        lambda e: _first(e.stage("detect"), "*.npz").unlink(),
        says="is missing",
    ),
    Fault(
        "stage completion record deleted",
        lambda e: (e.stage("fuse") / "complete.json").unlink(),
        says="writer did not finish",
    ),
    Fault(
        "stage product rewritten, same size",
        lambda e: _same_size_garbage(_first(e.stage("track"), "*.npz")),
        check="status --verify",
        says="does not hold what was written",
        repair="rebuild --verify",
    ),
    # root cause 2: the published store is checked against what was published
    Fault("zarr chunk deleted", lambda e: _chunk(e).unlink(), says="is missing"),
    Fault("zarr chunk garbage", lambda e: _put(_chunk(e), b"garbage"), says="bytes"),
    Fault(
        "zarr chunk rewritten, same size",
        lambda e: _same_size_garbage(_chunk(e)),
        check="status --verify",
        says="does not hold what was written",
        repair="rebuild --verify",
    ),
    Fault(
        "zarr metadata garbage",
        lambda e: _put(e.store() / "semantics" / "zarr.json", "{"),
        says="bytes",
    ),
    Fault(
        "table partition garbage",
        lambda e: _put(e.out / "tables/frames/sequence=1/data.parquet", b"PAR1 garbage PAR1"),
        says="data.parquet",
    ),
    Fault(
        "table partition deleted",
        lambda e: (e.out / "tables/instances/sequence=1/data.parquet").unlink(),
        says="is missing",
    ),
    Fault("current.json garbage", lambda e: _put(e.current(), "{oops"), says="current.json"),
    Fault("current.json deleted", lambda e: e.current().unlink(), says="current.json"),
    Fault(
        "current.json points at another version",
        lambda e: _put(e.current(), json.dumps({"version": "0" * 24})),
        says="current.json",
    ),
    Fault(
        "published arrays deleted",
        lambda e: shutil.rmtree(e.store()),
        says="is missing",
    ),
    # root cause 3: the dataset-level export is checked too
    Fault(
        "dataset export deleted",
        lambda e: shutil.rmtree(e.out / "exports" / "occ3d"),
        says="occ3d export",
    ),
    Fault(
        "dataset export label file deleted",
        lambda e: _first(e.out / "exports" / "occ3d" / "gts", "labels.npz").unlink(),
        says="occ3d export",
    ),
]


@pytest.mark.parametrize("fault", STORE_FAULTS, ids=lambda f: f.name.replace(" ", "-"))
def test_a_damaged_store_is_found_and_repaired(fault: Fault, built, tmp_path, capsys, monkeypatch):
    _inline_flow(monkeypatch)
    env = _env(built, tmp_path)
    fault.damage(env)
    code, text = _cli(env, fault.check, capsys)
    assert code == fault.code and fault.says in text, text
    assert "Traceback" not in text
    assert _published(env.out, "0") == built.published["0"]
    code, text = _cli(env, fault.repair, capsys)
    assert code == 0, text
    assert fault.repair_says in text
    assert _published(env.out, "1") == built.published["1"]
    assert _published(env.out, "0") == built.published["0"]
    assert _exports(env.out) == built.exports
    code, text = _cli(env, "status --verify", capsys)
    assert code == 0, text
    print(f"\nCASE | {fault.name} | {fault.check} exit {fault.code} | {fault.says}")
