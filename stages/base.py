"""The shared 3D encoder and the base of every stage (its checkpoint contract: :mod:`threedq.stages.checkpoint`).

Every stage is a LightningModule that owns ``self.encoder`` (a :class:`~threedq.nets.UNet3D` over ``cat[occ, occ *
rgb]`` of the input grid, L2-normalised features at half resolution, or the input's with ``feature_stride=1``). View
prediction trains it; later stages load it from ``encoder_ckpt`` (any stage's Lightning checkpoint or a plain encoder
``state_dict``, ``weights_only=True``), with the grid fields it does not name, and may freeze it (``freeze_encoder``).
"""

from __future__ import annotations

import contextlib
import inspect
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor

from threedq.geometry import VoxelGridSpec, crop_boxes, occupancy_from_depth, unproject_rgb
from threedq.nets import UNet3D
from threedq.stages.crop_cache import CropCache, pack_bits, pack_sparse, unpack_bits, unpack_sparse
from threedq.stages.checkpoint import (  # noqa: F401 - re-exported beside the stage base
    DEFAULT_GRID, checkpoint_hparams, checkpoint_stage, checkpoint_state, encoder_grid_from_checkpoint,
    encoder_state_from_checkpoint, load_encoder_state, require_stage, resolve_grid)

__all__ = ["DEFAULT_GRID", "EncoderStage", "RetrievalEvaluation", "SplitEvaluation", "checkpoint_hparams",
           "checkpoint_stage", "checkpoint_state", "encoder_grid_from_checkpoint", "encoder_state_from_checkpoint",
           "load_encoder_state", "resolve_grid", "stage_arguments"]


def stage_arguments(cls: type) -> dict[str, Any]:
    """``{name: default}`` of every constructor argument of a stage (or DataModule) class and its parents, at the
    default of the most derived class that declares it."""
    out: dict[str, Any] = {}
    for c in cls.__mro__:
        if c.__module__.startswith("lightning"):
            break
        init = c.__dict__.get("__init__")
        if init is None:
            continue
        for name, p in inspect.signature(init).parameters.items():
            if p.default is not p.empty:
                out.setdefault(name, p.default)
    return out


def builtin_number(value: Any) -> Any:
    """``value`` as a plain ``int`` or ``float`` where it is a subclass instance (jsonargparse's ``PositiveInt``), else
    unchanged (``bool`` too)."""
    for base in (int, float):
        if isinstance(value, base) and type(value) not in (base, bool):
            return base(value)
    return value


class EncoderStage(L.LightningModule):
    """Base of every stage: the voxel grid, the shared encoder and multi-view encoding.

    Args:
        grid_min: ``(xmin, ymin, zmin)`` of the input grid in R, metres (None: the encoder checkpoint's).
        grid_max: ``(xmax, ymax, zmax)``, metres (None: the encoder checkpoint's).
        grid_resolution: ``(nx, ny, nz)`` voxels of the input grid, each divisible by 8 (None: the checkpoint's).
        feature_dim: channels of the feature grid (None: the encoder checkpoint's).
        encoder_channels: widths ``(c1, c2, c3)`` of the encoder's levels (None: the checkpoint's, else 64, 128, 256).
        feature_stride: input voxels per feature voxel along each axis, 1 or 2 (None: the checkpoint's, else 2).
        encoder_ckpt: checkpoint to load the encoder from (see the module docstring).
        freeze_encoder: keep the encoder fixed.
        channels_last: run the encoder in ``channels_last_3d`` memory format (numerically the same).

    Attributes:
        crop_cache: an optional :class:`~threedq.stages.crop_cache.CropCache` (:meth:`use_crop_cache`), read and
            filled by :meth:`object_crops` and :meth:`encode_views` while the encoder is frozen.

    Convention: frame R metres, z up; volumes ``[B, C, Z, Y, X]``.
    """

    def __init__(
        self, *, grid_min: tuple[float, float, float] | None = None, grid_max: tuple[float, float, float] | None = None,
        grid_resolution: tuple[int, int, int] | None = None, feature_dim: int | None = None,
        encoder_channels: tuple[int, int, int] | None = None, feature_stride: int | None = None,
        encoder_ckpt: str | None = None, freeze_encoder: bool = False, channels_last: bool = True,
    ) -> None:
        super().__init__()
        given = {"grid_min": grid_min, "grid_max": grid_max, "grid_resolution": grid_resolution,
                 "feature_dim": feature_dim, "encoder_channels": encoder_channels, "feature_stride": feature_stride}
        #: the resolved grid fields, written into every checkpoint's hyperparameters
        self.grid_fields = resolve_grid(given, encoder_ckpt)
        g = self.grid_fields
        self.grid = VoxelGridSpec(g["grid_min"], g["grid_max"], g["grid_resolution"])
        if g["feature_stride"] not in (1, 2):
            raise ValueError(f"feature_stride: expected 1 or 2, got {g['feature_stride']!r}")
        self.feature_grid = self.grid.half() if g["feature_stride"] == 2 else self.grid
        self.feature_dim = g["feature_dim"]
        self.encoder = UNet3D(in_channels=4, out_channels=self.feature_dim, channels=g["encoder_channels"],
                              output_stride=g["feature_stride"])
        self.freeze_encoder = freeze_encoder
        self.channels_last = channels_last
        if channels_last:
            self.encoder.to(memory_format=torch.channels_last_3d)
        if encoder_ckpt:
            load_encoder_state(self.encoder, encoder_ckpt)
        if freeze_encoder:
            # eval mode now: Lightning (>= 2.2) never calls train() at fit start
            self.encoder.requires_grad_(False).eval()
        self.crop_cache: CropCache | None = None  # handed over by the caller (use_crop_cache); not a hyperparameter

    def use_crop_cache(self, cache: CropCache | None) -> None:
        """Read and fill ``cache`` (shared between stages and rounds) wherever crops cannot depend on the batch."""
        if cache is not None and not isinstance(cache, CropCache):
            raise TypeError(f"crop_cache: expected a CropCache or None, got {type(cache).__name__}")
        self.crop_cache = cache

    def setup(self, stage: str) -> None:
        """Fix the run folder on every process (see :attr:`run_dir`)."""
        super().setup(stage)
        self._run_dir = Path(self.trainer.log_dir or self.trainer.default_root_dir)

    @property
    def run_dir(self) -> Path:
        """The folder this run writes its pictures and diagnostics to (the logger's folder), taken in :meth:`setup` on
        every process: under DDP ``trainer.log_dir`` is a broadcast, which rank-0-only code must not call."""
        cached = getattr(self, "_run_dir", None)
        if cached is not None:
            return cached
        if self.trainer is None:
            raise RuntimeError("run_dir: the stage is not attached to a Trainer")
        return Path(self.trainer.default_root_dir)

    def save_hyperparameters(self, *args: Any, **kwargs: Any) -> None:
        """Lightning's, with every constructor argument of the stage and its parents (:func:`stage_arguments`), and
        only those, and the resolved grid in place of None."""
        kwargs.setdefault("frame", inspect.currentframe().f_back)
        super().save_hyperparameters(*args, **kwargs)
        ignore = set(kwargs.get("ignore") or ())
        own = stage_arguments(type(self))
        for name, default in own.items():
            if name not in ignore and name not in self.hparams:
                self.hparams[name] = default
        # LightningCLI also records the values it links from the data for a stage that takes no such argument
        for name in [k for k in self.hparams if not k.startswith("_") and k not in own]:
            del self.hparams[name]
        self.hparams.update({k: list(v) if isinstance(v, tuple) else v for k, v in self.grid_fields.items()})
        # plain int and float, so that the hyperparameters load with torch.load(weights_only=True)
        self.hparams.update({k: builtin_number(v) for k, v in self.hparams.items()})

    def train(self, mode: bool = True) -> EncoderStage:
        super().train(mode)
        if self.freeze_encoder:
            self.encoder.eval()  # frozen BatchNorm statistics too
        return self

    def configure_optimizers(self) -> torch.optim.Optimizer:
        """Adam at the stage's ``lr`` over its trainable parameters."""
        return torch.optim.Adam([p for p in self.parameters() if p.requires_grad], lr=self.hparams.lr)

    def encoder_input(self, rgb: Tensor, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Unproject views (rgb ``[N, 3, H, W]`` in [0, 1], depth ``[N, H, W]``, K ``[N, 3, 3]``, R_T_cam ``[N, 4, 4]``)
        into the input grid: ``x`` ``[N, 4, Z, Y, X]`` = ``cat[occ, occ * rgb]`` and ``seen`` ``[N, 1, Z, Y, X]``, 1
        where the voxel centre projects into the image in front of the camera."""
        occ = occupancy_from_depth(depth, K, R_T_cam, self.grid)
        ones = torch.ones_like(rgb[:, :1])
        sampled = unproject_rgb(torch.cat([rgb, ones], dim=1), K, R_T_cam, self.grid)
        rgb_vol, seen = sampled[:, :3], (sampled[:, 3:] > 0.5).to(rgb.dtype)
        return torch.cat([occ, occ * rgb_vol], dim=1), seen

    def views_input(self, rgb: Tensor, depth: Tensor, K: Tensor, R_T_cam: Tensor,
                    views: list[str] | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`encoder_input` of ``S`` views of ``B`` scenes (rgb ``[B, S, 3, H, W]``, depth ``[B, S, H, W]``, K,
        R_T_cam; ``views``: their :func:`~threedq.stages.crop_cache.views_key` if known), read from :attr:`crop_cache`
        (``input`` kind) where unprojected before: ``x`` ``[B*S, 4, Z, Y, X]`` and ``seen``, scene-major."""
        B, S = rgb.shape[:2]
        flat = (rgb.flatten(0, 1), depth.flatten(0, 1), K.flatten(0, 1), R_T_cam.flatten(0, 1))
        cache = self.crop_cache if self.crops_cacheable() else None
        if cache is None:
            return self.encoder_input(*flat)
        if views is None:
            views = [cache.views_key(rgb[b], depth[b], K[b], R_T_cam[b]) for b in range(B)]
        prefix = self.crop_cache_prefix()
        keys = [("input", prefix, v, part) for v in views for part in ("index", "values", "seen")]
        found = cache.get_many(keys)
        shape = (S, 4, *self.grid.volume_shape)
        if found is not None:
            x = [unpack_sparse(found[3 * b], found[3 * b + 1], shape) for b in range(B)]
            seen = [unpack_bits(found[3 * b + 2], (S, 1, *shape[2:])) for b in range(B)]
            return torch.cat(x).to(self.device), torch.cat(seen).to(device=self.device, dtype=rgb.dtype)
        x, seen = self.encoder_input(*flat)
        for b in range(B):
            index, values = pack_sparse(x[b * S:(b + 1) * S])
            cache.put(keys[3 * b], index)
            cache.put(keys[3 * b + 1], values)
            cache.put(keys[3 * b + 2], pack_bits(seen[b * S:(b + 1) * S] > 0))
        return x, seen

    def _to_device(self, batch: dict[str, Any]) -> dict[str, Any]:
        """``batch`` with its tensors on the stage's device."""
        return {k: v.to(self.device) if isinstance(v, Tensor) else v for k, v in batch.items()}

    @staticmethod
    def input_views(batch: dict[str, Tensor]) -> int:
        """How many of a batch's views are inputs: ``batch["num_input_views"]`` (set by the DataModule), else 1."""
        return int(batch["num_input_views"].reshape(-1)[0]) if "num_input_views" in batch else 1

    def crops_cacheable(self) -> bool:
        """Whether crops may come from :attr:`crop_cache` (a cache, no gradient, encoder in eval mode)."""
        return self.crop_cache is not None and not torch.is_grad_enabled() and not self.encoder.training

    def precision_context(self) -> Any:
        """The autocast context of the stage's trainer (``trainer.precision``) for work outside the trainer's loops; a
        no-op without a trainer."""
        trainer = getattr(self, "_trainer", None)
        return contextlib.nullcontext() if trainer is None else trainer.precision_plugin.forward_context()

    def crop_cache_prefix(self) -> str:
        """What besides weights and inputs decides a crop: grid, memory format, device type and autocast state."""
        dev = self.device.type
        amp = str(torch.get_autocast_dtype(dev)) if torch.is_autocast_enabled(dev) else "fp32"
        return f"{self.grid}|{self.channels_last}|{dev}|{amp}"

    def encode_views(self, rgb: Tensor, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> Tensor:
        """Encode each of S views of B scenes (rgb ``[B, S, 3, H, W]``, depth ``[B, S, H, W]``, K ``[B, S, 3, 3]``,
        R_T_cam ``[B, S, 4, 4]``) and aggregate them in R (mean over the views that see a voxel): ``[B, C, Z/2, Y/2,
        X/2]`` features, L2-normalised per voxel (from :attr:`crop_cache`, ``"grid"`` kind, where encoded before)."""
        return self._encode_views(rgb, depth, K, R_T_cam)[0]

    def _encode_views(self, rgb: Tensor, depth: Tensor, K: Tensor, R_T_cam: Tensor,
                      need_input: bool = False) -> tuple[Tensor, Tensor | None]:
        """:meth:`encode_views`, and the unprojected input ``[B*S, 4, Z, Y, X]`` when it was computed or
        ``need_input`` (else None)."""
        B, S = rgb.shape[:2]
        cache = self.crop_cache if self.crops_cacheable() else None
        views = [cache.views_key(rgb[b], depth[b], K[b], R_T_cam[b]) for b in range(B)] if cache is not None else None
        if cache is not None:
            head = ("grid", self.crop_cache_prefix(), cache.fingerprint(self.encoder))
            keys = [(*head, v) for v in views]
            found = cache.get_many(keys)
            if found is not None:
                x = self.views_input(rgb, depth, K, R_T_cam, views)[0] if need_input else None
                return torch.stack(found).to(self.device), x
        x, seen = self.views_input(rgb, depth, K, R_T_cam, views)
        feats = self.encode_input(x, seen, S)
        if cache is not None:
            for b in range(B):
                cache.put(keys[b], feats[b])
        return feats, x

    def encode_input(self, x: Tensor, seen: Tensor, num_views: int, encoder: torch.nn.Module | None = None) -> Tensor:
        """Encode unprojected views ``x`` ``[B*S, 4, Z, Y, X]`` and ``seen`` ``[B*S, 1, Z, Y, X]`` (scene-major) with
        ``encoder`` (default :attr:`encoder`) and aggregate each scene's ``num_views`` (S) of them as
        :meth:`encode_views` does: ``[B, C, Z/2, Y/2, X/2]``."""
        S = num_views
        B = x.shape[0] // S
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
        feats = (encoder or self.encoder)(x).contiguous()  # [B*S, C, z, y, x]
        if S == 1:
            return feats
        w = torch.nn.functional.max_pool3d(seen, 2)  # seen at feature resolution
        feats = feats.view(B, S, *feats.shape[1:])
        w = w.view(B, S, *w.shape[1:])
        agg = (feats * w).sum(1) / w.sum(1).clamp_min(1.0)
        none = w.sum(1) == 0
        agg = torch.where(none, feats.mean(1), agg)  # voxels no view sees: plain mean
        return torch.nn.functional.normalize(agg, dim=1, eps=1e-6)

    def object_crops(self, batch: dict[str, Tensor], num_input_views: int = 1, size: int = 16) -> dict[str, Tensor]:
        """Encode the first ``num_input_views`` views of each scene and crop every (valid) object box (read from
        :attr:`crop_cache` where the same encoder weights cropped the sample before).

        Args:
            batch: a SceneDataset batch (``rgb`` [B,S,3,H,W], ``depth``, ``K``, ``R_T_cam``, ``aabb`` [B,M,6],
                ``box_mask`` [B,M], ``categories``, ``boxes``, ``scene_index``).
            num_input_views: views aggregated per scene.
            size: crops are ``size^3``.

        Returns:
            ``features`` ``[N, C, s, s, s]`` crops of the feature grid, ``raw`` ``[N, 4, s, s, s]`` crops of the
            unprojected input ``cat[occ, occ * rgb]`` (union over the views), ``labels`` ``[N]``, ``boxes``
            ``[N, 7]`` (oriented GT), ``aabb`` ``[N, 6]``, ``scene`` ``[N]`` (the scene's index in its split), ``slot``
            ``[N]`` (the box's row in the scene) — N = valid boxes of the batch.

        Convention: boxes axis-aligned in R, each resized to a cube.
        """
        v = num_input_views
        rgb, depth, K, pose = (batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam"))
        B = rgb.shape[0]
        mask = batch["box_mask"]
        out = {"labels": batch["categories"][mask], "boxes": batch["boxes"][mask], "aabb": batch["aabb"][mask],
               "scene": batch["scene_index"][:, None].expand_as(mask)[mask],
               "slot": torch.arange(mask.shape[1], device=mask.device).expand_as(mask)[mask]}
        cache = self.crop_cache if self.crops_cacheable() else None
        if cache is not None:
            prefix = self.crop_cache_prefix()
            keys = [cache.sample_key(batch, b, v, size) for b in range(B)]
            f_keys = [("features", prefix, cache.fingerprint(self.encoder), k) for k in keys]
            r_keys = [("raw", prefix, k) for k in keys]
            feats, raw = cache.get_many(f_keys), cache.get_many(r_keys)
            if feats is not None and raw is not None:
                return {"features": torch.cat(feats).to(self.device), "raw": torch.cat(raw).to(self.device), **out}
        grid, x = self._encode_views(rgb, depth, K, pose, need_input=True)
        feats = crop_boxes(grid, batch["aabb"], self.feature_grid, size, mask=mask)  # [N, ...], the valid boxes only
        raw = crop_boxes(x.view(B, v, *x.shape[1:]).amax(1), batch["aabb"], self.grid, size, mask=mask)
        if cache is not None:
            counts = mask.sum(1).tolist()
            for b, (f, r) in enumerate(zip(feats.split(counts), raw.split(counts), strict=True)):
                cache.put(f_keys[b], f)
                cache.put(r_keys[b], r)
        return {"features": feats, "raw": raw, **out}


class SplitEvaluation:
    """Mixin: Lightning's validation and test hooks call ``_eval_step(batch, split, batch_idx)`` and
    ``_eval_epoch_end(split)`` with ``split`` ``"val"`` or ``"test"``."""

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._eval_step(batch, "val", batch_idx)

    def on_validation_epoch_end(self) -> None:
        self._eval_epoch_end("val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._eval_step(batch, "test", batch_idx)

    def on_test_epoch_end(self) -> None:
        self._eval_epoch_end("test")

    def _eval_epoch_end(self, split: str) -> None:
        """Nothing by default."""


class RetrievalEvaluation(SplitEvaluation):
    """Mixin: validation and test log the strict precision@K (``retrieval_k``) of the GT-labelled boxes' crops
    (``crop_size^3``) in ``self.metrics[split]`` (:class:`~threedq.metrics.RetrievalPrecisionAtK`), once more than K
    crops were seen."""

    def _eval_step(self, batch: dict[str, Tensor], split: str, batch_idx: int = 0) -> None:
        crops = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
        keep = crops["labels"] >= 0
        if keep.any():
            self.metrics[split].update(crops["features"][keep], crops["labels"][keep])

    def _eval_epoch_end(self, split: str) -> None:
        m, k = self.metrics[split], self.hparams.retrieval_k
        n = sum(c.shape[0] for c in m.crops) if isinstance(m.crops, list) else m.crops.shape[0]
        if n > k:
            self.log(f"{split}/precision_at_{k}", m.compute(), prog_bar=True)
        m.reset()
