"""The six-number colour + size descriptor (a reference row of Table 2) and the coarse labels of the retrieval table."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.baselines.descriptor import colour_size_descriptor, descriptor_similarity
from threedq.geometry import rotate_yaw


def _raw(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    occ = (torch.rand(n, 1, 8, 8, 8, generator=g) > 0.6).float()
    rgb = torch.rand(n, 3, 1, 1, 1, generator=g).expand(n, 3, 8, 8, 8)
    return torch.cat([occ, occ * rgb], dim=1)


class TestColourSizeDescriptor:
    def test_smoke(self) -> None:
        assert colour_size_descriptor(_raw(3), torch.rand(3, 6)).shape == (3, 6)

    def test_hand_computed(self) -> None:
        raw = torch.zeros(1, 4, 4, 4, 4)
        raw[0, 0, 0, 0, 0], raw[0, 1:, 0, 0, 0] = 1.0, torch.tensor([1.0, 0.0, 0.0])  # a red voxel
        raw[0, 0, 1, 1, 1], raw[0, 1:, 1, 1, 1] = 0.5, 0.5 * torch.tensor([0.0, 0.0, 1.0])  # half-occupied blue
        aabb = torch.tensor([[0.0, 0.0, 0.0, 0.2, 0.5, 0.3]])
        d = colour_size_descriptor(raw, aabb)[0]
        # occupancy-weighted mean colour: (1 * red + 0.5 * blue) / 1.5; extents sorted (0.5, 0.2), height 0.3
        expected = torch.tensor([2 / 3, 0.0, 1 / 3, 0.5, 0.2, 0.3], dtype=torch.float64)
        assert torch.allclose(d, expected, atol=1e-7)

    def test_does_not_change_when_the_object_turns(self) -> None:
        raw = _raw(2, seed=1)
        aabb = torch.tensor([[0.0, 0.0, 0.0, 0.4, 0.2, 0.3], [-0.1, -0.1, 0.0, 0.1, 0.3, 0.2]])
        turned = rotate_yaw(raw, torch.full((2,), math.radians(90)))
        swapped = aabb[:, [1, 0, 2, 4, 3, 5]]  # a quarter turn swaps the horizontal extents
        a, b = colour_size_descriptor(raw, aabb), colour_size_descriptor(turned, swapped)
        assert torch.allclose(a[:, 3:], b[:, 3:]) and torch.allclose(a[:, :3], b[:, :3], atol=1e-5)

    def test_empty_crop_has_colour_zero(self) -> None:
        d = colour_size_descriptor(torch.zeros(1, 4, 4, 4, 4), torch.tensor([[0.0, 0, 0, 1, 1, 1]]))
        assert torch.equal(d[0, :3], torch.zeros(3, dtype=torch.float64))

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="raw"):
            colour_size_descriptor(torch.zeros(2, 3, 4, 4, 4), torch.zeros(2, 6))
        with pytest.raises(ValueError, match="aabb"):
            colour_size_descriptor(torch.zeros(2, 4, 4, 4, 4), torch.zeros(3, 6))


class TestDescriptorSimilarity:
    def test_standardised_distance_hand_computed(self) -> None:
        q = torch.tensor([[0.0, 0.0], [2.0, 20.0]])
        # pool std per dimension: 1 and 10 -> scaled [[0, 0], [2, 2]]: distance 2 * sqrt(2) between the two
        sim = descriptor_similarity(q, q)
        assert sim[0, 1].item() == pytest.approx(-2 * math.sqrt(2))
        assert sim[0, 0].item() == 0.0 and torch.equal(sim, sim.T)

    def test_a_constant_dimension_is_left_as_is(self) -> None:
        q = torch.tensor([[1.0, 5.0], [3.0, 5.0]])
        assert descriptor_similarity(q, q)[0, 1].item() == pytest.approx(-2.0)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="query"):
            descriptor_similarity(torch.zeros(2, 6), torch.zeros(2, 5))


class TestCoarseLabels:
    def test_clevr_primitives_by_shape(self) -> None:
        from threedq.data.catalog import CATEGORY_NAMES, coarse_category

        assert coarse_category("cube_red") == "cube" and coarse_category("cylinder_cyan") == "cylinder"
        assert coarse_category("mug") == "mug" and coarse_category("cube_unknowncolour") == "cube_unknowncolour"
        assert len({coarse_category(n) for n in CATEGORY_NAMES}) == 20  # 3 shapes + 17 meshes

    def test_ids_and_a_dataset_without_merges(self) -> None:
        from threedq.pipeline.report import coarse_labels

        cats = ["cube_red", "mug", "cube_blue", "sphere_red"]
        got = coarse_labels(cats, torch.tensor([0, 1, 2, 3, 2]))
        assert got.tolist() == [0, 1, 0, 2, 0]
        assert coarse_labels(["mug", "bowl"], torch.tensor([0, 1])) is None
