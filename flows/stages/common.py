"""What every stage shares: its context, frame chunking, the body model, per-frame random numbers."""

from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np

from flows.pipeline.inputs import BodyModelFiles, Runtime, SequenceRef, StageInputs
from storage.body_model_files import (
    BodyFileError,
    UnsafePickleError,
    load_body_model,
    load_pose_prior,
    save_body_model_npz,
    save_pose_prior_pkl,
)
from storage.manifest import PROCEDURAL_MODEL, PROCEDURAL_PRIOR
from storage.products import read_summary
from storage.sources import SequenceSource
from tasks.body.model import BodyModel
from tasks.body.prior import GMMPosePrior, generate_pose_prior
from tasks.body.procedural import generate_body_model

#: the inputs type of one stage: ``StageContext[FitInputs]`` is the fit stage's context
InputsT = TypeVar("InputsT", bound=StageInputs)


@dataclass(frozen=True)
class StageContext(Generic[InputsT]):
    """One (sequence, stage) unit: its inputs object (the only settings it reads), the sequence
    (where it lives, what the config says about it alone), where its upstream products are and
    where it writes (a hidden staging folder published by rename when the stage returns)."""

    ref: SequenceRef
    inputs: InputsT
    out_root: Path
    out_dir: Path
    upstream: dict[str, Path] = field(default_factory=dict)
    #: the unit's stage key (names its output versions)
    key: str = ""
    #: content fingerprint of the sequence's input files (provenance in the published tables)
    fingerprint: str = ""
    runtime: Runtime = Runtime()

    def open(self) -> SequenceSource:
        return self.inputs.source.open(self.ref)

    @property
    def sequence(self) -> str:
        return self.ref.sequence


def detected_positions(ctx: StageContext, seq: SequenceSource) -> list[int]:
    """Positions (in ``seq.info.frame_indices``) of the frames the detect stage produced: a frame
    whose input was bad is in its ``failed_frames`` instead and no later stage reads it."""
    summary = read_summary(ctx.upstream["detect"])
    at = {raw: k for k, raw in enumerate(seq.info.frame_indices)}
    return [at[int(raw)] for raw in summary["frames"]]


def chunks(n: int, size: int) -> list[list[int]]:
    """Frame positions 0..n-1 in consecutive chunks of ``size``."""
    return [list(range(a, min(a + size, n))) for a in range(0, n, size)]


def is_night(seq: SequenceSource) -> bool:
    """dataset.lighting of the sequence, else what its source says (a CODa metadata file)."""
    return seq.info.is_night


def frame_rng(seed: int, sequence: str, frame: int, salt: int) -> np.random.Generator:
    """A generator that depends only on (seed, sequence, frame, purpose): order-independent, and
    the same in every process (a sequence name is hashed with CRC-32, never with ``hash``)."""
    seq_num = int(sequence) if sequence.isdigit() else zlib.crc32(sequence.encode())
    return np.random.default_rng([seed, seq_num, frame, salt])


#: our procedural stand-ins are generated once per output store and saved in the official
#: formats: OUT/.cache/PROCEDURAL_MODEL, PROCEDURAL_PRIOR (storage.manifest.CACHE_PRODUCTS)


def _procedural(out_root: str, name: str) -> BodyModel | GMMPosePrior:
    """OUT/.cache/<name>: our procedural stand-in, made and saved once per output store, loaded
    once per process and file. A cache product like any other: verified before use (read in full
    by its loader, every key and shape checked), made again when damaged (truncated, not a zip, a
    key missing) or gone (``rebuild --force`` removes it: storage.manifest.remove_caches)."""
    path = Path(out_root) / ".cache" / name
    for attempt in (0, 1):
        if path.exists():
            st = path.stat()
            try:
                return _load_procedural(str(path), name, (st.st_ino, st.st_mtime_ns, st.st_size))
            except (BodyFileError, UnsafePickleError, OSError):
                if attempt:
                    raise
        # missing or damaged: made again (deterministic bytes; concurrent makers each rename a
        # whole file)
        if name == PROCEDURAL_MODEL:
            save_body_model_npz(path, generate_body_model())
        else:
            save_pose_prior_pkl(path, generate_pose_prior())
    raise AssertionError("unreachable")


@functools.lru_cache(maxsize=4)
def _load_procedural(path: str, name: str, identity: tuple) -> BodyModel | GMMPosePrior:
    if name == PROCEDURAL_MODEL:
        return BodyModel(load_body_model(path))
    p = load_pose_prior(path)
    return GMMPosePrior(p["means"], p["covars"], p["weights"])


@functools.lru_cache(maxsize=4)
def _load_model(path: str) -> BodyModel:
    return BodyModel(load_body_model(path))


@functools.lru_cache(maxsize=4)
def _load_prior(path: str) -> GMMPosePrior:
    p = load_pose_prior(path)
    return GMMPosePrior(p["means"], p["covars"], p["weights"])


def body_model(files: BodyModelFiles, out_root: Path) -> BodyModel:
    """The user's SMPL file, or our procedural model in the same format (loaded once per process)."""
    if files.body_model_path:
        return _load_model(str(files.body_model_path))
    return _procedural(str(out_root), PROCEDURAL_MODEL)


def pose_prior(files: BodyModelFiles, out_root: Path) -> GMMPosePrior:
    """The user's gmm_08.pkl, or our generated prior in the same format."""
    if files.pose_prior_path:
        return _load_prior(str(files.pose_prior_path))
    return _procedural(str(out_root), PROCEDURAL_PRIOR)
