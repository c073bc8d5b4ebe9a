"""The checkpoint contract of every stage: one object per checkpoint file, loaded once, and the grid beside it.

:func:`load_checkpoint` reads a file once (``torch.load(weights_only=True)``, CPU) into a :class:`StageCheckpoint`
(its stage, hyperparameters, grid and weights by prefix) and keeps the last few in memory; a file it cannot read safely
is refused in one line naming it (:class:`~threedq.errors.InputError`). Every helper below reads through it. The grid
travels with the encoder: every stage checkpoint stores the :data:`DEFAULT_GRID` fields, and :func:`resolve_grid`
takes those a stage does not name from its ``encoder_ckpt`` (a different one is refused). :class:`AtomicCheckpointIO`
writes each checkpoint atomically; :class:`LastStepCheckpoint`'s ``last.ckpt`` holds the final step.
"""

from __future__ import annotations

import io
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO
from torch import Tensor

from threedq.atomic_io import atomic_write_bytes
from threedq.errors import InputError

__all__ = ["DEFAULT_GRID", "AtomicCheckpointIO", "StageCheckpoint", "checkpoint_hparams", "checkpoint_stage",
           "checkpoint_state", "encoder_grid_from_checkpoint", "encoder_state_from_checkpoint", "load_checkpoint",
           "load_encoder_state", "require_stage", "resolve_grid"]

#: The grid, encoder widths and output stride of a stage that is given none and whose encoder checkpoint carries none.
DEFAULT_GRID: dict[str, Any] = {
    "grid_min": (-1.28, -1.28, -0.32), "grid_max": (1.28, 1.28, 0.96), "grid_resolution": (64, 64, 32),
    "feature_dim": 32, "encoder_channels": (64, 128, 256), "feature_stride": 2,
}


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's ``torch.save`` checkpoint writer, each file written atomically in its own folder
    (:func:`threedq.atomic_io.atomic_write_bytes`); a failed write raises ``OSError`` and leaves the previous file."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__}.save_checkpoint takes no storage_options, got {storage_options!r}")
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        atomic_write_bytes(path, buf.getvalue())


class LastStepCheckpoint(ModelCheckpoint):
    """Lightning's ``ModelCheckpoint`` whose ``last.ckpt`` always holds the final training step (written again when
    training ends, unless Lightning would not save now)."""

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        if self.save_last and not self._should_skip_saving_checkpoint(trainer):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
            return
        super().on_train_end(trainer, pl_module)


def _torch_reason(e: Exception) -> str:
    """One line of why ``torch.load`` refused a file (torch's own messages run over many lines)."""
    text = str(e)
    if "WeightsUnpickler error:" in text:  # weights_only=True refused a Python object; the next line says which
        detail = next((ln.strip() for ln in text.split("WeightsUnpickler error:", 1)[1].splitlines() if ln.strip()), "")
        detail = detail.split(" was not an allowed global")[0]
        return f"torch.load(weights_only=True) refuses it: it holds Python objects, not only tensors ({detail})"
    first = next((ln.strip() for ln in text.splitlines() if ln.strip()), type(e).__name__)
    first = first.split(". This is an internal miniz error", 1)[0]
    return f"truncated or not a checkpoint ({type(e).__name__}: {first})"


#: The stage of a checkpoint without a saved class path, by the weights it holds (first match wins).
_STAGE_BY_WEIGHTS = (("self_labelling", ("bank.", "head.")), ("quantizer", ("bank.",)), ("detector", ("head.",)),
                     ("mining", ("moco.",)), ("viewpred", ("decoder.",)))


@dataclass(frozen=True)
class StageCheckpoint:
    """One checkpoint file as loaded (read-only, shared): its ``path`` and ``content``, what
    ``torch.load(weights_only=True)`` returned (a Lightning checkpoint dict, or a bare state dict)."""

    path: Path
    content: Any

    @property
    def is_lightning(self) -> bool:
        """A Lightning checkpoint (a dict with a ``state_dict``), not a bare state dict."""
        return isinstance(self.content, dict) and isinstance(self.content.get("state_dict"), dict)

    @property
    def hparams(self) -> dict[str, Any] | None:
        """The saved hyperparameters (a copy), or None for a file without them."""
        hp = self.content.get("hyper_parameters") if isinstance(self.content, dict) else None
        return dict(hp) if isinstance(hp, dict) else None

    @property
    def state(self) -> dict[str, Tensor]:
        """The Lightning ``state_dict`` (a copy of the mapping; the tensors are shared)."""
        if not self.is_lightning:
            raise InputError(f"{self.path}: field 'state_dict': not a Lightning checkpoint")
        return dict(self.content["state_dict"])

    def prefixed(self, prefix: str) -> dict[str, Tensor]:
        """The weights under ``prefix`` (e.g. ``"bank."``), with the prefix stripped; {} if none."""
        return {k[len(prefix):]: v for k, v in self.state.items() if k.startswith(prefix)}

    @property
    def grid(self) -> dict[str, Any]:
        """The grid fields (:data:`DEFAULT_GRID` keys) stored in the hyperparameters ({} if none)."""
        hp = self.hparams or {}
        return {k: hp[k] for k in DEFAULT_GRID if hp.get(k) is not None}

    @property
    def anchor(self) -> tuple[float, float, float] | None:
        """The anchor a detector checkpoint decodes with: its ``anchor`` buffer, else its ``anchor_size``
        hyperparameter, else None."""
        buf = self.content["state_dict"].get("anchor") if self.is_lightning else None
        if isinstance(buf, Tensor) and buf.numel() == 3:
            return tuple(round(float(a), 6) for a in buf.tolist())  # float32: to the micrometre
        hp = (self.hparams or {}).get("anchor_size")
        return None if hp is None else tuple(float(a) for a in hp)

    @property
    def stage(self) -> str | None:
        """Which stage wrote it (``viewpred``, ``detector``, ...): from the saved class path
        (``threedq.stages.<stage>.<Class>``), else by the weights it holds; None if neither tells."""
        cls = (self.hparams or {}).get("_class_path")
        if isinstance(cls, str) and cls.startswith("threedq.stages.") and cls.count(".") >= 3:
            return cls.split(".")[2]
        if not self.is_lightning:
            return None
        keys = self.content["state_dict"].keys()
        for stage, prefixes in _STAGE_BY_WEIGHTS:
            if all(any(k.startswith(p) for k in keys) for p in prefixes):
                return stage
        return None

    def encoder_state(self) -> dict[str, Tensor]:
        """The encoder's weights: the ``encoder.*`` of a Lightning checkpoint, or a bare encoder state dict."""
        obj = self.content
        state = obj["state_dict"] if self.is_lightning else obj
        if not isinstance(state, dict):
            raise InputError(f"{self.path}: field 'state_dict': expected a checkpoint or a state dict")
        enc = {k[len("encoder."):]: v for k, v in state.items() if k.startswith("encoder.")}
        if not enc and not self.is_lightning and state and all(isinstance(v, Tensor) for v in state.values()):
            enc = dict(state)  # a plain encoder state dict
        if not enc:
            raise InputError(f"{self.path}: field 'state_dict': no 'encoder.*' weights in this checkpoint")
        return enc


#: Checkpoints kept in memory by :func:`load_checkpoint` (the most recently read ones).
CACHE_SIZE = 4
_CACHE: OrderedDict[tuple[str, int, int, int], StageCheckpoint] = OrderedDict()


def load_checkpoint(path: str | Path) -> StageCheckpoint:
    """The checkpoint ``path``, read once (``torch.load(weights_only=True)``, CPU), then from memory while unchanged.

    Raises:
        FileNotFoundError: no such file.
        InputError: a file ``torch.load(weights_only=True)`` cannot read (truncated, or holding Python objects).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint: no such file: {path}")
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_ino, st.st_mtime_ns)
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit if hit.path == path else StageCheckpoint(path, hit.content)
    try:
        content = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt files
        raise InputError(f"{path}: field '<file>': cannot be loaded safely: {_torch_reason(e)}") from e
    ckpt = StageCheckpoint(path, content)
    _CACHE[key] = ckpt
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return ckpt


def checkpoint_state(path: str | Path) -> dict[str, Tensor]:
    """The ``state_dict`` of a Lightning checkpoint (:func:`load_checkpoint`)."""
    return load_checkpoint(path).state


def encoder_state_from_checkpoint(path: str | Path) -> dict[str, Tensor]:
    """The encoder's ``state_dict`` stored in ``path`` (a Lightning checkpoint or a plain state dict).

    Raises:
        FileNotFoundError: no such file.
        InputError: the file holds no encoder weights (message names the file).
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"encoder_ckpt: no such file: {path}")
    return load_checkpoint(path).encoder_state()


def checkpoint_hparams(path: str | Path, missing_ok: bool = False) -> dict[str, Any]:
    """The ``hyper_parameters`` of a stage checkpoint; ``{}`` for a file without them when ``missing_ok``.

    Raises:
        FileNotFoundError: no such file. InputError: not loadable safely, or no hyperparameters (names the file).
    """
    hp = load_checkpoint(path).hparams
    if hp is None:
        if missing_ok:
            return {}
        raise InputError(f"{path}: field 'hyper_parameters': missing (not a threedq stage checkpoint)")
    return hp


def encoder_grid_from_checkpoint(path: str | Path) -> dict[str, Any]:
    """The grid fields (:data:`DEFAULT_GRID` keys) stored in a stage checkpoint's hyperparameters ({} if none)."""
    return load_checkpoint(path).grid


def checkpoint_stage(path: str | Path) -> str | None:
    """Which stage wrote the checkpoint ``path`` (:attr:`StageCheckpoint.stage`); raises as :func:`load_checkpoint`."""
    return load_checkpoint(path).stage


def require_stage(path: str | Path, wanted: str, option: str, needs: str | None = None) -> None:
    """Refuse, in one line naming the file, a checkpoint that is missing or that another stage wrote.

    Args:
        path: the checkpoint; wanted: the stage it must come from (``quantizer``, ``viewpred``, ...); option: the
            command-line option that named it (for a missing file); needs: who needs it (default ``option``).
    """
    if not Path(path).is_file():
        raise InputError(f"{option} {path}: no such file")
    stage = checkpoint_stage(path)  # a truncated or unsafe file is refused here, in one line
    if stage != wanted:
        kind = f"a {stage}" if stage else "not a stage"
        raise InputError(f"{path}: this is {kind} checkpoint; {needs or option} needs a {wanted} checkpoint")


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return float(a) == float(b)


def resolve_grid(given: dict[str, Any], encoder_ckpt: str | Path | None) -> dict[str, Any]:
    """The grid of a stage: what it names, else what its encoder checkpoint carries, else :data:`DEFAULT_GRID`.

    Raises:
        InputError: the stage names a value that differs from its encoder checkpoint's.
    """
    if encoder_ckpt and not Path(encoder_ckpt).is_file():
        raise FileNotFoundError(f"encoder_ckpt: no such file: {encoder_ckpt}")
    stored = encoder_grid_from_checkpoint(encoder_ckpt) if encoder_ckpt else {}
    out: dict[str, Any] = {}
    for k, default in DEFAULT_GRID.items():
        mine, theirs = given.get(k), stored.get(k)
        if mine is not None and theirs is not None and not _same(mine, theirs):
            raise InputError(f"{encoder_ckpt}: field '{k}': the encoder was trained with {k}={_plain(theirs)}, this "
                             f"stage asks for {_plain(mine)} (drop {k} from the stage config to use the encoder's)")
        value = mine if mine is not None else theirs if theirs is not None else default
        out[k] = (int(value) if k in ("feature_dim", "feature_stride") else tuple(int(v) for v in value)
                  if k == "encoder_channels" else tuple(value))
    return out


def _plain(v: Any) -> Any:
    return list(v) if isinstance(v, (list, tuple)) else v


def load_encoder_state(encoder: torch.nn.Module, path: str | Path) -> None:
    """Load the encoder weights of ``path`` into ``encoder`` (strict: every key and shape must match)."""
    state = encoder_state_from_checkpoint(path)
    own = encoder.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        raise InputError(f"{path}: field 'state_dict': encoder weights do not fit this encoder "
                         f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
    for k, v in state.items():
        if own[k].shape != v.shape:
            raise InputError(f"{path}: field 'encoder.{k}': shape {tuple(v.shape)} does not fit {tuple(own[k].shape)} "
                             "(different feature_dim or channels?)")
    encoder.load_state_dict(state)


