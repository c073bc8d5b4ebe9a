"""The prototype bank: K pose-canonical 3D prototypes and the EM steps that learn them (paper Sec. 3.2).

E-step: every object crop is assigned its best (prototype, yaw) by
:func:`threedq.quantization.rotation_search.best_prototype_and_yaw`. M-step: every prototype becomes the mean of
its members rotated into its canonical pose, the closed-form minimiser of the paper's quantization loss
``sum_o ||e_k(o) - Rotate(M_o, R_o)||^2``. The bank starts empty and is filled incrementally: an exemplar becomes a
prototype only if its rotation-max cosine to every existing prototype is below ``init_threshold``. All state is in
registered buffers (``prototypes``, ``active``, ``member_sum``, ``member_count``).

Convention: crops ``[N, C, S, S, S]`` in frame R order ``(C, Z, Y, X)``, z up; a yaw index ``a`` means
``2 pi a / num_angles`` counter-clockwise seen from above; "object o has yaw a" means rotating the object
by ``a`` aligns it with its prototype's canonical pose.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from threedq.geometry import occupancy_weighted, rotate_yaw, yaw_angles

from .rotation_search import PolarSpectrum, RotationSearchResult, best_prototype_and_yaw, polar_spectrum

__all__ = ["PrototypeBank", "assign_chunked", "fill_free_slots", "fit_prototype_bank", "prototype_crops",
           "quantization_loss", "run_prototype_em"]

#: A cache of the polar spectra of ``crops[start : start + chunk]``, by ``start``.
_Spectra = dict[int, PolarSpectrum | None]


class PrototypeBank(nn.Module):
    """K prototypes of shape ``[C, D, S, S]`` (``D = S`` for 3D crops) with incremental initialisation and
    closed-form EM updates.

    Args:
        num_prototypes: K, the number of slots.
        channels: C, feature channels of the crops.
        size: S, crops are ``S^3``.
        num_angles: yaw steps of the rotation search (36 = 10 deg); 1 = no rotation search (no-rot-3DQ).
        init_threshold: an exemplar opens a new prototype only if its best cosine to every prototype is below this.
        method: rotation search implementation, ``"fast"`` or ``"exact"``.
        depth: D, the crops' extent along the rotation axis (default ``size``); ``depth=1`` holds 2D prototypes
            ``[C, 1, S, S]`` whose yaw search is an in-plane rotation search (2.5DQ-Nets: an image crop's angle
            index ``a`` turns it by ``2 pi a / A`` clockwise as displayed, row y down).
    """

    def __init__(self, num_prototypes: int = 50, channels: int = 32, size: int = 16, num_angles: int = 36,
                 init_threshold: float = 0.8, method: str = "fast", depth: int | None = None) -> None:
        super().__init__()
        depth = size if depth is None else depth
        if num_prototypes < 1 or channels < 1 or size < 1 or num_angles < 1 or depth < 1:
            got = f"{num_prototypes}, {channels}, {size}, {num_angles}"
            raise ValueError(f"num_prototypes, channels, size, num_angles must be >= 1, got {got}")
        if method not in ("fast", "exact"):
            raise ValueError(f"method: expected 'fast' or 'exact', got {method!r}")
        self.num_angles, self.init_threshold, self.method = num_angles, init_threshold, method
        shape = (num_prototypes, channels, depth, size, size)
        self.register_buffer("prototypes", torch.zeros(shape))
        self.register_buffer("active", torch.zeros(num_prototypes, dtype=torch.bool))
        self.register_buffer("member_sum", torch.zeros(shape))
        self.register_buffer("member_count", torch.zeros(num_prototypes))

    @property
    def num_active(self) -> int:
        return int(self.active.sum())

    def _as_bank(self, objects: Tensor) -> Tensor:
        """``objects`` checked for shape and cast to the bank's dtype (bf16 autocast crops are searched in float32)."""
        if objects.ndim != 5 or tuple(objects.shape[1:]) != tuple(self.prototypes.shape[1:]):
            shape = ", ".join(map(str, self.prototypes.shape[1:]))
            raise ValueError(f"objects: expected shape [N, {shape}], got {tuple(objects.shape)}")
        return objects.to(self.prototypes.dtype)

    def _search(self, objects: Tensor, prototypes: Tensor, spectrum: PolarSpectrum | None) -> RotationSearchResult:
        return best_prototype_and_yaw(objects, prototypes, num_angles=self.num_angles, method=self.method,
                                      objects_spectrum=spectrum)

    @torch.no_grad()
    def spectrum(self, objects: Tensor) -> PolarSpectrum | None:
        """The polar spectrum :meth:`assign` would compute for ``objects`` (``"fast"`` search), to hand back to it
        while the objects stay the same and the prototypes change; None for the ``"exact"`` search."""
        objects = self._as_bank(objects)
        return polar_spectrum(objects, self.num_angles) if self.method == "fast" else None

    @torch.no_grad()
    def assign(self, objects: Tensor, spectrum: PolarSpectrum | None = None) -> RotationSearchResult:
        """E-step: best (prototype, yaw) of each object among the active prototypes.

        ``spectrum``: :meth:`spectrum` of ``objects``, computed earlier (the same result, without recomputing it).

        Returns:
            :class:`~threedq.quantization.rotation_search.RotationSearchResult` with prototype ids in bank numbering
            ``[N]``, yaw indices ``[N]``, cosine scores ``[N]`` and all scores ``[N, K_active, A]``.
        """
        objects = self._as_bank(objects)
        idx = self.active.nonzero().flatten()
        if idx.numel() == 0:
            raise RuntimeError("the prototype bank is empty: initialise it first (init_from / add)")
        res = self._search(objects, self.prototypes[idx], spectrum)
        return RotationSearchResult(prototype=idx[res.prototype], angle=res.angle, score=res.score, scores=res.scores)

    @torch.no_grad()
    def add(self, objects: Tensor, threshold: float | None = None, reuse_spectrum: bool = True) -> Tensor:
        """Incremental initialisation: in order, each object opens a new prototype (in canonical pose = its
        own) if the bank has a free slot and its best cosine to every active prototype is below ``threshold``.

        ``reuse_spectrum`` (``"fast"`` search): the objects' polar spectrum is computed once and sliced for every
        comparison (the same result); False recomputes it for each opened prototype.

        Returns:
            ``[N]`` bool, which objects became prototypes.
        """
        objects = self._as_bank(objects)
        thr = self.init_threshold if threshold is None else threshold
        opened = torch.zeros(objects.shape[0], dtype=torch.bool, device=objects.device)
        if self.num_active == self.active.numel():
            return opened
        spectrum = self.spectrum(objects) if reuse_spectrum and objects.shape[0] > 1 else None
        # score every candidate against the current bank once, then against the ones opened in this call
        best = torch.full((objects.shape[0],), -1.0, device=objects.device)
        if self.num_active:
            best = self.assign(objects, spectrum).score
        for i in range(objects.shape[0]):
            if self.num_active == self.active.numel():
                break
            if best[i] >= thr:
                continue
            slot = int((~self.active).nonzero()[0])
            self.prototypes[slot] = objects[i]
            self.active[slot] = True
            opened[i] = True
            rest = objects[i + 1 :]
            if rest.shape[0]:
                s = self._search(rest, objects[i : i + 1], None if spectrum is None else spectrum.take(i + 1))
                best[i + 1 :] = torch.maximum(best[i + 1 :], s.score)
        return opened

    @torch.no_grad()
    def accumulate(self, objects: Tensor, result: RotationSearchResult,
                   previous: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """Add each object, rotated into its prototype's canonical pose, to that prototype's running sum.

        Args:
            objects: ``[N, C, D, S, S]``; result: their E-step.
            previous: what this returned for the same objects at an earlier E-step: the objects whose yaw index is
                unchanged are not rotated again (bitwise the same sums); its ``aligned`` tensor is updated in place.

        Returns:
            ``(angle [N], aligned [N, C, D, S, S])``: the yaw indices and the rotated objects, for ``previous``.
        """
        objects = self._as_bank(objects)
        angles = yaw_angles(self.num_angles, device=objects.device, dtype=objects.dtype)
        if previous is not None and previous[0].shape == result.angle.shape and previous[1].shape == objects.shape:
            aligned = previous[1]
            moved = (result.angle != previous[0]).nonzero().flatten()
            if moved.numel():
                aligned[moved] = rotate_yaw(objects[moved], angles[result.angle[moved]])
        else:
            aligned = rotate_yaw(objects, angles[result.angle])
        ones = torch.ones_like(result.prototype, dtype=self.member_count.dtype)
        self.member_sum.index_add_(0, result.prototype, aligned.to(self.member_sum.dtype))
        self.member_count.index_add_(0, result.prototype, ones)
        return result.angle.clone(), aligned

    @torch.no_grad()
    def update(self) -> Tensor:
        """M-step: every prototype with members becomes the mean of its aligned members; the sums reset.

        Returns:
            ``[K]`` member counts of this update.
        """
        counts = self.member_count.clone()
        has = counts > 0
        self.prototypes[has] = self.member_sum[has] / counts[has].view(-1, 1, 1, 1, 1)
        self.member_sum.zero_()
        self.member_count.zero_()
        return counts

    @torch.no_grad()
    def canonical_rotation(self, objects: Tensor, result: RotationSearchResult) -> Tensor:
        """Objects rotated into their prototypes' canonical pose ``[N, C, S, S, S]`` (for pictures)."""
        angles = yaw_angles(self.num_angles, device=objects.device, dtype=objects.dtype)[result.angle]
        return rotate_yaw(objects, angles)


def prototype_crops(features: Tensor, raw: Tensor | None, occupancy_floor: float | None = None) -> Tensor:
    """The crops a prototype bank is fitted on and scores: the feature crops as they are (``occupancy_floor`` None,
    the paper's) or weighted by their input occupancy (:func:`threedq.geometry.occupancy_weighted` with this floor
    and a 3^3 dilation).

    Args:
        features: ``[N, C, s, s, s]`` feature crops.
        raw: ``[N, 4, s, s, s]`` crops of the unprojected input ``cat[occ, occ * rgb]`` (or ``[N, 1, s, s, s]``
            occupancy) of the same boxes; only read with a floor.
        occupancy_floor: the weight of empty space, or None.

    Returns:
        ``[N, C, s, s, s]``, ``features`` itself without a floor.

    Convention: the weight does not change with yaw, so weighted crops go through the rotation search as they are.
    """
    if occupancy_floor is None:
        return features
    if raw is None:
        raise ValueError("raw: the occupancy-weighted prototype crops need the input occupancy crops")
    return occupancy_weighted(features, raw[:, :1], floor=occupancy_floor)


def quantization_loss(bank: PrototypeBank, objects: Tensor, result: RotationSearchResult) -> Tensor:
    """The paper's quantization objective ``mean_o ||e_k(o) - Rotate(M_o, R_o)||^2`` at a given assignment."""
    sums = []
    for s in range(0, objects.shape[0], 256):  # per object exactly as over all at once, without the big temporaries
        sl = slice(s, s + 256)
        part = RotationSearchResult(result.prototype[sl], result.angle[sl], result.score[sl], None)
        aligned = bank.canonical_rotation(objects[sl], part)
        sums.append((bank.prototypes[part.prototype] - aligned).pow(2).flatten(1).sum(1))
    return torch.cat(sums).mean()


@torch.no_grad()
def fit_prototype_bank(crops: Tensor, num_prototypes: int = 50, iterations: int = 10, num_angles: int = 36,
                       init_threshold: float = 0.8, method: str = "fast", seed: int = 0,
                       chunk: int = 256) -> PrototypeBank:
    """A new bank fitted to ``crops`` ``[N, C, D, S, S]`` (3D crops, ``D = S``, or 2D ones, ``D = 1``) by
    :func:`run_prototype_em`."""
    if crops.ndim != 5 or crops.shape[3] != crops.shape[4]:
        raise ValueError(f"crops: expected [N, C, D, S, S], got {tuple(crops.shape)}")
    C, D, S = crops.shape[1], crops.shape[2], crops.shape[3]
    bank = PrototypeBank(num_prototypes, C, S, num_angles, init_threshold, method, depth=D).to(crops.device)
    return run_prototype_em(bank, crops, iterations, seed=seed, fill_free=True, chunk=chunk)


@torch.no_grad()
def run_prototype_em(bank: PrototypeBank, crops: Tensor, iterations: int = 10, seed: int = 0, fill_free: bool = True,
                     chunk: int = 256, reuse_spectra: bool = True, spectra: _Spectra | None = None,
                     reuse_aligned: bool = True, restarts: int = 1) -> PrototypeBank:
    """The prototype EM of the paper (Sec. 3.2) on ``crops`` ``[N, C, S, S, S]``, in place; returns ``bank``.

    An empty bank is first initialised incrementally, visiting the objects in a seeded random order; with
    ``fill_free`` the remaining free slots are then filled with the objects farthest from the bank. A bank that
    already holds prototypes skips the initialisation. Then ``iterations`` rounds of E-step (in chunks of ``chunk``)
    and M-step.

    Args:
        reuse_spectra: ``"fast"`` search: compute each chunk's polar spectrum once for every E-step (the same bank).
        spectra: the spectra cache to use (one the caller keeps, e.g. for :func:`assign_chunked` afterwards).
        reuse_aligned: rotate an object into its prototype's pose again only when its yaw changes (the same bank).
        restarts: an empty bank only: run the initialisation and EM with seeds ``seed, seed + 1, ...`` and keep the
            bank of lowest :func:`quantization_loss` (the first of equal ones).
    """
    crops = bank._as_bank(crops)
    N = crops.shape[0]
    if N == 0:
        raise ValueError("crops: no objects to fit prototypes to")
    if isinstance(restarts, bool) or not isinstance(restarts, int) or restarts < 1:
        raise ValueError(f"restarts: expected an int >= 1, got {restarts!r}")
    spectra = ({} if spectra is None else spectra) if reuse_spectra else None
    if bank.num_active == 0 and restarts > 1:
        empty = {k: v.clone() for k, v in bank.state_dict().items()}
        best: dict[str, Tensor] | None = None
        best_loss = float("inf")
        for i in range(restarts):
            bank.load_state_dict(empty)
            run_prototype_em(bank, crops, iterations, seed + i, fill_free, chunk, reuse_spectra, spectra, reuse_aligned)
            loss = float(quantization_loss(bank, crops, assign_chunked(bank, crops, chunk, spectra)))
            if best is None or loss < best_loss:
                best, best_loss = {k: v.clone() for k, v in bank.state_dict().items()}, loss
        bank.load_state_dict(best)
        return bank
    if bank.num_active == 0:
        g = torch.Generator().manual_seed(seed)
        order = torch.randperm(N, generator=g).to(crops.device)
        for start in range(0, N, chunk):
            bank.add(crops[order[start : start + chunk]], reuse_spectrum=reuse_spectra)
        if fill_free:
            fill_free_slots(bank, crops, chunk, spectra)
    aligned: dict[int, tuple[Tensor, Tensor]] = {}
    for _ in range(iterations):
        for start in range(0, N, chunk):
            part = crops[start : start + chunk]
            res = bank.assign(part, _chunk_spectrum(bank, crops, start, chunk, spectra))
            kept = bank.accumulate(part, res, aligned.get(start))
            if reuse_aligned:
                aligned[start] = kept
        bank.update()
    return bank


def _chunk_spectrum(bank: PrototypeBank, crops: Tensor, start: int, chunk: int,
                    spectra: _Spectra | None) -> PolarSpectrum | None:
    """The spectrum of ``crops[start : start + chunk]``, computed once per ``spectra`` cache (None: no cache)."""
    if spectra is None:
        return None
    if start not in spectra:
        spectra[start] = bank.spectrum(crops[start : start + chunk])
    return spectra[start]


@torch.no_grad()
def assign_chunked(bank: PrototypeBank, crops: Tensor, chunk: int = 256,
                   spectra: _Spectra | None = None) -> RotationSearchResult:
    """:meth:`PrototypeBank.assign` of ``crops`` in chunks of ``chunk`` (reusing a :func:`run_prototype_em` cache of
    spectra when given)."""
    crops = bank._as_bank(crops)
    starts = range(0, crops.shape[0], chunk)
    parts = [bank.assign(crops[s : s + chunk], _chunk_spectrum(bank, crops, s, chunk, spectra)) for s in starts]
    fields = ("prototype", "angle", "score", "scores")
    return RotationSearchResult(**{f: torch.cat([getattr(r, f) for r in parts]) for f in fields})


@torch.no_grad()
def fill_free_slots(bank: PrototypeBank, crops: Tensor, chunk: int = 256, spectra: _Spectra | None = None) -> int:
    """Open prototypes from the objects farthest from the bank (lowest best score) while slots are free.

    ``spectra``: a cache of the chunks' polar spectra (filled here, reused by the caller's E-steps); None
    recomputes them for every comparison.

    Returns:
        The number of prototypes opened.
    """
    crops = bank._as_bank(crops)
    free = bank.active.numel() - bank.num_active
    if free == 0 or crops.shape[0] == 0:
        return 0
    opened = 0
    if bank.num_active == 0:
        bank.add(crops[:1], threshold=float("inf"))
        free, opened = free - 1, 1

    def best_against(protos: Tensor) -> Tensor:
        out = []
        for s in range(0, crops.shape[0], chunk):
            spectrum = _chunk_spectrum(bank, crops, s, chunk, spectra)
            out.append(bank._search(crops[s : s + chunk], protos, spectrum).score)
        return torch.cat(out)

    scores = best_against(bank.prototypes[bank.active])
    while free > 0:
        far = int(scores.argmin())
        if scores[far] >= 1.0 - 1e-6:
            break  # every object already matches a prototype exactly
        bank.add(crops[far : far + 1], threshold=float("inf"))
        scores = torch.maximum(scores, best_against(crops[far : far + 1]))
        free, opened = free - 1, opened + 1
    return opened


def normalized(crops: Tensor) -> Tensor:
    """Crops scaled to unit norm over their whole tensor (what cosine scores compare)."""
    return F.normalize(crops.flatten(1), dim=1).view_as(crops)
