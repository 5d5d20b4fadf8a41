"""tasks/body/params.py: the one body-parameter bundle, and the records that carry its arrays."""

from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace

import numpy as np

from tasks.body.params import BodyParams
from tasks.fit.optimize import FitResult


def _params(n: int, offset: float = 0.0) -> BodyParams:
    return BodyParams(
        *(np.full((n, w), offset + k, np.float32) for k, w in enumerate((10, 3, 69, 3)))
    )


def test_rows_concat_and_empty():
    a, b = _params(2), _params(3, offset=10.0)
    both = BodyParams.concat([a, b])
    assert len(both) == 5 and both.transl.shape == (5, 3)
    picked = both.take([4, 0])
    assert picked.betas[:, 0].tolist() == [10.0, 0.0] and picked.body_pose[:, 0].tolist() == [
        12.0,
        2.0,
    ]
    assert len(BodyParams.empty()) == 0 and BodyParams.empty().body_pose.shape == (0, 69)


def test_of_reads_attributes_or_keys_and_fit_results_are_body_params():
    p = _params(2)
    arrays = {f: getattr(p, f) for f in BodyParams.FIELDS}
    q = BodyParams.of(SimpleNamespace(**arrays, vertices=None))
    assert type(q) is BodyParams and all(getattr(q, f) is arrays[f] for f in BodyParams.FIELDS)
    assert BodyParams.of({**arrays, "rows": None}).transl is p.transl
    assert BodyParams.FIELDS == tuple(f.name for f in fields(BodyParams))
    fit = FitResult(
        **arrays, vertices=np.zeros((2, 5, 3)), joints=np.zeros((2, 24, 3)), residuals={}
    )
    assert isinstance(fit, BodyParams) and len(fit) == 2
    assert type(fit.params()) is BodyParams and fit.params().betas is p.betas
