"""Read a published dataset: ``ds = open_dataset(out); ds.sequences; ds.arrays(seq); ds.table(...)``.

Only published data is seen: hidden ``.tmp-*`` staging directories are skipped, and each
sequence's arrays are the version named by ``occupancy/<seq>/current.json``; a store whose
publication a killed run interrupted is refused until it is completed (storage.publish.reading
completes it), so arrays and tables are always of one version; so is a sequence whose
``current.json`` is missing or unreadable, or a file it lists missing or of another size (one
``stat`` per file; content is checked by ``mobileocc status --verify``). Arrays are lazy
(dask arrays over the zarr arrays, or the zarr arrays themselves); the zarr metadata carries
``dimension_names`` so ``xarray.open_zarr`` can open a store directly. Tables are pyarrow Tables
(``.to_pandas()`` for pandas).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import zarr

from storage import tables
from storage.layout import OCCUPANCY_DIR, StoreError
from storage.occupancy_store import ARRAYS, read_attrs, store_path
from storage.publish import damaged_publication, pending_publications


@dataclass(frozen=True)
class Dataset:
    """A published dataset rooted at ``root``."""

    root: Path
    sequences: tuple[str, ...]

    def store_path(self, sequence: str) -> Path:
        """Path of the published zarr store of ``sequence``."""
        self._check(sequence)
        return store_path(self.root, sequence)

    def attrs(self, sequence: str) -> dict[str, Any]:
        """Group attributes: grid range / voxel size, class table, config hash, code version."""
        return read_attrs(self.store_path(sequence))

    def zarr_group(self, sequence: str) -> zarr.Group:
        return zarr.open_group(str(self.store_path(sequence)), mode="r", zarr_format=3)

    def arrays(self, sequence: str, lazy: str = "dask") -> dict[str, Any]:
        """name -> lazy array (F, X, Y, Z[, 2]); ``lazy="dask"`` (dask.array) or ``"zarr"``."""
        group = self.zarr_group(sequence)
        out = {name: group[name] for name in ARRAYS if name in group}
        if lazy == "zarr":
            return out
        if lazy != "dask":
            raise ValueError(f"lazy must be 'dask' or 'zarr', got {lazy!r}")
        import dask.array as da

        return {name: da.from_zarr(arr) for name, arr in out.items()}

    def table(self, name: str, sequence: str | None = None) -> pa.Table:
        """A table (frames / instances / sequences), all sequences or one."""
        if sequence is not None:
            self._check(sequence)
        return tables.read_table(self.root, name, sequence)

    def _check(self, sequence: str) -> None:
        if sequence not in self.sequences:
            raise StoreError(
                f"dataset {self.root}: no published sequence {sequence!r}; have {list(self.sequences)}"
            )


def open_dataset(path: str | os.PathLike) -> Dataset:
    """Open the dataset at ``path`` (the output root holding ``occupancy/`` and ``tables/``)."""
    root = Path(path)
    occ = root / OCCUPANCY_DIR
    if not occ.is_dir() and not (root / tables.TABLES_DIR).is_dir():
        raise StoreError(
            f"{root} is not a mobileocc dataset (no {OCCUPANCY_DIR}/ or {tables.TABLES_DIR}/)"
        )
    pending = pending_publications(root)
    if pending:  # its arrays and tables may be of two versions until it is completed
        raise StoreError(
            f"dataset {root}: the publication of sequence(s) {', '.join(pending)} was interrupted "
            "by a killed run; `mobileocc export` or the next run completes it "
            "(storage.publish.reading)"
        )
    seqs = sorted(
        p.name
        for p in (occ.iterdir() if occ.is_dir() else ())
        if p.is_dir() and not p.name.startswith((".", "_"))
    )
    for seq in seqs:  # a damaged sequence is never read as if it were whole (nor left out)
        problem = damaged_publication(root, seq)
        if problem:
            raise StoreError(
                f"dataset {root}: sequence {seq} is damaged: {problem}; `mobileocc rebuild` "
                "publishes it again (`mobileocc status --verify` lists what is damaged)"
            )
    return Dataset(root, tuple(seqs))
