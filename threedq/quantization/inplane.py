"""In-plane rotation search over 2D crops (2.5DQ-Nets): the yaw search of 3DQ-Nets on one-slice volumes.

An in-plane rotation of a 2D crop ``[C, H, W]`` is exactly a yaw of the one-slice volume ``[C, 1, H, W]``
(:func:`threedq.geometry.rotate_yaw` rotates every z-slice in its own plane). So the 2D search reuses the 3D
machinery unchanged: the ``"fast"`` kernel resamples each crop once onto a polar grid (rings x 36 angles) and
correlates along the angle with one GEMM per angular frequency
(:func:`~threedq.quantization.rotation_search.best_prototype_and_yaw`); the ``"exact"`` kernel rotates every
crop by every angle and compares. Nothing here is a second implementation: these functions only fix the
layout and validate 2D inputs.

Convention:
    Crops are ``[N, C, H, W]`` images: row ``y`` points down, column ``x`` right, pixel centres at integer
    indices, rotation centre ``((W - 1) / 2, (H - 1) / 2)``. Angle index ``a`` means ``2 pi a / A`` radians
    CLOCKWISE as displayed (y down): content at +x moves towards +y (the same formula as ``rotate_yaw``,
    counter-clockwise in a y-up frame). A returned angle ``a`` for (object ``o``, prototype/gallery item
    ``k``) means: rotating ``o`` by ``a`` steps aligns it with ``k``.
"""

from __future__ import annotations

from torch import Tensor

from threedq.geometry.rotate import rotate_yaw
from threedq.quantization.rotation_search import (
    RotationSearchResult,
    all_pairs_rotation_max,
    best_prototype_and_yaw,
)

__all__ = ["all_pairs_inplane_max", "as_slices", "best_prototype_and_angle", "rotate_inplane"]


def _check_images(x: Tensor, name: str) -> None:
    if not isinstance(x, Tensor) or x.ndim != 4:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"{name} must have shape [N, C, H, W], got {shape}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {x.dtype}")


def as_slices(images: Tensor) -> Tensor:
    """``[N, C, H, W]`` crops as one-slice volumes ``[N, C, 1, H, W]`` (a view), the layout of the 3D search."""
    _check_images(images, "images")
    return images.unsqueeze(2)


def rotate_inplane(images: Tensor, angle: Tensor) -> Tensor:
    """Rotate 2D crops in the image plane about their centre (bilinear, zeros outside).

    Args:
        images: ``[N, C, H, W]``.
        angle: ``[N]`` or ``[N, A]`` radians.

    Returns:
        ``[N, C, H, W]`` for ``angle`` ``[N]``, ``[N, A, C, H, W]`` for ``[N, A]``. Differentiable.

    Convention: clockwise as displayed (y down) for a positive angle; output pixel ``p`` (offset from the
    centre) takes the input at ``R(-angle) p`` (see the module docstring).
    """
    out = rotate_yaw(as_slices(images), angle)
    return out.squeeze(-3)


def best_prototype_and_angle(
    objects: Tensor, prototypes: Tensor, num_angles: int = 36, method: str = "fast", **kwargs
) -> RotationSearchResult:
    """Best 2D prototype and in-plane angle per object crop (2.5DQ-Nets' quantisation step).

    ``scores[n, k, a] = cos(rotate_inplane(objects[n], 2 pi a / A), prototypes[k])``; argmax over ``K * A``.
    ``"fast"``: polar spectrum + one GEMM per angular frequency, cosine over the inscribed disc;
    ``"exact"``: every rotated object compared with every prototype, cosine over the full square.

    Args:
        objects: ``[N, C, S, S]`` crops.
        prototypes: ``[K, C, S, S]``.
        num_angles: ``A`` (36 = 10 deg).
        method: ``"fast"`` or ``"exact"``.
        **kwargs: passed to :func:`~threedq.quantization.rotation_search.best_prototype_and_yaw`
            (``num_radii``, ``bandlimit``, ``compute_dtype``, ``chunk``).

    Returns:
        ``RotationSearchResult`` (``prototype`` ``[N]``, ``angle`` ``[N]``, ``score`` ``[N]``, ``scores``
        ``[N, K, A]``).

    Convention: angle ``a`` = rotating the object by ``2 pi a / A`` clockwise as displayed aligns it with
    the prototype.
    """
    _check_images(objects, "objects")
    _check_images(prototypes, "prototypes")
    return best_prototype_and_yaw(as_slices(objects), as_slices(prototypes), num_angles, method, **kwargs)


def all_pairs_inplane_max(
    query: Tensor, gallery: Tensor, num_angles: int = 36, method: str = "fast", **kwargs
) -> tuple[Tensor, Tensor]:
    """Cosine of every query crop to every gallery crop at the query's best in-plane angle.

    Args:
        query: ``[N, C, H, W]``; gallery ``[M, C, H, W]``.
        num_angles: ``A``.
        method: ``"fast"`` or ``"exact"``.
        **kwargs: passed to :func:`~threedq.quantization.rotation_search.all_pairs_rotation_max`.

    Returns:
        ``sim`` ``[N, M]`` and ``angle`` ``[N, M]`` long (rotating query ``n`` by ``2 pi angle / A`` clockwise as
        displayed aligns it with gallery crop ``m``).
    """
    _check_images(query, "query")
    _check_images(gallery, "gallery")
    q = as_slices(query)
    g = q if gallery is query else as_slices(gallery)
    return all_pairs_rotation_max(q, g, num_angles, method, **kwargs)
