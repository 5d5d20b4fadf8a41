"""CODa's own labels in our classes: the mapping tables behind ``mobileocc evaluate --labels coda``.

CODa (ut-amrl/coda-devkit, helpers/constants.py and docs/DATA_REPORT.md) labels LiDAR points of the
*terrain* with 25 ids (3d_semantic) and objects with 3D boxes of 59 class names (3d_bbox). Our
classes (tasks.conventions) follow Cityscapes, whose ``road`` takes road and sidewalk, ``terrain``
grass, soil and low horizontal vegetation, ``vegetation`` trees, hedges and vertical vegetation.

3d_semantic id -> our class (``CODA_SEMANTIC_TO_CLASS``):

| id | CODa name | ours | why |
| --- | --- | --- | --- |
| 0 | Unlabeled | ignored | not terrain: the point has no label |
| 1 | Concrete | road | sidewalk surface; Cityscapes (and our static map) call sidewalks road |
| 2 | Grass | terrain | |
| 3 | Rocks | terrain | natural ground |
| 4 | Speedway Bricks | road | paved walkway |
| 5 | Red Bricks | road | paved walkway |
| 6 | Pebble Pavement | road | paved walkway |
| 7 | Light Marble Tiling | road | paved walkway |
| 8 | Dark Marble Tiling | road | paved walkway |
| 9 | Dirt Paths | terrain | unpaved ground (Cityscapes terrain: soil) |
| 10 | Road Pavement | road | |
| 11 | Short Vegetation | vegetation | the paper's road / vegetation / terrain figures need it; a segmenter calls it terrain or vegetation depending on context, which the paper names as the main loss |
| 12 | Porcelain Tile | road | walkable floor |
| 13 | Metal Grates | road | walkable floor |
| 14 | Blond Marble Tiling | road | walkable floor |
| 15 | Wood Panel | road | walkable floor |
| 16 | Patterned Tile | road | walkable floor |
| 17 | Carpet | road | walkable floor (indoor) |
| 18 | Crosswalk | road | |
| 19 | Dome Mat | road | tactile paving |
| 20 | Stairs | road | walkable surface (Cityscapes puts outdoor steps in sidewalk) |
| 21 | Door Mat | road | walkable floor |
| 22 | Threshold | road | walkable floor |
| 23 | Metal Floor | road | walkable floor |
| 24 | Unknown | ignored | the annotators could not tell |

3d_bbox class -> our class (``CODA_BOX_CLASS_TO_CLASS``): Pedestrian -> pedestrian; Car, Golf Cart
-> car; Truck, Pickup Truck, Delivery Truck, Service Vehicle, Utility Vehicle, Bus -> truck
(Cityscapes puts pickups and buses with trucks); Bike, Motorcycle, Scooter, Segway, Skateboard ->
two-wheeler; Tree, Freestanding Plant -> vegetation; Pole, Traffic Light, Traffic Sign, Bollard ->
pole; Horse -> ignored (no class); every other (static) class -> other-structure. The evaluation
uses the pedestrian boxes; the rest of the table says what the other boxes are.
"""

from __future__ import annotations

import numpy as np

from tasks import conventions as C

#: CODa 3d_semantic id -> name (coda-devkit helpers/constants.py SEM_CLASS_TO_ID, inverted)
CODA_SEMANTIC_NAMES: tuple[str, ...] = (
    "Unlabeled",
    "Concrete",
    "Grass",
    "Rocks",
    "Speedway Bricks",
    "Red Bricks",
    "Pebble Pavement",
    "Light Marble Tiling",
    "Dark Marble Tiling",
    "Dirt Paths",
    "Road Pavement",
    "Short Vegetation",
    "Porcelain Tile",
    "Metal Grates",
    "Blond Marble Tiling",
    "Wood Panel",
    "Patterned Tile",
    "Carpet",
    "Crosswalk",
    "Dome Mat",
    "Stairs",
    "Door Mat",
    "Threshold",
    "Metal Floor",
    "Unknown",
)
CODA_SEMANTIC_IDS: dict[str, int] = {name: i for i, name in enumerate(CODA_SEMANTIC_NAMES)}

_SEMANTIC_TO_CLASS: dict[str, int] = {
    "Concrete": C.ROAD,
    "Grass": C.TERRAIN,
    "Rocks": C.TERRAIN,
    "Speedway Bricks": C.ROAD,
    "Red Bricks": C.ROAD,
    "Pebble Pavement": C.ROAD,
    "Light Marble Tiling": C.ROAD,
    "Dark Marble Tiling": C.ROAD,
    "Dirt Paths": C.TERRAIN,
    "Road Pavement": C.ROAD,
    "Short Vegetation": C.VEGETATION,
    "Porcelain Tile": C.ROAD,
    "Metal Grates": C.ROAD,
    "Blond Marble Tiling": C.ROAD,
    "Wood Panel": C.ROAD,
    "Patterned Tile": C.ROAD,
    "Carpet": C.ROAD,
    "Crosswalk": C.ROAD,
    "Dome Mat": C.ROAD,
    "Stairs": C.ROAD,
    "Door Mat": C.ROAD,
    "Threshold": C.ROAD,
    "Metal Floor": C.ROAD,
}

#: (256,) uint8 lookup CODa 3d_semantic id -> our class id (UNLABELED: ignored or not a CODa id)
CODA_SEMANTIC_TO_CLASS: np.ndarray = np.full(256, C.UNLABELED, dtype=np.uint8)
for _name, _cls in _SEMANTIC_TO_CLASS.items():
    CODA_SEMANTIC_TO_CLASS[CODA_SEMANTIC_IDS[_name]] = _cls

_CAR = ("Car", "Golf Cart")
_TRUCK = ("Truck", "Pickup Truck", "Delivery Truck", "Service Vehicle", "Utility Vehicle", "Bus")
_TWO_WHEELER = ("Bike", "Motorcycle", "Scooter", "Segway", "Skateboard")
_VEGETATION = ("Tree", "Freestanding Plant")
_POLE = ("Pole", "Traffic Light", "Traffic Sign", "Bollard")
_OTHER_STRUCTURE = (
    "Canopy",
    "Bike Rack",
    "Construction Barrier",
    "Parking Kiosk",
    "Mailbox",
    "Fire Hydrant",
    "Informational Sign",
    "Door",
    "Fence",
    "Railing",
    "Cone",
    "Chair",
    "Bench",
    "Table",
    "Trash Can",
    "Newspaper Dispenser",
    "Room Label",
    "Stanchion",
    "Sanitizer Dispenser",
    "Condiment Dispenser",
    "Vending Machine",
    "Emergency Aid Kit",
    "Fire Extinguisher",
    "Computer",
    "Television",
    "Other",
    "Fire Alarm",
    "ATM",
    "Cart",
    "Couch",
    "Traffic Arm",
    "Wall Sign",
    "Floor Sign",
    "Door Switch",
    "Emergency Phone",
    "Dumpster",
    "Vacuum Cleaner",
    "Water Fountain",
)

#: CODa 3d_bbox classId -> our class id (UNLABELED: no class of ours, e.g. Horse)
CODA_BOX_CLASS_TO_CLASS: dict[str, int] = {
    "Pedestrian": C.PEDESTRIAN,
    "Horse": C.UNLABELED,
    **{n: C.CAR for n in _CAR},
    **{n: C.TRUCK for n in _TRUCK},
    **{n: C.TWO_WHEELER for n in _TWO_WHEELER},
    **{n: C.VEGETATION for n in _VEGETATION},
    **{n: C.POLE for n in _POLE},
    **{n: C.OTHER_STRUCTURE for n in _OTHER_STRUCTURE},
}


def semantic_to_classes(coda_ids: np.ndarray) -> np.ndarray:
    """(N,) uint8 CODa 3d_semantic ids -> (N,) uint8 our class ids (UNLABELED = ignored)."""
    return CODA_SEMANTIC_TO_CLASS[np.asarray(coda_ids, dtype=np.uint8)]


def box_class(class_name: str) -> int | None:
    """Our class id of a CODa 3d_bbox classId (UNLABELED for Horse), None for an unknown name."""
    return CODA_BOX_CLASS_TO_CLASS.get(class_name)
