"""The bench's stage breakdown charges library time to the functions of ours that called it."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from flows.bench.pipeline import _charge_to_own_code


def test_library_time_split_over_our_callers_by_time():
    a = ("/x/tasks/occupancy/fuse.py", 10, "voxelize_mesh")
    b = ("/x/tasks/occupancy/visibility.py", 20, "camera_mask")
    wait = ("~", 0, "<method 'acquire' of '_thread.lock' objects>")
    result = ("/usr/lib/python3/concurrent/futures/_base.py", 5, "result")
    stats = SimpleNamespace(
        stats={
            a: (1, 1, 0.5, 2.0, {}),
            b: (1, 1, 0.25, 4.25, {}),
            result: (2, 2, 0.0, 4.0, {a: (1, 1, 0.0, 1.0), b: (1, 1, 0.0, 3.0)}),
            wait: (2, 2, 4.0, 4.0, {result: (2, 2, 4.0, 4.0)}),
        }
    )
    costs = _charge_to_own_code(stats)
    assert costs["tasks/occupancy/fuse.py:voxelize_mesh"] == pytest.approx(0.5 + 1.0)
    assert costs["tasks/occupancy/visibility.py:camera_mask"] == pytest.approx(0.25 + 3.0)
    assert sum(costs.values()) == pytest.approx(4.75)
