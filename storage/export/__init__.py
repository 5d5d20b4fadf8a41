"""Exports of a published dataset to the formats occupancy trainers read.

- :func:`storage.export.occ3d.export_occ3d`: Occ3D ``gts/<scene>/<token>/labels.npz`` + ``annotations.json``.
- :func:`storage.export.nuscenes.export_nuscenes`: the 13 nuScenes tables, sweeps and images.

Both name scenes and samples the same way (:mod:`storage.export.common`), so the Occ3D labels of a
sample are found from its nuScenes sample token, as BEVDet / FlashOcc look them up.
"""

from storage.export.nuscenes import export_nuscenes
from storage.export.occ3d import export_occ3d

__all__ = ["export_nuscenes", "export_occ3d"]
