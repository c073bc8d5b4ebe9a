"""The pictures package (``threedq.viz``): PNG round trips, every figure drawn from a small case, and no pyplot."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from threedq.viz import figure_png, new_figure, rgb_png, write_png
from threedq.viz.curves import accuracy_vs_k_figure, runs_figure, table3_figure
from threedq.viz.detection import aabb_to_boxes7, self_labels_figure, size_band_figure
from threedq.viz.features import alignment_figure, per_category_figure, retrieval_figure


def _decode(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None, "not a PNG"
    return img[:, :, ::-1]


class TestPng:
    def test_rgb_round_trip_keeps_channel_order(self) -> None:
        img = np.zeros((5, 7, 3), np.uint8)
        img[..., 0] = 200  # red
        img[2, 3] = (1, 2, 3)
        np.testing.assert_array_equal(_decode(rgb_png(img)), img)

    def test_write_png_takes_arrays_figures_and_bytes(self, tmp_path: Path) -> None:
        img = np.full((4, 6, 3), 9, np.uint8)
        np.testing.assert_array_equal(_decode(write_png(tmp_path / "a.png", img).read_bytes()), img)
        fig = new_figure(figsize=(2, 1), dpi=50)
        fig.add_subplot(1, 1, 1).plot([0, 1], [0, 1])
        assert _decode(write_png(tmp_path / "b.png", fig).read_bytes()).shape == (50, 100, 3)
        assert _decode(figure_png(fig, dpi=100)).shape == (100, 200, 3)
        write_png(tmp_path / "c.png", rgb_png(img))
        assert (tmp_path / "c.png").read_bytes() == rgb_png(img)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png", "c.png"]  # no temporary file left

    def test_exceptions(self) -> None:
        with pytest.raises(ValueError, match="uint8"):
            rgb_png(np.zeros((4, 4, 3), np.float32))
        with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
            rgb_png(np.zeros((4, 4), np.uint8))


class TestFigures:
    def test_curves(self) -> None:
        rows = [{"round": r, "k": 10, "precision_at_10": 0.4 + r / 20, "precision_at_10_paper": None,
                 "hungarian_acc": 0.3, "map_50": 0.5} for r in range(3)]  # fmt: skip
        assert _decode(figure_png(table3_figure(rows))).shape[2] == 3
        curve = {"threedq": {"10": 0.3, "50": 0.4}, "no_rot": {"10": 0.2, "50": 0.35}}
        assert _decode(figure_png(accuracy_vs_k_figure(curve, {"threedq": "3DQ"}, 41))).ndim == 3

    def test_runs_figure_draws_a_line_a_run_and_names_each_group_once(self) -> None:
        runs = {"a": [[(0, 0.1), (1, 0.2)], [(0, 0.15), (1, 0.25)], []], "b": [[(0, 0.3), (1, 0.3)]]}
        fig = runs_figure([("p", runs, [(0.05, "--", "raw")]), ("q", {"a": runs["a"]}, [])], "step", xticks=[0, 1])
        first, second = fig.axes
        assert len(first.lines) == 4 and len(second.lines) == 2  # 3 drawn runs + 1 reference; the empty run skipped
        assert [t.get_text() for t in first.get_legend().texts] == ["a", "b", "raw"]
        assert first.lines[0].get_color() == first.lines[1].get_color() != first.lines[2].get_color()
        assert list(second.get_xticks()) == [0, 1]
        assert _decode(figure_png(fig)).ndim == 3

    def test_runs_figure_draws_a_groups_own_reference_in_its_colour(self) -> None:
        runs = {"a": [[(0, 0.1), (1, 0.2)]], "b": [[(0, 0.3), (1, 0.3)]]}
        fig = runs_figure([("p", runs, [(0.05, "--", "raw (a)", "a"), (0.07, "--", "raw (b)", "b"),
                                        (0.01, ":", "floor")])], "step")
        a, b, ref_a, ref_b, floor = fig.axes[0].lines
        assert ref_a.get_color() == a.get_color() and ref_b.get_color() == b.get_color() != a.get_color()
        assert floor.get_color() == "grey" and list(ref_b.get_ydata()) == [0.07, 0.07]

    def test_features(self) -> None:
        g = torch.Generator().manual_seed(0)
        test = {"raw": torch.rand(8, 4, 6, 6, 6, generator=g), "labels": torch.tensor([0, 0, 1, 1, 2, 2, 0, 1])}
        sim = torch.rand(8, 8, generator=g)
        assert _decode(rgb_png(retrieval_figure(test, sim, ["a", "b", "c"], queries=3, k=2))).ndim == 3
        clusters, angles = torch.tensor([0, 0, 1, 1, 1, 2, 0, 1]), torch.tensor([0, 3, 1, 0, 2, 5, 4, 1])
        assert _decode(rgb_png(alignment_figure(test, clusters, angles, 8, ["a", "b", "c"], rows=2, cols=3))).ndim == 3
        curves = {"strict": {0: 0.5, 1: 0.25, 2: 0.0}, "paper": {0: 0.75, 1: 0.5, 2: 0.5}}
        pairs = [{"a": "a", "b": "b", "slots": 3}]
        fig = per_category_figure(curves, torch.tensor([3, 3, 2]), ["a", "b", "c"], 2, pairs)
        assert _decode(figure_png(fig)).ndim == 3

    def test_retrieval_mosaic_against_hand_placed_tiles(self) -> None:
        """Each tile is the crop's bird's-eye view, scaled, where the layout puts it (20-pixel title; rows of a 16-pixel
        caption over the picture, 4 pixels apart); a neighbour of another category has a red caption, the query's
        own category a black one."""
        from threedq.data.draw import crop_birds_eye

        g = torch.Generator().manual_seed(1)
        raw = (torch.rand(4, 4, 5, 5, 5, generator=g) > 0.5).float()
        test = {"raw": raw, "labels": torch.tensor([0, 0, 1, 1])}
        sim = torch.tensor([[0, 0.9, 0.5, 0.1], [0.9, 0, 0.2, 0.8], [0.5, 0.2, 0, 0.3], [0.1, 0.8, 0.3, 0]])
        img = retrieval_figure(test, sim, ["a", "b"], queries=2, k=2, scale=3)
        tile, gap = 15, 4
        assert img.shape == (20 + 2 * (16 + tile) + gap, 3 * tile + 2 * gap, 3) and img.dtype == np.uint8
        # queries 0 and 3 (linspace over 4 objects); their neighbours by similarity: 1, 2 and 1, 2
        for r, order in enumerate(([0, 1, 2], [3, 1, 2])):
            y = 20 + r * (16 + tile + gap)
            for c, i in enumerate(order):
                x = c * (tile + gap)
                want = np.kron((crop_birds_eye(raw[i], background=0.5) * 255).round().astype(np.uint8),
                               np.ones((3, 3, 1), np.uint8))
                np.testing.assert_array_equal(img[y + 16:y + 16 + tile, x:x + tile], want)
                caption = img[y:y + 16, x:x + tile].astype(int)
                red = ((caption[..., 0] > 150) & (caption[..., 1] < 80)).any()
                assert red == (test["labels"][i] != test["labels"][order[0]]), (r, c)

    def test_alignment_mosaic_rows_are_the_members_turned(self) -> None:
        """The aligned row shows each member rotated by its own yaw (a quarter turn: exact on the voxel grid)."""
        from threedq.data.draw import crop_birds_eye
        from threedq.geometry import rotate_yaw, yaw_angles

        g = torch.Generator().manual_seed(2)
        raw = (torch.rand(2, 4, 6, 6, 6, generator=g) > 0.5).float()
        test = {"raw": raw, "labels": torch.tensor([0, 1])}
        img = alignment_figure(test, torch.tensor([0, 0]), torch.tensor([0, 2]), 8, ["a", "b"], rows=1, cols=2, scale=2)
        tile, gap = 12, 4
        assert img.shape == (20 + 2 * (16 + 16 + tile) + gap, 2 * tile + gap, 3)
        turned = rotate_yaw(raw, yaw_angles(8)[torch.tensor([0, 2])])
        for r, vols in enumerate((raw, turned)):
            y = 20 + r * (16 + 16 + tile + gap) + 32
            for c in range(2):
                want = np.kron((crop_birds_eye(vols[c], background=0.5) * 255).round().astype(np.uint8),
                               np.ones((2, 2, 1), np.uint8))
                np.testing.assert_array_equal(img[y:y + tile, c * (tile + gap):c * (tile + gap) + tile], want)
        seen, aligned = (img[y:y + tile, tile + gap:] for y in (20 + 32, 20 + 48 + 32))
        assert seen.shape == aligned.shape == (tile, tile, 3) and not np.array_equal(seen, aligned)  # really turned

    def test_detection(self) -> None:
        rows = [{"band": "< 0.2 m", "objects": 3, "found_25": 2 / 3, "found_50": 1 / 3},
                {"band": ">= 0.2 m", "objects": 0, "found_25": float("nan"), "found_50": float("nan")}]  # fmt: skip
        assert _decode(figure_png(size_band_figure({"detector": rows, "pseudo-boxes": rows}))).ndim == 3
        np.testing.assert_allclose(aabb_to_boxes7(np.array([[0.0, 1.0, 2.0, 2.0, 2.0, 5.0]])),
                                   [[1.0, 1.5, 3.5, 2.0, 1.0, 3.0, 0.0]])  # fmt: skip
        K = torch.tensor([[50.0, 0, 15.5], [0, 50.0, 15.5], [0, 0, 1]])
        pose = torch.eye(4)
        pose[2, 3] = -3.0  # camera 3 m behind the origin, looking along +z
        sample = {"rgb": torch.zeros(1, 3, 32, 32), "K": K[None], "R_T_cam": pose[None]}
        labels = torch.tensor([[1.0, -0.2, -0.2, -0.2, 0.2, 0.2, 0.2], [0.0, 0.3, 0.3, 0.0, 0.5, 0.5, 0.2]])
        img = self_labels_figure([(sample, labels), (sample, labels[:1])], upscale=2)
        assert img.dtype == np.uint8 and img.shape == (64, 2 * (64 + 4), 3)
        assert (img[:, :64] != 0).any()  # boxes were drawn on the black view


def test_the_backend_is_never_changed() -> None:
    """A user's matplotlib backend (a notebook's) survives importing every layer of threedq and drawing its
    figures, and no pyplot figure is left open (threedq draws on its own Agg canvases; report.py once called
    ``matplotlib.use("Agg")`` at import)."""
    code = (
        "import matplotlib\n"
        "matplotlib.use('svg')\n"
        "import threedq.cli, threedq.pipeline.em, threedq.pipeline.report, threedq.pipeline.detection_eval\n"
        "import threedq.stages.viewpred, threedq.stages.mining, threedq.stages.self_labelling\n"
        "from threedq.viz.curves import table3_figure\n"
        "from threedq.viz.png import figure_png\n"
        "figure_png(table3_figure([{'round': 0, 'hungarian_acc': 0.5}]))\n"
        "import matplotlib.pyplot as plt\n"
        "assert matplotlib.get_backend() == 'svg', matplotlib.get_backend()\n"
        "assert plt.get_fignums() == [], plt.get_fignums()\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
