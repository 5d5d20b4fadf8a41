"""What became of one (sequence, stage) unit in a run: the runner makes it, the report counts it,
the manifest records it (storage.manifest.StageRecord: done, failed and skipped units)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum


class Status(StrEnum):
    #: ran now (or was finished by a run killed before recording it: its output was found)
    DONE = "done"
    #: fresh in the manifest: not run
    CACHED = "cached"
    #: the stage raised: ``error`` says why
    FAILED = "failed"
    #: an upstream unit of the sequence did not finish
    SKIPPED = "skipped"


@dataclass(frozen=True)
class UnitOutcome:
    sequence: str
    stage: str
    key: str
    #: the key's ingredients (flows.pipeline.plan.unit_keys)
    parts: dict
    status: Status
    #: the output folder, relative to the store (done or cached)
    location: str = ""
    #: the stage's JSON-able summary (done or cached)
    summary: dict = field(default_factory=dict)
    #: inside the stage (0 when it did not run)
    seconds: float = 0.0
    error: str = ""
    traceback: str = ""

    @property
    def ran(self) -> bool:
        """Run in this run (finished or failed), not taken from the manifest or skipped."""
        return self.status in (Status.DONE, Status.FAILED)

    @property
    def finished(self) -> bool:
        """Its output exists: run now or cached."""
        return self.status in (Status.DONE, Status.CACHED)
