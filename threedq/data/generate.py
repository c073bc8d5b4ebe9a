"""The resumable, multi-process writer of the embedded dataset: :func:`generate_dataset`.

Each scene is sampled (seeded per scene as :mod:`threedq.data.splits` describes), rendered, given the capture
conditions of ``config.capture_level`` if it is above 0 (:mod:`threedq.data.sensor`) and written to
``out/<split>/scene_<index:06d>.npz``; ``out/index.json`` lists the scenes at the end. The files do not depend on the
worker count or the scheduling. A scene file that loads, validates and whose ``meta`` names the same generator
version, config hash, seed, split and index is kept; anything else is (re)written atomically.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from threedq.data.generator_config import GENERATOR_VERSION, GeneratorConfig, _is_int
from threedq.data.layout import sample_scene
from threedq.data.render import Renderer
from threedq.data.render_scene import make_renderer, render_scene
from threedq.data.sensor import apply_capture
from threedq.data.spawn import refuse_in_spawned_main, unspawnable_main
from threedq.data.splits import (
    SPLIT_CODES,
    SPLITS,
    capture_seed_sequence,
    derive_test_seed,
    scene_file,
    scene_seed_sequence,
    split_sizes,
)
from threedq.locks import exclusive
from threedq.scene import DatasetIndex, SceneValidationError, load_scene, save_index, save_scene

__all__ = ["generate_dataset"]


@dataclass(frozen=True)
class _Task:
    split: str
    index: int
    seed: int


def _scene_is_current(path: Path, expected: dict[str, Any], config: GeneratorConfig) -> bool:
    """``path`` loads, validates (bounds, categories) and its meta matches ``expected``."""
    if not path.is_file():
        return False
    try:
        rec = load_scene(path, validate=True, bounds=config.scene_bounds, num_categories=len(config.category_names))
    except SceneValidationError:
        return False
    if any(rec.meta.get(k) != v for k, v in expected.items()):
        return False
    H, W = config.image_size
    return rec.rgb.shape == (config.num_views, H, W, 3) and rec.instance is not None


def _run_task(task: _Task, out: Path, config: GeneratorConfig, config_hash: str, renderer_fn) -> tuple[str, int, str]:
    """Keep or (re)write one scene file; returns ``(split, index, "kept" | "written")``."""
    path = out / scene_file(task.split, task.index)
    expected = {"generator_version": GENERATOR_VERSION, "config_hash": config_hash, "seed": task.seed,
                "split": task.split, "index": task.index}
    if _scene_is_current(path, expected, config):
        return task.split, task.index, "kept"
    layout = sample_scene(config, scene_seed_sequence(task.seed, task.split, task.index))
    layout.meta.update(expected)
    record = render_scene(layout, renderer_fn())
    if config.capture_level > 0:
        rng = np.random.default_rng(capture_seed_sequence(task.seed, task.split, task.index))
        record = apply_capture(record, rng, config.capture_level, config.capture_effects)
    save_scene(path, record)
    return task.split, task.index, "written"


# Per-process state of a pool worker (its GL context), filled by the pool initializer.
_WORKER: dict[str, Any] = {}


def _init_worker(out: str, config_dict: dict[str, Any], raster_threads: int) -> None:
    # Mesa's llvmpipe threads, read when the GL driver loads below; a user's own setting wins
    os.environ.setdefault("LP_NUM_THREADS", str(raster_threads))
    config = GeneratorConfig.from_dict(config_dict)
    _WORKER.clear()
    _WORKER.update(out=Path(out), config=config, hash=config.hash())
    try:
        _WORKER["renderer"] = make_renderer(config)
    except Exception as e:  # noqa: BLE001 - reported by the first task (a failing initializer would respawn forever)
        _WORKER["error"] = f"{type(e).__name__}: {e}"


def _worker_renderer() -> Renderer:
    if "error" in _WORKER:
        raise RuntimeError(f"worker process {os.getpid()} could not create its renderer: {_WORKER['error']}")
    return _WORKER["renderer"]


def _worker_task(task: _Task) -> tuple[str, int, str]:
    return _run_task(task, _WORKER["out"], _WORKER["config"], _WORKER["hash"], _worker_renderer)


def _remove_stale_temporaries(folder: Path, min_age_s: float = 3600.0) -> None:
    """Delete temporary files a killed run left behind (``.scene_XXXXXX.npz.*.tmp``, older than an hour)."""
    now = time.time()
    for p in folder.glob(".scene_*.npz.*.tmp"):
        with contextlib.suppress(OSError):
            if now - p.stat().st_mtime > min_age_s:
                p.unlink()


def _checked_arguments(num_scenes: int, seed: int, config: GeneratorConfig | None,
                       split_fractions: tuple[float, float, float], test_seed: int | None, splits: Sequence[str],
                       workers: int) -> tuple[GeneratorConfig, tuple[str, ...], tuple[float, ...]]:
    """Validate :func:`generate_dataset`'s arguments: the config (``None`` = ``GeneratorConfig()``), the requested
    splits in canonical order and the three split fractions as floats, or a ``ValueError`` naming the argument."""
    config = GeneratorConfig() if config is None else config
    if not isinstance(config, GeneratorConfig):
        raise ValueError(f"config: expected a GeneratorConfig, got {type(config).__name__}")  # noqa: TRY004 - the API promises ValueError naming the argument
    ints = [("num_scenes", num_scenes, 1, ""), ("seed", seed, 0, ""), ("test_seed", test_seed, 0, " or None")]
    for name, v, lo, or_none in [*ints, ("workers", workers, 1, "")]:
        if not (or_none and v is None) and (not _is_int(v) or v < lo):
            raise ValueError(f"{name}: expected an int >= {lo}{or_none}, got {v!r}")
    if isinstance(splits, str) or not all(isinstance(s, str) for s in splits):
        raise ValueError(f"splits: expected a sequence of split names, got {splits!r}")
    splits = tuple(splits)
    if not splits or any(s not in SPLITS for s in splits) or len(set(splits)) != len(splits):
        raise ValueError(f"splits: expected distinct names from {SPLITS}, got {splits!r}")
    splits = tuple(s for s in SPLITS if s in splits)  # canonical order
    try:
        fractions = tuple(float(f) for f in split_fractions)
    except (TypeError, ValueError):
        raise ValueError(f"split_fractions: expected 3 numbers (train, val, test), got {split_fractions!r}") from None
    if len(fractions) != 3 or not all(math.isfinite(f) and f >= 0 for f in fractions):
        raise ValueError(
            f"split_fractions: expected 3 non-negative numbers (train, val, test), got {split_fractions!r}")
    if sum(fractions[SPLIT_CODES[s]] for s in splits) <= 0:
        raise ValueError(f"split_fractions: the requested splits {splits} all have fraction 0")
    return config, splits, fractions


def _render_tasks(tasks: list[_Task], out: Path, config: GeneratorConfig, config_hash: str, workers: int,
                  progress: bool) -> None:
    """Keep or (re)write every task's scene file, in this process or in a "spawn" pool of ``workers``."""
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), disable=not progress, desc="threedq scenes", unit="scene", dynamic_ncols=True)
    kept = 0
    try:
        n_proc = min(workers, len(tasks))
        main_file = unspawnable_main()
        if n_proc > 1 and main_file is not None:
            warnings.warn(f"workers={workers}: the main script {main_file!r} is not a file; rendering in-process",
                          stacklevel=3)
            n_proc = 1
        if n_proc <= 1:
            renderer: list[Renderer] = []

            def get_renderer() -> Renderer:
                if not renderer:
                    renderer.append(make_renderer(config))
                return renderer[0]

            try:
                for task in tasks:
                    kept += _run_task(task, out, config, config_hash, get_renderer)[2] == "kept"
                    bar.update(1)
            finally:
                for r in renderer:
                    r.release()
        else:
            ctx = multiprocessing.get_context("spawn")
            threads = max(1, (os.cpu_count() or 1) // n_proc)
            with ctx.Pool(n_proc, initializer=_init_worker, initargs=(str(out), config.to_dict(), threads)) as pool:
                for _, _, status in pool.imap_unordered(_worker_task, tasks, chunksize=1):
                    kept += status == "kept"
                    bar.update(1)
                    bar.set_postfix(kept=kept, refresh=False)
    finally:
        bar.close()


def generate_dataset(out: str | Path, num_scenes: int, seed: int = 0,
                     config: GeneratorConfig | None = GeneratorConfig(),  # noqa: B008 - frozen, never mutated
                     split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1), test_seed: int | None = None,
                     splits: Sequence[str] = SPLITS, workers: int = 2, progress: bool = True) -> DatasetIndex:
    """Generate (or complete) a dataset folder and write its ``index.json`` last.

    Args:
        num_scenes: scenes over the requested splits (see :func:`split_sizes`).
        seed: seed of the train and val scenes; test_seed: of the test scenes (``None``: :func:`derive_test_seed`).
        config: scene parameters (``None`` = ``GeneratorConfig()``).
        split_fractions: ``(train, val, test)`` shares (renormalised over the requested ``splits``).
        workers: processes rendering in parallel ("spawn" pool, one GL context each); 1 = in this process.

    Returns:
        The :class:`~threedq.scene.DatasetIndex` written to ``out/index.json``.

    Raises:
        ValueError: a bad argument (the message names it).
        RuntimeError: no OpenGL context could be created (the message says what to install).
    """
    config, splits, fractions = _checked_arguments(num_scenes, seed, config, split_fractions, test_seed, splits,
                                                   workers)
    out = Path(out)
    eff_test_seed = derive_test_seed(seed) if test_seed is None else int(test_seed)
    sizes = split_sizes(int(num_scenes), fractions, splits)
    split_seed = {"train": int(seed), "val": int(seed), "test": eff_test_seed}
    tasks = [_Task(s, i, split_seed[s]) for s in splits for i in range(sizes[s])]
    with exclusive(out, what="generating", before_wait=lambda: refuse_in_spawned_main(out, "generating the dataset")):
        for s in splits:
            (out / s).mkdir(parents=True, exist_ok=True)
            _remove_stale_temporaries(out / s)
        config_hash = config.hash()
        _render_tasks(tasks, out, config, config_hash, workers, progress)
        generator = {"name": "threedq.data.generate", "version": GENERATOR_VERSION, "config": config.to_dict(),
                     "config_hash": config_hash, "seed": int(seed), "test_seed": eff_test_seed,
                     "split_fractions": list(fractions), "num_scenes": int(num_scenes),
                     "split_sizes": {s: sizes[s] for s in splits}}
        index = DatasetIndex(categories=list(config.category_names), symmetry_order=list(config.symmetry_order),
                             scenes=[{"file": scene_file(t.split, t.index), "split": t.split} for t in tasks],
                             scene_bounds=config.scene_bounds, generator=generator, seed=int(seed))
        save_index(out, index)
    return index
