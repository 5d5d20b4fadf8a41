"""Multi-object tracking of pedestrians across frames (OC-SORT)."""
