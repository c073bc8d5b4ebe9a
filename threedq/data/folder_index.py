"""Write the ``index.json`` of a folder of canonical scene ``.npz`` files (``threedq data index FOLDER``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from threedq.boxes import box_corners
from threedq.scene import DatasetIndex, SceneValidationError, load_scene, save_index

__all__ = ["index_folder"]

SPLITS = ("train", "val", "test")


def index_folder(folder: str | Path, categories: list[str] | None = None, symmetry_order: list[int] | None = None,
                 bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
                 default_split: str = "train", margin: float = 0.05) -> tuple[DatasetIndex, list[str]]:
    """Build and write ``folder/index.json`` from the scene files found (every ``*.npz`` under it, checked).

    Args:
        categories: category names, index = category id; ``None`` = ``category_<id>`` up to the largest id used.
        symmetry_order: per category (see :class:`~threedq.scene.DatasetIndex`); ``None`` = all 1.
        bounds: ``((xmin, ymin, zmin), (xmax, ymax, zmax))``; ``None`` = the union of every box's corners and every
            record's ``meta["scene_bounds"]``, grown by ``margin`` metres.
        default_split: split of files not under ``train/``, ``val/`` or ``test/``.

    Returns:
        The index written and one line per file left out (unreadable or invalid, naming file and field).

    Raises:
        SceneValidationError: no valid scene file, or no bounds can be taken from the data.
    """
    folder = Path(folder)
    if default_split not in SPLITS:
        raise ValueError(f"default_split: expected one of {SPLITS}, got {default_split!r}")
    scenes, problems = [], []
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    max_cat = -1
    for path in sorted(folder.rglob("*.npz")):
        rel = path.relative_to(folder)
        if rel.parts[0] == "proposals":
            continue
        try:
            rec = load_scene(path)
        except SceneValidationError as e:
            problems.append(str(e))
            continue
        split = rel.parts[0] if len(rel.parts) > 1 and rel.parts[0] in SPLITS else default_split
        scenes.append({"file": rel.as_posix(), "split": split})
        if rec.num_objects:
            c = box_corners(rec.boxes.astype(np.float64)).reshape(-1, 3)
            lo, hi = np.minimum(lo, c.min(0)), np.maximum(hi, c.max(0))
            max_cat = max(max_cat, int(rec.categories.max()))
        sb = rec.meta.get("scene_bounds")
        if isinstance(sb, dict) and "min" in sb and "max" in sb:
            lo, hi = np.minimum(lo, sb["min"]), np.maximum(hi, sb["max"])
    source = str(folder / "index.json")
    if not scenes:
        raise SceneValidationError(str(folder), "scenes", "no valid scene .npz file found")
    if categories is None:
        categories = [f"category_{i}" for i in range(max_cat + 1)]
    elif max_cat >= len(categories):
        why = f"{len(categories)} names but a scene uses category id {max_cat}"
        raise SceneValidationError(source, "categories", why)
    symmetry_order = [1] * len(categories) if symmetry_order is None else list(symmetry_order)
    if len(symmetry_order) != len(categories):
        raise SceneValidationError(source, "symmetry_order", f"expected {len(categories)} integers, one per category")
    if bounds is None:
        if not np.all(np.isfinite(lo)):
            why = "no boxes or meta scene_bounds in the data: give the bounds"
            raise SceneValidationError(source, "scene_bounds", why)
        bounds = (tuple(float(x) for x in lo - margin), tuple(float(x) for x in hi + margin))  # type: ignore[assignment]
    index = DatasetIndex(categories=list(categories), symmetry_order=symmetry_order, scenes=scenes,
                         scene_bounds=bounds, generator={"name": "threedq data index"}, seed=None)
    save_index(folder, index)
    return index, problems
