"""Per-point classes from geometry alone against the simulator's exact point labels.

``mobileocc bench geometric-classes --data DATA [--config CFG] [--set k=v ...] [--every N] --json J``

For every N-th frame of every sequence under DATA (written by ``mobileocc simulate``): the map
stage's weight-free classifier (:func:`tasks.occupancy.geometric_classes.geometric_classes`, the
config's ``map.geometry`` settings) labels the sweep, and each return is compared with the class of
the triangle it hit (``gt/{SEQ}/gt_{SEQ}_{FRAME}.npz`` ``point_class``). Per true class: precision,
recall, IoU over the labelled returns, and the share the classifier left UNLABELED; the confusion
matrix (rows: truth, columns: predicted, the last column UNLABELED).
"""

from __future__ import annotations

import time

import numpy as np

from flows.pipeline.inputs import open_sequence
from flows.pipeline.plan import selected_sequences
from storage.gt import read_frame_gt
from tasks.conventions import CLASS_NAMES, NUM_SEMANTIC_CLASSES, UNLABELED
from tasks.occupancy.geometric_classes import (
    GeometricClassSettings,
    geometric_classes,
    gravity_aligned,
)

#: the semantic classes (0 .. 8): rows of the confusion matrix
CLASSES = NUM_SEMANTIC_CLASSES


def sweep_confusion(truth: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """(CLASSES, CLASSES + 1) int64 counts: truth (N,) uint8 (returns of class >= CLASSES are
    skipped), predicted (N,) uint8 (UNLABELED in the last column)."""
    t = np.asarray(truth).astype(np.int64)
    p = np.asarray(predicted).astype(np.int64)
    keep = t < CLASSES
    p = np.where(p == UNLABELED, CLASSES, p)
    if np.any(p[keep] > CLASSES):
        raise ValueError(f"predicted class {int(p[keep].max())} is not a class id")
    flat = np.bincount(t[keep] * (CLASSES + 1) + p[keep], minlength=CLASSES * (CLASSES + 1))
    return flat.reshape(CLASSES, CLASSES + 1)


def class_scores(confusion: np.ndarray) -> list[dict]:
    """Per true class of a :func:`sweep_confusion` sum: returns, precision, recall and IoU (NaN
    where undefined), the UNLABELED share."""
    c = np.asarray(confusion, np.float64)
    tp = np.diag(c[:, :CLASSES])
    truth = c.sum(axis=1)
    predicted = c[:, :CLASSES].sum(axis=0)
    rows = []
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = tp / predicted
        recall = tp / truth
        iou = tp / (truth + predicted - tp)
        unlabeled = c[:, CLASSES] / truth
    for k in range(CLASSES):
        rows.append(
            {
                "class": CLASS_NAMES[k],
                "returns": int(truth[k]),
                "predicted": int(predicted[k]),
                "precision": float(precision[k]),
                "recall": float(recall[k]),
                "iou": float(iou[k]),
                "unlabeled_share": float(unlabeled[k]),
            }
        )
    return rows


def bench_geometric_classes(config, every: int = 1) -> dict:
    """Confusion and per-class scores of the classifier on DATA's sequences (every ``every``-th
    frame)."""
    settings = config.map.geometry.to(GeometricClassSettings)
    total = np.zeros((CLASSES, CLASSES + 1), np.int64)
    frames, seconds = 0, 0.0
    for seq_id in selected_sequences(config):
        seq = open_sequence(config, seq_id)
        for i in range(0, seq.info.num_frames, every):
            frame = seq.frame(i)
            gt = read_frame_gt(seq.root, seq_id, frame.index)
            if frame.point_index is None:
                raise ValueError(
                    f"{frame.lidar_path} (frame {frame.index}): no organised point order to "
                    "align the ground truth's point_class with"
                )
            truth = gt.point_class[frame.point_index]
            t = time.perf_counter()
            predicted = geometric_classes(
                gravity_aligned(frame.T_world_from_lidar, frame.points_lidar),
                frame.intensity if frame.intensity_present else None,
                settings,
            )
            seconds += time.perf_counter() - t
            total += sweep_confusion(truth, predicted)
            frames += 1
    labelled = total[:, :CLASSES].sum()
    return {
        "frames": frames,
        "ms_per_sweep": 1000.0 * seconds / max(frames, 1),
        "returns": int(total.sum()),
        "unlabeled_share": float(total[:, CLASSES].sum() / max(total.sum(), 1)),
        "accuracy_of_labelled": float(np.trace(total[:, :CLASSES]) / max(labelled, 1)),
        "classes": class_scores(total),
        "confusion": total.tolist(),
    }


def format_table(result: dict) -> str:
    """The per-class scores and the confusion matrix as text."""
    lines = [
        f"{result['frames']} sweeps, {result['returns']} returns, "
        f"{result['ms_per_sweep']:.0f} ms/sweep; unlabeled {result['unlabeled_share']:.3f}, "
        f"accuracy of the labelled {result['accuracy_of_labelled']:.3f}",
        f"{'class':16s} {'returns':>8s} {'prec':>6s} {'recall':>6s} {'IoU':>6s} {'unlab':>6s}",
    ]
    for r in result["classes"]:
        lines.append(
            f"{r['class']:16s} {r['returns']:8d} {r['precision']:6.3f} {r['recall']:6.3f} "
            f"{r['iou']:6.3f} {r['unlabeled_share']:6.3f}"
        )
    short = [n[:6] for n in CLASS_NAMES[:CLASSES]] + ["unlab"]
    lines.append("confusion (rows truth, columns predicted):")
    lines.append(f"{'':16s} " + " ".join(f"{n:>7s}" for n in short))
    for name, row in zip(CLASS_NAMES, result["confusion"]):
        lines.append(f"{name:16s} " + " ".join(f"{v:7d}" for v in row))
    return "\n".join(lines)
