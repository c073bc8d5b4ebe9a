"""Prototype bank: incremental init, E-step, closed-form M-step, state in buffers; the quantizer stage."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
from conftest import refused as refused_by
from conftest import tiny_data_yaml

from threedq.geometry import rotate_yaw
from threedq.metrics import cluster_confusion, hungarian_accuracy
from threedq.quantization.prototypes import (PrototypeBank, assign_chunked, fit_prototype_bank, prototype_crops,
                                              quantization_loss, run_prototype_em)

S = 12


def base_shapes(n: int = 3, channels: int = 4, seed: int = 0) -> torch.Tensor:
    """Distinct smooth asymmetric volumes, zero outside the inscribed cylinder (rotation loses nothing)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, channels, S, S, S, generator=g)
    x = torch.nn.functional.avg_pool3d(x, 3, 1, 1) - 0.45
    x = x.clamp_min(0) * 4
    c = (torch.arange(S) - (S - 1) / 2).abs()
    r = (c[None, :] ** 2 + c[:, None] ** 2).sqrt()
    return x * (r < S / 2 - 1.5)[None, None, None]


def rotated_copies(shapes: torch.Tensor, per: int, seed: int = 1, noise: float = 0.02):
    g = torch.Generator().manual_seed(seed)
    idx = torch.arange(shapes.shape[0]).repeat_interleave(per)
    steps = torch.randint(0, 36, (idx.numel(),), generator=g)
    objs = rotate_yaw(shapes[idx], steps * (2 * math.pi / 36))
    return objs + noise * torch.randn(objs.shape, generator=g), idx, steps


class TestPrototypeBank:
    def test_incremental_init_one_prototype_per_shape(self) -> None:
        objs, labels, _ = rotated_copies(base_shapes(), per=6)
        bank = PrototypeBank(num_prototypes=10, channels=4, size=S, num_angles=36, init_threshold=0.8)
        opened = bank.add(objs)
        assert bank.num_active == 3 and int(opened.sum()) == 3
        # the first copy of each shape opened its prototype
        assert sorted(labels[opened].tolist()) == [0, 1, 2]

    @pytest.mark.parametrize("method", ["fast", "exact"])
    def test_bf16_crops_fit_as_their_float32_copy(self, method: str) -> None:
        # crops of an encoder under a GPU's bf16 autocast reached the EM in bf16 and failed the spectrum's plan check
        # (found on an H200, 2026-12-04); the bank searches them in its own float32, as the float32 copy
        objs, _, _ = rotated_copies(base_shapes(), per=6)
        low = objs.to(torch.bfloat16)
        banks = []
        for crops in (low, low.float()):
            bank = PrototypeBank(num_prototypes=4, channels=4, size=S, num_angles=36, method=method)
            spectra: dict = {}
            run_prototype_em(bank, crops, 2, seed=0, spectra=spectra)
            banks.append((bank, assign_chunked(bank, crops, spectra=spectra)))
        (a, ra), (b, rb) = banks
        assert a.num_active == b.num_active >= 3
        assert torch.equal(a.prototypes, b.prototypes) and a.prototypes.dtype == torch.float32
        assert torch.equal(ra.prototype, rb.prototype) and torch.equal(ra.angle, rb.angle)
        assert torch.equal(ra.score, rb.score)

    def test_em_clusters_and_aligns(self) -> None:
        shapes = base_shapes()
        objs, labels, steps = rotated_copies(shapes, per=8)
        bank = fit_prototype_bank(objs, num_prototypes=3, iterations=3, num_angles=36, seed=0)
        res = bank.assign(objs)
        conf = cluster_confusion(res.prototype, labels, 3, 3)
        assert float(hungarian_accuracy(conf)) == 1.0
        # relative yaw within a cluster: rotating by angle aligns, so angle + step is constant per cluster
        for k in range(3):
            members = res.prototype == k
            rel = (res.angle[members] + steps[members]) % 36
            assert rel.unique().numel() == 1

    def test_update_is_mean_of_aligned_members(self) -> None:
        shapes = base_shapes(1)
        bank = PrototypeBank(num_prototypes=2, channels=4, size=S, num_angles=36)
        bank.add(shapes)
        objs = rotate_yaw(shapes.expand(2, -1, -1, -1, -1), torch.tensor([0.0, math.pi / 2]))
        objs[1] *= 3.0  # same shape, other pose, other scale
        res = bank.assign(objs)
        assert res.angle.tolist() == [0, 27]  # rotating by 270 deg undoes the 90 deg turn
        bank.accumulate(objs, res)
        counts = bank.update()
        assert counts.tolist() == [2.0, 0.0]
        expected = (objs[0] + rotate_yaw(objs[1:], torch.tensor([1.5 * math.pi]))[0]) / 2
        torch.testing.assert_close(bank.prototypes[0], expected, atol=1e-5, rtol=1e-5)
        assert bank.member_count.sum() == 0 and bank.member_sum.abs().sum() == 0

    def test_closed_form_beats_gradient_descent(self) -> None:
        """The mean is the minimiser of the quantization loss at a fixed assignment (the M-step's justification)."""
        objs, _, _ = rotated_copies(base_shapes(), per=6, noise=0.1)
        bank = fit_prototype_bank(objs, num_prototypes=3, iterations=1, num_angles=36)
        res = bank.assign(objs)
        protos = bank.prototypes.clone().requires_grad_(True)
        opt = torch.optim.Adam([protos], lr=1e-2)
        aligned = bank.canonical_rotation(objs, res)
        for _ in range(50):
            loss = (protos[res.prototype] - aligned).pow(2).flatten(1).sum(1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        bank.accumulate(objs, res)
        bank.update()
        assert quantization_loss(bank, objs, res) <= loss.item() + 1e-6

    def test_state_lives_in_buffers(self) -> None:
        bank = PrototypeBank(num_prototypes=4, channels=4, size=S)
        bank.add(base_shapes())
        state = bank.state_dict()
        assert set(state) == {"prototypes", "active", "member_sum", "member_count"}
        other = PrototypeBank(num_prototypes=4, channels=4, size=S)
        other.load_state_dict(state)
        assert other.num_active == 3 and torch.equal(other.prototypes, bank.prototypes)

    def test_exceptions(self) -> None:
        bank = PrototypeBank(num_prototypes=2, channels=4, size=S)
        with pytest.raises(RuntimeError, match="empty"):
            bank.assign(base_shapes())
        with pytest.raises(ValueError, match="objects: expected shape"):
            bank.add(torch.zeros(1, 3, S, S, S))
        with pytest.raises(ValueError, match="method"):
            PrototypeBank(method="slow")

    def test_no_rotation_search(self) -> None:
        objs, labels, _ = rotated_copies(base_shapes(), per=4)
        bank = fit_prototype_bank(objs, num_prototypes=3, iterations=2, num_angles=1)
        assert bank.assign(objs).angle.eq(0).all()


class TestRestarts:
    """``run_prototype_em(restarts=R)`` against a naive loop: R separate fits, the lowest quantization loss kept."""

    def _crops(self) -> torch.Tensor:
        # 8 shapes into 3 prototypes: the initialisation order decides which optimum the EM reaches
        crops, _, _ = rotated_copies(base_shapes(8, channels=4, seed=5), per=4, seed=2, noise=0.1)
        return crops

    @staticmethod
    def _fit(crops: torch.Tensor, seed: int, restarts: int = 1) -> PrototypeBank:
        from threedq.quantization.prototypes import run_prototype_em

        bank = PrototypeBank(3, crops.shape[1], crops.shape[-1], 36, init_threshold=0.8)
        return run_prototype_em(bank, crops, iterations=3, seed=seed, restarts=restarts)

    @staticmethod
    def _loss(bank: PrototypeBank, crops: torch.Tensor) -> float:
        return float(quantization_loss(bank, crops, bank.assign(crops)))

    def test_keeps_the_fit_of_lowest_loss(self) -> None:
        crops = self._crops()
        singles = [self._fit(crops, seed) for seed in (4, 5, 6, 7)]
        losses = [self._loss(b, crops) for b in singles]
        assert len({round(v, 4) for v in losses}) > 1  # the seeds reach different optima: the choice matters
        best = singles[min(range(4), key=lambda i: losses[i])]
        chosen = self._fit(crops, seed=4, restarts=4)
        assert torch.equal(chosen.prototypes, best.prototypes)
        assert torch.equal(chosen.active, best.active)
        assert self._loss(chosen, crops) == pytest.approx(min(losses))
        assert chosen.member_count.sum() == 0  # the kept bank is as a single fit leaves it

    def test_one_restart_is_the_single_fit(self) -> None:
        crops = self._crops()
        assert torch.equal(self._fit(crops, seed=3, restarts=1).prototypes, self._fit(crops, seed=3).prototypes)

    def test_a_warm_bank_is_refined_once(self) -> None:
        from threedq.quantization.prototypes import run_prototype_em

        crops = self._crops()
        warm = self._fit(crops, seed=0)
        a, b = copy.deepcopy(warm), copy.deepcopy(warm)
        run_prototype_em(a, crops, iterations=2, seed=9, restarts=5)
        run_prototype_em(b, crops, iterations=2, seed=9)
        assert torch.equal(a.prototypes, b.prototypes)

    @pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
    def test_exception(self, bad) -> None:
        with pytest.raises(ValueError, match="restarts: expected an int >= 1"):
            self._fit(self._crops(), seed=0, restarts=bad)

    @pytest.mark.parametrize("bad", [0, -1, 1.5])
    def test_stage_exception(self, bad) -> None:
        assert "em_restarts" in refused(em_restarts=bad)


def refused(**init_args: object) -> str:
    """The parser's error for the quantizer's ``init_args`` on the tiny grid."""
    from threedq.stages.quantizer import Quantizer

    return refused_by(Quantizer, grid_resolution=[32, 32, 16], **init_args)


class TestPrototypeCrops:
    """The crops a bank compares: the features as they are (the paper) or weighted by their input occupancy."""

    def test_plain_is_the_features_themselves(self) -> None:
        f = torch.randn(2, 3, 4, 4, 4)
        assert prototype_crops(f, None) is f
        assert prototype_crops(f, torch.rand(2, 4, 4, 4, 4), None) is f

    def test_weighted_is_floor_plus_dilated_occupancy(self) -> None:
        from threedq.geometry import occupancy_weighted

        g = torch.Generator().manual_seed(0)
        f = torch.randn(2, 3, 5, 5, 5, generator=g, dtype=torch.float64)
        raw = torch.rand(2, 4, 5, 5, 5, generator=g, dtype=torch.float64)
        raw[:, 0] = (raw[:, 0] > 0.8).double()  # channel 0 is the occupancy; the colour channels are not read
        want = occupancy_weighted(f, raw[:, :1], floor=0.3, dilation=3)
        torch.testing.assert_close(prototype_crops(f, raw, 0.3), want)
        torch.testing.assert_close(prototype_crops(f, raw[:, :1], 0.3), want)
        # hand-computed: one occupied voxel in a corner; its 2^3 neighbourhood weighs 1.3, the rest 0.3
        one = torch.zeros(1, 1, 3, 3, 3, dtype=torch.float64)
        one[0, 0, 0, 0, 0] = 1.0
        w = prototype_crops(torch.ones(1, 1, 3, 3, 3, dtype=torch.float64), one, 0.3)
        assert torch.allclose(w.sum(), torch.tensor(8 * 1.3 + 19 * 0.3, dtype=torch.float64))

    def test_rotated_copy_found_at_its_angle(self) -> None:
        # a bank fitted on weighted crops finds an object turned by a known quarter turn (features and occupancy
        # turned together) at that yaw: the weight goes through the rotation search as it is
        shapes = base_shapes(3, channels=4)
        occ = (shapes.sum(1, keepdim=True) > 0).float()
        bank = fit_prototype_bank(prototype_crops(shapes, occ, 0.2), num_prototypes=3, iterations=2, num_angles=4,
                                  init_threshold=0.99, method="exact")
        turned = torch.rot90(shapes, 1, dims=(3, 4)), torch.rot90(occ, 1, dims=(3, 4))
        res = bank.assign(prototype_crops(*turned, 0.2))
        ref = bank.assign(prototype_crops(shapes, occ, 0.2))
        assert torch.equal(res.prototype, ref.prototype)
        assert (res.angle - ref.angle).remainder(4).unique().numel() == 1  # the same turn for every object
        assert (res.angle - ref.angle).remainder(4)[0] in (1, 3)  # a quarter turn (its sign: the yaw convention)
        torch.testing.assert_close(res.score, ref.score, atol=1e-5, rtol=0)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="raw"):
            prototype_crops(torch.zeros(1, 2, 4, 4, 4), None, 0.2)
        with pytest.raises(ValueError):
            prototype_crops(torch.zeros(1, 2, 4, 4, 4), torch.zeros(2, 1, 4, 4, 4), 0.2)


def _quantizer_config(tmp_path: Path, data_dir: Path, encoder_ckpt: Path) -> Path:
    cfg = tmp_path / "q.yaml"
    cfg.write_text(
        f"""
model:
  init_args:
    grid_resolution: [32, 32, 16]
    encoder_ckpt: {encoder_ckpt}
    num_prototypes: 4
    crop_size: 8
    em_iterations: 2
{tiny_data_yaml(data_dir)}
trainer:
  enable_progress_bar: false
  enable_model_summary: false
  log_every_n_steps: 1
"""
    )
    return cfg


def _banks_fitted_with(tmp_path: Path, tiny_dataset: Path, option: str, values: dict) -> dict:
    """``{value: (checkpoint, prototypes)}`` of quantizer stages fitted through the CLI on one random encoder, each
    with ``--model.init_args.<option>=<its command-line text>`` (every fit's metrics checked)."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
    cfg = _quantizer_config(tmp_path, tiny_dataset, enc)
    banks = {}
    for value, text in values.items():
        run = tmp_path / f"q_{option}_{text}"
        cli = ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/quantizer.yaml")), "--config", str(cfg),
                               f"--trainer.default_root_dir={run}", f"--model.init_args.{option}={text}"])
        assert 0.0 <= float(cli.trainer.logged_metrics["val/hungarian_acc"]) <= 1.0
        banks[value] = (run / "checkpoints" / "last.ckpt", cli.model.bank.prototypes.clone())
    return banks


class TestQuantizerStage:
    def test_fit_validate_and_warm_start(self, tmp_path: Path, tiny_dataset: Path) -> None:
        from threedq.stages.base import EncoderStage
        from threedq.stages.quantizer import Quantizer

        from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config

        torch.manual_seed(0)
        enc = tmp_path / "enc.pt"
        torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
        cfg = _quantizer_config(tmp_path, tiny_dataset, enc)
        run = tmp_path / "q"
        cli = ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/quantizer.yaml")), "--config", str(cfg),
                               f"--trainer.default_root_dir={run}"])
        model = cli.model
        assert isinstance(model, Quantizer) and model.bank.num_active == 4
        logged = cli.trainer.logged_metrics
        for key in ("val/hungarian_acc", "val/fewshot_acc", "train/prototypes_active"):
            assert key in logged
        assert 0.0 <= float(logged["val/hungarian_acc"]) <= 1.0
        ckpt = run / "checkpoints" / "last.ckpt"
        state = torch.load(ckpt, weights_only=True, map_location="cpu")["state_dict"]
        assert state["bank.active"].sum() == 4
        warm = Quantizer(grid_resolution=(32, 32, 16), num_prototypes=4, crop_size=8, init_bank_ckpt=str(ckpt))
        assert torch.equal(warm.bank.prototypes, state["bank.prototypes"])
        with pytest.raises(ValueError, match="bank"):
            Quantizer(grid_resolution=(32, 32, 16), num_prototypes=5, crop_size=8, init_bank_ckpt=str(ckpt))


    def test_occupancy_floor_travels_with_the_bank(self, tmp_path: Path, tiny_dataset: Path) -> None:
        from threedq.stages.quantizer import Quantizer, bank_occupancy_floor

        banks = _banks_fitted_with(tmp_path, tiny_dataset, "occupancy_floor", {None: "null", 0.2: "0.2"})
        for floor, (ckpt, _) in banks.items():
            assert bank_occupancy_floor(str(ckpt)) == floor
        assert not torch.allclose(banks[None][1], banks[0.2][1])  # the weighted crops make other prototypes
        # a round's warm start must weight as the bank it starts from
        with pytest.raises(ValueError, match="occupancy_floor"):
            Quantizer(grid_resolution=(32, 32, 16), num_prototypes=4, crop_size=8, init_bank_ckpt=str(banks[None][0]),
                      occupancy_floor=0.2)
        Quantizer(grid_resolution=(32, 32, 16), num_prototypes=4, crop_size=8, init_bank_ckpt=str(banks[0.2][0]),
                  occupancy_floor=0.2)
        for bad in (-0.1, 1.0):
            assert "occupancy_floor" in refused(occupancy_floor=bad)
        # a checkpoint brings its bank's weighting into a stage built with another (one without the field holds a
        # plain bank)
        ck = torch.load(banks[None][0], weights_only=True, map_location="cpu")
        q = Quantizer(grid_resolution=(32, 32, 16), num_prototypes=4, crop_size=8)
        assert q.hparams.occupancy_floor == 0.2
        q.on_load_checkpoint(ck)
        assert q.hparams.occupancy_floor is None
        q.on_load_checkpoint({"hyper_parameters": {k: v for k, v in ck["hyper_parameters"].items() if k != "occupancy_floor"}})
        assert q.hparams.occupancy_floor is None
        q.on_load_checkpoint(torch.load(banks[0.2][0], weights_only=True, map_location="cpu"))
        assert q.hparams.occupancy_floor == 0.2


class TestSpectrumReuse:
    """The EM computes each chunk's polar spectrum once: one test body against the recomputing reference path."""

    def _crops(self) -> torch.Tensor:
        shapes = base_shapes(6, channels=4)
        crops, _, _ = rotated_copies(shapes, per=12)
        return torch.nn.functional.normalize(crops + 0.05 * torch.randn(crops.shape, generator=torch.Generator().manual_seed(3)), dim=1)

    @pytest.mark.parametrize("chunk", [7, 256])
    @pytest.mark.parametrize("reuse", ["reuse_spectra", "reuse_aligned"])  # spectra; rotated objects between M-steps
    def test_em_equals_the_recomputing_path(self, chunk: int, reuse: str) -> None:
        from threedq.quantization.prototypes import run_prototype_em

        crops = self._crops()
        banks = []
        for on in (False, True):
            bank = PrototypeBank(10, crops.shape[1], crops.shape[-1], 36, 0.8)
            banks.append(run_prototype_em(bank, crops, iterations=4, seed=0, chunk=chunk, **{reuse: on}))
        assert torch.equal(banks[0].active, banks[1].active)
        assert torch.equal(banks[0].prototypes, banks[1].prototypes)

    def test_accumulate_rotates_only_the_objects_whose_yaw_moved(self, monkeypatch) -> None:
        from threedq.quantization import prototypes as P
        from threedq.quantization.rotation_search import RotationSearchResult

        crops = self._crops()[:20]
        bank = PrototypeBank(3, crops.shape[1], crops.shape[-1], 36, 0.8)
        g = torch.Generator().manual_seed(4)
        first = RotationSearchResult(prototype=torch.randint(0, 3, (20,), generator=g),
                                     angle=torch.randint(0, 36, (20,), generator=g), score=torch.zeros(20),
                                     scores=torch.zeros(20, 3, 36))  # fmt: skip
        kept = bank.accumulate(crops, first)
        bank.update()
        second = RotationSearchResult(prototype=first.prototype.roll(1), angle=first.angle.clone(),
                                      score=first.score, scores=first.scores)  # fmt: skip
        second.angle[[2, 5, 11]] = (second.angle[[2, 5, 11]] + 7) % 36
        rotated: list[int] = []
        real = P.rotate_yaw
        monkeypatch.setattr(P, "rotate_yaw", lambda v, a: rotated.append(v.shape[0]) or real(v, a))
        angle, aligned = bank.accumulate(crops, second, kept)
        assert rotated == [3] and torch.equal(angle, second.angle)
        ref = PrototypeBank(3, crops.shape[1], crops.shape[-1], 36, 0.8)
        ref.accumulate(crops, second)  # every object rotated afresh
        assert torch.equal(aligned, real(crops, P.yaw_angles(36)[second.angle]))
        assert torch.equal(bank.member_sum, ref.member_sum) and torch.equal(bank.member_count, ref.member_count)

    def test_add_and_chunked_assign(self) -> None:
        from threedq.quantization.prototypes import assign_chunked

        crops = self._crops()
        a, b = (PrototypeBank(10, crops.shape[1], crops.shape[-1], 36, 0.8) for _ in range(2))
        assert torch.equal(a.add(crops, reuse_spectrum=False), b.add(crops, reuse_spectrum=True))
        assert torch.equal(a.prototypes, b.prototypes)
        whole = a.assign(crops)
        spectra: dict = {}
        parts = assign_chunked(a, crops, chunk=5, spectra=spectra)
        assert len(spectra) == math.ceil(crops.shape[0] / 5)
        assert torch.equal(parts.prototype, whole.prototype) and torch.equal(parts.angle, whole.angle)
        assert torch.allclose(parts.score, whole.score, atol=1e-6)

    def test_spectrum_slices_and_errors(self) -> None:
        from threedq.quantization.rotation_search import best_prototype_and_yaw, polar_spectrum

        crops = self._crops()
        spec = polar_spectrum(crops, 36)
        part = polar_spectrum(crops[3:9], 36)
        assert torch.equal(spec.take(3, 9).coef, part.coef) and torch.equal(spec.take(3, 9).norm, part.norm)
        with pytest.raises(ValueError, match="objects_spectrum"):
            best_prototype_and_yaw(crops[:4], crops[:2], 36, objects_spectrum=spec.take(0, 3))
        with pytest.raises(ValueError, match="another plan"):
            best_prototype_and_yaw(crops[:4], crops[:2], 36, objects_spectrum=polar_spectrum(crops[:4], 12))
