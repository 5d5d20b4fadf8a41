"""The CODa label mapping of `evaluate --labels coda`."""

from __future__ import annotations

import numpy as np

from tasks import conventions as C
from tasks.metrics.coda_labels import (
    CODA_BOX_CLASS_TO_CLASS,
    CODA_SEMANTIC_IDS,
    CODA_SEMANTIC_NAMES,
    box_class,
    semantic_to_classes,
)


def test_semantic_table():
    # coda-devkit helpers/constants.py: 25 terrain ids, 0 Unlabeled .. 24 Unknown
    assert len(CODA_SEMANTIC_NAMES) == 25
    assert (
        CODA_SEMANTIC_IDS["Concrete"],
        CODA_SEMANTIC_IDS["Road Pavement"],
        CODA_SEMANTIC_IDS["Short Vegetation"],
        CODA_SEMANTIC_IDS["Unknown"],
    ) == (1, 10, 11, 24)
    ids = np.arange(256, dtype=np.uint8)
    got = semantic_to_classes(ids)
    assert got[0] == got[24] == C.UNLABELED and np.all(got[25:] == C.UNLABELED)
    assert (
        got[1] == got[10] == got[18] == C.ROAD
        and got[2] == got[9] == C.TERRAIN
        and got[11] == C.VEGETATION
    )
    assert set(got[1:24].tolist()) == {
        C.ROAD,
        C.TERRAIN,
        C.VEGETATION,
    }  # every terrain id has a class


def test_box_table():
    assert len(CODA_BOX_CLASS_TO_CLASS) == 59  # every classId of the devkit's BBOX_CLASS_TO_ID
    assert box_class("Pedestrian") == C.PEDESTRIAN and box_class("Bus") == C.TRUCK
    assert box_class("Segway") == C.TWO_WHEELER and box_class("Tree") == C.VEGETATION
    assert box_class("Bench") == C.OTHER_STRUCTURE and box_class("Horse") == C.UNLABELED
    assert box_class("Spaceship") is None
