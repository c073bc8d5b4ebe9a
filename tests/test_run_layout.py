"""``RunLayout``: the names ``threedq em`` writes are the names ``parse`` and ``label`` read back."""

from __future__ import annotations

from pathlib import Path

import pytest

from threedq.pipeline.run_layout import ROUND_PARTS, RunLayout


def _finish(stage_dir: Path) -> Path:
    ckpt = RunLayout.checkpoint(stage_dir)
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"x")
    RunLayout.stage_marker(stage_dir).write_text("{}")
    return ckpt


class TestRunLayout:
    def test_smoke_names_as_documented(self, tmp_path: Path) -> None:
        lay = RunLayout(tmp_path)
        # the tree of docs/architecture.md and threedq em's docstring, written out by hand
        assert [p.name for p in (lay.viewpred, lay.viewpred_eval, lay.detector, lay.detector_eval)] == [
            "00_viewpred", "01_viewpred_eval", "02_detector", "03_detector_eval"]
        assert [lay.round(1, part).name for part in ROUND_PARTS] == [
            "r01_mining", "r01_quantizer", "r01_eval", "r01_self_labelling", "r01_detector_eval"]
        assert lay.round(0, "quantizer").name == "r00_quantizer" and lay.round(12, "eval").name == "r12_eval"
        assert RunLayout.checkpoint(lay.detector) == tmp_path / "02_detector" / "checkpoints" / "last.ckpt"
        assert str(RunLayout.detections(lay.detector_eval)).endswith("03_detector_eval/detections_{split}.npz")
        assert RunLayout.detections(lay.detector_eval, "test").name == "detections_test.npz"

    def test_exception(self, tmp_path: Path) -> None:
        lay = RunLayout(tmp_path)
        with pytest.raises(ValueError, match="part"):
            lay.round(1, "quantiser")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="r:"):
            lay.round(100, "eval")
        with pytest.raises(ValueError, match="r:"):
            lay.round(True, "eval")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="part"):
            lay.rounds("nope")  # type: ignore[arg-type]

    def test_round_trip_written_then_found(self, tmp_path: Path) -> None:
        lay = RunLayout(tmp_path / "run")
        assert lay.rounds("quantizer") == [] and lay.final_quantizer() is None and lay.final_detector() is None
        for r in (0, 1, 2, 10):
            lay.round(r, "quantizer").mkdir(parents=True)
        (lay.work / "r3_quantizer").mkdir()  # not a name em writes
        (lay.work / "r04_quantizer_old").mkdir()
        (lay.work / "r05_quantizer").write_text("a file")
        assert lay.rounds("quantizer") == [0, 1, 2, 10]
        assert lay.rounds("mining") == []

    def test_finished_needs_marker_and_checkpoint(self, tmp_path: Path) -> None:
        lay = RunLayout(tmp_path)
        d = lay.round(1, "quantizer")
        RunLayout.checkpoint(d).parent.mkdir(parents=True)
        RunLayout.checkpoint(d).write_bytes(b"x")
        assert RunLayout.finished(d) is None  # interrupted: no stage.json
        RunLayout.stage_marker(d).write_text("{}")
        assert RunLayout.finished(d) == RunLayout.checkpoint(d)

    def test_final_parts(self, tmp_path: Path) -> None:
        lay = RunLayout(tmp_path)
        warm = _finish(lay.detector)
        assert lay.final_detector() == warm  # no round self-labelled: the warm start
        q1, q2 = _finish(lay.round(1, "quantizer")), _finish(lay.round(2, "quantizer"))
        lay.round(3, "quantizer").mkdir()  # round 3 started, not finished
        s1 = _finish(lay.round(1, "self_labelling"))
        assert lay.final_quantizer() == q2 and q1 != q2
        assert lay.final_detector() == s1
        assert lay.viewpred_checkpoint() is None
        vp = _finish(lay.viewpred)
        assert lay.viewpred_checkpoint() == vp
