"""Label-free pseudo-boxes of a whole dataset split, computed once and cached in a box file: :func:`propose_dataset`.

Convention: world frame in metres, z up; boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)`` float32.
"""

from __future__ import annotations

import json
import multiprocessing
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from threedq.data.box_files import load_boxes_file_with_params, save_boxes_file
from threedq.data.spawn import refuse_in_spawned_main, unspawnable_main
from threedq.locks import exclusive
from threedq.proposals import PROPOSALS_VERSION, Bounds, ProposalParams, propose_boxes
from threedq.scene import load_index, load_scene

__all__ = ["propose_dataset"]


def _params_json(params: ProposalParams, bounds: Bounds | None) -> str:
    d: dict[str, Any] = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in asdict(params).items()}
    d["bounds"] = None if bounds is None else [list(map(float, bounds[0])), list(map(float, bounds[1]))]
    d["version"] = PROPOSALS_VERSION
    if not d["align_floor"]:  # the caches written before the option keep their key
        del d["align_floor"]
    return json.dumps(d, sort_keys=True)


def propose_dataset(data_dir: str | Path, split: str, cache_path: str | Path, *, params: ProposalParams | None = None,
                    max_scenes: int | None = None, save_every: int = 50, progress: bool = True,
                    workers: int = 1) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Proposals for every scene of a split, cached in one box file (:mod:`threedq.data.box_files`) whose ``params``
    is the JSON of the parameters, the bounds and :data:`PROPOSALS_VERSION`.

    Args:
        cache_path: a cache made with the same parameters is reused and completed (an interrupted run resumes); one
            made with other parameters is recomputed and overwritten (with a warning).
        params: :class:`ProposalParams` (``None`` = defaults); the points are cropped to the index's ``scene_bounds``.
        max_scenes: only the first ``max_scenes`` scenes of the split (``None`` = all).
        save_every: the cache is rewritten (atomically) after every this many newly computed scenes.
        workers: processes computing scenes at once ("spawn" pool; fewer than :data:`MIN_POOL_SCENES` missing scenes
            run in this process). The results do not depend on it.

    Returns:
        ``{scene file as listed in index.json -> (aabb [P,6] float32, scores [P] float32)}`` in index order.
    """
    params = ProposalParams() if params is None else params
    if not isinstance(params, ProposalParams):
        raise ValueError(f"params: expected a ProposalParams or None, got {type(params).__name__}")  # noqa: TRY004 - ValueError naming the argument
    for name, v in (("save_every", save_every), ("workers", workers)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
    data_dir, cache_path = Path(data_dir), Path(cache_path)
    index = load_index(data_dir)
    files = index.files(split)
    if not files:
        known = sorted({s["split"] for s in index.scenes})
        raise ValueError(f"split: no scenes of split {split!r} in {data_dir / 'index.json'} (splits: {known})")
    if max_scenes is not None:
        if isinstance(max_scenes, bool) or not isinstance(max_scenes, int) or max_scenes < 0:
            raise ValueError(f"max_scenes: expected an int >= 0 or None, got {max_scenes!r}")
        files = files[:max_scenes]
    bounds = index.scene_bounds
    pjson = _params_json(params, bounds)

    def read_cache(warn: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        if not cache_path.exists():
            return {}
        cached_params, cached = load_boxes_file_with_params(cache_path)  # a corrupt file: ValueError naming it
        if cached_params != pjson:
            if warn:
                warnings.warn(f"{cache_path}: made with other parameters; recomputing it", stacklevel=3)
            return {}
        return dict(cached.items())

    results = read_cache(warn=False)
    if cache_path.exists() and all(f in results for f in files):
        return {f: results[f] for f in files}
    with exclusive(cache_path, what="computing proposals into",
                   before_wait=lambda: refuse_in_spawned_main(cache_path, "computing the pseudo-boxes")):
        results = read_cache(warn=True)
        _complete(results, files, data_dir, cache_path, pjson, bounds, params, save_every, progress, workers)
    return {f: results[f] for f in files}


#: the fewest missing scenes for which :func:`propose_dataset` starts a process pool
MIN_POOL_SCENES = 32


def _propose_scene(path: Path, bounds: Bounds | None, kwargs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """One scene's proposals; a ``ValueError`` of the proposer names the file."""
    record = load_scene(path, validate=False)
    try:
        return propose_boxes(record, bounds=bounds, **kwargs)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e


def _init_pool_worker() -> None:
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    threadpool_limits(1)


def _pool_task(args: tuple[Path, Bounds | None, dict[str, Any]]) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`_propose_scene` in a pool worker; None on any error (the parent then computes that scene itself)."""
    try:
        return _propose_scene(*args)
    except Exception:  # noqa: BLE001 - re-raised by the parent
        return None


def _pool_size(workers: int, todo: int) -> int:
    """How many processes compute ``todo`` scenes: ``workers``, or 1 where a pool would not pay or cannot start."""
    if workers <= 1 or todo < MIN_POOL_SCENES:
        return 1
    return 1 if unspawnable_main() is not None else min(workers, todo)


def _complete(results: dict[str, tuple[np.ndarray, np.ndarray]], files: list[str], data_dir: Path, cache_path: Path,
              pjson: str, bounds: Bounds | None, params: ProposalParams, save_every: int, progress: bool,
              workers: int = 1) -> None:  # fmt: skip
    """Compute the scenes of ``files`` missing from ``results`` into it, in order, saving the cache every
    ``save_every`` scenes."""
    from tqdm import tqdm

    all_names = list(dict.fromkeys([*results.keys(), *files]))
    todo = [f for f in files if f not in results]
    kwargs = asdict(params)
    tasks = [(data_dir / f, bounds, kwargs) for f in todo]
    n_proc = _pool_size(workers, len(todo))
    dirty = 0
    with tqdm(total=len(files), initial=len(files) - len(todo), disable=not progress, desc="proposals",
              unit="scene", dynamic_ncols=True) as bar:  # fmt: skip
        pool = multiprocessing.get_context("spawn").Pool(n_proc, _init_pool_worker) if n_proc > 1 else None
        try:
            done = (pool.imap(_pool_task, tasks, chunksize=4) if pool is not None
                    else (_propose_scene(*t) for t in tasks))
            for f, task, out in zip(todo, tasks, done, strict=True):
                results[f] = out if out is not None else _propose_scene(*task)
                dirty += 1
                bar.update(1)
                if dirty >= save_every:
                    save_boxes_file(cache_path, {k: results[k] for k in all_names if k in results}, pjson)
                    dirty = 0
        finally:
            if pool is not None:
                pool.terminate()
                pool.join()
    if dirty or not cache_path.exists():
        save_boxes_file(cache_path, {k: results[k] for k in all_names if k in results}, pjson)
