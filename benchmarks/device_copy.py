"""A cut, compact copy of a scene folder for a machine that takes little data (a lent GPU's 64 MiB upload).

``pack`` keeps, per scene, only the views a study reads: ``--train_views`` views of each training scene drawn from
``--view_seed``; the two fixed views of the retrieval protocols of each val and test scene (for the DataModule seed
``--seed``), in the order that makes the copy's fixed-view loader pick the same query and gallery views. RGB is stored
as lossless WebP, depth as 16-bit PNG in millimetres (0 stays invalid); instance masks are left out. ``unpack`` turns
the copy back into a threedq scene folder (``index.json`` + validated ``.npz`` scenes).

    python benchmarks/device_copy.py pack data/clevr_veggie_256 .devdata/p256 --train_views 6
    python benchmarks/device_copy.py unpack .devdata/p256 /tmp/clevr_veggie_256 --workers 16   # on the device
"""

from __future__ import annotations

import argparse
import json
from functools import partial
from multiprocessing import Pool
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from threedq.datamodules.scene_folder import fixed_views
from threedq.scene import INDEX_NAME, SceneRecord, SceneValidationError, load_index, load_scene, save_scene

#: depth is stored in millimetres as uint16
MAX_DEPTH_M = 65.535


def copy_views(split: str, pos: int, scene: int, num_views: int, train_views: int, view_seed: int, seed: int) -> np.ndarray:
    """The original views a scene keeps, in the order they are stored in the copy."""
    if split == "train":
        n = min(train_views, num_views)
        return np.sort(np.random.default_rng([view_seed, scene]).permutation(num_views)[:n])
    want = fixed_views(seed, pos, num_views, 2)  # (query, gallery) of the original
    order = fixed_views(seed, pos, 2, 2)  # the copy's loader reads its views in this order
    stored = np.empty_like(want)
    stored[order] = want  # the copy's loader then reads want[0] as query and want[1] as gallery
    return stored


def _map(fn, items: list, workers: int, desc: str) -> list:
    """``fn`` over ``items`` with a progress bar, in ``workers`` processes (in this one for ``workers <= 1``)."""
    if workers <= 1:
        return [fn(x) for x in tqdm(items, desc=desc, unit="scene")]
    with Pool(workers) as p:
        return list(tqdm(p.imap(fn, items, chunksize=8), total=len(items), desc=desc, unit="scene"))


def _pack_one(task: tuple[str, int, int, str], src: Path, dst: Path, train_views: int, view_seed: int, seed: int) -> int:
    split, pos, scene, file = task
    rec = load_scene(src / file)
    views = copy_views(split, pos, scene, rec.rgb.shape[0], train_views, view_seed, seed)
    out: dict[str, np.ndarray] = {"views": views.astype(np.int64)}
    for j, v in enumerate(views):
        depth = rec.depth[v]
        if depth.max() >= MAX_DEPTH_M:
            raise SceneValidationError(str(src / file), "depth",
                                       f"view {v} holds {depth.max():.2f} m: the copy stores depth up to {MAX_DEPTH_M} m")
        ok_rgb, rgb = cv2.imencode(".webp", np.ascontiguousarray(rec.rgb[v][..., ::-1]), [cv2.IMWRITE_WEBP_QUALITY, 101])
        ok_d, d = cv2.imencode(".png", np.round(depth * 1000.0).astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not (ok_rgb and ok_d):
            raise SceneValidationError(str(src / file), "rgb" if not ok_rgb else "depth", f"view {v} could not be encoded")
        out[f"rgb{j}"], out[f"depth{j}"] = rgb.reshape(-1), d.reshape(-1)
    out["K"], out["world_T_cam"] = rec.K[views], rec.world_T_cam[views]
    out["boxes"], out["categories"] = rec.boxes, rec.categories
    out["meta"] = np.array(json.dumps(rec.meta))
    (dst / file).parent.mkdir(parents=True, exist_ok=True)
    np.savez(dst / file, **out)
    return (dst / file).stat().st_size


def pack(src: Path, dst: Path, train_views: int = 6, view_seed: int = 12345, seed: int = 0, workers: int = 2) -> int:
    """Write the copy of ``src`` into ``dst`` (``index.json`` last); returns the bytes written."""
    if train_views < 2:
        raise ValueError(f"train_views: view prediction needs >= 2 views per training scene, got {train_views}")
    index = load_index(src)
    tasks, pos = [], {}
    for k, s in enumerate(index.scenes):
        tasks.append((s["split"], pos.get(s["split"], 0), k, s["file"]))
        pos[s["split"]] = pos.get(s["split"], 0) + 1
    dst.mkdir(parents=True, exist_ok=True)
    fn = partial(_pack_one, src=src, dst=dst, train_views=train_views, view_seed=view_seed, seed=seed)
    sizes = _map(fn, tasks, workers, "pack")
    (dst / INDEX_NAME).write_text((src / INDEX_NAME).read_text())
    return sum(sizes)


def _unpack_one(file: str, src: Path, dst: Path) -> None:
    path = src / file
    try:
        with np.load(path, allow_pickle=False) as z:
            n = len(z["views"])
            rgb = np.stack([cv2.imdecode(z[f"rgb{j}"], cv2.IMREAD_COLOR)[..., ::-1] for j in range(n)])
            depth = np.stack([cv2.imdecode(z[f"depth{j}"], cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
                              for j in range(n)])
            rec = SceneRecord(rgb=np.ascontiguousarray(rgb), depth=depth, K=z["K"], world_T_cam=z["world_T_cam"],
                              boxes=z["boxes"], categories=z["categories"], meta=json.loads(str(z["meta"])))
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise SceneValidationError(str(path), "<file>", f"not a packed scene ({type(e).__name__}: {e})") from e
    save_scene(dst / file, rec)  # validated


def unpack(src: Path, dst: Path, workers: int = 8) -> int:
    """Turn the copy ``src`` into the scene folder ``dst`` (``index.json`` last); returns the number of scenes."""
    index = load_index(src)
    files = index.files()
    dst.mkdir(parents=True, exist_ok=True)
    _map(partial(_unpack_one, src=src, dst=dst), files, workers, "unpack")
    (dst / INDEX_NAME).write_text((src / INDEX_NAME).read_text())
    return len(files)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack", help="write the cut copy of a scene folder")
    u = sub.add_parser("unpack", help="turn a copy back into a scene folder")
    for q, workers in ((p, 2), (u, 8)):
        q.add_argument("src", type=Path)
        q.add_argument("dst", type=Path)
        q.add_argument("--workers", type=int, default=workers)
    p.add_argument("--train_views", type=int, default=6)
    p.add_argument("--view_seed", type=int, default=12345, help="seed of the training scenes' kept views")
    p.add_argument("--seed", type=int, default=0, help="the DataModule seed whose fixed views val/test scenes keep")
    args = ap.parse_args()
    if args.cmd == "pack":
        n = pack(args.src, args.dst, args.train_views, args.view_seed, args.seed, args.workers)
        print(f"packed {args.src} into {args.dst}: {n / 1e6:.1f} MB")
    else:
        print(f"unpacked {unpack(args.src, args.dst, args.workers)} scenes into {args.dst}")


if __name__ == "__main__":
    main()
