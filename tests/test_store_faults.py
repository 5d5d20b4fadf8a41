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
from tests.oracle import oracle_yaml

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
    """A copy of hard links; without the store's lock file, which runs write into (and whose
    flock, shared by every link, would make runs in two copies exclude each other)."""
    shutil.copytree(
        src, dst, copy_function=os.link, symlinks=True, ignore=shutil.ignore_patterns(".lock")
    )
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
    config.write_text(yaml.safe_dump(oracle_yaml(CHEAP)))
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
    #: what `export` says refusing the damaged store ("": it exports, the published files are
    #: whole or their damage keeps sizes, which only hashing finds)
    export_says: str = ""


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
    Fault(
        "stage product rewritten, same size, read by a unit that runs",
        lambda e: (
            _same_size_garbage(_first(e.stage("track"), "*.npz")),
            shutil.rmtree(e.stage("export")),
        ),
        says="output damaged",
        repair_says="REPAIRED 1/track: output damaged (found by export)",
    ),
    # root cause 2: the published store is checked against what was published
    Fault(
        "zarr chunk deleted",
        lambda e: _chunk(e).unlink(),
        says="is missing",
        export_says="is damaged",
    ),
    Fault(
        "zarr chunk garbage",
        lambda e: _put(_chunk(e), b"garbage"),
        says="bytes",
        export_says="is damaged",
    ),
    Fault(
        "zarr chunk rewritten, same size",
        lambda e: _same_size_garbage(_chunk(e)),
        check="status --verify",
        says="does not hold what was written",
        repair="rebuild --verify",
        export_says="cannot be read",
    ),
    Fault(
        "zarr metadata garbage",
        lambda e: _put(e.store() / "semantics" / "zarr.json", "{"),
        says="bytes",
        export_says="is damaged",
    ),
    Fault(
        "table partition garbage",
        lambda e: _put(e.out / "tables/frames/sequence=1/data.parquet", b"PAR1 garbage PAR1"),
        says="data.parquet",
        export_says="is damaged",
    ),
    Fault(
        "table partition deleted",
        lambda e: (e.out / "tables/instances/sequence=1/data.parquet").unlink(),
        says="is missing",
        export_says="is damaged",
    ),
    Fault(
        "current.json garbage",
        lambda e: _put(e.current(), "{oops"),
        says="current.json",
        export_says="is damaged",
    ),
    Fault(
        "current.json deleted",
        lambda e: e.current().unlink(),
        says="current.json",
        export_says="is damaged",
    ),
    Fault(
        "current.json points at another version",
        lambda e: _put(e.current(), json.dumps({"version": "0" * 24})),
        says="current.json",
        export_says="is damaged",
    ),
    Fault(
        "published arrays deleted",
        lambda e: shutil.rmtree(e.store()),
        says="is missing",
        export_says="is damaged",
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
    to = env.out.parent / "export-to"
    code, text = _cli(env, f"export --format occ3d --to {to}", capsys)
    if fault.export_says:  # never a dataset exported from a damaged store, nor a traceback
        assert code == 1 and fault.export_says in text and "rebuild" in text, text
        assert len(text.strip().splitlines()) == 1 and not to.exists(), text
    else:
        assert code == 0, text
    code, text = _cli(env, fault.repair, capsys)
    assert code == 0, text
    assert fault.repair_says in text
    assert _published(env.out, "1") == built.published["1"]
    assert _published(env.out, "0") == built.published["0"]
    assert _exports(env.out) == built.exports
    code, text = _cli(env, "status --verify", capsys)
    assert code == 0, text
    print(f"\nCASE | {fault.name} | {fault.check} exit {fault.code} | {fault.says}")


def test_force_computes_every_unit_again(built, tmp_path, capsys, monkeypatch):
    """Regression: `rebuild --force` reported every unit as run in 0.0 s and recomputed nothing
    (a unit whose key folder existed counted as done)."""
    _inline_flow(monkeypatch)
    env = _env(built, tmp_path)
    before = {k: r.finished_at for k, r in Manifest.load(env.out).rows.items()}
    records = {
        k: os.stat(env.out / r.location / "complete.json").st_ino
        for k, r in Manifest.load(env.out).rows.items()
    }
    code, text = _cli(env, "rebuild --force", capsys)
    assert code == 0, text
    assert "detect      2       0" in text and "export      2       0" in text, text
    after = Manifest.load(env.out).rows
    assert all(after[k].finished_at > t for k, t in before.items())
    assert all(
        os.stat(env.out / after[k].location / "complete.json").st_ino != ino
        for k, ino in records.items()
    )
    assert {s: _published(env.out, s) for s in ("0", "1")} == built.published
    assert _exports(env.out) == built.exports


@pytest.mark.parametrize("change", ["calibration fixed", "config reverted"])
def test_a_withdrawn_sequence_comes_back_when_its_input_or_config_does(
    change, built, tmp_path, capsys, monkeypatch
):
    """Regression: fixing a broken calibration (or reverting a config) and re-running exited 0,
    `status` said fresh, but the sequence stayed withdrawn and out of the exports (a unit whose
    key folder existed counted as done). calibration fixed: sequence 1 was withdrawn for its
    calibration, which is now fixed; config reverted: a config under which every sequence fails
    (image detections read from an empty folder) is reverted. Either way `status` says what will
    run, and a plain `rebuild` publishes the clean run's bytes, reusing the stage products of the
    earlier keys."""
    _inline_flow(monkeypatch)
    if change == "calibration fixed":
        env = _env(built, tmp_path, out=built.withdrawn)
        failing = ["1"]
    else:
        env = _env(built, tmp_path)
        (tmp_path / "empty").mkdir()
        bad = ["--set", "detect.image_provider=precomputed"]
        bad += ["--set", f"detect.precomputed_dir={tmp_path / 'empty'}"]
        code, text = _cli(env, "rebuild", capsys, *bad)
        assert code == 1 and "FAILED 0/detect" in text and "FAILED 1/detect" in text, text
        assert not (env.out / "occupancy" / "1" / "current.json").exists()
        assert not (env.out / "exports" / "occ3d").exists()  # no sequence: no export
        failing = ["0", "1"]
    code, text = _cli(env, "status", capsys)
    assert code == 1, text
    for seq in failing:
        assert f"{seq}  detect  failed: " in text or f"{seq}  detect  stale: " in text, text
    code, text = _cli(env, "rebuild", capsys)
    assert code == 0, text
    assert {s: _published(env.out, s) for s in ("0", "1")} == built.published
    assert _exports(env.out) == built.exports
    if change == "config reverted":  # the earlier keys' products are reused, not recomputed
        assert "detect      0       2" in text and "fuse        0       2" in text, text
        assert "export      2       0" in text, text
    code, text = _cli(env, "status --verify", capsys)
    assert code == 0 and "fresh" in text, text
    print(f"\nCASE | {change} | rebuild exit 0 | the clean run's bytes")


# ---- a kill at every step of a publication -------------------------------------------------------

#: runs (the CLI's runner, without Prefect), each SIGKILLed at its N-th rename (0: never),
#: logging every rename first: the injection hook of these tests. One process imports everything,
#: then forks one child per (store, N) (no compute ran in the parent before the fork), so a kill
#: point costs its run only. Prints each child's exit status (negative: killed by that signal).
KILL_AT_RENAME = textwrap.dedent("""
    import json, os, signal, sys
    from configs.schema import load_config
    from flows.pipeline.units import run_units
    import flows.stages  # imported once, before the forks (nothing computed yet)
    config, data = sys.argv[1:3]
    real = os.replace
    for out, n, log in json.loads(sys.argv[3]):
        pid = os.fork()
        if pid == 0:
            count = [0]
            def replace(src, dst, *args, **kwargs):
                count[0] += 1
                with open(log, "a") as fh:
                    fh.write(json.dumps([count[0], os.fspath(src), os.fspath(dst)]) + "\\n")
                if count[0] == n:
                    os.kill(os.getpid(), signal.SIGKILL)
                return real(src, dst, *args, **kwargs)
            os.replace = replace
            cfg = load_config(config, {"dataset.root": data, "output.root": out})
            os._exit(run_units(cfg, progress=False).exit_code)
        _, status = os.waitpid(pid, 0)
        print(json.dumps(-os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)))
""")


def _runs_killed_at(built, data: Path, runs: list[tuple[Path, int, Path]]) -> list[int]:
    """Exit statuses of runs on ``(store, N, log)``: each killed at its N-th rename."""
    run = subprocess.run(
        [sys.executable, "-c", KILL_AT_RENAME, str(built.config), str(data)]
        + [json.dumps([[str(out), n, str(log)] for out, n, log in runs])],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return [int(line) for line in run.stdout.split()]


def _publication_steps(log: Path, out: Path) -> list[int]:
    """The renames that change what readers see: onto or out of the published places (arrays,
    current.json, table partitions, the intent records, the dataset export's folder)."""
    steps = []
    for line in log.read_text().splitlines():
        n, src, dst = json.loads(line)
        rel = [os.path.relpath(p, out) for p in (src, dst)]
        if any(
            r.startswith(("occupancy/", "tables/", ".publishing/")) or r == "exports/occ3d"
            for r in rel
        ):
            steps.append(n)
    return steps


def _consistent(out: Path, seq: str) -> str:
    """What readers see of a sequence: "published" (current.json, its frames, a sequences row
    "ok" naming the same version) or "withdrawn" (none of those, a row "failed"); AssertionError
    on anything in between."""
    from storage.tables import read_table

    current = out / "occupancy" / seq / "current.json"
    rows = read_table(out, "sequences", seq).to_pylist()
    frames = read_table(out, "frames", seq).num_rows
    if current.exists():
        version = json.loads(current.read_text())["version"]
        assert [(r["status"], r["occupancy_version"]) for r in rows] == [("ok", version)], rows
        assert frames > 0
        return "published"
    assert [r["status"] for r in rows] == ["failed"] and frames == 0, (rows, frames)
    return "withdrawn"


@pytest.mark.parametrize("scenario", ["publish", "withdraw"])
def test_a_kill_at_any_publication_step_leaves_one_version(scenario, built, tmp_path, capsys):
    """publish: sequence 1 withdrawn, its calibration fixed, the run republishes it; withdraw:
    sequence 1's calibration broken, the run withdraws it. The run is SIGKILLed at each rename
    that changes what readers see; then a reader (``export``) sees one whole version, and the
    next run gives the bytes of a run never killed. Regression: a kill between table partitions
    left old arrays with a new frames table; a kill between a withdrawal and the dataset export
    left the withdrawn sequence in the export for good."""
    start, data = (
        (built.withdrawn, built.data) if scenario == "publish" else (built.out, built.broken)
    )
    want = "published" if scenario == "publish" else "withdrawn"
    probe = tmp_path / "probe"
    log = tmp_path / "renames.jsonl"
    status = 0 if scenario == "publish" else 1
    assert _runs_killed_at(built, data, [(_link_copy(start, probe), 0, log)]) == [status]
    expected = {"1": _published(probe, "1"), "exports": _exports(probe)}
    assert _consistent(probe, "1") == want
    if scenario == "publish":  # a fixed calibration brings the sequence back, as a clean run
        assert expected == {"1": built.published["1"], "exports": built.exports}
    steps = _publication_steps(log, probe)
    assert len(steps) >= 5, log.read_text()
    runs = [(_link_copy(start, tmp_path / f"out-{n}"), n, tmp_path / f"log-{n}") for n in steps]
    assert _runs_killed_at(built, data, runs) == [-signal.SIGKILL] * len(steps)
    for out, n, _ in runs:
        to = tmp_path / f"export-{n}"
        capsys.readouterr()
        code = cli.main(
            ["export", "--config", str(built.config), "--data", str(data), "--out", str(out)]
            + ["--format", "occ3d", "--to", str(to)]
        )
        assert code == 0, capsys.readouterr()
        seen = _consistent(out, "1")
        scenes = json.loads((to / "annotations.json").read_text())["scene_infos"]
        assert ("coda-1" in scenes) == (seen == "published"), (n, seen, sorted(scenes))
        report = run_units(
            load_config(built.config, {"dataset.root": str(data), "output.root": str(out)}),
            progress=False,
        )
        assert report.exit_code == (0 if scenario == "publish" else 1), summary_table(report)
        assert _consistent(out, "1") == want
        assert _published(out, "1") == expected["1"], n
        assert _exports(out) == expected["exports"], n
        assert _published(out, "0") == built.published["0"]
        shutil.rmtree(out)
    print(f"\nCASE | killed at each of {len(steps)} publication steps ({scenario}) | consistent")


# ---- the data changed under the dataset ----------------------------------------------------------


def _without_sequence(data: Path, seq: str) -> None:
    for path in sorted(data.rglob("*"), reverse=True):
        rel = path.relative_to(data)
        if seq in rel.parts or rel.stem == seq or f"_{seq}_" in path.name:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif os.path.lexists(path):
                path.unlink()


def test_a_sequence_gone_from_the_input_is_reported_and_pruned(
    built, tmp_path, capsys, monkeypatch
):
    """Regression: a sequence deleted from --data stayed published and exported, never
    mentioned."""
    _inline_flow(monkeypatch)
    env = _env(built, tmp_path)
    _without_sequence(env.data, "1")
    code, text = _cli(env, "status", capsys)
    assert code == 1 and "1  in the dataset but no longer under the data root" in text, text
    code, text = _cli(env, "rebuild", capsys)
    assert code == 0 and "GONE 1: " in text and "--prune" in text, text
    assert _published(env.out, "1") == built.published["1"]  # reported, not taken out
    code, text = _cli(env, "rebuild", capsys, "--prune")
    assert code == 0 and "PRUNED 1" in text, text
    assert not (env.out / "occupancy" / "1").exists()
    assert not list((env.out / "tables").glob("*/sequence=1"))
    assert not list((env.out / "stages").glob("*/1"))
    assert {seq for seq, _ in Manifest.load(env.out).rows} == {"0"}
    scenes = json.loads((env.out / "exports/occ3d/annotations.json").read_text())["scene_infos"]
    assert sorted(scenes) == ["coda-0"]
    assert _published(env.out, "0") == built.published["0"]
    code, text = _cli(env, "status", capsys)
    assert code == 0, text


def _rename_sequence(data: Path, old: str, new: str) -> None:
    for path in sorted(data.rglob("*"), key=lambda p: -len(p.parts)):
        name = path.name
        renamed = name.replace(f"_{old}_", f"_{new}_")
        if name == old:
            renamed = new
        elif path.is_file() and path.stem == old:
            renamed = new + path.suffix
        if path.suffix == ".json" and path.is_file():
            text = path.read_text()
            _put(path, text.replace(f"/{old}/", f"/{new}/").replace(f"_{old}_", f"_{new}_"))
        if renamed != name:
            path.rename(path.with_name(renamed))


def test_a_renamed_sequence_is_reported(built, tmp_path, capsys):
    """Regression: a renamed sequence was published twice, the old name never mentioned."""
    env = _env(built, tmp_path)
    _rename_sequence(env.data, "1", "5")
    code, text = _cli(env, "status", capsys)
    assert code == 1 and "1  in the dataset but no longer under the data root" in text, text
    assert "5  detect  stale: never ran" in text, text


@pytest.mark.parametrize("where", ["the data root", "a folder of other files"])
def test_out_must_be_a_store_of_its_own(where, built, tmp_path, capsys):
    """Regression: --out equal to --data was accepted (and the sweep of leftovers then deleted
    the user's own .tmp-* files in the data root)."""
    data = _link_copy(built.data, tmp_path / "data")
    (data / ".tmp-mine").write_text("the user's")
    out = data
    if where != "the data root":
        out = tmp_path / "elsewhere"
        out.mkdir()
        (out / "notes.txt").write_text("the user's")
    capsys.readouterr()
    code = cli.main(
        ["rebuild", "--config", str(built.config), "--data", str(data), "--out", str(out)]
    )
    err = capsys.readouterr().err
    says = "is the data root" if where == "the data root" else "not a mobileocc store's ('notes"
    assert code == cli.EXIT_USAGE and says in err and len(err.strip().splitlines()) == 1, err
    assert (data / ".tmp-mine").read_text() == "the user's"
    assert not (out / "manifest.json").exists()


# ---- signals ----------------------------------------------------------------------------------

#: the real CLI, with one stage slowed down in this process (thread runner): it leaves a marker
#: and sleeps, as a long stage computing in a pool thread would
SLOW_CLI = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    import flows.stages as stages
    stage, marker = sys.argv[1], Path(sys.argv[2])
    run = stages.STAGE_FUNCTIONS[stage]
    def slowed(ctx):
        marker.write_text(str(os.getpid()))
        time.sleep(600)
        return run(ctx)
    stages.STAGE_FUNCTIONS[stage] = slowed
    from flows.cli import main
    sys.exit(main(sys.argv[3:]))
""")


@pytest.mark.usefixtures("prefect_harness")
@pytest.mark.xdist_group("prefect")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_stops_a_run_within_seconds(sig, built, tmp_path, capsys, monkeypatch):
    """Regression: SIGTERM or Ctrl-C while a stage computed in a pool thread left the run
    computing and holding the lock for minutes; Ctrl-C printed a 60-line traceback."""
    from prefect.settings import PREFECT_API_URL

    from storage.manifest import run_lock

    env = _env(built, tmp_path)
    shutil.rmtree(env.stage("export"))  # the export of sequence 1 runs again, slowed
    marker = tmp_path / "started"
    proc = subprocess.Popen(
        [sys.executable, "-c", SLOW_CLI, "export", str(marker), *env.args("rebuild")],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "PREFECT_API_URL": PREFECT_API_URL.value()},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.time() + 300
        while not marker.exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.1)  # a start-up timeout, not a speed check
        assert marker.exists(), proc.communicate(timeout=60)
        proc.send_signal(sig)
        # the stage sleeps 600 s: ending before it means the run did not wait for it
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, err
    lines = err.strip().splitlines()
    assert lines[-1] == (
        f"mobileocc rebuild: stopped by {signal.Signals(sig).name}; finished units are kept, "
        "the same command resumes"
    ), err
    assert "Traceback" not in err
    with run_lock(env.out):  # released
        pass
    _inline_flow(monkeypatch)
    code, text = _cli(env, "rebuild", capsys)
    assert code == 0, text
    assert _published(env.out, "1") == built.published["1"]
    assert _exports(env.out) == built.exports


def test_ctrl_c_in_a_short_command_is_one_line():
    """Regression: Ctrl-C during a short command printed a 60-line traceback. Every command runs
    inside flows.pipeline.signals.stop_on_signals (flows.cli.main); a SIGINT arriving in the
    main thread while it computes ends it with one line and exit 130."""
    code = textwrap.dedent("""
        import os, signal, time
        from flows.pipeline.signals import stop_on_signals
        with stop_on_signals("mobileocc status"):
            sum(range(10**5))
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(60)
        print("not stopped")
    """)
    run = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 130 and run.stdout == "", (run.stdout, run.stderr)
    assert run.stderr.strip() == "mobileocc status: stopped by SIGINT", run.stderr


# ---- exports and readers ---------------------------------------------------------------------


def _export(env: Env, to: Path, capsys, *more: str) -> tuple[int, str]:
    return _cli(env, f"export --format occ3d --to {to}", capsys, *more)


@pytest.mark.parametrize(
    "target, says",
    [
        ("a-file", "exists and is not a folder"),
        ("others", "holds files that are not a mobileocc export"),
        ("/proc/mobileocc-export", "is not writable"),
        ("a-file/deeper", "a file stands where its folder"),
    ],
)
def test_export_refuses_a_place_it_cannot_take(target, says, built, tmp_path, capsys):
    """Regression: `export --to` an existing file or a read-only place printed a traceback."""
    env = Env(built.data, built.out, built.config)  # read only
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "others").mkdir()
    (tmp_path / "others" / "notes.txt").write_text("the user's")
    to = Path(target) if target.startswith("/") else tmp_path / target
    code, text = _export(env, to, capsys)
    assert code == cli.EXIT_USAGE and says in text and len(text.strip().splitlines()) == 1, text
    assert (tmp_path / "others" / "notes.txt").read_text() == "the user's"


def test_export_into_an_earlier_export_replaces_it_whole(built, tmp_path, capsys):
    """Regression: `--to` was written in place, so a withdrawn sequence's old labels stayed in a
    reused folder."""
    to = tmp_path / "export"
    code, _ = _export(Env(built.data, built.out, built.config), to, capsys)
    assert code == 0 and (to / "gts" / "coda-1").is_dir()
    code, text = _export(Env(built.broken, built.withdrawn, built.config), to, capsys)
    assert code == 0, text
    assert not (to / "gts" / "coda-1").exists()
    scenes = json.loads((to / "annotations.json").read_text())["scene_infos"]
    assert sorted(scenes) == ["coda-0"]


HOLD = textwrap.dedent("""
    import sys
    from storage.manifest import read_lock, run_lock
    with (run_lock if sys.argv[2] == "run" else read_lock)(sys.argv[1]):
        print("holding", flush=True)
        sys.stdin.read()
""")


@pytest.mark.parametrize("holder", ["run", "read"])
def test_readers_and_runs_exclude_each_other(holder, built, tmp_path, capsys):
    """Regression: `export` took no lock; during a rebuild it wrote 0.4 m and 0.8 m grids side
    by side."""
    env = _env(built, tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(env.out), holder],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "holding"
        if holder == "run":
            code, text = _export(env, tmp_path / "export", capsys)
            says = "is in use by a run"
        else:
            code, text = _cli(env, "rebuild", capsys)
            says = "is being read"
        assert code == cli.EXIT_BUSY and says in text, text
        assert len(text.strip().splitlines()) == 1, text
        if holder == "read":  # readers share it
            code, text = _export(env, tmp_path / "export", capsys)
            assert code == 0, text
    finally:
        proc.communicate("", timeout=60)


def test_evaluate_names_a_withdrawn_sequence(built, tmp_path, capsys):
    """Regression: `evaluate` never mentioned a withdrawn sequence."""
    out = _link_copy(built.withdrawn, tmp_path / "out")
    capsys.readouterr()
    code = cli.main(
        [
            "evaluate",
            "--dataset",
            str(out),
            "--gt",
            str(built.data),
            "--report",
            str(tmp_path / "r"),
        ]
    )
    text = capsys.readouterr().out
    assert code == 0 and "NOT EVALUATED sequence 1: withdrawn, not evaluated" in text, text
    assert "calib_os1_to_cam0.yaml" in text
    results = json.loads((tmp_path / "r" / "results.json").read_text())
    assert "withdrawn" in results["notes"]["sequence 1"]["note"]


def test_a_read_only_store_can_be_read(built, tmp_path, capsys, monkeypatch):
    """Issue 41: on a read-only store (a finished dataset on a read-only mount) `status`,
    `evaluate --report ELSEWHERE`, `export --to ELSEWHERE` and `view --html` work and write
    nothing into it; a run, or a report into it, is one line naming the read-only place."""
    from tests.read_only import read_only_store

    out = _link_copy(built.out, tmp_path / "out")
    before = _files(out)
    with read_only_store(out, monkeypatch) as (ro, how):
        env = Env(built.data, ro, built.config)
        code, text = _cli(env, "status", capsys)
        assert code == 0 and "fresh" in text and "Traceback" not in text, (how, text)
        code, text = _export(env, tmp_path / "export", capsys)
        assert code == 0 and "export written" in text, (how, text)
        assert (tmp_path / "export" / "annotations.json").is_file()
        for args in (
            [
                "evaluate",
                "--dataset",
                str(ro),
                "--gt",
                str(built.data),
                "--report",
                str(tmp_path / "r"),
            ],
            ["view", "--dataset", str(ro), "--html", str(tmp_path / "v.html")],
        ):
            capsys.readouterr()
            code = cli.main(args)
            text = "".join(capsys.readouterr())
            assert code == 0 and "Traceback" not in text, (how, args[0], text)
        code, text = _cli(env, "rebuild", capsys)
        assert code == cli.EXIT_USAGE and str(ro) in text and "not writable" in text, (how, text)
        assert len(text.strip().splitlines()) == 1, text
        capsys.readouterr()
        code = cli.main(["evaluate", "--dataset", str(ro), "--report", str(ro / "r")])
        text = capsys.readouterr().err
        assert code == cli.EXIT_FAILED and str(ro / "r") in text and "Traceback" not in text, text
        assert "read-only" in text or "ermission denied" in text, text
    assert _files(out) == before


def _full_disk_under(monkeypatch, folder: Path, part: str = "") -> None:
    """Every atomic write under ``folder`` (whose path holds ``part``) fails as on a full disk:
    ENOSPC at the fsync of storage.atomic, the helper every file of the store is written through
    (a loop device or tmpfs the test could fill is not there as a user in CI)."""
    import errno

    from storage import atomic

    real = atomic._fsync_path

    def fsync(path, directory=False):
        if str(path).startswith(str(folder)) and part in str(path) and not directory:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, directory)

    monkeypatch.setattr(atomic, "_fsync_path", fsync)


def test_a_full_disk_ends_the_run_at_once_and_the_next_run_completes(
    built, tmp_path, capsys, monkeypatch
):
    """Issue 41: a full disk while a stage writes ended in a hang, then "in use by another run"
    and `.tmp-*` files left. Now: exit 1 and one line naming the file system, no lock and no
    temporary left; after space is freed the next run completes, byte-identical."""
    _inline_flow(monkeypatch)
    env = _env(built, tmp_path)
    (env.stage("fuse") / "complete.json").unlink()  # sequence 1's fuse runs again
    _full_disk_under(monkeypatch, env.out, "stages/fuse")
    code, text = _cli(env, "rebuild", capsys)
    assert code == cli.EXIT_FAILED, text
    assert "no space left on the file system at" in text and "MB free" in text, text
    assert len(text.strip().splitlines()) == 1 and "Traceback" not in text, text
    assert not (env.out / ".lock").exists()
    assert not [p for p in env.out.rglob(".tmp-*")], list(env.out.rglob(".tmp-*"))
    assert _published(env.out, "0") == built.published["0"]
    monkeypatch.undo()  # space freed
    _inline_flow(monkeypatch)
    code, text = _cli(env, "rebuild", capsys)
    assert code == 0, text
    assert _published(env.out, "1") == built.published["1"]


def test_a_full_disk_during_export_to_is_not_export_written(built, tmp_path, capsys, monkeypatch):
    """Issue 41: a full disk during `export --to` gave exit 0 and "export written"."""
    env = Env(built.data, built.out, built.config)  # read only
    to = tmp_path / "export"
    _full_disk_under(monkeypatch, tmp_path)
    code, text = _export(env, to, capsys)
    assert code == cli.EXIT_FAILED and "no space left on the file system" in text, text
    assert "export written" not in text and len(text.strip().splitlines()) == 1, text
    assert not to.exists() and not list(tmp_path.glob(".tmp-*"))


# ---- the command line's edges --------------------------------------------------------------------


def _edge(kind: str, env: Env, tmp_path: Path) -> tuple[list[str], dict, int, str]:
    """(arguments, environment, exit code, what stderr must say) of one edge."""
    run = env.args("rebuild")
    return {
        "--set without =": (run + ["--set", "fit.iterations"], {}, 2, "expected KEY=VALUE"),
        "--set broken YAML": (run + ["--set", "fit.iterations=[1"], {}, 2, "is not YAML"),
        "1e12 for a number": (
            run + ["--set", "fit.iterations=1e12"],
            {},
            2,
            "YAML reads 1e12 as text (an exponent needs a decimal point and a sign",
        ),
        "fit.iterations that cannot finish": (
            run + ["--set", "fit.iterations=1.0e+12"],
            {},
            2,
            "one person-frame alone would take ~63.4 years",
        ),
        "a grid of 10^9 voxels": (
            run
            + ["--set", "fuse.grid.voxel_size_m=0.02", "--set", "fuse.grid.range_min=[-10,-10,-10]"]
            + ["--set", "fuse.grid.range_max=[10,10,10]"],
            {},
            2,
            "would take 9.0 GB of memory",
        ),
        "simulate --frames 0": (
            ["simulate", "--out", str(tmp_path / "sim"), "--frames", "0"],
            {},
            2,
            "--frames: must be at least 1, got 0",
        ),
        "a stale PREFECT_API_URL": (
            run + ["--force"],
            {"PREFECT_API_URL": "http://127.0.0.1:9/api"},
            2,
            "PREFECT_API_URL=http://127.0.0.1:9/api does not answer",
        ),
        "--address of a dead scheduler": (
            run + ["--address", "tcp://127.0.0.1:9"],
            {},
            2,
            "dask.address tcp://127.0.0.1:9: no Dask scheduler answers there",
        ),
        # issue 41
        "view --port 99999": (
            ["view", "--dataset", str(env.out), "--port", "99999"],
            {},
            2,
            "--port: must be at most 65535, got 99999",
        ),
        "simulate --frames 1e9": (
            ["simulate", "--out", str(tmp_path / "sim"), "--frames", "1000000000"],
            {},
            2,
            "--frames: must be at most 36000",
        ),
        "a binary --config": (run + ["--config", str(_binary(tmp_path))], {}, 2, "is not UTF-8"),
        "a folder as --config": (run + ["--config", str(tmp_path)], {}, 2, "is a folder"),
        "a non-UTF-8 --out": (
            run + ["--out", str(tmp_path) + "/\udcff"],
            {},
            2,
            "the path is not UTF-8",
        ),
        "status --out a missing folder": (
            env.args("status") + ["--out", str(tmp_path / "nowhere")],
            {},
            2,
            "nowhere does not exist",
        ),
        "fit.iterations: -5": (
            run + ["--set", "fit.iterations=-5"],
            {},
            2,
            "fit.iterations: Input should be greater than or equal to 0",
        ),
    }[kind]


def _binary(tmp_path: Path) -> Path:
    path = tmp_path / "garbage.yaml"
    path.write_bytes(bytes(range(256)) * 4)
    return path


EDGES = [
    "--set without =",
    "--set broken YAML",
    "1e12 for a number",
    "fit.iterations that cannot finish",
    "a grid of 10^9 voxels",
    "simulate --frames 0",
    "a stale PREFECT_API_URL",
    "--address of a dead scheduler",
    "view --port 99999",
    "simulate --frames 1e9",
    "a binary --config",
    "a folder as --config",
    "a non-UTF-8 --out",
    "status --out a missing folder",
    "fit.iterations: -5",
]


@pytest.mark.parametrize("kind", EDGES)
def test_an_edge_of_the_command_line_is_one_clear_line(kind, built, tmp_path, capsys, monkeypatch):
    env = _env(built, tmp_path)
    args, environ, want, says = _edge(kind, env, tmp_path)
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    capsys.readouterr()
    try:
        code = cli.main(args)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    err = capsys.readouterr().err
    assert code == want and says in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 2, err
    assert _published(env.out, "1") == built.published["1"]
    print(f"\nCASE | {kind} | cli | exit {code} | {err.strip().splitlines()[-1][:160]}")


def test_a_sequence_id_that_is_not_a_number(built, tmp_path):
    """Regression: a non-numeric sequence id failed on int() (the oracle's ground truth)."""
    from flows.pipeline.plan import plan_run
    from flows.pipeline.units import execute_unit

    data = _link_copy(built.data, tmp_path / "data")
    _rename_sequence(data, "1", "west")
    cfg = load_config(
        built.config,
        {
            "dataset.root": str(data),
            "output.root": str(tmp_path / "out"),
            "dataset.sequences": ["west"],
        },
    )
    [plan] = plan_run(cfg, Manifest(tmp_path / "out"))
    assert not plan.error, plan.error
    outcome = execute_unit(plan.units["detect"], tmp_path / "out", {}, plan.fingerprint)
    assert outcome.status == "done", outcome.error


def test_an_empty_precomputed_cliff_file_is_refused(tmp_path):
    """Regression: an empty precomputed CLIFF file gave a dataset without bodies, no warning."""
    from flows.pipeline.inputs import PrecomputedSpec
    from flows.stages.providers import PrecomputedCliff
    from storage.cliff_files import CliffFileError, cliff_path, write_cliff_estimates

    path = cliff_path(tmp_path, "1")
    write_cliff_estimates(
        path, np.zeros(0, int), np.zeros(0, int), np.zeros((0, 24, 3, 3)), np.zeros((0, 10))
    )
    cliff = PrecomputedCliff(
        PrecomputedSpec(str(tmp_path)),
        SimpleNamespace(sequence="1"),
        None,
        SimpleNamespace(K=np.eye(3)),
    )
    tracks = SimpleNamespace(
        track_id=np.array([1, 1]), frame=np.array([0, 2]), det_index=np.array([0, 0])
    )
    with pytest.raises(CliffFileError, match="holds no CLIFF estimate, but 2 tracked detection"):
        cliff.available(tracks)
    assert str(path) in str(pytest.raises(CliffFileError, cliff.available, tracks).value)
    empty = SimpleNamespace(track_id=np.zeros(0), frame=np.zeros(0), det_index=np.zeros(0))
    assert len(cliff.available(empty)) == 0  # no person, no estimate needed
