"""Evaluation metric kernels (issue #9): label quality, detection, tracking, velocity.

Pure numpy / scipy (py-motmetrics for MOTA / IDF1). Grids follow :mod:`tasks.conventions`:
``[x, y, z]`` uint8 class ids (0 pedestrian .. 8 vegetation, 9 unclassified, 10 free). Every score that can be
accumulated over frames or sequences is a frozen dataclass of counts with ``+`` (micro average:
sum the counts, then divide), and ``as_dict()`` giving the plain numbers the report writer takes.
Ratios are fractions in [0, 1] (the report prints them as percentages); NaN where undefined.
Fit metrics (PVE / MPJPE / PA-MPJPE / MPERE) live in :mod:`tasks.fit.metrics`.
"""
