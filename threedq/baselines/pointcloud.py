"""The "point cloud registration" baseline of 3DQ-Nets (section 4.2): objects clustered by geometry alone.

Each object is the set of occupied voxels of its occupancy crop; registered point-set prototypes are found by the
rotation-aware EM of 3DQ-Nets over ``num_angles`` yaws (seeds: exemplars in a seeded order whose best similarity to
every prototype so far is below ``init_threshold``, then the farthest objects; M-step: voxels occupied in at least
half of a prototype's aligned members). Similarity of object ``X`` rotated by yaw ``a`` and prototype ``Y``::

    precision_t = |{x in R_a(X) : d(x, Y) <= t}| / |R_a(X)|,   recall_t = |{y in Y : d(y, R_a(X)) <= t}| / |Y|
    score       = mean over t in TOLERANCES of 2 precision_t recall_t / (precision_t + recall_t)  (0 when both 0)

Convention:
    Occupancy crops are ``[N, 1, S, S, S]`` volumes ``[N, C, Z, Y, X]`` in the reference frame R (z up); for raw
    ``cat[occ, occ * rgb]`` crops pass ``crops[:, :1]``. Yaw index ``a`` is the angle ``2 pi a / A`` counter-clockwise
    about +z seen from above; a returned angle ``a`` means "rotating the object by ``a`` aligns it with the prototype".
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.geometry.rotate import rotate_yaw, yaw_angles

__all__ = ["PointCloudPrototypes"]

#: The matching distances (voxels) the F-score is averaged over.
TOLERANCES: tuple[float, ...] = (0.0, 1.0)
#: A rotated voxel is occupied iff the bilinear interpolation of the 0/1 occupancy there is at least this.
ROTATED_OCCUPANCY_THRESHOLD = 0.5


def _check_crops(name: str, crops: Tensor, size: int | None = None) -> None:
    if not isinstance(crops, Tensor) or crops.ndim != 5 or crops.shape[1] != 1 or len(set(crops.shape[2:])) != 1:
        shape = tuple(crops.shape) if isinstance(crops, Tensor) else type(crops).__name__
        why = "for raw cat[occ, occ*rgb] crops pass crops[:, :1]"
        raise ValueError(f"{name} must be occupancy crops of shape [N, 1, S, S, S] ({why}), got {shape}")
    if not (crops.is_floating_point() or crops.dtype == torch.bool):
        raise ValueError(f"{name} must be a floating-point or bool tensor, got {crops.dtype}")
    if size is not None and crops.shape[-1] != size:
        raise ValueError(f"{name} must have crop size S={size} (that of the prototypes), got {crops.shape[-1]}")


def _check_int(name: str, value: object, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    return value


def _check_float(name: str, value: object, low: float, high: float, low_open: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (low < value if low_open else low <= value) and value <= high  # type: ignore[operator]
    if not ok:
        interval = f"{'(' if low_open else '['}{low}, {high}]"
        raise ValueError(f"{name} must be a finite number in {interval}, got {value!r}")
    return float(value)  # type: ignore[arg-type]


def _binarise(crops: Tensor, threshold: float) -> Tensor:
    """``[N, 1, S, S, S]`` 0/1 volumes (float32, or float64 for float64 input)."""
    occupied = crops if crops.dtype == torch.bool else crops >= threshold
    return occupied.to(crops.dtype if crops.dtype in (torch.float32, torch.float64) else torch.float32)


def _ball_kernel(tolerance: float) -> tuple[tuple[int, int, int], ...] | None:
    """Offsets ``(dz, dy, dx)`` of the lattice ball ``|d| <= tolerance`` (None: distance 0, the identity)."""
    radius = math.floor(tolerance + 1e-9)
    if radius == 0:
        return None
    span = range(-radius, radius + 1)
    return tuple((z, y, x) for z in span for y in span for x in span if z * z + y * y + x * x <= tolerance**2 + 1e-9)


def _dilate(binary: Tensor, kernel: tuple[tuple[int, int, int], ...] | None) -> Tensor:
    """Lattice dilation of ``[M, 1, S, S, S]`` 0/1 volumes by the ball offsets ``kernel`` (an OR of shifts)."""
    if kernel is None:
        return binary
    radius = max(max(abs(c) for c in d) for d in kernel)
    nz, ny, nx = binary.shape[-3:]
    padded = F.pad(binary.bool(), (radius,) * 6)
    out = torch.zeros_like(binary, dtype=torch.bool)
    for dz, dy, dx in kernel:
        z, y, x = radius + dz, radius + dy, radius + dx
        out |= padded[..., z : z + nz, y : y + ny, x : x + nx]
    return out.to(binary.dtype)


class _Similarity:
    """The ball kernels of :data:`TOLERANCES` (``None``: distance 0, no dilation)."""

    def __init__(self) -> None:
        self.kernels = [_ball_kernel(t) for t in TOLERANCES]
        # the object side is dilated only for the recall, and only for tolerances >= 1 voxel
        self.object_kernels = [k for k in self.kernels if k is not None]

    def object_sets(self, rot: Tensor) -> list[Tensor]:
        """Dilations ``[n, A, V]`` of rotated object sets ``[n, A, V]``, one per entry of ``object_kernels``."""
        s = round(rot.shape[-1] ** (1 / 3))
        flat = rot.reshape(-1, 1, s, s, s)
        return [_dilate(flat, k).reshape(rot.shape) for k in self.object_kernels]

    def prototype_sets(self, protos: Tensor) -> tuple[Tensor, list[Tensor]]:
        """Flattened 0/1 prototypes ``[K, V]`` and their dilation per tolerance (``[K, V]`` each)."""
        return protos.flatten(1), [_dilate(protos, k).flatten(1) for k in self.kernels]

    def scores(self, rot: Tensor, rot_dils: list[Tensor], protos: tuple[Tensor, list[Tensor]]) -> Tensor:
        """Similarities ``[n, K, A]`` of rotated objects ``[n, A, V]`` to prototypes (all 0/1)."""
        flat, flat_dils = protos
        n, n_angles, v = rot.shape
        x = rot.reshape(n * n_angles, v)
        nx = x.sum(1, keepdim=True).clamp_min(1.0)  # empty object: all counts are 0 -> score 0
        ny = flat.sum(1).clamp_min(1.0)
        exact: Tensor | None = None  # |R_a(X) & Y|, shared by every tolerance < 1
        dils = iter(rot_dils)
        total = x.new_zeros(n * n_angles, flat.shape[0])
        for kernel, flat_dil in zip(self.kernels, flat_dils):
            if kernel is None:
                exact = x @ flat.T if exact is None else exact
                inter_p = inter_r = exact
            else:
                inter_p = x @ flat_dil.T
                inter_r = next(dils).reshape(n * n_angles, v) @ flat.T
            precision, recall = inter_p / nx, inter_r / ny
            both = precision + recall
            total += torch.where(both > 0, 2.0 * precision * recall / both.clamp_min(1e-12), 0.0)
        total /= len(self.kernels)
        return total.reshape(n, n_angles, -1).transpose(1, 2)


class _RotatedBank:
    """The rotated (and, for the F-score, dilated) point sets of ``N`` objects at every yaw, cached or not."""

    def __init__(self, binary: Tensor, num_angles: int, sim: _Similarity, chunk: int, cache_bytes: int) -> None:
        self.binary, self.num_angles, self.sim, self.chunk = binary, num_angles, sim, chunk
        n, size = binary.shape[0], binary.shape[-1]
        need = n * num_angles * size**3 * (1 + len(sim.object_kernels))
        self._rot: Tensor | None = None
        self._dils: list[Tensor] = []
        if need <= cache_bytes and n > 0:
            computed = (self._compute(binary[start : start + chunk]) for start in range(0, n, chunk))
            parts = [(rot.bool(), [d.bool() for d in dils]) for rot, dils in computed]  # bool: 1 byte per voxel
            self._rot = torch.cat([rot for rot, _ in parts])
            self._dils = [torch.cat([dils[i] for _, dils in parts]) for i in range(len(sim.object_kernels))]

    def __len__(self) -> int:
        return self.binary.shape[0]

    def _compute(self, binary: Tensor) -> tuple[Tensor, list[Tensor]]:
        """``[n, 1, S, S, S]`` 0/1 volumes rotated by every yaw candidate (``[n, A, V]`` 0/1), and their dilations."""
        n, size = binary.shape[0], binary.shape[-1]
        angles = yaw_angles(self.num_angles, device=binary.device, dtype=binary.dtype).expand(n, self.num_angles)
        rotated = rotate_yaw(binary, angles)  # [n, A, 1, S, S, S]
        rot = (rotated >= ROTATED_OCCUPANCY_THRESHOLD).to(binary.dtype).reshape(n, self.num_angles, size**3)
        return rot, self.sim.object_sets(rot)

    def get(self, index: Tensor) -> tuple[Tensor, list[Tensor]]:
        """Rotated point sets ``[n, A, V]`` of objects ``index`` and their dilations (0/1, work dtype)."""
        if self._rot is None:
            return self._compute(self.binary[index])
        dtype = self.binary.dtype
        return self._rot[index].to(dtype), [d[index].to(dtype) for d in self._dils]

    def chunks(self) -> Iterator[tuple[Tensor, Tensor, list[Tensor]]]:
        """``(index [n], rot [n, A, V], dilations)`` over all objects in order."""
        for start in range(0, len(self), self.chunk):
            index = torch.arange(start, min(start + self.chunk, len(self)), device=self.binary.device)
            yield (index, *self.get(index))


class PointCloudPrototypes:
    """K registered point-set prototypes fitted by rotation-aware EM (the paper's point cloud baseline).

    Args:
        num_angles: yaw candidates ``A``. threshold: a crop voxel is occupied iff its value is ``>= threshold``.
        chunk: objects rotated at once. max_cache_bytes: :meth:`fit` caches the rotated (and dilated) point sets of
            all objects as bool tensors (``2 N A S^3`` bytes) when they fit in this, else recomputes them every pass.

    Attributes (after :meth:`fit`):
        prototypes_: ``[K, 1, S, S, S]`` 0/1 registered point sets; labels_, angles_, scores_: ``[N]`` best
            prototype, yaw index and score of each training object (rotating object ``i`` by ``angles_[i]`` aligns it
            with ``prototypes_[labels_[i]]``); init_indices_: ``[K]`` the seed objects; num_accepted_: how many the
            threshold rule accepted; n_iter_: M-steps run; converged_; mean_scores_: mean best score per E-step.
    """

    def __init__(self, num_angles: int = 36, threshold: float = 0.5, chunk: int = 64,
                 max_cache_bytes: int = 2**30) -> None:  # fmt: skip
        self.num_angles = _check_int("num_angles", num_angles, 1)
        self.threshold = _check_float("threshold", threshold, 0.0, 1.0, low_open=True)
        self.chunk = _check_int("chunk", chunk, 1)
        self.max_cache_bytes = _check_int("max_cache_bytes", max_cache_bytes, 0)
        self.prototypes_: Tensor | None = None
        self.labels_: Tensor | None = None
        self.angles_: Tensor | None = None
        self.scores_: Tensor | None = None
        self.init_indices_: Tensor | None = None
        self.num_accepted_, self.n_iter_, self.converged_ = 0, 0, False
        self.mean_scores_: list[float] = []

    def _max_over(self, bank: _RotatedBank, index: Tensor, protos: Tensor) -> Tensor:
        """Best similarity over prototypes and angles of objects ``index``: ``[n]``."""
        rot, dils = bank.get(index)
        return bank.sim.scores(rot, dils, bank.sim.prototype_sets(protos)).amax(dim=(1, 2))

    def _max_all(self, bank: _RotatedBank, protos: Tensor) -> Tensor:
        """Best similarity over prototypes and angles of every object: ``[N]``."""
        sets = bank.sim.prototype_sets(protos)
        return torch.cat([bank.sim.scores(rot, dils, sets).amax(dim=(1, 2)) for _, rot, dils in bank.chunks()])

    def _e_step(self, bank: _RotatedBank, protos: Tensor,
                accumulate: bool) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:  # fmt: skip
        """Best (prototype, angle, score) per object, and (``accumulate``) the M-step's votes ``[K, V]``."""
        sets = bank.sim.prototype_sets(protos)
        votes = sets[0].new_zeros(sets[0].shape) if accumulate else None
        best = []
        for _, rot, dils in bank.chunks():
            flat = bank.sim.scores(rot, dils, sets).flatten(1)  # [n, K * A]
            idx = flat.argmax(1)  # the first maximum: ties go to the lowest prototype, then angle
            k, a, s = idx // bank.num_angles, idx % bank.num_angles, flat.gather(1, idx[:, None])[:, 0]
            if votes is not None:
                votes.index_add_(0, k, rot[torch.arange(rot.shape[0], device=rot.device), a])
            best.append((k, a, s))
        labels, angles, scores = (torch.cat(column) for column in zip(*best))
        return labels, angles, scores, votes

    def _initialise(self, bank: _RotatedBank, binary: Tensor, num_prototypes: int, init_threshold: float,
                    seed: int) -> tuple[Tensor, int]:  # fmt: skip
        """Incremental exemplar initialisation, then farthest-object fill: ``(init indices [K], accepted)``."""
        n, device = binary.shape[0], binary.device
        order = torch.randperm(n, generator=torch.Generator().manual_seed(seed)).to(device)
        chosen: list[int] = []
        for start in range(0, n, self.chunk):
            if len(chosen) == num_prototypes:
                break
            index = order[start : start + self.chunk]
            if chosen:
                best = self._max_over(bank, index, binary[torch.tensor(chosen, device=device)])
            else:
                best = torch.full((index.shape[0],), -math.inf, dtype=binary.dtype, device=device)
            for j in range(index.shape[0]):
                if len(chosen) == num_prototypes:
                    break
                if best[j].item() < init_threshold:
                    i = int(index[j])
                    chosen.append(i)
                    if j + 1 < index.shape[0]:  # the later candidates of this chunk must beat it too
                        later = self._max_over(bank, index[j + 1 :], binary[i : i + 1])
                        best[j + 1 :] = torch.maximum(best[j + 1 :], later)
        accepted = len(chosen)
        if len(chosen) < num_prototypes:  # farthest-object fill
            nearest = self._max_all(bank, binary[torch.tensor(chosen, device=device)])
            nearest[torch.tensor(chosen, device=device)] = math.inf
            while len(chosen) < num_prototypes:
                i = int(nearest.argmin())
                chosen.append(i)
                nearest[i] = math.inf
                if len(chosen) < num_prototypes:
                    nearest = torch.maximum(nearest, self._max_all(bank, binary[i : i + 1]))
        return torch.tensor(chosen, dtype=torch.long, device=device), accepted

    def _m_step(self, bank: _RotatedBank, binary: Tensor, labels: Tensor, angles: Tensor, scores: Tensor,
                votes: Tensor) -> tuple[Tensor, bool]:  # fmt: skip
        """Majority vote ``[K, 1, S, S, S]`` of the aligned members (``votes [K, V]``); empty clusters reseeded with
        the farthest objects."""
        size, num_prototypes = binary.shape[-1], votes.shape[0]
        counts = torch.bincount(labels, minlength=num_prototypes).to(votes.dtype)  # [K]
        protos = ((2.0 * votes >= counts[:, None]) & (counts[:, None] > 0)).to(votes.dtype)  # [K, V]
        for k in torch.nonzero((counts > 0) & (protos.sum(1) == 0)).flatten().tolist():
            # no voxel has a majority: fall back to the best-fitting member's aligned point set
            members = torch.nonzero(labels == k).flatten()
            i = int(members[scores[members].argmax()])
            protos[k] = bank.get(torch.tensor([i], device=labels.device))[0][0, int(angles[i])]
        empty = torch.nonzero(counts == 0).flatten().tolist()
        if empty:
            farthest = torch.argsort(scores, stable=True)[: len(empty)]
            for k, i in zip(empty, farthest.tolist()):
                protos[k] = binary[i].flatten()
        return protos.reshape(num_prototypes, 1, size, size, size), bool(empty)

    def fit(self, occupancy_crops: Tensor, K: int = 50, iterations: int = 10, init_threshold: float = 0.8,
            seed: int = 0) -> PointCloudPrototypes:  # fmt: skip
        """Cluster ``occupancy_crops`` ``[N, 1, S, S, S]`` (``N >= K``) into ``K`` prototypes with rotation-aware EM.

        ``iterations``: maximum EM iterations (stops once the assignments no longer change; 0: the initial exemplars
        are the prototypes); ``init_threshold`` in ``[0, 1]`` and ``seed`` (the exemplar order): see the module
        docstring. Returns ``self``; prototypes live in the frame of their seed exemplar.
        """
        _check_crops("occupancy_crops", occupancy_crops)
        num_prototypes = _check_int("K", K, 1)
        if occupancy_crops.shape[0] < num_prototypes:
            raise ValueError(f"need at least K={num_prototypes} objects, got {occupancy_crops.shape[0]}")
        _check_int("iterations", iterations, 0)
        init_threshold = _check_float("init_threshold", init_threshold, 0.0, 1.0)
        _check_int("seed", seed, 0)

        binary = _binarise(occupancy_crops, self.threshold)
        bank = _RotatedBank(binary, self.num_angles, _Similarity(), self.chunk, self.max_cache_bytes)
        self.init_indices_, self.num_accepted_ = self._initialise(bank, binary, num_prototypes, init_threshold, seed)
        protos = binary[self.init_indices_]
        self.mean_scores_, self.n_iter_, self.converged_ = [], 0, False
        previous: tuple[Tensor, Tensor] | None = None
        reseeded = False
        for _ in range(iterations):
            labels, angles, scores, votes = self._e_step(bank, protos, accumulate=True)
            self.mean_scores_.append(float(scores.mean()))
            same = previous is not None and torch.equal(labels, previous[0]) and torch.equal(angles, previous[1])
            if same and not reseeded:
                self.converged_ = True
                break
            assert votes is not None
            protos, reseeded = self._m_step(bank, binary, labels, angles, scores, votes)
            self.n_iter_ += 1
            previous = (labels, angles)
        else:
            labels, angles, scores, _ = self._e_step(bank, protos, accumulate=False)
            self.mean_scores_.append(float(scores.mean()))
        self.prototypes_ = protos
        self.labels_, self.angles_, self.scores_ = labels, angles, scores
        return self

    def assign(self, occupancy_crops: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Best ``prototype`` ``[N]`` long, yaw index ``angle`` ``[N]`` long and similarity ``score`` ``[N]`` of each of
        ``occupancy_crops`` ``[N, 1, S, S, S]`` (the prototypes' ``S``); ties go to the lowest prototype, then angle."""
        if self.prototypes_ is None:
            raise RuntimeError("PointCloudPrototypes is not fitted: call fit() first")
        protos = self.prototypes_
        _check_crops("occupancy_crops", occupancy_crops, size=protos.shape[-1])
        binary = _binarise(occupancy_crops, self.threshold)
        if binary.shape[0] == 0:
            empty = torch.zeros(0, dtype=torch.long, device=binary.device)
            return empty, empty.clone(), binary.new_zeros(0)
        bank = _RotatedBank(binary, self.num_angles, _Similarity(), self.chunk, 0)
        labels, angles, scores, _ = self._e_step(bank, protos.to(device=binary.device, dtype=binary.dtype), False)
        return labels, angles, scores
