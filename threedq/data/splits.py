"""The splits of a generated dataset: their names, sizes, per-scene seeds and file names.

Scene ``i`` of split ``s`` draws everything from ``np.random.SeedSequence([seed_s, code_s, i])`` (split codes train 0,
val 1, test 2; ``seed_s = seed`` for train and val, ``test_seed`` for test); its capture conditions
(:mod:`threedq.data.sensor`) from ``np.random.SeedSequence([seed_s, code_s, i, 0x5E4502])``.

Files: scene ``i`` of split ``s`` is ``<dataset>/<s>/scene_<i:06d>.npz``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["SPLITS", "SPLIT_CODES", "capture_seed_sequence", "derive_test_seed", "scene_file", "scene_seed_sequence",
           "split_sizes"]

SPLITS: tuple[str, ...] = ("train", "val", "test")
SPLIT_CODES: dict[str, int] = {"train": 0, "val": 1, "test": 2}
_TEST_SEED_SALT = 0x7E57_5EED
_CAPTURE_SALT = 0x5E4502


def scene_seed_sequence(seed: int, split: str, index: int) -> np.random.SeedSequence:
    """The seed sequence of scene ``index`` of ``split`` (``seed`` is the split's seed: ``test_seed`` for test)."""
    return np.random.SeedSequence([int(seed), SPLIT_CODES[split], int(index)])


def capture_seed_sequence(seed: int, split: str, index: int) -> np.random.SeedSequence:
    """The seed sequence of the capture conditions of scene ``index`` of ``split`` (apart from its layout's)."""
    return np.random.SeedSequence([int(seed), SPLIT_CODES[split], int(index), _CAPTURE_SALT])


def derive_test_seed(seed: int) -> int:
    """The default test seed: a 32-bit value drawn from its own stream of ``seed``."""
    return int(np.random.SeedSequence([int(seed), _TEST_SEED_SALT]).generate_state(1, dtype=np.uint32)[0])


def split_sizes(num_scenes: int, split_fractions: Sequence[float], splits: Sequence[str]) -> dict[str, int]:
    """Scenes per requested split: ``num_scenes`` shared by the requested splits' renormalised fractions, rounded by
    largest remainder (ties to the earlier split), then at least one scene (from the largest) per split with a positive
    fraction when ``num_scenes`` allows it."""
    fr = [float(split_fractions[SPLIT_CODES[s]]) for s in splits]
    total = sum(fr)
    raw = [round(num_scenes * f / total, 9) for f in fr]
    counts = [math.floor(r) for r in raw]
    order = sorted(range(len(splits)), key=lambda i: (-(raw[i] - counts[i]), i))
    for i in order[: num_scenes - sum(counts)]:
        counts[i] += 1
    positive = [i for i, f in enumerate(fr) if f > 0]
    if num_scenes >= len(positive):
        for i in positive:
            if counts[i] == 0:
                j = max(range(len(counts)), key=lambda k: (counts[k], -k))
                counts[j] -= 1
                counts[i] += 1
    return dict(zip(splits, counts))


def scene_file(split: str, index: int) -> str:
    """Path of a scene file relative to the dataset folder, e.g. ``train/scene_000042.npz``."""
    return f"{split}/scene_{index:06d}.npz"
