"""The folder layout of a ``threedq em`` run: written by :mod:`threedq.pipeline.em`, read by ``parse`` and ``label``::

    work_dir/
      00_viewpred/  01_viewpred_eval/  02_detector/  03_detector_eval/
      r00_quantizer/  r00_eval/                                         # round 0: the view-prediction encoder
      r01_mining/  r01_quantizer/  r01_eval/  r01_self_labelling/  r01_detector_eval/   # round 1, 2, ...
      metrics.json  report.md  table3.png

A stage folder has finished when its ``stage.json`` exists; its checkpoint is ``checkpoints/last.ckpt``. A detector
evaluation hands its boxes on as ``detections_<split>.npz``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

__all__ = ["ROUND_PARTS", "RoundPart", "RunLayout"]

RoundPart = Literal["mining", "quantizer", "eval", "self_labelling", "detector_eval"]
#: The folders of a round, in the order the round writes them.
ROUND_PARTS: tuple[RoundPart, ...] = ("mining", "quantizer", "eval", "self_labelling", "detector_eval")


@dataclass(frozen=True)
class RunLayout:
    """Where each part of a ``threedq em`` run lives inside its work folder ``work``."""

    work: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "work", Path(self.work))

    @property
    def viewpred(self) -> Path:
        return self.work / "00_viewpred"

    @property
    def viewpred_eval(self) -> Path:
        return self.work / "01_viewpred_eval"

    @property
    def detector(self) -> Path:
        return self.work / "02_detector"

    @property
    def detector_eval(self) -> Path:
        return self.work / "03_detector_eval"

    def round(self, r: int, part: RoundPart) -> Path:
        """The folder of ``part`` of round ``r`` (``r00_quantizer``, ``r01_mining``, ...)."""
        if part not in ROUND_PARTS:
            raise ValueError(f"part: expected one of {ROUND_PARTS}, got {part!r}")
        if isinstance(r, bool) or not isinstance(r, int) or not 0 <= r <= 99:
            raise ValueError(f"r: expected a round number in 0..99, got {r!r}")
        return self.work / f"r{r:02d}_{part}"

    def rounds(self, part: RoundPart) -> list[int]:
        """The round numbers that have a ``part`` folder, ascending."""
        if part not in ROUND_PARTS:
            raise ValueError(f"part: expected one of {ROUND_PARTS}, got {part!r}")
        found = []
        for d in self.work.iterdir() if self.work.is_dir() else []:
            digits = d.name[1:3]
            if d.is_dir() and d.name[:1] == "r" and digits.isdigit() and d.name[3:] == f"_{part}":
                found.append(int(digits))
        return sorted(found)

    @staticmethod
    def checkpoint(stage_dir: Path) -> Path:
        """A stage folder's checkpoint."""
        return Path(stage_dir) / "checkpoints" / "last.ckpt"

    @staticmethod
    def stage_marker(stage_dir: Path) -> Path:
        """The file that says a stage folder has finished."""
        return Path(stage_dir) / "stage.json"

    @classmethod
    def finished(cls, stage_dir: Path) -> Path | None:
        """The checkpoint of a finished stage folder, else ``None``."""
        ckpt = cls.checkpoint(stage_dir)
        return ckpt if cls.stage_marker(stage_dir).is_file() and ckpt.is_file() else None

    @staticmethod
    def detections(eval_dir: Path, split: str = "{split}") -> Path:
        """The boxes a detector evaluation hands on for ``split`` (``{split}`` kept as a pattern by default)."""
        return Path(eval_dir) / f"detections_{split}.npz"

    def final_quantizer(self) -> Path | None:
        """The checkpoint of the last finished round's quantizer (the final encoder and prototype bank)."""
        done = [c for r in self.rounds("quantizer") if (c := self.finished(self.round(r, "quantizer")))]
        return done[-1] if done else None

    def final_detector(self) -> Path | None:
        """The last finished detector: the last self-labelled round's, else the warm start."""
        done = [c for r in self.rounds("self_labelling") if (c := self.finished(self.round(r, "self_labelling")))]
        return done[-1] if done else self.finished(self.detector)

    def viewpred_checkpoint(self) -> Path | None:
        """View prediction's checkpoint (its decoder draws renders), if there is one."""
        ckpt = self.checkpoint(self.viewpred)
        return ckpt if ckpt.is_file() else None
