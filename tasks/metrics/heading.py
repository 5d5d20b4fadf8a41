"""Heading errors of boxes: angle between predicted and true yaw, in degrees."""

from __future__ import annotations

import numpy as np


def heading_errors_deg(pred_yaw, gt_yaw) -> np.ndarray:
    """|pred - gt| wrapped to [0, 180] degrees; pred_yaw, gt_yaw: (N,) rad about the same z axis."""
    d = np.asarray(pred_yaw, np.float64) - np.asarray(gt_yaw, np.float64)
    return np.degrees(np.abs(np.arctan2(np.sin(d), np.cos(d))))


def heading_summary(errors_deg) -> dict:
    """Median / p90 of heading errors (deg), the share more than 45 deg off along the box axis
    (modulo 180 deg: l / w swapped), and the count. NaN figures when there are no boxes."""
    e = np.asarray(errors_deg, np.float64).reshape(-1)
    if e.size == 0:
        return {
            "boxes": 0,
            "median_deg": float("nan"),
            "p90_deg": float("nan"),
            "axis_off_45_share": float("nan"),
        }
    axis = np.minimum(e, 180.0 - e)
    return {
        "boxes": int(e.size),
        "median_deg": float(np.median(e)),
        "p90_deg": float(np.percentile(e, 90)),
        "axis_off_45_share": float(np.mean(axis > 45.0)),
    }
