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
    load_body_model,
    load_pose_prior,
    save_body_model_npz,
    save_pose_prior_pkl,
)
from storage.coda import CodaSequence
from storage.products import read_summary
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

    def open(self) -> CodaSequence:
        return self.inputs.source.open(self.ref)

    @property
    def sequence(self) -> str:
        return self.ref.sequence


def detected_positions(ctx: StageContext, seq: CodaSequence) -> list[int]:
    """Positions (in ``seq.info.frame_indices``) of the frames the detect stage produced: a frame
    whose input was bad is in its ``failed_frames`` instead and no later stage reads it."""
    summary = read_summary(ctx.upstream["detect"])
    at = {raw: k for k, raw in enumerate(seq.info.frame_indices)}
    return [at[int(raw)] for raw in summary["frames"]]


def chunks(n: int, size: int) -> list[list[int]]:
    """Frame positions 0..n-1 in consecutive chunks of ``size``."""
    return [list(range(a, min(a + size, n))) for a in range(0, n, size)]


def is_night(seq: CodaSequence) -> bool:
    """dataset.lighting of the sequence, else its metadata's lighting (storage.coda)."""
    return seq.info.is_night


def frame_rng(seed: int, sequence: str, frame: int, salt: int) -> np.random.Generator:
    """A generator that depends only on (seed, sequence, frame, purpose): order-independent, and
    the same in every process (a sequence name is hashed with CRC-32, never with ``hash``)."""
    seq_num = int(sequence) if sequence.isdigit() else zlib.crc32(sequence.encode())
    return np.random.default_rng([seed, seq_num, frame, salt])


#: our procedural stand-ins are generated once per output store and saved in the official formats
PROCEDURAL_MODEL = "procedural_smpl_v1.npz"
PROCEDURAL_PRIOR = "procedural_gmm_08_v1.pkl"


def _procedural_file(out_root: Path, name: str, make, save) -> Path:
    """OUT/.cache/<name>: our procedural stand-in, made and saved once per output store."""
    path = Path(out_root) / ".cache" / name
    if not path.exists():
        save(path, make())
    return path


@functools.lru_cache(maxsize=4)
def _load_model(path: str) -> BodyModel:
    return BodyModel(load_body_model(path))


@functools.lru_cache(maxsize=4)
def _load_prior(path: str) -> GMMPosePrior:
    p = load_pose_prior(path)
    return GMMPosePrior(p["means"], p["covars"], p["weights"])


def body_model(files: BodyModelFiles, out_root: Path) -> BodyModel:
    """The user's SMPL file, or our procedural model in the same format (loaded once per process)."""
    path = files.body_model_path or _procedural_file(
        out_root, PROCEDURAL_MODEL, generate_body_model, save_body_model_npz
    )
    return _load_model(str(path))


def pose_prior(files: BodyModelFiles, out_root: Path) -> GMMPosePrior:
    """The user's gmm_08.pkl, or our generated prior in the same format."""
    path = files.pose_prior_path or _procedural_file(
        out_root, PROCEDURAL_PRIOR, generate_pose_prior, save_pose_prior_pkl
    )
    return _load_prior(str(path))
