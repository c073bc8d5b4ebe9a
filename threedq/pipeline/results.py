"""What the stages of a ``threedq em`` run hand back to its loop: small records, stored as JSON (``to_json``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["MiningResult", "SelfLabellingResult", "StageRecord"]


@dataclass(frozen=True)
class StageRecord:
    """A finished training stage (its ``stage.json``): which stage, its checkpoint, how long it took.

    Attributes:
        stage: the loop's name of the stage (``viewpred``, ``detector``, ``round 1 mining``, ...).
        checkpoint: its ``checkpoints/last.ckpt`` (or, with ``given``, a checkpoint given by the user).
        seconds: wall-clock seconds of its training (0 when given).
        given: handed in (``--viewpred_ckpt``), not trained here.
    """

    stage: str
    checkpoint: str
    seconds: float
    given: bool = False

    @property
    def path(self) -> Path:
        return Path(self.checkpoint)

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        if not self.given:
            del out["given"]
        return out

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> StageRecord:
        return cls(stage=str(doc["stage"]), checkpoint=str(doc["checkpoint"]), seconds=float(doc["seconds"]),
                   given=bool(doc.get("given", False)))


@dataclass(frozen=True)
class MiningResult:
    """A round's mining stage and the diagnostics of each of its pool refreshes (``mining/refresh_*.json``)."""

    record: StageRecord
    refreshes: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {**self.record.to_json(), "refreshes": self.refreshes}


@dataclass(frozen=True)
class SelfLabellingResult:
    """A round's self-labelling stage, the labels it trained on (``self_labels/labels.json``, None if absent) and
    the evaluation of the detector it wrote (``evaluate_detection``'s result)."""

    record: StageRecord
    labels: dict[str, Any] | None
    detector_eval: dict[str, Any]

    @property
    def map_50(self) -> float:
        return float(self.detector_eval["detector"]["map_50"])

    def to_json(self) -> dict[str, Any]:
        return {**self.record.to_json(), "labels": self.labels, "detector_eval": self.detector_eval}
