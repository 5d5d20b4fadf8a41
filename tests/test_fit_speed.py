"""The fit stage's speed cuts (issue 29 item 6) keep its results: the oracle's starts read each
frame's ground truth once, and the cuts in the fit kernel give what the plain code gave."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tasks.body.params import BodyParams
from tasks.body.procedural import default_body_model


@pytest.fixture(scope="module")
def model():
    return default_body_model()


def _frame_truth(frame: int, persons: int) -> SimpleNamespace:
    rng = np.random.default_rng(frame)
    return SimpleNamespace(
        betas=rng.normal(0, 0.5, (persons, 10)).astype(np.float32),
        global_orient=rng.normal(0, 0.3, (persons, 3)).astype(np.float32),
        body_pose=rng.normal(0, 0.1, (persons, 69)).astype(np.float32),
        transl=(rng.normal(0, 1, (persons, 3)) + [0, 0, 6]).astype(np.float32),
    )


def test_oracle_starts_read_each_frame_once_and_match_a_read_per_row(model, monkeypatch):
    import flows.stages.providers as providers
    from flows.pipeline.inputs import OracleInitSpec
    from flows.stages.common import frame_rng
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.reframe import reframe_params

    truths = {f: _frame_truth(f, 4) for f in (10, 12, 14)}
    reads: list[int] = []

    def read(root, sequence, frame):
        reads.append(frame)
        return truths[frame]

    monkeypatch.setattr(providers, "read_frame_gt", read)
    T_cl = np.eye(4)
    T_cl[:3, 3] = [0.1, -0.2, 0.3]
    seq = SimpleNamespace(root="unused", sequence="0")
    init = providers.OracleInit(
        OracleInitSpec(3), seq, model, SimpleNamespace(T_cam_from_lidar=T_cl)
    )
    frame = np.array([10, 10, 12, 12, 12, 14, 10, 14])
    gt_index = np.array([0, 2, 1, 3, 0, 2, 3, 0])
    tracks = SimpleNamespace(frame=frame, gt_index=gt_index)
    rows = np.array([1, 0, 2, 3, 4, 5, 6, 7])
    got = init.estimates(tracks, rows)
    assert sorted(reads) == [10, 12, 14]  # one read per frame, not one per row
    truth = BodyParams.concat(
        [BodyParams.of(truths[int(frame[r])]).take([int(gt_index[r])]) for r in rows]
    )
    want = oracle_initial_estimate(
        model, reframe_params(model, truth, T_cl), frame_rng(3, "0", int(rows[0]), 3)
    )
    for k in BodyParams.FIELDS:
        assert np.array_equal(getattr(got, k), getattr(want, k)), k
