"""Every cache product is verified before use and made again when damaged (issue 41, item 4).

OUT/.cache holds the procedural body model and prior, the log indexes, the odometry and the
planning memos: each is checked when read (a truncated, foreign or garbage file is a miss, never a
failed fit), and ``rebuild --force`` removes them all (storage.manifest.remove_caches)."""

from __future__ import annotations

import numpy as np
import pytest

from flows.pipeline.inputs import BodyModelFiles
from flows.stages.common import body_model, pose_prior
from storage.manifest import (
    CACHE_PRODUCTS,
    PROCEDURAL_MODEL,
    PROCEDURAL_PRIOR,
    FingerprintCache,
    remove_caches,
)
from storage.sources.log.reader import LogSequence
from tests.log_fixture import make_log

NO_FILES = BodyModelFiles(None, None)


def _damage(path, how):
    data = path.read_bytes()
    path.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"\x00" * 64,
                      "empty": b""}[how])  # fmt: skip


@pytest.mark.parametrize("how", ["truncated", "garbage", "empty"])
@pytest.mark.parametrize("name", [PROCEDURAL_MODEL, PROCEDURAL_PRIOR])
def test_a_damaged_procedural_cache_is_made_again(name, how, tmp_path):
    get = body_model if name == PROCEDURAL_MODEL else pose_prior
    first = get(NO_FILES, tmp_path)
    path = tmp_path / ".cache" / name
    good = path.read_bytes()
    _damage(path, how)
    again = get(NO_FILES, tmp_path)  # no BadZipFile: verified, made again
    assert path.read_bytes() == good
    ref = first.v_template if name == PROCEDURAL_MODEL else first.means
    new = again.v_template if name == PROCEDURAL_MODEL else again.means
    np.testing.assert_array_equal(np.asarray(new), np.asarray(ref))


def test_force_removes_every_cache_product(tmp_path):
    body_model(NO_FILES, tmp_path)
    pose_prior(NO_FILES, tmp_path)
    for folder in ("log-index", "odometry", "sequences"):
        (tmp_path / ".cache" / folder).mkdir(parents=True)
        (tmp_path / ".cache" / folder / "x").write_bytes(b"1")
    (tmp_path / ".cache" / "keep.txt").write_bytes(b"not ours")
    assert remove_caches(tmp_path) == len(CACHE_PRODUCTS)
    assert sorted(p.name for p in (tmp_path / ".cache").iterdir()) == ["keep.txt"]


@pytest.mark.parametrize("how", ["truncated", "garbage", "empty"])
def test_a_damaged_log_index_and_odometry_are_computed_again(how, tmp_path):
    path = make_log(tmp_path / "a.mcap", poses="none")
    cache = tmp_path / "cache"
    first = LogSequence(path, frame_stride=1, cache_dir=cache).odometry_poses()
    files = [*(cache / "log-index").iterdir(), *(cache / "odometry").iterdir()]
    assert len(files) == 2
    for f in files:
        _damage(f, how)
    again = LogSequence(path, frame_stride=1, cache_dir=cache).odometry_poses()
    np.testing.assert_array_equal(again, first)


@pytest.mark.parametrize("memo", [b"[1, 2]", b'{"files": 3}', b"\xff garbage", b"null"])
def test_a_damaged_fingerprint_memo_is_not_used(memo, tmp_path):
    (tmp_path / "seq0.json").write_bytes(memo)
    assert FingerprintCache(tmp_path).load("seq0") == {}
