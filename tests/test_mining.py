"""Tests for threedq.contrastive.miner: retrieval, patch matching, verification and the correspondence miner."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from threedq.contrastive import (
    calibrate_context_cosine,
    context_offsets,
    match_patch,
    mine_correspondences,
    patch_grid,
    retrieve_targets,
    rotate_patch_positions,
    salient_positions,
    verify_match,
)
from threedq.geometry import rotate_yaw, yaw_angles

A = 36
S = 16


def unit(*shape: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Random crops ``[N, C, Z, Y, X]`` with L2-normalised per-voxel features."""
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(*shape, generator=g, dtype=dtype), dim=1)


def yaw_dist(a: torch.Tensor | int, b: int, n: int = A) -> int:
    d = abs(int(a) - b) % n
    return min(d, n - d)


def planted(degrees: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Queries ``[3, 8, S, S, S]`` and targets ``[4, ...]``; target 2 holds query 0 rotated by ``degrees``.

    The aligned target ``rotate_yaw(target 2, -degrees)`` equals query 0 inside the part the rotation fills
    (exactly for multiples of 90 degrees); query 0 gets fresh random values elsewhere. Returns the expected yaw
    index of the match (the yaw that rotates target 2 onto query 0).
    """
    base = unit(1, 8, S, S, S, seed=seed)
    theta = math.radians(degrees)
    if degrees % 90 == 0:
        query0, target = base, rotate_yaw(base, torch.tensor([theta]))
    else:  # query0 = the target rotated by -theta, so the miner's own re-rotation reproduces it exactly
        target = base
        query0 = rotate_yaw(base, torch.tensor([-theta]))
        cover = rotate_yaw(torch.ones(1, 1, S, S, S), torch.tensor([-theta]))
        query0 = torch.where(cover < 0.5, unit(1, 8, S, S, S, seed=seed + 1), query0)
    queries = torch.cat([query0, unit(2, 8, S, S, S, seed=seed + 2)])
    others = unit(3, 8, S, S, S, seed=seed + 3)
    targets = torch.cat([others[:2], target, others[2:]])
    return queries, targets, (-degrees // 10) % A


def expected_target_pos(query_pos: torch.Tensor, degrees: int) -> torch.Tensor:
    """Where the content of the query patch sits in the unrotated planted target (float)."""
    return rotate_patch_positions(query_pos.double(), math.radians(degrees), (S, S, S), round=False)


class TestPatchGrid:
    def test_values(self) -> None:
        assert patch_grid(16) == [1, 5, 9, 13]
        assert patch_grid(8) == [0, 2, 4, 6]
        assert patch_grid(16, grid=1) == [7]

    def test_centred(self) -> None:
        for size, grid in ((16, 4), (8, 4), (12, 3), (32, 4)):
            centres = [s + 0.5 for s in patch_grid(size, grid)]
            assert sum(centres) / grid == pytest.approx((size - 1) / 2)

    def test_errors(self) -> None:
        with pytest.raises(ValueError, match="does not fit"):
            patch_grid(8, grid=9)
        with pytest.raises(ValueError, match="does not fit"):
            patch_grid(4, grid=4, patch=2)
        with pytest.raises(ValueError, match="grid must be"):
            patch_grid(8, grid=0)


class TestContextOffsets:
    def test_count_and_norm(self) -> None:
        for d in (1, 2, 6):
            off = context_offsets(d)
            assert off.shape == (4 * d * d + 2, 3) and off.dtype == torch.long
            assert (off.abs().sum(dim=1) == d).all()
            assert len({tuple(o) for o in off.tolist()}) == off.shape[0]

    def test_errors(self) -> None:
        with pytest.raises(ValueError, match="context_distance"):
            context_offsets(0)


class TestRotatePatchPositions:
    def test_shape_and_dtype(self) -> None:
        pos = torch.zeros(4, 5, 3, dtype=torch.long)
        out = rotate_patch_positions(pos, 0.3, (S, S, S))
        assert out.shape == (4, 5, 3) and out.dtype == torch.long
        assert rotate_patch_positions(pos, 0.3, (S, S, S), round=False).is_floating_point()

    def test_identity(self) -> None:
        pos = torch.randint(0, S - 1, (20, 3))
        assert torch.equal(rotate_patch_positions(pos, 0.0, (S, S, S)), pos)

    def test_round_trip(self) -> None:
        g = torch.Generator().manual_seed(3)
        pos = torch.randint(0, S - 1, (50, 3), generator=g)
        yaw = torch.rand(50, generator=g, dtype=torch.float64) * 2 * math.pi
        back = rotate_patch_positions(rotate_patch_positions(pos.double(), yaw, (S, S, S), round=False), -yaw,
                                      (S, S, S), round=False)
        torch.testing.assert_close(back, pos.double(), rtol=0, atol=1e-9)
        # rounded twice: within one voxel; exact for quarter turns (the grid maps onto itself)
        rounded = rotate_patch_positions(rotate_patch_positions(pos, yaw, (S, S, S)), -yaw, (S, S, S))
        assert (rounded - pos).abs().max() <= 1
        for k in range(4):
            t = k * math.pi / 2
            assert torch.equal(rotate_patch_positions(rotate_patch_positions(pos, t, (S, S, S)), -t, (S, S, S)), pos)

    @pytest.mark.parametrize("degrees", [90, 180, 270])
    def test_matches_rotate_yaw_quarter_turns(self, degrees: int) -> None:
        pos = torch.tensor([3, 2, 11])
        vol = torch.zeros(1, 1, S, S, S)
        vol[0, 0, 3:5, 2:4, 11:13] = 1.0
        rot = rotate_yaw(vol, torch.tensor([math.radians(degrees)]))[0, 0]
        z, y, x = rotate_patch_positions(pos, math.radians(degrees), (S, S, S)).tolist()
        assert rot[z : z + 2, y : y + 2, x : x + 2].min() > 0.999 and rot.sum() == pytest.approx(8.0, abs=1e-4)

    def test_matches_rotate_yaw_centroid(self) -> None:
        # the centre of mass of a rotated 2^3 block is (about) where the block's centre is mapped
        vol = torch.zeros(1, 1, S, S, S, dtype=torch.float64)
        vol[0, 0, 6:8, 3:5, 9:11] = 1.0
        t = math.radians(40)
        rot = rotate_yaw(vol, torch.tensor([t], dtype=torch.float64))[0, 0]
        zz, yy, xx = torch.meshgrid(*(torch.arange(S, dtype=torch.float64),) * 3, indexing="ij")
        centroid = torch.stack([(rot * c).sum() / rot.sum() for c in (zz, yy, xx)])
        start = torch.tensor([6.0, 3.0, 9.0], dtype=torch.float64)
        mapped = rotate_patch_positions(start, t, (S, S, S), round=False) + 0.5
        torch.testing.assert_close(centroid, mapped, rtol=0, atol=0.15)  # bilinear sampling moves it a little
        wrong = rotate_patch_positions(start, -t, (S, S, S), round=False)
        assert (centroid - wrong - 0.5).abs().max() > 2  # the opposite sense of rotation is far off

    def test_errors(self) -> None:
        with pytest.raises(ValueError, match=r"positions must have shape \[\.\.\., 3\]"):
            rotate_patch_positions(torch.zeros(4, 2), 0.1, (S, S, S))
        with pytest.raises(ValueError, match="size must be"):
            rotate_patch_positions(torch.zeros(4, 3), 0.1, (S, S))


class TestRetrieveTargets:
    def test_shapes(self) -> None:
        q, t = unit(3, 4, 8, 8, 8, seed=1), unit(5, 4, 8, 8, 8, seed=2)
        idx, sim, angle = retrieve_targets(q, t, top_k=2, num_angles=8)
        assert idx.shape == sim.shape == angle.shape == (3, 2)
        assert idx.dtype == angle.dtype == torch.long and sim.dtype == torch.float32
        assert (sim[:, 0] >= sim[:, 1]).all()

    def test_top_k_clamped(self) -> None:
        idx, _, _ = retrieve_targets(unit(2, 4, 8, 8, 8), unit(3, 4, 8, 8, 8, seed=1), top_k=30, num_angles=8)
        assert idx.shape == (2, 3)

    @pytest.mark.parametrize("degrees", [90, 40])
    def test_finds_planted_target_and_angle(self, degrees: int) -> None:
        queries, targets, b = planted(degrees)
        idx, sim, angle = retrieve_targets(queries, targets, top_k=3)
        assert idx[0, 0] == 2 and sim[0, 0] > 0.8 and sim[0, 1] < 0.3
        # retrieval angle rotates the query onto the target: the opposite sign of the match yaw
        assert yaw_dist(angle[0, 0], (-b) % A) <= 1

    def test_exclude(self) -> None:
        queries, targets, _ = planted(90)
        exclude = torch.zeros(3, 4, dtype=torch.bool)
        exclude[0, 2] = True
        exclude[1] = True
        idx, sim, _ = retrieve_targets(queries, targets, top_k=4, exclude=exclude)
        assert 2 not in idx[0, :3].tolist() and idx[0, 3] == 2 and sim[0, 3] == float("-inf")
        assert torch.isinf(sim[1]).all() and torch.isfinite(sim[2]).all()

    def test_errors(self) -> None:
        q, t = unit(2, 4, 8, 8, 8), unit(3, 4, 8, 8, 8)
        with pytest.raises(ValueError, match="must share"):
            retrieve_targets(q, unit(3, 2, 8, 8, 8))
        with pytest.raises(ValueError, match=r"exclude must be a bool tensor of shape \[2, 3\]"):
            retrieve_targets(q, t, exclude=torch.zeros(3, 2, dtype=torch.bool))
        with pytest.raises(ValueError, match="exclude must be a bool"):
            retrieve_targets(q, t, exclude=torch.zeros(2, 3))
        with pytest.raises(ValueError, match="top_k"):
            retrieve_targets(q, t, top_k=0)
        with pytest.raises(ValueError, match=r"query_crops must have shape \[N, C, Z, Y, X\]"):
            retrieve_targets(q[0], t)


class TestMatchPatch:
    def test_shapes(self) -> None:
        yaw, pos, cos = match_patch(unit(1, 4, 8, 8, 8)[0], (1, 2, 3), unit(5, 4, 8, 8, 8, seed=1), num_angles=6)
        assert yaw.shape == (5,) and pos.shape == (5, 3) and cos.shape == (5,)
        assert yaw.dtype == pos.dtype == torch.long and cos.dtype == torch.float32
        assert ((yaw >= 0) & (yaw < 6)).all() and set(pos.flatten().tolist()) <= {0, 2, 4, 6}

    def test_naive_reference(self) -> None:
        query, targets = unit(1, 2, 8, 8, 8, seed=4)[0], unit(3, 2, 8, 8, 8, seed=5)
        qpos = (3, 2, 5)
        yaw, pos, cos = match_patch(query, qpos, targets, num_angles=4)
        qvec = query[:, 3:5, 2:4, 5:7].reshape(-1)
        angles = yaw_angles(4)
        for k in range(3):
            best = (-2.0, -1, (-1, -1, -1))
            for a in range(4):
                rot = rotate_yaw(targets[k : k + 1], angles[a : a + 1])[0]
                for z in patch_grid(8):
                    for y in patch_grid(8):
                        for x in patch_grid(8):
                            c = F.cosine_similarity(rot[:, z : z + 2, y : y + 2, x : x + 2].reshape(-1), qvec, dim=0)
                            if c.item() > best[0]:
                                best = (c.item(), a, (z, y, x))
            assert cos[k].item() == pytest.approx(best[0], abs=1e-5)
            assert yaw[k].item() == best[1] and tuple(pos[k].tolist()) == best[2]

    def test_naive_reference_odd_angle_count_float64(self) -> None:
        query = unit(1, 3, 8, 8, 8, seed=6, dtype=torch.float64)[0]
        targets = unit(2, 3, 8, 8, 8, seed=7, dtype=torch.float64)
        yaw, pos, cos = match_patch(query, torch.tensor([0, 4, 2]), targets, num_angles=5, grid=2)
        assert cos.dtype == torch.float64
        qvec = query[:, 0:2, 4:6, 2:4].reshape(-1)
        rot = rotate_yaw(targets, yaw_angles(5, dtype=torch.float64)[None].expand(2, -1))  # [2, 5, C, 8, 8, 8]
        for k in range(2):
            table = torch.stack([
                torch.stack([F.cosine_similarity(rot[k, a, :, z : z + 2, y : y + 2, x : x + 2].reshape(-1), qvec, dim=0)
                             for z in (1, 5) for y in (1, 5) for x in (1, 5)]) for a in range(5)
            ])
            assert cos[k].item() == pytest.approx(table.max().item(), abs=1e-12)
            a, g = divmod(int(table.argmax()), 8)
            assert yaw[k] == a and pos[k].tolist() == [(1, 5)[g // 4], (1, 5)[(g // 2) % 2], (1, 5)[g % 2]]

    @pytest.mark.parametrize("degrees", [90, 40])
    def test_planted(self, degrees: int) -> None:
        queries, targets, b = planted(degrees)
        qpos = torch.tensor([5, 9, 5])
        yaw, pos, cos = match_patch(queries[0], qpos, targets)
        assert int(cos.argmax()) == 2 and cos[2] > 0.99 and cos[[0, 1, 3]].max() < 0.7
        assert yaw_dist(yaw[2], b) <= 1 and (pos[2] - qpos).abs().max() <= 1
        unrotated = rotate_patch_positions(pos[2], -2 * math.pi * int(yaw[2]) / A, (S, S, S))
        assert (unrotated - expected_target_pos(qpos, degrees)).abs().max() <= 1

    def test_allowed_yaws(self) -> None:
        queries, targets, b = planted(90)
        qpos = torch.tensor([5, 9, 5])
        allowed = torch.zeros(4, A, dtype=torch.bool)
        allowed[:, b] = True
        yaw, _, cos = match_patch(queries[0], qpos, targets, allowed_yaws=allowed)
        assert (yaw == b).all() and cos[2] > 0.99
        allowed = torch.ones(4, A, dtype=torch.bool)
        allowed[:, [(b + d) % A for d in (-1, 0, 1)]] = False  # the true yaw forbidden: the match gets worse
        yaw, _, cos_off = match_patch(queries[0], qpos, targets, allowed_yaws=allowed)
        assert all(yaw_dist(y, b) > 1 for y in yaw.tolist()) and cos_off[2] < cos[2]
        with pytest.raises(ValueError, match="allowed_yaws"):
            match_patch(queries[0], qpos, targets, allowed_yaws=torch.zeros(4, A, dtype=torch.bool))

    def test_allowed_yaws_equal_the_masked_full_search(self) -> None:
        """Searching only the allowed yaws (windows of varying width, rows of different sizes) gives what the full
        36-yaw search masked to those yaws gives: the same yaw, position and cosine."""
        torch.manual_seed(3)
        queries, targets = unit(1, 4, S, S, S), unit(6, 4, S, S, S, seed=1)
        qpos = torch.tensor([5, 9, 5])
        allowed = torch.zeros(6, A, dtype=torch.bool)
        for k, (centre, w) in enumerate([(0, 1), (35, 1), (10, 0), (20, 3), (7, 2), (30, 1)]):
            allowed[k, [(centre + d) % A for d in range(-w, w + 1)]] = True
        allowed[5, 2] = True  # a row with two separate windows
        yaw, pos, cos = match_patch(queries[0], qpos, targets, allowed_yaws=allowed)
        for k in range(6):
            best = None
            for a in range(A):  # the naive reference: one yaw at a time, first maximum wins
                if not allowed[k, a]:
                    continue
                one = torch.zeros(1, A, dtype=torch.bool)
                one[0, a] = True
                y, p, c = match_patch(queries[0], qpos, targets[k : k + 1], allowed_yaws=one)
                if best is None or c.item() > best[2]:
                    best = (int(y), p[0].tolist(), c.item())
            assert (int(yaw[k]), pos[k].tolist()) == best[:2]
            assert cos[k].item() == pytest.approx(best[2], abs=1e-6)

    def test_errors(self) -> None:
        q, t = unit(1, 4, 8, 8, 8)[0], unit(2, 4, 8, 8, 8)
        with pytest.raises(ValueError, match="leaves the volume"):
            match_patch(q, (7, 0, 0), t)
        with pytest.raises(ValueError, match="query_pos must be 3 ints"):
            match_patch(q, (1, 2), t)
        with pytest.raises(ValueError, match="query_pos must be 3 ints"):
            match_patch(q, torch.tensor([1.0, 2.0, 3.0]), t)
        with pytest.raises(ValueError, match="C=4 channels"):
            match_patch(q, (0, 0, 0), unit(2, 3, 8, 8, 8))
        with pytest.raises(ValueError, match="does not fit"):
            match_patch(q, (0, 0, 0), t, grid=8)
        with pytest.raises(ValueError, match="num_angles"):
            match_patch(q, (0, 0, 0), t, num_angles=0)
        with pytest.raises(ValueError, match=r"query_crop must have shape \[C, Z, Y, X\]"):
            match_patch(q[None], (0, 0, 0), t)


class TestVerifyMatch:
    def test_identity(self) -> None:
        crop = unit(1, 8, S, S, S)[0]
        score = verify_match(crop, (5, 9, 5), crop, (5, 9, 5), 0)
        assert score.shape == () and score.item() == 1.0

    @pytest.mark.parametrize("degrees", [90, 40])
    def test_planted_accepted(self, degrees: int) -> None:
        queries, targets, _ = planted(degrees)
        qpos = (5, 9, 5)
        yaw, pos, _ = match_patch(queries[0], qpos, targets[2:3])
        assert verify_match(queries[0], qpos, targets[2], pos[0], int(yaw[0])) > 0.9

    def test_unrelated_rejected(self) -> None:
        queries, targets, _ = planted(90)
        yaw, pos, _ = match_patch(queries[0], (5, 9, 5), targets[:1])
        assert verify_match(queries[0], (5, 9, 5), targets[0], pos[0], int(yaw[0])) < 0.2

    def test_shuffled_context_rejected(self) -> None:
        queries, targets, b = planted(90)
        qpos = (5, 9, 5)
        z, y, x = rotate_patch_positions(torch.tensor(qpos), math.pi / 2, (S, S, S)).tolist()
        target = targets[2].clone()
        keep = torch.zeros(S, S, S, dtype=torch.bool)
        keep[z : z + 2, y : y + 2, x : x + 2] = True
        outside = (~keep).flatten().nonzero()[:, 0]
        shuffled = outside[torch.randperm(outside.numel(), generator=torch.Generator().manual_seed(0))]
        flat = target.reshape(8, -1)
        flat[:, outside] = flat[:, shuffled].clone()
        yaw, pos, cos = match_patch(queries[0], qpos, target[None])
        assert cos[0] > 0.99 and yaw[0] == b and pos[0].tolist() == list(qpos)  # the match itself survives
        assert verify_match(queries[0], qpos, targets[2], pos[0], int(yaw[0])) == 1.0
        assert verify_match(queries[0], qpos, target, pos[0], int(yaw[0])) < 0.5

    def test_min_cosine_and_no_context(self) -> None:
        crop = unit(1, 4, 8, 8, 8)[0]
        other = unit(1, 4, 8, 8, 8, seed=9)[0]
        assert verify_match(crop, (3, 3, 3), other, (3, 3, 3), 0, context_distance=2, min_cosine=-1.0) == 1.0
        # no context patch fits inside an 8^3 crop at distance 20: unverifiable, score 0
        assert verify_match(crop, (3, 3, 3), crop, (3, 3, 3), 0, context_distance=20) == 0.0

    def test_errors(self) -> None:
        crop = unit(1, 4, 8, 8, 8)[0]
        with pytest.raises(ValueError, match=r"yaw_index must be an int in \[0, 36\)"):
            verify_match(crop, (0, 0, 0), crop, (0, 0, 0), 36)
        with pytest.raises(ValueError, match="min_cosine"):
            verify_match(crop, (0, 0, 0), crop, (0, 0, 0), 0, min_cosine=1.5)
        with pytest.raises(ValueError, match="target_pos"):
            verify_match(crop, (0, 0, 0), crop, (0, 0, 7), 0)
        with pytest.raises(ValueError, match="C=4 channels"):
            verify_match(crop, (0, 0, 0), crop[:2], (0, 0, 0), 0)


class TestSalientPositions:
    def test_finds_distinct_patch(self) -> None:
        crops = torch.zeros(2, 4, 8, 8, 8)
        crops[:, 0] = 1.0  # every voxel the same feature
        crops[0, :, 2:4, 5:7, 1:3] = torch.tensor([0.0, 1.0, 0.0, 0.0])[:, None, None, None]
        crops[1, :, 4:6, 0:2, 6:8] = torch.tensor([0.0, 0.0, 1.0, 0.0])[:, None, None, None]
        assert salient_positions(crops).tolist() == [[2, 5, 1], [4, 0, 6]]

    def test_candidates(self) -> None:
        crops = unit(3, 4, 8, 8, 8)
        cands = torch.tensor([[0, 0, 0], [2, 2, 2], [6, 6, 6]])
        out = salient_positions(crops, cands)
        assert out.shape == (3, 3) and all(row in cands.tolist() for row in out.tolist())
        with pytest.raises(ValueError, match="inside the crops"):
            salient_positions(crops, torch.tensor([[7, 0, 0]]))


class TestMineCorrespondences:
    KEYS = {"query_index", "target_index", "query_pos", "target_pos", "target_pos_aligned", "yaw", "match_cosine",
            "score", "retrieval_sim"}

    @pytest.mark.parametrize("degrees", [90, 40])
    def test_planted(self, degrees: int) -> None:
        queries, targets, b = planted(degrees)
        out = mine_correspondences(queries, targets, top_k=4)
        assert set(out) == self.KEYS
        # only the planted pair passes verification; the distractors are rejected
        assert out["query_index"].tolist() == [0] and out["target_index"].tolist() == [2]
        assert yaw_dist(out["yaw"][0], b) <= 1 and out["score"][0] > 0.9 and out["match_cosine"][0] > 0.99
        qpos = out["query_pos"][0]
        assert set(qpos.tolist()) <= {5, 9}  # an inner grid position (default query patch)
        assert (out["target_pos"][0] - expected_target_pos(qpos, degrees)).abs().max() <= 1
        # searching only near the object-level retrieval's yaw finds the same correspondence
        near = mine_correspondences(queries, targets, top_k=4, yaw_window=1)
        assert near["target_index"].tolist() == [2] and yaw_dist(near["yaw"][0], b) <= 1
        assert (near["target_pos"][0] - expected_target_pos(near["query_pos"][0], degrees)).abs().max() <= 1

    def test_shapes_and_order(self) -> None:
        queries, targets, _ = planted(90)
        out = mine_correspondences(queries, targets, top_k=3, keep=5, min_score=0.0)
        p = out["query_index"].shape[0]
        assert p == 5 and out["query_pos"].shape == out["target_pos"].shape == (p, 3)
        assert all(out[k].shape == (p,) for k in ("target_index", "yaw", "match_cosine", "score", "retrieval_sim"))
        long_keys = ("query_index", "target_index", "query_pos", "target_pos", "yaw")
        assert all(out[k].dtype == torch.long for k in long_keys)
        assert (out["score"][:-1] >= out["score"][1:]).all()
        assert out["query_index"][0] == 0 and out["target_index"][0] == 2
        by_sim = mine_correspondences(queries, targets, top_k=3, keep=5, min_score=0.0, rank_by="retrieval")
        rs = by_sim["retrieval_sim"]
        assert (rs[:-1] >= rs[1:]).all() and by_sim["query_index"].numel() == p
        with pytest.raises(ValueError, match="rank_by"):
            mine_correspondences(queries, targets, rank_by="cosine")

    @pytest.mark.parametrize("keep", [1, 3, 10, 1000])
    def test_ranked_by_retrieval_verifies_only_what_can_be_kept(self, keep: int, monkeypatch: pytest.MonkeyPatch) -> None:
        """Verification stops once ``keep`` pairs passed (pairs from the most similar down): the kept pairs equal
        those of verifying every pair, and fewer pairs are verified when few are kept."""
        import threedq.contrastive.miner as mining

        queries, targets = unit(6, 4, S, S, S, seed=4), unit(9, 4, S, S, S, seed=5)
        kwargs = dict(top_k=6, keep=keep, min_score=0.3, min_cosine=0.0, rank_by="retrieval", yaw_window=1)
        monkeypatch.setattr(mining, "_VERIFY_PAIRS", 10_000)  # one chunk: every pair is verified
        full = mine_correspondences(queries, targets, **kwargs)
        calls = []
        real = mining._verify_batch
        monkeypatch.setattr(mining, "_verify_batch", lambda *a, **k: calls.append(a[0].shape[0]) or real(*a, **k))
        monkeypatch.setattr(mining, "_VERIFY_PAIRS", 4)
        lazy = mine_correspondences(queries, targets, **kwargs)
        assert set(full) == set(lazy)
        for k in full:
            torch.testing.assert_close(lazy[k], full[k], rtol=0, atol=1e-6)
        assert 0 < full["query_index"].numel() <= keep
        if keep < full["query_index"].numel() + 1:  # enough pairs passed: the rest was not verified
            assert sum(calls) < 6 * 6
        else:
            assert sum(calls) == 6 * 6

    def test_keep_and_explicit_positions(self) -> None:
        queries, targets, b = planted(90)
        qpos = torch.tensor([[9, 5, 9], [5, 5, 5], [9, 9, 9]])
        out = mine_correspondences(queries, targets, top_k=2, keep=1, query_positions=qpos, min_score=0.0)
        assert out["query_index"].tolist() == [0] and out["query_pos"].tolist() == [[9, 5, 9]]
        assert out["yaw"].tolist() == [b]
        assert out["target_pos"][0].tolist() == rotate_patch_positions(qpos[0], math.pi / 2, (S, S, S)).tolist()

    def test_exclude_removes_the_match(self) -> None:
        queries, targets, _ = planted(90)
        exclude = torch.zeros(3, 4, dtype=torch.bool)
        exclude[:, 2] = True
        out = mine_correspondences(queries, targets, top_k=4, exclude=exclude)
        assert out["query_index"].numel() == 0 and out["target_pos"].shape == (0, 3)

    def test_errors(self) -> None:
        queries, targets, _ = planted(90)
        with pytest.raises(ValueError, match=r"query_positions must be an integer tensor of shape \[3, 3\]"):
            mine_correspondences(queries, targets, query_positions=torch.zeros(2, 3, dtype=torch.long))
        with pytest.raises(ValueError, match="inside crops"):
            mine_correspondences(queries, targets, query_positions=torch.full((3, 3), 15))
        with pytest.raises(ValueError, match="keep"):
            mine_correspondences(queries, targets, keep=0)
        with pytest.raises(ValueError, match="min_score"):
            mine_correspondences(queries, targets, min_score=2.0)


class TestCalibrateContextCosine:
    def test_identical_features_give_one(self) -> None:
        crops = torch.zeros(4, 8, 8, 8, 8)
        crops[:, 0] = 1.0
        assert calibrate_context_cosine(crops, torch.arange(4), generator=torch.Generator().manual_seed(0)) == (
            pytest.approx(1.0))

    def test_random_features_low_and_best_of_neighbourhood(self) -> None:
        g = torch.Generator().manual_seed(0)
        crops = unit(6, 64, 8, 8, 8)
        lo = calibrate_context_cosine(crops, torch.arange(6), quantile=0.5, generator=g)
        hi = calibrate_context_cosine(crops, torch.arange(6), quantile=0.99, generator=torch.Generator().manual_seed(0))
        # the max of 27 cosines of independent random 512-d unit vectors: positive, well below 1
        assert 0.0 < lo < hi < 0.5

    def test_bf16_cosines_of_a_gpu_autocast(self, monkeypatch: pytest.MonkeyPatch) -> None:
        # under a GPU's bf16 autocast the einsum returns bf16, which torch.quantile refuses (found on an H200,
        # 2026-12-04); emulated here by an einsum that rounds to bf16 as CUDA's autocast does
        import threedq.contrastive.miner as mining_mod

        crops = unit(6, 16, 8, 8, 8)
        ref = calibrate_context_cosine(crops, torch.arange(6), generator=torch.Generator().manual_seed(0))
        einsum = torch.einsum
        monkeypatch.setattr(mining_mod.torch, "einsum", lambda *a: einsum(*a).bfloat16())
        low = calibrate_context_cosine(crops, torch.arange(6), generator=torch.Generator().manual_seed(0))
        assert low == pytest.approx(ref, abs=2 ** -8)

    def test_one_scene_and_errors(self) -> None:
        crops = unit(3, 4, 8, 8, 8)
        assert calibrate_context_cosine(crops, torch.zeros(3, dtype=torch.long)) == 0.5
        with pytest.raises(ValueError, match="quantile"):
            calibrate_context_cosine(crops, torch.arange(3), quantile=1.0)
