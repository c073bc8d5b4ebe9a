"""An in-memory cache of object crops computed by a fixed encoder, keyed by content.

A key is the hash of everything a crop depends on: the encoder's weights (:func:`module_fingerprint`; none for the raw
input crops), the input views' pixels, depth and cameras, the boxes and the crop size (:func:`sample_key`), so a
changed encoder, other views or other boxes are misses, never stale hits. Entries live on the CPU; the oldest are
dropped beyond ``max_bytes``. Stages consult it only with no gradient and the encoder in eval mode.
"""

from __future__ import annotations

import hashlib
import math
import weakref
from collections import OrderedDict
from collections.abc import Iterable

import numpy as np
import torch
from torch import Tensor

__all__ = ["CropCache", "module_fingerprint", "pack_bits", "pack_sparse", "sample_key", "unpack_bits", "unpack_sparse",
           "views_key"]


def _update(h: hashlib._Hash, t: Tensor) -> None:
    t = t.detach()
    h.update(f"{t.dtype}{tuple(t.shape)}".encode())
    if t.dtype == torch.bool:
        t = t.to(torch.uint8)
    h.update(t.contiguous().cpu().view(-1).view(torch.uint8).numpy().tobytes())


def module_fingerprint(module: torch.nn.Module) -> str:
    """Hex digest of a module's ``state_dict`` (names, dtypes, shapes and values of every tensor)."""
    h = hashlib.blake2b(digest_size=16)
    for name, t in module.state_dict().items():
        h.update(name.encode())
        _update(h, t)
    return h.hexdigest()


def views_key(rgb: Tensor, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> str:
    """Hex digest of one scene's input views (``rgb`` ``[S,3,H,W]``, ``depth`` ``[S,H,W]``, ``K``, ``R_T_cam``):
    what its feature grid depends on besides the encoder."""
    h = hashlib.blake2b(digest_size=16)
    h.update(b"views")
    for t in (rgb, depth, K, R_T_cam):
        _update(h, t)
    return h.hexdigest()


def pack_sparse(t: Tensor) -> tuple[Tensor, Tensor]:
    """A tensor (any dtype) as its entries that are not ``+0.0``, for :func:`unpack_sparse` (bitwise round trip).

    Returns:
        ``index`` ``[N]`` int32 (int64 beyond 2^31 elements) positions in ``t.reshape(-1)``, and ``values`` ``[N]``
        (dtype of ``t``) there: every entry but ``+0.0`` (``-0.0`` and NaN included).
    """
    flat = t.detach().reshape(-1)
    keep = flat != 0
    if flat.is_floating_point():
        keep |= torch.signbit(flat)
    index = keep.nonzero().squeeze(1)
    values = flat[index]
    return (index.to(torch.int32) if flat.numel() < 2**31 else index), values


def unpack_sparse(index: Tensor, values: Tensor, shape: tuple[int, ...]) -> Tensor:
    """The tensor of shape ``shape`` that :func:`pack_sparse` gave ``index`` and ``values`` for (bitwise; device and
    dtype of ``values``)."""
    out = values.new_zeros(shape)
    out.view(-1)[index.to(device=values.device, dtype=torch.long)] = values
    return out


def pack_bits(mask: Tensor) -> Tensor:
    """A bool tensor as ``uint8`` bytes of 8 entries each (``numpy.packbits``, big-endian bit order), on the CPU."""
    return torch.from_numpy(np.packbits(mask.detach().to("cpu", torch.bool).reshape(-1).numpy()))


def unpack_bits(bits: Tensor, shape: tuple[int, ...]) -> Tensor:
    """The bool tensor of shape ``shape`` that :func:`pack_bits` gave ``bits`` for (on the CPU)."""
    count = math.prod(shape)
    return torch.from_numpy(np.unpackbits(bits.numpy(), count=count).view(np.bool_)).reshape(shape)


def sample_key(batch: dict[str, Tensor], b: int, num_input_views: int, crop_size: int) -> str:
    """Hex digest of what sample ``b``'s object crops depend on besides the encoder: its first ``num_input_views``
    views, its boxes (``aabb``, ``box_mask``) and ``crop_size``."""
    h = hashlib.blake2b(digest_size=16)
    h.update(f"v{num_input_views}s{crop_size}".encode())
    for k in ("rgb", "depth", "K", "R_T_cam"):
        _update(h, batch[k][b, :num_input_views])
    for k in ("aabb", "box_mask"):
        _update(h, batch[k][b])
    return h.hexdigest()


class CropCache:
    """Content-keyed store of per-sample crop tensors (see the module docstring).

    Args:
        max_bytes: drop the oldest entries beyond this many bytes (default 8 GiB).

    Attributes:
        hits, misses: lookups answered / not answered since creation.
    """

    def __init__(self, max_bytes: int = 8 << 30) -> None:
        if max_bytes <= 0:
            raise ValueError(f"max_bytes: expected > 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self.nbytes = self.hits = self.misses = 0
        self._store: OrderedDict[tuple[str, ...], Tensor] = OrderedDict()
        self._fingerprints: weakref.WeakKeyDictionary[torch.nn.Module, tuple[tuple[int, ...], str]] = (
            weakref.WeakKeyDictionary()
        )

    def __len__(self) -> int:
        return len(self._store)

    #: :func:`sample_key` and :func:`views_key`, reachable from the cache object
    sample_key = staticmethod(sample_key)
    views_key = staticmethod(views_key)

    def fingerprint(self, module: torch.nn.Module) -> str:
        """:func:`module_fingerprint`, recomputed only when a tensor of ``module`` was replaced or written."""
        state = list(module.state_dict(keep_vars=True).values())
        sig = tuple(x for t in state for x in (t.data_ptr(), t._version))
        known = self._fingerprints.get(module)
        if known is None or known[0] != sig:
            known = (sig, module_fingerprint(module))
            self._fingerprints[module] = known
        return known[1]

    def get_many(self, keys: Iterable[tuple[str, ...]]) -> list[Tensor] | None:
        """The entries of all ``keys``, or None (counting misses) unless every one is present."""
        keys = list(keys)
        found = [self._store.get(k) for k in keys]
        if any(f is None for f in found):
            self.misses += len(keys)
            return None
        self.hits += len(keys)
        return found  # type: ignore[return-value]

    def put(self, key: tuple[str, ...], value: Tensor) -> None:
        """Store a CPU copy of ``value`` under ``key``, then drop the oldest entries over ``max_bytes``."""
        with torch.inference_mode(False):  # a plain tensor even when filled under Lightning's inference mode
            value = value.detach().to("cpu", copy=True)
        old = self._store.pop(key, None)
        if old is not None:
            self.nbytes -= old.numel() * old.element_size()
        self._store[key] = value
        self.nbytes += value.numel() * value.element_size()
        while self.nbytes > self.max_bytes and len(self._store) > 1:
            _, dropped = self._store.popitem(last=False)
            self.nbytes -= dropped.numel() * dropped.element_size()

    def drop(self, kind: str) -> int:
        """Remove every entry whose key starts with ``kind`` (e.g. ``"features"``); returns how many were removed."""
        gone = [k for k in self._store if k[0] == kind]
        for k in gone:
            v = self._store.pop(k)
            self.nbytes -= v.numel() * v.element_size()
        return len(gone)
