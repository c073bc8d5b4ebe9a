"""Tests for threedq.baselines.pointcloud (the paper's point cloud registration baseline)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from threedq.baselines import PointCloudPrototypes
from threedq.baselines.pointcloud import _binarise, _RotatedBank, _Similarity

Shape = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def _box(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, b: tuple[float, ...]) -> torch.Tensor:
    return (x >= b[0]) & (x <= b[1]) & (y >= b[2]) & (y <= b[3]) & (z >= b[4]) & (z <= b[5])


# Asymmetric shapes in voxel units about the crop centre (box faces on integers: never on a voxel centre),
# inside the radius-8 cylinder of a 16^3 crop so that every yaw keeps them in the crop.
SHAPES: dict[str, Shape] = {
    "L": lambda x, y, z: _box(x, y, z, (-5, 5, -5, -2, -6, 0)) | _box(x, y, z, (-5, -2, -5, 5, -6, 0)),
    "T": lambda x, y, z: _box(x, y, z, (-6, 6, 1, 5, -6, 3)) | _box(x, y, z, (-2, 2, -6, 5, -6, 3)),
    "bar": lambda x, y, z: _box(x, y, z, (-6, 6, -2, 2, -6, -2)) | _box(x, y, z, (2, 6, -2, 2, -6, 5)),
    "blob": lambda x, y, z: (
        (((x + 1) / 4.5) ** 2 + ((y - 1) / 3) ** 2 + ((z + 2) / 4) ** 2 <= 1)
        | (((x - 3) ** 2 + (y + 3) ** 2 + (z + 4) ** 2) <= 6)
    ),
}


def raster(
    name: str, steps: int, size: int = 16, drop: float = 0.0, gen: torch.Generator | None = None
) -> torch.Tensor:
    """``[1, S, S, S]`` occupancy of shape ``name`` rotated by ``10 * steps`` degrees (exact point-in-shape test).

    Voxel centre ``p`` is occupied iff ``R(-theta) p`` lies in the shape; ``drop`` removes each occupied voxel
    with that probability (noise).
    """
    ax = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    z, y, x = torch.meshgrid(ax, ax, ax, indexing="ij")
    theta = math.radians(10 * steps)
    c, s = math.cos(theta), math.sin(theta)
    occ = SHAPES[name](c * x + s * y, -s * x + c * y, z)
    if drop > 0:
        occ = occ & (torch.rand(occ.shape, generator=gen, dtype=torch.float64) >= drop)
    return occ.float()[None]


def hungarian_accuracy(labels: torch.Tensor, clusters: torch.Tensor) -> float:
    n_lab, n_clu = int(labels.max()) + 1, int(clusters.max()) + 1
    confusion = np.zeros((n_lab, n_clu))
    np.add.at(confusion, (labels.numpy(), clusters.numpy()), 1)
    rows, cols = linear_sum_assignment(-confusion)
    return float(confusion[rows, cols].sum() / len(labels))


def rotation_aware_similarity(objects: torch.Tensor, prototypes: torch.Tensor, num_angles: int = 36) -> torch.Tensor:
    """``[N, K, A]`` similarity of every object, rotated by every yaw, to every prototype (the E-step's scores)."""
    binary, protos = _binarise(objects, 0.5), _binarise(prototypes, 0.5)
    sim = _Similarity()
    bank = _RotatedBank(binary, num_angles, sim, chunk=64, cache_bytes=0)
    return torch.cat([sim.scores(rot, dils, sim.prototype_sets(protos)) for _, rot, dils in bank.chunks()])


def occupied_points(crops: torch.Tensor) -> list[torch.Tensor]:
    """Centres ``[P, 3]`` (x, y, z in [-1, 1], cell-centred) of the occupied voxels of each ``[N, 1, S, S, S]`` crop."""
    size = crops.shape[-1]
    return [(2.0 * vol.nonzero().flip(-1).double() + 1.0) / size - 1.0 for vol in crops[:, 0] >= 0.5]


# ------------------------------------------------------------------------- naive per-point reference
def naive_rotated_points(points: torch.Tensor, size: int, theta: float) -> set[tuple[int, int, int]]:
    """Lattice voxels ``(i, j, k)`` (x, y, z) where the bilinear interpolation of the point set's indicator at
    ``R(-theta) p`` is >= 0.5; computed from the points of :func:`occupied_points`, one voxel at a time."""
    c = (size - 1) / 2
    vox = [tuple(v) for v in ((points.double() + 1.0) * size / 2 - 0.5).tolist()]  # voxel indices (x, y, z)
    cos, sin = math.cos(theta), math.sin(theta)
    out = set()
    for k in range(size):
        in_slice = [(vx, vy) for vx, vy, vz in vox if round(vz) == k]
        for j in range(size):
            for i in range(size):
                qx = cos * (i - c) + sin * (j - c) + c
                qy = -sin * (i - c) + cos * (j - c) + c
                value = sum(max(0.0, 1 - abs(qx - vx)) * max(0.0, 1 - abs(qy - vy)) for vx, vy in in_slice)
                if value >= 0.5:
                    out.add((i, j, k))
    return out


def naive_score(xs: set, ys: set, tolerances: tuple[float, ...] = (0.0, 1.0)) -> float:
    def near(p: tuple, others: set, t: float) -> bool:
        return any(math.dist(p, q) <= t + 1e-9 for q in others)

    total = 0.0
    for t in tolerances:
        t = t if t >= 1 else 0.0
        precision = sum(near(x, ys, t) for x in xs) / len(xs) if xs else 0.0
        recall = sum(near(y, xs, t) for y in ys) / len(ys) if ys else 0.0
        total += 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return total / len(tolerances)


def test_similarity_matches_naive_point_loop() -> None:
    gen = torch.Generator().manual_seed(3)
    size, num_angles = 6, 12
    objects = (torch.rand(2, 1, size, size, size, generator=gen, dtype=torch.float64) < 0.12).double()
    protos = (torch.rand(2, 1, size, size, size, generator=gen, dtype=torch.float64) < 0.12).double()
    objects[1, 0, 1:4, 2:4, 1:5] = 1.0  # a solid part: rotations fill/erode it
    scores = rotation_aware_similarity(objects, protos, num_angles)
    assert scores.shape == (2, 2, num_angles) and scores.dtype == torch.float64
    obj_pts, proto_pts = occupied_points(objects), occupied_points(protos)
    for i in range(2):
        for k in range(2):
            ys = naive_rotated_points(proto_pts[k], size, 0.0)
            for a in range(num_angles):
                xs = naive_rotated_points(obj_pts[i], size, 2 * math.pi * a / num_angles)
                assert scores[i, k, a].item() == pytest.approx(naive_score(xs, ys), abs=1e-9)


def test_rotated_shape_recovered_at_the_right_angle() -> None:
    names = list(SHAPES)
    protos = torch.stack([raster(n, 0) for n in names])
    steps = [0, 3, 7, 9, 13, 18, 25, 27, 34]
    objects = torch.stack([raster(n, s) for n in names for s in steps])
    scores = rotation_aware_similarity(objects, protos)
    best = scores.flatten(1).argmax(1)
    label, angle = best // 36, best % 36
    assert label.tolist() == [k for k in range(len(names)) for _ in steps]
    # the object was rotated by +10 s degrees: rotating it by -10 s degrees aligns it with the prototype
    assert angle.tolist() == [(-s) % 36 for _ in names for s in steps]
    assert scores.amax(dim=(1, 2)).min() > 0.9
    l_quarter_turns = [i for i, s in enumerate(steps) if s % 9 == 0]  # the L (first) at 0, 90, 180, 270 deg: exact
    assert torch.all(scores.amax(dim=(1, 2))[l_quarter_turns] == 1.0)
    # other shapes are clearly less similar at any yaw
    other = scores.amax(2).clone()
    other[torch.arange(len(label)), label] = 0
    assert other.max() < 0.8


def _synthetic(copies: int = 10, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    crops, labels, steps = [], [], []
    for c, name in enumerate(SHAPES):
        for _ in range(copies):
            s = int(torch.randint(36, (1,), generator=gen))
            crops.append(raster(name, s, drop=0.05, gen=gen))
            labels.append(c)
            steps.append(s)
    perm = torch.randperm(len(labels), generator=gen)
    return torch.stack(crops)[perm], torch.tensor(labels)[perm], torch.tensor(steps)[perm]


def test_fit_clusters_synthetic_shapes_and_recovers_relative_yaw() -> None:
    crops, labels, steps = _synthetic()
    model = PointCloudPrototypes().fit(crops, K=len(SHAPES), iterations=10, seed=0)
    assert hungarian_accuracy(labels, model.labels_) == 1.0
    assert model.prototypes_.shape == (4, 1, 16, 16, 16) and model.converged_
    # object i = R(10 s_i) shape, and rotating it by a_i aligns it with the prototype: a_i + s_i is constant
    # per cluster (the prototype's own yaw); re-voxelisation may shift a rare member by one 10 degree step
    offsets = (model.angles_ + steps) % 36
    exact = 0
    for k in range(len(SHAPES)):
        members = offsets[model.labels_ == k]
        error = ((members - torch.mode(members).values + 18) % 36 - 18).abs()
        assert error.max() <= 1
        exact += int((error == 0).sum())
    assert exact >= 0.9 * len(labels)
    assert model.scores_.min() > 0.85
    # assign() on the training crops gives the final E-step
    prototype, angle, score = model.assign(crops)
    assert torch.equal(prototype, model.labels_) and torch.equal(angle, model.angles_)
    torch.testing.assert_close(score, model.scores_)
    # the full similarity agrees with assign()
    sim = rotation_aware_similarity(crops, model.prototypes_)
    assert sim.shape == (len(labels), 4, 36)
    torch.testing.assert_close(sim.amax(dim=(1, 2)), score)


def test_fit_is_deterministic_and_cache_independent() -> None:
    crops, _, _ = _synthetic(copies=3, seed=1)
    a = PointCloudPrototypes().fit(crops, K=5, iterations=3, seed=7)
    b = PointCloudPrototypes(max_cache_bytes=0, chunk=8).fit(crops, K=5, iterations=3, seed=7)
    for attr in ("prototypes_", "labels_", "angles_", "scores_", "init_indices_"):
        assert torch.equal(getattr(a, attr), getattr(b, attr)), attr
    c = PointCloudPrototypes().fit(crops, K=5, iterations=3, seed=8)
    assert not torch.equal(a.init_indices_, c.init_indices_)


def test_initialisation_threshold_and_farthest_fill() -> None:
    crops, labels, _ = _synthetic(copies=3, seed=2)
    one = PointCloudPrototypes().fit(crops, K=4, iterations=0, init_threshold=0.0)
    assert one.num_accepted_ == 1 and one.n_iter_ == 0
    # the farthest-object fill still picks one exemplar of every shape
    assert sorted(labels[one.init_indices_].tolist()) == [0, 1, 2, 3]
    assert torch.equal(one.prototypes_, crops[one.init_indices_])
    strict = PointCloudPrototypes().fit(crops, K=4, iterations=0, init_threshold=0.85)
    assert strict.num_accepted_ == 4 and sorted(labels[strict.init_indices_].tolist()) == [0, 1, 2, 3]


def test_more_prototypes_than_shapes_and_empty_object() -> None:
    crops, _, _ = _synthetic(copies=3, seed=3)
    crops[0] = 0  # an object without occupied voxels scores 0 everywhere
    model = PointCloudPrototypes().fit(crops, K=6, iterations=4, seed=0)
    assert model.labels_.max() < 6 and model.prototypes_.shape[0] == 6
    assert model.scores_[0] == 0 and torch.all(model.scores_[1:] > 0.5)
    proto, angle, score = model.assign(crops[:0])
    assert proto.shape == angle.shape == score.shape == (0,)


def test_errors() -> None:
    crops = torch.zeros(4, 1, 8, 8, 8)
    with pytest.raises(ValueError, match=r"\[N, 1, S, S, S\].*crops\[:, :1\]"):
        PointCloudPrototypes().fit(torch.zeros(4, 4, 8, 8, 8), K=2)
    with pytest.raises(ValueError, match=r"\[N, 1, S, S, S\]"):
        PointCloudPrototypes().fit(torch.zeros(4, 1, 8, 8, 6), K=2)
    with pytest.raises(ValueError, match="floating-point or bool"):
        PointCloudPrototypes().fit(crops.long(), K=2)
    with pytest.raises(ValueError, match="threshold"):
        PointCloudPrototypes(threshold=0.0)
    with pytest.raises(ValueError, match="num_angles"):
        PointCloudPrototypes(num_angles=0)
    model = PointCloudPrototypes()
    with pytest.raises(RuntimeError, match="not fitted"):
        model.assign(crops)
    with pytest.raises(ValueError, match="at least K=5"):
        model.fit(crops, K=5)
    with pytest.raises(ValueError, match="K must be an int >= 1"):
        model.fit(crops, K=0)
    with pytest.raises(ValueError, match="iterations"):
        model.fit(crops, K=2, iterations=-1)
    with pytest.raises(ValueError, match="init_threshold"):
        model.fit(crops, K=2, init_threshold=1.5)
    with pytest.raises(ValueError, match="seed"):
        model.fit(crops, K=2, seed=-1)
    model.fit(crops, K=2, iterations=1)
    with pytest.raises(ValueError, match="crop size S=8"):
        model.assign(torch.zeros(1, 1, 6, 6, 6))
