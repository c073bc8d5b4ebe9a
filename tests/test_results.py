"""The records ``threedq em`` hands between its stages: attributes in the loop, the old JSON shapes on disk."""

from __future__ import annotations

import json
from pathlib import Path

from threedq.pipeline.results import MiningResult, SelfLabellingResult, StageRecord


class TestStageRecord:
    def test_round_trip_and_shape(self) -> None:
        rec = StageRecord(stage="detector", checkpoint="runs/em/02_detector/checkpoints/last.ckpt", seconds=12.5)
        doc = json.loads(json.dumps(rec.to_json()))
        assert doc == {"stage": "detector", "checkpoint": "runs/em/02_detector/checkpoints/last.ckpt", "seconds": 12.5}
        assert StageRecord.from_json(doc) == rec and rec.path == Path(rec.checkpoint)

    def test_given(self) -> None:
        rec = StageRecord(stage="viewpred", checkpoint="/x/vp.ckpt", seconds=0.0, given=True)
        assert rec.to_json()["given"] is True and StageRecord.from_json(rec.to_json()) == rec

    def test_reads_a_stage_json_of_an_older_run(self) -> None:
        rec = StageRecord.from_json({"stage": "round 1 mining", "checkpoint": "c.ckpt", "seconds": 3})
        assert rec.seconds == 3.0 and not rec.given


def test_round_results_serialise_as_before() -> None:
    rec = StageRecord(stage="round 1 self-labelling", checkpoint="s.ckpt", seconds=1.0)
    ev = {"detector": {"map_50": 0.5, "map_25": 0.7}}
    sl = SelfLabellingResult(rec, {"positives": 3}, ev)
    assert sl.map_50 == 0.5
    assert sl.to_json() == {"stage": "round 1 self-labelling", "checkpoint": "s.ckpt", "seconds": 1.0,
                            "labels": {"positives": 3}, "detector_eval": ev}
    m = MiningResult(StageRecord(stage="round 1 mining", checkpoint="m.ckpt", seconds=2.0), [{"step": 0}])
    assert m.to_json() == {"stage": "round 1 mining", "checkpoint": "m.ckpt", "seconds": 2.0, "refreshes": [{"step": 0}]}
