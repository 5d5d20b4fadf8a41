"""What every stage shares: its context, frame chunking, provider settings from the config."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from configs.schema import Config
from flows.plan import open_sequence
from storage.coda import CodaSequence


@dataclass(frozen=True)
class StageContext:
    config: Config
    sequence: str
    out_root: Path
    out_dir: Path
    upstream: dict[str, Path] = field(default_factory=dict)
    #: the unit's stage key (names its output versions)
    key: str = ""

    def open(self) -> CodaSequence:
        return open_sequence(self.config, self.sequence)


def chunks(n: int, size: int) -> list[list[int]]:
    """Frame positions 0..n-1 in consecutive chunks of ``size``."""
    return [list(range(a, min(a + size, n))) for a in range(0, n, size)]


def is_night(seq: CodaSequence) -> bool:
    """dataset.lighting of the sequence, else its metadata's lighting (storage.coda)."""
    return seq.info.is_night


def frame_rng(seed: int, sequence: str, frame: int, salt: int) -> np.random.Generator:
    """A generator that depends only on (seed, sequence, frame, purpose): order-independent."""
    seq_num = int(sequence) if sequence.isdigit() else abs(hash(sequence)) % (2**31)
    return np.random.default_rng([seed, seq_num, frame, salt])
