"""Fast search over yaw rotations: cylindrical resampling + correlation along the angle (rFFT).

The ``"exact"`` kernel rotates every crop by every candidate yaw (``threedq.geometry.rotate_yaw``) and compares.
The ``"fast"`` kernel resamples each crop ONCE onto a polar grid per z-slice (rings ``r`` x angles ``a``), where a
yaw by one angle step is a circular shift along ``a``, and computes the inner products at all ``A`` shifts as one
correlation along ``a`` in the Fourier domain:

1. :func:`polar_interpolation_matrix`: the bilinear weights of the ``R x A`` polar samples from the ``Y x X`` slice
   pixels (cached per shape/device/dtype), scaled by ``sqrt(area)`` of each polar cell.
2. Composed with an orthonormal real DFT along the angle, one batched matmul maps Cartesian slices straight to polar
   Fourier coefficients (:func:`polar_spectrum`), laid out ``[N, K, C * Z]``. With ``bandlimit=True`` ring ``i``
   keeps only angular frequencies ``<= ceil(pi * r_i)`` (``r_i`` in voxels), what a ring of circumference
   ``2 pi r_i`` voxels carries.
3. Per frequency ``f``, GEMMs of the query and gallery blocks give ``Re(conj(Q_f) G_f)`` and ``Im(conj(Q_f) G_f)``,
   and an ``[A, K]`` inverse real DFT gives the inner products at all ``A`` yaw shifts.

Precision: fp32 (or fp64) inputs are computed in their dtype. ``compute_dtype=torch.bfloat16`` runs the resampling
and the per-frequency GEMMs in bf16; the frequency-0 term is computed from fp32 copies with an fp32 output, and the
inverse DFT, norms and scores are fp32.

Area weighting: sample ``(i, a)`` stands for the polar cell of area ``(2 pi / A) * (rho / R) * r_i`` voxels^2
(``rho`` the inscribed radius, ``r_i = (i + 0.5) rho / R``) and is multiplied by ``sqrt(area)``, so that a plain
inner product of two cylinders approximates the inner product of the two crops over the inscribed disc of each
slice. The ``"fast"`` cosine therefore ignores the corners of the crop outside the inscribed cylinder, whereas the
``"exact"`` cosine normalises over the full cube.

Convention:
    Crops are ``[N, C, Z, Y, X]`` in frame R, z up (the yaw axis). Yaw index ``a`` means ``2 pi a / A``
    radians counter-clockwise seen from above (``threedq.geometry.rotate_yaw``); a returned angle ``a`` for
    (object ``o``, prototype/gallery item ``k``) means: rotating ``o`` by ``a`` steps aligns it with ``k``.
    Polar sample ``(i, a)`` of a slice sits at ``x = (X - 1)/2 + r_i cos(2 pi a / A)``,
    ``y = (Y - 1)/2 + r_i sin(2 pi a / A)`` (voxel indices, cell-centred), so rotating a crop by ``s`` steps
    is ``torch.roll(cylinder, s, dims=-1)``.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.geometry.grid import _desc
from threedq.geometry.rotate import rotate_yaw, yaw_angles

__all__ = ["SEARCH_METHODS", "PolarSpectrum", "RotationSearchResult", "all_pairs_rotation_max",
           "best_prototype_and_yaw", "cylindrical_resample", "default_num_radii", "polar_interpolation_matrix",
           "polar_spectrum", "rotation_max_similarity", "yaw_confidence", "yaw_margin"]

#: The two kernels of every rotation search: ``"fast"`` (polar spectrum + FFT over the angle, cosine over the
#: inscribed cylinder) and ``"exact"`` (every crop rotated by every yaw, cosine over the full cube).
SEARCH_METHODS = ("fast", "exact")
_LOW_PRECISION = (torch.bfloat16, torch.float16)
#: Bytes of scratch a correlation chunk may use (sizes the automatic query chunk).
_CHUNK_BYTES = 1 << 26


def default_num_radii(ny: int, nx: int) -> int:
    """Rings of the polar grid when not given: one per voxel of inscribed radius, ``ceil(min(Y, X) / 2)``."""
    return max(1, math.ceil(min(ny, nx) / 2))


def _positive_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


def _check_grid(ny: int, nx: int, num_angles: int, num_radii: int | None) -> int:
    for name, v in (("ny", ny), ("nx", nx), ("num_angles", num_angles)):
        if not _positive_int(v):
            raise ValueError(f"{name} must be a positive int, got {v!r}")
    if num_radii is None:
        return default_num_radii(ny, nx)
    if not _positive_int(num_radii):
        raise ValueError(f"num_radii must be a positive int or None, got {num_radii!r}")
    return num_radii


def _ring_radii(ny: int, nx: int, num_radii: int) -> Tensor:
    """``[R]`` ring radii in voxels (float64): ``(i + 0.5) / R`` of the inscribed radius ``min(Y, X) / 2``."""
    rho = min(ny, nx) / 2.0
    return (torch.arange(num_radii, dtype=torch.float64) + 0.5) * (rho / num_radii)


def _polar_matrix_f64(ny: int, nx: int, num_angles: int, num_radii: int, area_weighted: bool) -> Tensor:
    """Dense float64 ``[R, A, Y * X]`` bilinear weights (zero padding), optionally times ``sqrt(cell area)``."""
    radii = _ring_radii(ny, nx, num_radii)  # [R]
    phi = torch.arange(num_angles, dtype=torch.float64) * (2.0 * math.pi / num_angles)  # [A]
    px = (nx - 1) / 2.0 + radii[:, None] * torch.cos(phi)[None]  # [R, A] voxel index coordinates
    py = (ny - 1) / 2.0 + radii[:, None] * torch.sin(phi)[None]
    x0, y0 = torch.floor(px), torch.floor(py)
    fx, fy = px - x0, py - y0
    weights = torch.zeros(num_radii * num_angles, ny * nx, dtype=torch.float64)
    rows = torch.arange(num_radii * num_angles)
    for dy, dx, w in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):
        xi, yi = (x0 + dx).long().flatten(), (y0 + dy).long().flatten()
        ok = (xi >= 0) & (xi < nx) & (yi >= 0) & (yi < ny)  # zero padding outside the slice
        weights.index_put_((rows[ok], (yi * nx + xi)[ok]), w.flatten()[ok], accumulate=True)
    weights = weights.view(num_radii, num_angles, ny * nx)
    if area_weighted:
        rho = min(ny, nx) / 2.0
        area = (2.0 * math.pi / num_angles) * (rho / num_radii) * radii  # [R] voxel^2 per polar cell
        weights = weights * area.sqrt()[:, None, None]
    return weights


@functools.lru_cache(maxsize=32)
def _polar_matrix_cached(ny: int, nx: int, num_angles: int, num_radii: int, area_weighted: bool, device: torch.device,
                         dtype: torch.dtype) -> Tensor:
    weights = _polar_matrix_f64(ny, nx, num_angles, num_radii, area_weighted)
    return weights.reshape(num_radii * num_angles, -1).to(device=device, dtype=dtype)


def polar_interpolation_matrix(ny: int, nx: int, num_angles: int = 36, num_radii: int | None = None, *,
                               area_weighted: bool = True, device: torch.device | str | None = None,
                               dtype: torch.dtype | None = None) -> Tensor:
    """Bilinear interpolation matrix from a ``Y x X`` slice to its ``R x A`` polar samples (cached).

    Row ``i * A + a`` holds the (at most 4) bilinear weights of polar sample ``(i, a)`` on the flattened slice
    pixels, zero padding as ``grid_sample`` with ``align_corners=False, padding_mode="zeros"``. With
    ``area_weighted`` the row is multiplied by ``sqrt(area_i)``, ``area_i = (2 pi / A) (rho / R) r_i`` voxels^2.

    Args:
        ny: slice height ``Y``.
        nx: slice width ``X``.
        num_angles: angles ``A`` per ring.
        num_radii: rings ``R`` (default ``ceil(min(Y, X) / 2)``, one per voxel of radius).
        area_weighted: scale rows by ``sqrt`` of the polar cell area.
        device: device of the result.
        dtype: floating dtype of the result (default: torch's default dtype).

    Returns:
        ``[R * A, Y * X]`` dense matrix (a cached tensor: do not modify it in place).

    Convention:
        Sample ``(i, a)`` at ``x = (X - 1)/2 + r_i cos(2 pi a / A)``, ``y = (Y - 1)/2 + r_i sin(2 pi a / A)``
        (voxel indices), ``r_i = (i + 0.5) / R * min(Y, X) / 2``; angles counter-clockwise seen from above.
    """
    num_radii = _check_grid(ny, nx, num_angles, num_radii)
    device, dtype = torch.device(device or "cpu"), dtype or torch.get_default_dtype()
    return _polar_matrix_cached(ny, nx, num_angles, num_radii, bool(area_weighted), device, dtype)


def _check_crops(x: Tensor, name: str, ndim: int = 5) -> None:
    if not isinstance(x, Tensor) or x.ndim != ndim:
        raise ValueError(f"{name} must have shape {'[N, C, Z, Y, X]' if ndim == 5 else '[C, Z, Y, X]'}, got {_desc(x)}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {x.dtype}")


def cylindrical_resample(crops: Tensor, num_angles: int = 36, num_radii: int | None = None, *,
                         area_weighted: bool = True) -> Tensor:
    """Resample every z-slice of every crop onto a polar grid, so that a yaw step is a roll along the angle.

    One matmul with :func:`polar_interpolation_matrix`; linear, hence differentiable.

    Args:
        crops: ``[N, C, Z, Y, X]`` crops.
        num_angles: angles ``A`` per ring.
        num_radii: rings ``R`` (default ``ceil(min(Y, X) / 2)``).
        area_weighted: multiply each sample by ``sqrt`` of its polar cell area (voxels^2) so that plain inner
            products of cylinders approximate inner products over the inscribed disc of each slice.

    Returns:
        ``[N, C, Z, R, A]`` cylinders in the dtype of ``crops``.

    Convention:
        ``rotate_yaw(crops, 2 pi s / A)`` resampled equals (up to interpolation) ``roll(cylinder, s, dims=-1)``;
        angle ``a`` is ``2 pi a / A`` counter-clockwise seen from above, ring ``i`` at ``(i + 0.5) / R`` of the
        inscribed radius ``min(Y, X) / 2``.
    """
    _check_crops(crops, "crops")
    n, c, nz, ny, nx = crops.shape
    num_radii = _check_grid(ny, nx, num_angles, num_radii)
    w = polar_interpolation_matrix(ny, nx, num_angles, num_radii, area_weighted=area_weighted, device=crops.device,
                                   dtype=crops.dtype)
    out = F.linear(crops.reshape(n * c * nz, ny * nx), w)  # [N*C*Z, R*A]
    return out.view(n, c, nz, num_radii, num_angles)


@dataclass(frozen=True)
class _Block:
    """One angular frequency ``f`` of ``rings``; complex blocks hold the real parts of all rings, then the
    imaginary parts (``f = 0`` and the Nyquist frequency are real)."""

    freq: int
    rings: tuple[int, ...]
    complex: bool

    @property
    def width(self) -> int:
        return len(self.rings) * (2 if self.complex else 1)


def _frequency_blocks(num_angles: int, caps: list[int]) -> tuple[_Block, ...]:
    """Blocks per frequency ``0 .. A // 2`` holding the rings whose cap is ``>= f``."""
    rings = [(f, tuple(i for i, cap in enumerate(caps) if cap >= f)) for f in range(num_angles // 2 + 1)]
    return tuple(_Block(f, r, f != 0 and 2 * f != num_angles) for f, r in rings if r)


def _ring_caps(ny: int, nx: int, num_angles: int, num_radii: int, bandlimit: bool) -> list[int]:
    top = num_angles // 2
    if not bandlimit:
        return [top] * num_radii
    return [min(top, math.ceil(math.pi * r)) for r in _ring_radii(ny, nx, num_radii).tolist()]


def _lag_basis_f64(blocks: tuple[_Block, ...], num_angles: int) -> Tensor:
    """``[A, K]``: inner product at shift ``s`` = ``sum_k L[s, k] P_k`` over the per-frequency GEMM outputs.

    ``P`` rows are, per block, ``Re(conj(Q_f) G_f)`` then (complex blocks) ``Im(conj(Q_f) G_f)`` of
    orthonormally scaled coefficients: the inverse real DFT ``c[s] = P_0 + sum_f (Re_f cos - Im_f sin)(2 pi f s
    / A) + P_nyq (-1)^s``.
    """
    s = torch.arange(num_angles, dtype=torch.float64)
    cols = []
    for b in blocks:
        theta = 2.0 * math.pi * b.freq * s / num_angles
        cols.append(torch.cos(theta))
        if b.complex:
            cols.append(-torch.sin(theta))
    return torch.stack(cols, dim=1)


def _fourier_matrix_f64(ny: int, nx: int, num_angles: int, num_radii: int, blocks: tuple[_Block, ...]) -> Tensor:
    """``[K_total, Y * X]``: area-weighted polar sampling composed with the orthonormal real DFT along angle.

    Rows per block ``f``: ``Re`` for each ring in the block, then (complex blocks) ``Im`` for each ring, of
    ``sqrt(w_f / A) sum_a exp(-2 pi i f a / A) W[i, a, :]`` with ``w_f = 2`` for complex, ``1`` for real
    frequencies (so that the coefficients are an orthonormal transform of each ring).
    """
    w = _polar_matrix_f64(ny, nx, num_angles, num_radii, area_weighted=True)  # [R, A, P]
    a = torch.arange(num_angles, dtype=torch.float64)
    rows = []
    for b in blocks:
        theta = 2.0 * math.pi * b.freq * a / num_angles
        scale = math.sqrt((2.0 if b.complex else 1.0) / num_angles)
        rows.append(torch.einsum("a,rap->rp", torch.cos(theta) * scale, w[list(b.rings)]))  # [R_f, P] real parts
        if b.complex:  # then all imaginary parts
            rows.append(torch.einsum("a,rap->rp", -torch.sin(theta) * scale, w[list(b.rings)]))
    return torch.cat(rows, dim=0)


@dataclass(frozen=True)
class _SpectrumPlan:
    blocks: tuple[_Block, ...]
    matrix: Tensor  # [K_total, Y * X]
    lag_basis: Tensor  # [A, K]
    num_angles: int

    @property
    def offsets(self) -> tuple[int, ...]:
        """First coefficient row of each block."""
        return tuple(itertools.accumulate([0] + [b.width for b in self.blocks[:-1]]))


@functools.lru_cache(maxsize=32)
def _spectrum_plan(ny: int, nx: int, num_angles: int, num_radii: int, bandlimit: bool, device: torch.device,
                   dtype: torch.dtype) -> _SpectrumPlan:
    blocks = _frequency_blocks(num_angles, _ring_caps(ny, nx, num_angles, num_radii, bandlimit))
    matrix = _fourier_matrix_f64(ny, nx, num_angles, num_radii, blocks).to(device=device, dtype=dtype)
    lag = _lag_basis_f64(blocks, num_angles).to(device=device, dtype=_acc_dtype(dtype))
    return _SpectrumPlan(blocks, matrix, lag, num_angles)


def _acc_dtype(dtype: torch.dtype) -> torch.dtype:
    """Accumulation/result dtype: float32 for low-precision inputs, else the dtype itself."""
    return torch.float32 if dtype in _LOW_PRECISION else dtype


@dataclass(frozen=True)
class PolarSpectrum:
    """Real-ified angular Fourier coefficients of ``N`` items (crops or cylinders), grouped by frequency.

    Attributes:
        coef: ``[N, K, D]`` coefficients in the compute dtype: per frequency block ``f`` (``plan.blocks``), the
            real parts of its ``R_f`` rings, then (complex frequencies) their imaginary parts; ``D = C * Z``
            for crops. Scaled so that the coefficients are an orthonormal transform of each (band-limited) ring.
        dc: ``[N, K_0, D]`` the frequency-0 rows again in the accumulation dtype (float32 for bf16 compute), so
            that the rotation-independent part of every score is not rounded to low precision.
        plan: frequency blocks, the cached sampling matrix and the ``[A, K]`` inverse-DFT lag basis.
        norm: ``[N]`` norms of the area-weighted (band-limited) cylinders before any normalisation.
    """

    coef: Tensor
    dc: Tensor
    plan: _SpectrumPlan
    norm: Tensor

    def __len__(self) -> int:
        return self.coef.shape[0]

    def take(self, start: int, stop: int | None = None) -> PolarSpectrum:
        """The spectrum of items ``start:stop`` (views, no copy): what ``polar_spectrum`` of those items gives."""
        return PolarSpectrum(self.coef[start:stop], self.dc[start:stop], self.plan, self.norm[start:stop])

    def block(self, index: int, start: int = 0, stop: int | None = None) -> Tensor:
        """``[n, width * D]`` view of block ``index`` for items ``start:stop`` (no copy)."""
        b = self.plan.blocks[index]
        if b.freq == 0:
            part = self.dc[start:stop]
        else:
            k0 = self.plan.offsets[index]
            part = self.coef[start:stop, k0 : k0 + b.width]
        return part.reshape(part.shape[0], -1)


def polar_spectrum(crops: Tensor, num_angles: int = 36, num_radii: int | None = None, *, bandlimit: bool = True,
                   compute_dtype: torch.dtype | None = None, chunk: int = 64) -> PolarSpectrum:
    """Area-weighted cylindrical resampling fused with an orthonormal real DFT along the angle (without gradient).

    Equals ``torch.fft.rfft(cylindrical_resample(crops), norm="ortho")`` (times ``sqrt(2)`` on the complex
    frequencies, real-ified), one batched matmul per chunk of crops; with ``bandlimit`` ring ``i`` keeps only
    frequencies ``f <= ceil(pi r_i)`` (``r_i`` in voxels).

    Args:
        crops: ``[N, C, Z, Y, X]`` crops.
        num_angles: angles ``A``.
        num_radii: rings ``R`` (default ``ceil(min(Y, X) / 2)``).
        bandlimit: drop angular frequencies a ring cannot carry (see module docstring).
        compute_dtype: dtype of the resampling matmul and of the stored coefficients (e.g. ``torch.bfloat16``;
            default: the crops' dtype). The DC rows are also kept in float32 (see ``PolarSpectrum.dc``).
        chunk: crops resampled per matmul (bounds scratch memory).

    Returns:
        A ``PolarSpectrum`` of ``N`` crops.

    Convention:
        As ``cylindrical_resample``: a yaw of ``s`` steps multiplies frequency ``f`` by ``exp(-2 pi i f s / A)``.
    """
    _check_crops(crops, "crops")
    n, c, nz, ny, nx = crops.shape
    num_radii = _check_grid(ny, nx, num_angles, num_radii)
    compute_dtype = compute_dtype or crops.dtype
    if not compute_dtype.is_floating_point or compute_dtype.is_complex:
        raise ValueError(f"compute_dtype must be a real floating dtype, got {compute_dtype}")
    acc = _acc_dtype(crops.dtype if crops.dtype.itemsize > compute_dtype.itemsize else compute_dtype)
    plan = _spectrum_plan(ny, nx, num_angles, num_radii, bool(bandlimit), crops.device, compute_dtype)
    cz, k_total, k_dc = c * nz, plan.matrix.shape[0], plan.blocks[0].width
    with torch.no_grad():
        coef = torch.empty(n, k_total, cz, device=crops.device, dtype=compute_dtype)
        dc = torch.empty(n, k_dc, cz, device=crops.device, dtype=acc)
        norm = torch.empty(n, device=crops.device, dtype=acc)
        for start in range(0, n, max(1, chunk)):
            x = crops[start : start + chunk]
            m = x.shape[0]
            out = coef[start : start + m]
            slices = x.reshape(m, cz, ny * nx).to(compute_dtype).transpose(1, 2)  # [m, Y*X, C*Z]
            torch.bmm(plan.matrix.expand(m, -1, -1), slices, out=out)  # [m, K, C*Z]
            # partial norms over the contiguous C*Z runs in the compute dtype, their squares summed in float32
            norm[start : start + m] = torch.linalg.vector_norm(out, dim=2).to(acc).square().sum(dim=1).sqrt()
            dc[start : start + m] = out[:, :k_dc]
    return PolarSpectrum(coef, dc, plan, norm)


def _inverse_norms(x: PolarSpectrum) -> Tensor:
    """``[N]`` ``1 / norm`` in the accumulation dtype (``1e-12`` floor, like ``F.normalize``)."""
    return 1.0 / x.norm.to(x.plan.lag_basis.dtype).clamp_min(1e-12)


def _auto_chunk(n: int, m: int, num_angles: int) -> int:
    return max(1, min(n, _CHUNK_BYTES // max(1, 8 * m * num_angles)))


def _halves(x: Tensor) -> tuple[Tensor, Tensor]:
    """``[n, 2W]`` complex block (real parts | imaginary parts) -> two ``[n, W]`` views."""
    v = x.view(x.shape[0], 2, -1)
    return v[:, 0], v[:, 1]


def _correlate(q: PolarSpectrum, g: PolarSpectrum, chunk: int) -> Iterator[tuple[int, Tensor]]:
    """Yield ``(start, c)`` with ``c`` ``[A, n, M]``: inner products at every yaw shift, per query chunk.

    Per frequency block ``conj(Q) G`` (``Q = Qr + i Qi``, ``G = Gr + i Gi``, contracted over the block):
    ``Re = [Qr Qi] . [Gr Gi]`` (one GEMM over the whole block), ``Im = Qr . Gi - Qi . Gr`` (two half-width
    GEMMs), all operands strided views of the coefficient tensors (no copies). The GEMMs write into buffers reused
    across chunks (``c`` is overwritten by the next chunk: consume it before resuming).
    """
    lag = q.plan.lag_basis
    num_out, n_total, m = lag.shape[1], len(q), len(g)
    acc = lag.dtype
    low = q.coef.dtype != acc
    gallery = [g.block(i) for i in range(len(q.plan.blocks))]
    halves = [_halves(gb) if b.complex else None for b, gb in zip(q.plan.blocks, gallery)]
    buf = buf32 = cbuf = None
    for start in range(0, n_total, chunk):
        n = min(chunk, n_total - start)
        if buf32 is None or buf32.shape[1] != n:
            buf32 = torch.empty(num_out, n, m, device=lag.device, dtype=acc)
            buf = torch.empty(num_out, n, m, device=lag.device, dtype=q.coef.dtype) if low else buf32
            cbuf = torch.empty(lag.shape[0], n, m, device=lag.device, dtype=acc)
        k = 0
        for i, (b, gb) in enumerate(zip(q.plan.blocks, gallery)):
            qb = q.block(i, start, start + n)  # [n, W] view
            target = buf32 if qb.dtype == acc else buf
            torch.mm(qb, gb.T, out=target[k])  # Re = [Qr Qi] . [Gr Gi] (the whole block)
            if b.complex:
                (qr, qi), (gr, gi) = _halves(qb), halves[i]
                torch.mm(qr, gi.T, out=target[k + 1])
                target[k + 1].addmm_(qi, gr.T, alpha=-1)  # Im = Qr . Gi - Qi . Gr
            k += 1 + b.complex
        if low:
            buf32[1:].copy_(buf[1:])  # one conversion; row 0 (the DC term) was computed in float32
        yield start, torch.mm(lag, buf32.view(num_out, -1), out=cbuf.view(lag.shape[0], -1)).view(-1, n, m)


@dataclass(frozen=True)
class RotationSearchResult:
    """Best (prototype, yaw) per object.

    Attributes:
        prototype: ``[N]`` long, index of the best prototype.
        angle: ``[N]`` long, yaw index ``a``: rotating the object by ``2 pi a / A`` aligns it with the prototype.
        score: ``[N]`` cosine similarity at the best (prototype, yaw).
        scores: ``[N, K, A]`` cosine similarity for every prototype and yaw.
    """

    prototype: Tensor
    angle: Tensor
    score: Tensor
    scores: Tensor


def _check_method(method: str) -> None:
    if method not in SEARCH_METHODS:
        raise ValueError(f"method must be one of {SEARCH_METHODS}, got {method!r}")


def _check_pair(a: Tensor, b: Tensor, names: tuple[str, str]) -> None:
    _check_crops(a, names[0])
    _check_crops(b, names[1])
    if a.shape[1:] != b.shape[1:]:
        shapes = f"{tuple(a.shape)} and {tuple(b.shape)}"
        raise ValueError(f"{names[0]} and {names[1]} must be crops of one shape [*, C, Z, Y, X], got {shapes}")


def _exact_scores(objects: Tensor, prototypes: Tensor, num_angles: int, chunk: int) -> Iterator[tuple[int, Tensor]]:
    """Yield ``(start, s)``, ``s`` ``[n, K, A]``: cosine of each object rotated by each yaw (``rotate_yaw``)."""
    p = F.normalize(prototypes.flatten(1), dim=1)  # [K, D]
    angles = yaw_angles(num_angles, device=objects.device, dtype=objects.dtype)
    for start in range(0, objects.shape[0], chunk):
        o = objects[start : start + chunk]
        rotated = F.normalize(rotate_yaw(o, angles.expand(o.shape[0], num_angles)).flatten(2), dim=2)  # [n, A, D]
        s = (rotated.reshape(-1, p.shape[1]) @ p.T).view(o.shape[0], num_angles, -1)  # [n, A, K]
        yield start, s.transpose(1, 2)


def best_prototype_and_yaw(objects: Tensor, prototypes: Tensor, num_angles: int = 36, method: str = "fast", *,
                           num_radii: int | None = None, bandlimit: bool = True,
                           compute_dtype: torch.dtype | None = None, chunk: int | None = None,
                           objects_spectrum: PolarSpectrum | None = None) -> RotationSearchResult:
    """Best prototype and yaw for every object crop (the paper's quantisation step, Eq. 1), without gradient.

    ``scores[n, k, a] = cos(rotate(objects[n], 2 pi a / A), prototypes[k])``; the best (prototype, yaw) is the
    argmax over ``K * A`` (for L2-normalised crops, the argmin of the squared distance). ``"fast"``: polar spectra,
    cosine over the inscribed cylinder; ``"exact"``: ``rotate_yaw`` by every yaw, cosine over the full crop.

    Args:
        objects: ``[N, C, S, S, S]`` crops (any ``[N, C, Z, Y, X]``).
        prototypes: ``[K, C, S, S, S]`` crops of the same shape.
        num_angles: yaw candidates ``A`` (``2 pi a / A``).
        method: ``"fast"`` or ``"exact"``.
        num_radii: ``"fast"`` only: polar rings (default ``ceil(min(Y, X) / 2)``).
        bandlimit: ``"fast"`` only: drop angular frequencies above ``ceil(pi r)`` per ring.
        compute_dtype: ``"fast"`` only: e.g. ``torch.bfloat16``; default the objects' dtype.
        chunk: objects per GEMM (default: ~64 MiB of scratch for ``"fast"``, 16 for ``"exact"``).
        objects_spectrum: ``"fast"`` only: ``polar_spectrum(objects, ...)`` computed earlier with the same settings;
            its plan must be the one the prototypes get (else ``ValueError``).

    Returns:
        ``RotationSearchResult`` (``scores`` ``[N, K, A]`` float32 for low-precision compute, else the input
        dtype).

    Convention:
        Returned angle ``a``: rotating the object by ``2 pi a / A`` counter-clockwise (seen from above) aligns it
        with the returned prototype.
    """
    _check_pair(objects, prototypes, ("objects", "prototypes"))
    _check_method(method)
    if not _positive_int(num_angles):
        raise ValueError(f"num_angles must be a positive int, got {num_angles!r}")
    n, k = objects.shape[0], prototypes.shape[0]
    if k == 0:
        raise ValueError("prototypes must not be empty")
    with torch.no_grad():
        if method == "exact":
            scores = objects.new_empty(n, k, num_angles)
            for start, s in _exact_scores(objects, prototypes, num_angles, chunk or 16):
                scores[start : start + s.shape[0]] = s
        else:
            kw = {"bandlimit": bandlimit, "compute_dtype": compute_dtype}
            q = objects_spectrum
            if q is None:
                q = polar_spectrum(objects, num_angles, num_radii, **kw)
            g = polar_spectrum(prototypes, num_angles, num_radii, **kw)
            if len(q) != n or q.plan is not g.plan:
                other = "" if q.plan is g.plan else " of another plan"
                raise ValueError(f"objects_spectrum: expected the polar spectrum of the {n} objects computed with the "
                                 f"prototypes' settings, got {len(q)} items{other}")
            lag = q.plan.lag_basis
            scores = torch.empty(n, k, num_angles, device=objects.device, dtype=lag.dtype)
            inv_q, inv_g = _inverse_norms(q), _inverse_norms(g)
            for start, c in _correlate(q, g, chunk or _auto_chunk(n, k, num_angles)):
                rows = slice(start, start + c.shape[1])
                torch.mul(c.permute(1, 2, 0), (inv_q[rows, None] * inv_g[None])[..., None], out=scores[rows])
        best, flat = scores.reshape(n, -1).max(dim=1)
    return RotationSearchResult(prototype=torch.div(flat, num_angles, rounding_mode="floor"), angle=flat % num_angles,
                                score=best, scores=scores)


def rotation_max_similarity(query: Tensor, gallery: Tensor, num_angles: int = 36, chunk: int = 64,
                            method: str = "exact") -> tuple[Tensor, Tensor]:
    """The exact kernel of rotation-max retrieval (the reference of ``all_pairs_rotation_max``).

    ``method="exact"``: each query rotated by every candidate yaw (``rotate_yaw``), flattened and L2-normalised,
    compared with every flattened, L2-normalised gallery crop. ``method="fast"`` is :func:`all_pairs_rotation_max`.

    Args:
        query: ``[N, C, S, S, S]`` crops.
        gallery: ``[M, C, S, S, S]`` crops.
        num_angles: yaw candidates ``2 pi a / num_angles``.
        chunk: queries rotated at once (bounds memory: ``chunk * num_angles`` crops); ``"exact"`` only.
        method: ``"exact"`` or ``"fast"``.

    Returns:
        ``sim`` ``[N, M]`` the maximum cosine over yaw, and ``angle`` ``[N, M]`` long, the index ``a``
        of the best yaw (rotating the query by ``2 pi a / num_angles`` aligns it with the gallery crop).

    Convention: crops in frame R order ``[C, Z, Y, X]``, z up; yaw counter-clockwise seen from above.
    """
    if query.ndim != 5 or gallery.ndim != 5 or query.shape[1:] != gallery.shape[1:]:
        shapes = f"{tuple(query.shape)} and {tuple(gallery.shape)}"
        raise ValueError(f"query and gallery must be [N, C, Z, Y, X] crops of one shape, got {shapes}")
    _check_method(method)
    if method == "fast":
        return all_pairs_rotation_max(query, gallery, num_angles, method="fast")
    with torch.no_grad():
        best = [s.max(dim=2) for _, s in _exact_scores(query, gallery, num_angles, chunk)]  # s: [n, M, A]
    return torch.cat([b.values for b in best]), torch.cat([b.indices for b in best])


def all_pairs_rotation_max(query: Tensor, gallery: Tensor, num_angles: int = 36, method: str = "fast",
                           chunk: int | None = None, *, num_radii: int | None = None, bandlimit: bool = True,
                           compute_dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
    """Cosine similarity of every query to every gallery crop at the query's best yaw (rotation-max retrieval).

    The maximum over ``A`` yaws of ``cos(rotate(query_n, a), gallery_m)``; ``"exact"`` is
    :func:`rotation_max_similarity`, ``"fast"`` the cosine over the inscribed cylinder from polar spectra.

    Args:
        query: ``[N, C, Z, Y, X]`` crops.
        gallery: ``[M, C, Z, Y, X]`` crops.
        num_angles: yaw candidates ``A``.
        method: ``"fast"`` or ``"exact"``.
        chunk: queries per step (default: 64 for ``"exact"``, ~64 MiB of scratch for ``"fast"``).
        num_radii: ``"fast"`` only: polar rings.
        bandlimit: ``"fast"`` only: per-ring angular band limit.
        compute_dtype: ``"fast"`` only: e.g. ``torch.bfloat16``.

    Returns:
        ``sim`` ``[N, M]`` maximum cosine over yaw and ``angle`` ``[N, M]`` long, the best yaw index.

    Convention:
        Rotating query ``n`` by ``2 pi angle[n, m] / A`` counter-clockwise seen from above aligns it with gallery
        crop ``m``.
    """
    _check_pair(query, gallery, ("query", "gallery"))
    _check_method(method)
    if method == "exact":
        return rotation_max_similarity(query, gallery, num_angles, chunk or 64)
    n, m = query.shape[0], gallery.shape[0]
    with torch.no_grad():
        kw = {"bandlimit": bandlimit, "compute_dtype": compute_dtype}
        q = polar_spectrum(query, num_angles, num_radii, **kw)
        g = q if gallery is query else polar_spectrum(gallery, num_angles, num_radii, **kw)
        lag = q.plan.lag_basis
        sim = torch.empty(n, m, device=query.device, dtype=lag.dtype)
        angle = torch.empty(n, m, device=query.device, dtype=torch.long)
        inv_q, inv_g = _inverse_norms(q), _inverse_norms(g)
        for start, c in _correlate(q, g, chunk or _auto_chunk(n, m, num_angles)):
            best, arg = c.max(dim=0)  # a positive scale per pair does not move the argmax over yaw
            rows = slice(start, start + best.shape[0])
            torch.mul(best, inv_q[rows, None] * inv_g[None], out=sim[rows])
            angle[start : start + best.shape[0]] = arg
    return sim, angle


def yaw_margin(scores: Tensor, angle: Tensor, exclude: int) -> Tensor:
    """How clearly the rotation search's best yaw wins: its score minus the best score of every yaw more than
    ``exclude`` steps away from it (circularly).

    Args:
        scores: ``[N, A]`` the search's similarity at each of ``A`` yaws (one prototype per object).
        angle: ``[N]`` the chosen yaw index of each object.
        exclude: steps on either side of the chosen yaw that count as the same pose (``A > 2 * exclude + 1``).

    Returns:
        ``[N]`` margins, ``>= 0`` when ``angle`` is the argmax, in the scores' units (cosine similarity).

    Convention: yaw ``a`` is ``2 pi a / A``; steps are counted circularly (``A - 1`` is next to ``0``).
    """
    if scores.dim() != 2 or angle.shape != scores.shape[:1]:
        raise ValueError(f"scores, angle: expected [N, A] and [N], got {tuple(scores.shape)} and {tuple(angle.shape)}")
    a = scores.shape[1]
    if isinstance(exclude, bool) or not isinstance(exclude, int) or exclude < 0 or a <= 2 * exclude + 1:
        raise ValueError(f"exclude: expected an int >= 0 with {a} yaws > 2 * exclude + 1, got {exclude!r}")
    steps = torch.arange(a, device=scores.device)
    dist = (steps[None] - angle[:, None]).remainder(a)
    far = torch.minimum(dist, a - dist) > exclude
    best = scores.gather(1, angle[:, None])[:, 0]
    other = scores.masked_fill(~far, float("-inf")).amax(1)
    return best - other


def yaw_confidence(result: RotationSearchResult, exclude: int) -> Tensor:
    """:func:`yaw_margin` of each object at the prototype the search chose for it.

    Args:
        result: a search's result with its ``scores`` ``[N, K, A]`` (K the prototypes searched).
        exclude: as :func:`yaw_margin`'s.

    Returns:
        ``[N]`` float32 margins.
    """
    chosen = result.scores.amax(2).argmax(1)  # the chosen prototype's row among those searched (the argmax over K * A)
    rows = result.scores[torch.arange(chosen.shape[0], device=chosen.device), chosen].float()
    return yaw_margin(rows, result.angle, exclude)
