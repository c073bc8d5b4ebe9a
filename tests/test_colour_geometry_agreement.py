"""``benchmarks/colour_geometry_agreement.py``: its all-pairs shape search and its three measures, against the
miner's pairwise search, a copy turned a quarter and hand-made cases (its colours are the descriptor baseline's,
tested in ``test_baseline_descriptor.py``)."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import load_benchmark

cga = load_benchmark("colour_geometry_agreement")


def _raw(occ: torch.Tensor, rgb: tuple[float, float, float]) -> torch.Tensor:
    """``[4, s, s, s]`` raw crop ``cat[occ, occ * rgb]`` of one colour."""
    return torch.cat([occ[None], occ[None] * torch.tensor(rgb).view(3, 1, 1, 1)])


class TestShapeSimilarity:
    def test_matches_the_miners_pairwise_search(self) -> None:
        from threedq.stages.mining import shape_agreement

        g = torch.Generator().manual_seed(1)
        raw = (torch.rand(5, 4, 8, 8, 8, generator=g) > 0.7).float()
        sim = cga.shape_similarity(raw[:2], raw, num_angles=8)
        occ = torch.nn.functional.max_pool3d(raw[:, :1], 3, 1, 1)
        for i in range(2):
            cos, _ = shape_agreement(occ[i:i + 1].expand(5, -1, -1, -1, -1), occ, num_angles=8)
            assert torch.allclose(sim[i], cos, atol=1e-5)

    def test_a_copy_turned_a_quarter_is_found_whole(self) -> None:
        occ = torch.zeros(8, 8, 8)
        occ[:3, 1:3, 1:6] = 1  # two bars off the centre: not the same after a quarter turn
        occ[:2, 5:7, 2:3] = 1
        a = _raw(occ, (1.0, 0.0, 0.0))
        b = _raw(torch.rot90(occ, 1, dims=(1, 2)), (0.0, 1.0, 0.0))
        sim = cga.shape_similarity(a[None], torch.stack([a, b]), num_angles=4)
        assert sim[0, 0] == pytest.approx(1.0, abs=1e-5)
        assert sim[0, 1] == pytest.approx(1.0, abs=1e-5)  # found at one of the 4 yaws, whatever its colour
        assert cga.shape_similarity(a[None], b[None], num_angles=1)[0, 0] < 0.9  # without the search it is not


class TestAgreement:
    def _case(self, colours: list[tuple[float, float, float]]) -> dict[str, float]:
        # objects 0/1 and 2/3 are shape twins in different scenes; labels follow the shapes
        sim = torch.tensor([[1.0, 0.9, 0.1, 0.2], [0.9, 1.0, 0.2, 0.1], [0.1, 0.2, 1.0, 0.9], [0.2, 0.1, 0.9, 1.0]])
        scene = torch.tensor([0, 1, 0, 1])
        labels = torch.tensor([0, 0, 1, 1])
        return cga.agreement(torch.tensor(colours), sim, scene, labels)

    def test_shape_twins_of_one_colour_agree_fully(self) -> None:
        m = self._case([(1, 0, 0), (1, 0, 0), (0, 0, 1), (0, 0, 1)])
        assert m["label_free_agreement"] == pytest.approx(0.0)
        assert m["nn_same_category"] == pytest.approx(1.0)
        assert m["colour_within_category"] == pytest.approx(0.0)

    def test_hand_computed_ratio_when_colour_crosses_shape(self) -> None:
        # twins differ in colour: red/blue and blue/red. Cross-scene pairs: (0,1) (0,3) (1,0) (1,2) (2,1) (2,3)
        # (3,0) (3,2); colour distances sqrt(2) for twins, 0 for (0,3) (3,0) (1,2) (2,1): chance = sqrt(2) / 2
        m = self._case([(1, 0, 0), (0, 0, 1), (0, 0, 1), (1, 0, 0)])
        assert m["label_free_agreement"] == pytest.approx(math.sqrt(2) / (math.sqrt(2) / 2))
        assert m["colour_within_category"] == pytest.approx(2.0)

    def test_same_scene_neighbours_are_never_taken(self) -> None:
        sim = torch.tensor([[1.0, 0.99, 0.1], [0.99, 1.0, 0.2]])  # 0 and 1 share a scene
        m = cga.agreement(torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]]), sim, torch.tensor([0, 0, 1]),
                          torch.tensor([0, 0, 1]))
        assert m["nn_same_category"] == 0.0  # both find object 2, the only one in another scene
        assert math.isnan(m["colour_within_category"])


def test_subsets_split_the_embedded_categories_by_the_catalogue() -> None:
    from threedq.data.catalog import CATEGORY_NAMES

    labels = torch.arange(len(CATEGORY_NAMES))
    s = cga.subsets("embedded", labels)
    prims = [CATEGORY_NAMES[i] for i in s["primitives (3 shapes x 8 colours)"].nonzero().flatten()]
    assert len(prims) == 24 and all(n.split("_")[0] in ("cube", "sphere", "cylinder") for n in prims)
    assert int(s["meshes (one colour each)"].sum()) == len(CATEGORY_NAMES) - 24
    assert list(cga.subsets("shapes", labels)) == ["all"]


def test_table_means_and_ranges() -> None:
    rows = [{"dataset": "shapes", "subset": "all", "seed": s, "queries": 2, "pool": 4, "label_free_agreement": v,
             "nn_same_category": 0.5, "colour_within_category": 1.0} for s, v in ((0, 0.8), (1, 1.0))]
    md = cga.table(rows)
    assert "| shapes, all | 2 of 4 | 0.900 (0.800-1.000) | 0.500 (0.500-0.500) | 1.000 (1.000-1.000) |" in md


def test_figure_one_series_per_subset_a_point_per_seed(tmp_path) -> None:
    rows = [{"dataset": d, "subset": "all", "seed": s, "queries": 2, "pool": 4, "label_free_agreement": 0.5 + s / 10,
             "nn_same_category": 0.5, "colour_within_category": 0.3} for d in ("shapes", "embedded") for s in (0, 1)]
    fig = cga.figure(rows)
    series = fig.axes[0].collections
    assert len(series) == 2 and all(c.get_offsets().shape == (2, 2) for c in series)
    assert series[1].get_offsets()[1].tolist() == pytest.approx([0.6, 0.3])
    from threedq.viz.png import write_png

    assert write_png(tmp_path / "f.png", fig).read_bytes()[:4] == b"\x89PNG"


def test_table_only_reads_the_rows_back(tmp_path, monkeypatch, capsys) -> None:
    import json
    import sys

    rows = [{"dataset": "shapes", "subset": "all", "seed": 0, "queries": 2, "pool": 4, "label_free_agreement": 0.9,
             "nn_same_category": 0.5, "colour_within_category": 1.0}]
    out = tmp_path / "rows.jsonl"
    out.write_text(json.dumps(rows[0]) + "\n")
    monkeypatch.setattr(sys, "argv", ["x", "--table_only", "--out", str(out), "--md", str(tmp_path / "t.md")])
    cga.main()
    assert "| shapes, all | 2 of 4 | 0.900 |" in (tmp_path / "t.md").read_text()
