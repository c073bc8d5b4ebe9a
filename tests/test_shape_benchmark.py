"""``benchmarks/shape_benchmark.py``: its table from rows, its random encoders, its data configs."""

from __future__ import annotations

import pytest
import torch
import yaml

from conftest import load_benchmark

sb = load_benchmark("shape_benchmark")


def _row(ds: str, name: str, seed: int | None, **values: float) -> dict:
    return {"dataset": ds, "row": name, "seed": seed, "objects": 10, "cpu": "test cpu", "torch": "x", "threads": 2,
            "date": "2026-11-29", **values}


class TestTable:
    def test_rows_means_ranges_and_references(self) -> None:
        rows = [
            _row("shapes", "random encoder", 0, **{"cosine/strict": 0.2, "raw/strict": 0.5, "descriptor/strict": 0.1,
                                                   "threedq/yaw_median_deg": 80.0}),
            _row("shapes", "references", None, **{"pointcloud/hungarian_acc": 0.4, "raw_bank/hungarian_acc": 0.3}),
            _row("shapes", "random encoder", 1, **{"cosine/strict": 0.4, "raw/strict": 0.5, "descriptor/strict": 0.1,
                                                   "threedq/yaw_median_deg": 100.0}),
            _row("shapes", "vp", 0, **{"cosine/strict": 0.7, "threedq/hungarian_acc": float("nan")}),
        ]
        md = sb.table(rows)
        lines = {ln.split(" | ")[0].lstrip("| "): ln.strip("|").split(" | ") for ln in md.splitlines()
                 if ln.startswith("| ") and not ln.startswith("| features")}
        col = {name: i + 1 for i, (_, name) in enumerate(sb.COLUMNS)}
        assert lines["random encoder (2 seeds)"][col["strict P@10"]].strip() == "0.300 (0.200-0.400)"
        assert lines["random encoder (2 seeds)"][col["yaw median (deg, asym.)"]].strip() == "90 (80-100)"
        assert lines["vp (1 seed)"][col["strict P@10"]].strip() == "0.700"
        assert lines["vp (1 seed)"][col["Hungarian K=50"]].strip() == "-"  # NaN is no number
        assert lines["raw `cat[occ, occ * rgb]` crops"][col["strict P@10"]].strip() == "0.500"
        assert lines["raw `cat[occ, occ * rgb]` crops"][col["Hungarian K=50"]].strip() == "0.300"
        assert lines["point-cloud registration"][col["Hungarian K=50"]].strip() == "0.400"
        assert lines["colour + size descriptor"][col["strict P@10"]].strip() == "0.100"
        assert "test cpu" in md and "### shapes" in md

    def test_no_feature_rows_no_table(self) -> None:
        assert sb.table([_row("unseen", "references", None)]) == ""

    def test_imagenet_row_named_and_in_its_columns(self) -> None:
        stand_in = "ImageNet MobileNetV2 (stand-in for the paper's ResNet-18)"
        rows = [_row("shapes", "random encoder", 0, **{"cosine/strict": 0.2, "threedq/fewshot_acc": 0.3}),
                _row("shapes", stand_in, None, **{"cosine/strict": 0.6, "cosine/paper": 0.65, "probe/learned": 0.7,
                                                  "no_rot/hungarian_acc": 0.45, "no_rot/colour_hungarian_acc": 0.2,
                                                  "ret_acc": 0.5, "class_acc": 0.55, "backbone": "mobilenet_v2",
                                                  "backbone_label": stand_in, "feature_stage": "features.18"})]
        md = sb.table(rows)
        col = {name: i + 1 for i, (_, name) in enumerate(sb.COLUMNS)}
        label = f"{stand_in}, features.18 pooled in the projected GT box (no rotation search)"
        line = next(ln for ln in md.splitlines() if ln.startswith(f"| {label} |")).strip("|").split(" | ")
        assert line[col["strict P@10"]].strip() == "0.600" and line[col["shape probe"]].strip() == "0.700"
        assert line[col["no-rot Hungarian"]].strip() == "0.450" and line[col["Hungarian K=50"]].strip() == "-"
        assert line[col["few-shot"]].strip() == "-"  # not the prototype-propagated few-shot: the extra table's
        assert f"| {label} | 0.500 | 0.550 | 0.450 | 0.200 |" in md  # the extra table: ResNetRet, ResNetClass, bank
        assert "random encoder (1 seed)" in md and f"{stand_in} (1 seed)" not in md
        alone = sb.table([rows[1]])  # an ImageNet-only file still makes a table
        assert label in alone and "test cpu" in alone


class TestRandomStage:
    def test_seeded_and_of_the_main_jobs_architecture(self) -> None:
        a, b, c = sb.random_stage(0), sb.random_stage(0), sb.random_stage(1)
        wa, wb, wc = (torch.cat([p.flatten() for p in s.encoder.parameters()]) for s in (a, b, c))
        assert torch.equal(wa, wb) and not torch.equal(wa, wc)
        from threedq.pipeline.lightning_cli import resolve_config

        cfg = yaml.safe_load(resolve_config("stages/viewpred.yaml").read_text())
        assert list(a.encoder.channels) == cfg["model"]["init_args"]["encoder_channels"]


@pytest.mark.parametrize("name", list(sb.DATASETS))
def test_data_configs_name_the_shape_only_generator(name: str) -> None:
    from threedq.data.catalog import HELD_OUT_NAMES, SHAPE_ONLY_NAMES
    from threedq.pipeline.lightning_cli import load_config

    args = load_config(sb.DATASETS[name])["data"]["init_args"]  # with its base's keys
    assert args["color_mode"] == "random"
    assert tuple(args["categories"]) == (SHAPE_ONLY_NAMES if name == "shapes" else HELD_OUT_NAMES)
    if name == "unseen":
        assert not set(args["categories"]) & set(SHAPE_ONLY_NAMES)  # shapes never seen in training
        assert args["split_fractions"][0] == 0


def test_the_guard_dataset_is_the_main_jobs_data_and_only_scored_when_asked() -> None:
    """``--datasets embedded`` scores the CLI's default data (the guard of the shape issue), never by default."""
    from threedq.pipeline.lightning_cli import DEFAULT_DATA_CONFIG

    assert sb.GUARD_DATASETS == {"embedded": DEFAULT_DATA_CONFIG}
    assert not set(sb.GUARD_DATASETS) & set(sb.DATASETS)
    assert sb.ALL_DATASETS == {**sb.DATASETS, **sb.GUARD_DATASETS}


class TestInstanceColours:
    def test_each_object_gets_its_own_palette_colour_in_any_order(self, tmp_path) -> None:
        """The colour of each cropped object, found by its box in its scene (objects given out of order)."""
        from types import SimpleNamespace

        import numpy as np

        from threedq.data import GeneratorConfig, generate_dataset
        from threedq.data.catalog import RANDOM_COLOR_PALETTE
        from threedq.scene import load_index, load_scene

        cfg = GeneratorConfig(image_size=(16, 16), num_views=2, min_objects=2, max_objects=3,
                              categories=("cube", "mug"), color_mode="random", shadows=False)
        generate_dataset(tmp_path, 4, seed=2, config=cfg, split_fractions=(0, 0, 1), workers=1, progress=False)
        index = load_index(tmp_path)
        dm = SimpleNamespace(index=index, data_dir=str(tmp_path))
        scenes, boxes, want = [], [], []
        for s, f in enumerate(index.files("test")):
            rec = load_scene(tmp_path / f)
            for j in range(len(rec.boxes)):
                scenes.append(s)
                boxes.append(rec.boxes[j])
                want.append(RANDOM_COLOR_PALETTE.index(tuple(
                    min(RANDOM_COLOR_PALETTE, key=lambda c: np.abs(np.subtract(c, rec.meta["object_colors"][j])).sum()))))
        order = torch.randperm(len(scenes), generator=torch.Generator().manual_seed(0))
        crops = {"scene": torch.tensor(scenes)[order], "boxes": torch.tensor(np.stack(boxes))[order],
                 "labels": torch.zeros(len(scenes), dtype=torch.long)}
        got = sb.instance_colours(dm, "test", crops)
        assert got.tolist() == torch.tensor(want)[order].tolist()
        assert len(set(want)) > 1

    def test_category_coloured_data_has_none(self, tiny_dataset) -> None:
        from types import SimpleNamespace

        from threedq.scene import load_index, load_scene

        index = load_index(tiny_dataset)
        rec = load_scene(tiny_dataset / index.files("test")[0])
        crops = {"scene": torch.zeros(1, dtype=torch.long), "boxes": torch.tensor(rec.boxes[:1]),
                 "labels": torch.zeros(1, dtype=torch.long)}
        assert sb.instance_colours(SimpleNamespace(index=index, data_dir=str(tiny_dataset)), "test", crops) is None


class TestImagenetRow:
    @pytest.fixture(autouse=True)
    def one_thread(self):
        """Tiny MobileNetV2 inputs: one thread is as fast, and not slowed tenfold when other jobs share the cores."""
        n = torch.get_num_threads()
        torch.set_num_threads(1)
        yield
        torch.set_num_threads(n)

    def test_scores_of_a_stand_in_on_the_tiny_data(self, tiny_dataset) -> None:
        """Every number of the 2D row on real scenes (random MobileNetV2 weights): in range, the strict precision equal
        to a per-query count written out here; beside encoder rows, their objects are checked to be the same."""
        from threedq.baselines.mobilenet import MobileNetV2
        from threedq.datamodules.scene_folder import SceneFolderDataModule
        from threedq.pipeline.baselines2d import collect_resnet_features
        from threedq.pipeline.report import split_loader

        dm = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_input_views=1, num_target_views=0)
        dm.setup("fit")
        dm.setup("test")
        torch.manual_seed(0)
        net = MobileNetV2().eval()
        q = collect_resnet_features(net, split_loader(dm, "test", gallery=True), progress=False)
        n = q["labels"].shape[0]
        sym = list(dm.index.symmetry_order)
        row = sb.imagenet_row(net, dm, len(dm.index.categories), sym)  # alone: no encoder row's labels
        assert row["objects"] == q["labels"].shape[0]
        for key in ("cosine/strict", "cosine/paper", "cosine/top1", "probe/learned", "no_rot/hungarian_acc"):
            assert 0.0 <= row[key] <= 1.0, key
        for key in ("ret_acc", "class_acc"):  # undefined (NaN) where no category has more objects than its 2 shots
            assert row[key] != row[key] or 0.0 <= row[key] <= 1.0, key
        assert row["backbone"] == "mobilenet_v2" and row["feature_dim"] == 1280
        f = torch.nn.functional.normalize(q["features"].double(), dim=1)
        sim, k = f @ f.T, min(10, n - 1)
        hits = []
        for i in range(n):  # leave-one-out: the k nearest other objects, share of the query's category
            order = [j for j in sim[i].argsort(descending=True).tolist() if j != i][:k]
            hits.append(sum(int(q["labels"][j] == q["labels"][i]) for j in order) / k)
        assert row["cosine/strict"] == pytest.approx(sum(hits) / n)
        with pytest.raises(RuntimeError, match="test objects differ"):
            sb.imagenet_row(net, dm, 100, sym, labels=q["labels"].flip(0) + 1)


class TestWithInputOccupancy:
    def test_cosine_is_the_mean_of_the_parts(self) -> None:
        g = torch.Generator().manual_seed(0)
        crops = {"learned": torch.randn(3, 5, 4, 4, 4, generator=g), "raw": torch.rand(3, 4, 4, 4, 4, generator=g),
                 "gallery_learned": torch.randn(3, 5, 4, 4, 4, generator=g),
                 "gallery_raw": torch.rand(3, 4, 4, 4, 4, generator=g), "labels": torch.arange(3)}
        out = sb.with_input_occupancy(crops)
        assert out["learned"].shape == (3, 6, 4, 4, 4) and out["gallery_learned"].shape == (3, 6, 4, 4, 4)
        assert out["labels"] is crops["labels"] and torch.equal(out["raw"], crops["raw"])
        cos = torch.nn.functional.cosine_similarity
        a, b = out["learned"].flatten(1), out["gallery_learned"].flatten(1)
        want = 0.5 * (cos(crops["learned"].flatten(1), crops["gallery_learned"].flatten(1))
                      + cos(crops["raw"][:, :1].flatten(1), crops["gallery_raw"][:, :1].flatten(1)))
        assert torch.allclose(cos(a, b), want, atol=1e-5)

    def test_an_empty_occupancy_crop_stays_finite(self) -> None:
        crops = {"learned": torch.randn(1, 2, 2, 2, 2), "raw": torch.zeros(1, 4, 2, 2, 2)}
        assert torch.isfinite(sb.with_input_occupancy(crops)["learned"]).all()
