"""Import captures of one on-disk format into a canonical dataset folder (``threedq data import``).

``import_captures("tum", SRC, D)`` parses every capture found (``SRC`` itself, or its subfolders holding the format's
marker file), normalises each (:func:`~threedq.data.formats.normalise.normalise_capture`), writes
``D/<split>/<capture name>.npz`` and ``D/index.json`` (an existing index is extended, a re-imported capture replaces
its entry), and returns a summary.
"""

from __future__ import annotations

import inspect
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from threedq.data.formats.capture import FrameSkip
from threedq.data.formats.normalise import normalise_capture
from threedq.data.formats.registry import FORMATS
from threedq.scene import INDEX_NAME, DatasetIndex, SceneValidationError, load_index, save_index, save_scene

__all__ = ["ImportSummary", "find_captures", "import_captures"]

IMPORT_VERSION = 1


@dataclass
class ImportSummary:
    """What an import did: ``scenes`` (file, views kept, frames with a valid pose), ``skipped`` frames (and
    malformed lines), ``failed`` captures."""

    scenes: list[tuple[str, int, int]] = field(default_factory=list)
    skipped: list[FrameSkip] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        """Human-readable summary: one line per skipped frame and failed capture, then the totals."""
        out = [f"skipped: {s}" for s in self.skipped] + [f"failed: {f}" for f in self.failed]
        why = ", ".join(f"{k} {v}" for k, v in sorted(Counter(s.field for s in self.skipped).items()))
        out += [f"{f}: {kept} views kept of {read} posed frames" for f, kept, read in self.scenes]
        out.append(f"imported {len(self.scenes)} scene(s), {sum(k for _, k, _ in self.scenes)} views; "
                   f"{len(self.skipped)} frame(s) skipped" + (f" ({why})" if why else "")
                   + f"; {len(self.failed)} capture(s) failed")
        return out


def find_captures(fmt: str, src: str | Path) -> list[Path]:
    """``src`` if it is a capture of format ``fmt`` (holds its marker file), else its subfolders that are."""
    if fmt not in FORMATS:
        raise ValueError(f"format: expected one of {sorted(FORMATS)}, got {fmt!r}")
    src = Path(src)
    marker = FORMATS[fmt][1]
    if (src / marker).is_file():
        return [src]
    found = sorted(d for d in src.iterdir() if d.is_dir() and (d / marker).is_file()) if src.is_dir() else []
    if not found:
        raise SceneValidationError(str(src), "<folder>", f"no {fmt} capture: expected {marker} here or in a subfolder")
    return found


def _reader_kwargs(fmt: str, options: dict[str, Any]) -> dict[str, Any]:
    params = inspect.signature(FORMATS[fmt][0]).parameters
    given = {k: v for k, v in options.items() if v is not None}
    allowed = [p for p in params if p not in ("folder", "max_views")]
    bad = [k for k in given if k not in allowed]
    if bad:
        raise ValueError(f"option {bad[0]!r} does not apply to format {fmt!r} (it takes {allowed})")
    return given


def import_captures(fmt: str, src: str | Path, out: str | Path, split: str = "train", max_views: int = 28,
                    max_depth: float = 10.0, reader_options: dict[str, Any] | None = None,
                    progress: bool = True) -> ImportSummary:
    """Import every capture of ``src`` (one capture folder or a folder of them) into the dataset folder ``out``.

    Args:
        fmt: a name of :data:`~threedq.data.formats.registry.FORMATS`.
        split: the split the scenes go to (``train``, ``val`` or ``test``).
        max_views: views kept per scene; max_depth: depth beyond this many metres becomes 0.
        reader_options: keyword arguments of the format's reader (``None`` values are dropped).

    Raises:
        SceneValidationError: ``src`` holds no capture of this format.
        ValueError: a bad argument.
    """
    if split not in ("train", "val", "test"):
        raise ValueError(f"split: expected train, val or test, got {split!r}")
    captures = find_captures(fmt, src)
    kwargs = _reader_kwargs(fmt, reader_options or {})
    out = Path(out)
    old = load_index(out) if (out / INDEX_NAME).is_file() else None
    categories = list(old.categories) if old else []
    bounds = [np.array(old.scene_bounds[0]), np.array(old.scene_bounds[1])] if old else None
    scenes = list(old.scenes) if old else []
    summary = ImportSummary()

    from tqdm import tqdm

    bar = tqdm(captures, disable=not progress, desc=f"threedq import {fmt}", unit="capture", dynamic_ncols=True)
    for folder in bar:
        try:
            capture = FORMATS[fmt][0](folder, max_views=max_views, **kwargs)  # reads only the views it keeps
            record = normalise_capture(capture, categories, max_views=max_views, max_depth=max_depth)
        except SceneValidationError as e:
            summary.failed.append(str(e))
            continue
        summary.skipped.extend(capture.skipped)
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", folder.resolve().name) or "capture"
        rel = f"{split}/{name}.npz"
        save_scene(out / rel, record)
        lo, hi = (np.array(record.meta["scene_bounds"][k]) for k in ("min", "max"))
        bounds = [lo, hi] if bounds is None else [np.minimum(bounds[0], lo), np.maximum(bounds[1], hi)]
        scenes = [s for s in scenes if s["file"] != rel] + [{"file": rel, "split": split}]
        summary.scenes.append((rel, record.num_views, capture.num_frames))
    if bounds is not None:
        sym = list(old.symmetry_order) if old else []
        formats = sorted(set(old.generator.get("formats", []) if old else []) | {fmt})
        scene_bounds = (tuple(float(x) for x in bounds[0]), tuple(float(x) for x in bounds[1]))
        generator = {"name": "threedq.data.formats", "version": IMPORT_VERSION, "formats": formats}
        save_index(out, DatasetIndex(categories=categories, symmetry_order=sym + [1] * (len(categories) - len(sym)),
                                     scenes=scenes, scene_bounds=scene_bounds, generator=generator,  # type: ignore[arg-type]
                                     seed=None))
    return summary
