"""Where things are in an output store (``OUT``), and the error every store module raises.

``OUT/occupancy/<sequence>/<version>.zarr`` and ``current.json`` (storage.occupancy_store,
storage.publish), ``OUT/tables/<table>/sequence=<seq>/part.parquet`` (storage.tables); hidden
``.tmp-*`` entries are work in progress, never read.
"""

from __future__ import annotations

OCCUPANCY_DIR = "occupancy"
TABLES_DIR = "tables"
CURRENT_FILE = "current.json"
#: ``OUT/.publishing/<sequence>.json``: a publication in progress (storage.publish)
PUBLISHING_DIR = ".publishing"
TMP_PREFIX = ".tmp-"


class StoreError(ValueError):
    """Bad input to the store: wrong shape, dtype, misaligned region, missing store."""


def check_name(kind: str, value: str) -> None:
    """A sequence or version name usable as one path component (raises StoreError)."""
    if not value or value.startswith((".", "_")) or "/" in value or "\\" in value or "=" in value:
        raise StoreError(
            f"invalid {kind} {value!r}: must be non-empty, no '/', '=', leading '.' or '_'"
        )
