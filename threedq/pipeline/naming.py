"""``threedq label``: name a few objects, and the names propagate to the prototypes (paper Table 1's protocol).

A labels YAML names objects of scenes::

    scenes: data/clevr_veggie        # folder the scene paths are relative to (default: the YAML's folder)
    views: [0]                       # input views of the parse (default [0]; the same as threedq parse's)
    labels:
      - {scene: test/scene_000003.npz, object: 0, name: cube}      # object 0 of `threedq parse`'s list
      - {scene: test/scene_000007.npz, box: [-0.7, 0.0, 0.0, 0.0, 0.7, 0.6], name: mug}   # or a box (frame R)

Each prototype takes the name most of its named members carry (ties: the alphabetically first); the names are
stored beside the bank (``prototype_names.json``); conflicts and prototypes left unnamed are reported.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from threedq.atomic_io import atomic_write_json
from threedq.errors import InputError
from threedq.metrics.fewshot import few_shot_accuracy
from threedq.pipeline.parse import SceneParser, check_views, names_path, parse_records, resolve_run
from threedq.scene import SceneValidationError, load_scene

__all__ = ["load_labels", "propagate_names", "run_label"]


def load_labels(path: str | Path) -> tuple[Path, list[int], list[dict[str, Any]]]:
    """Read a labels YAML (module docstring): ``(scenes folder, views, labels)``; errors name the file and field."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"labels: no such file: {p}")
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise InputError(f"{p}: field '<file>': not valid YAML ({str(e).splitlines()[0]})") from e
    if not isinstance(doc, dict) or not isinstance(doc.get("labels"), list) or not doc["labels"]:
        raise InputError(f"{p}: field 'labels': expected a non-empty list of {{scene, object or box, name}}")
    root = Path(doc.get("scenes") or p.parent)
    if not root.is_absolute() and not root.is_dir():
        root = p.parent / root
    views = doc.get("views", [0])
    if not isinstance(views, list) or not views or not all(isinstance(v, int) for v in views):
        raise InputError(f"{p}: field 'views': expected a list of view indices, got {views!r}")
    out = []
    for i, item in enumerate(doc["labels"]):
        where = f"labels[{i}]"
        if (not isinstance(item, dict) or not isinstance(item.get("scene"), str)
                or not str(item.get("name", "")).strip()):
            raise InputError(f"{p}: field '{where}': expected a mapping with 'scene' and 'name', got {item!r}")
        has_obj, has_box = "object" in item, "box" in item
        if has_obj == has_box:
            raise InputError(f"{p}: field '{where}': give exactly one of 'object' (an index) and 'box' (6 numbers)")
        if has_obj and (not isinstance(item["object"], int) or item["object"] < 0):
            raise InputError(f"{p}: field '{where}.object': expected an index >= 0, got {item['object']!r}")
        if has_box:
            box = item["box"]
            ok = isinstance(box, list) and len(box) == 6 and all(isinstance(v, (int, float)) for v in box)
            if not ok or not all(box[j] < box[j + 3] for j in range(3)):
                raise InputError(f"{p}: field '{where}.box': expected [xmin, ymin, zmin, xmax, ymax, zmax], "
                                 f"got {box!r}")
        out.append({**item, "name": str(item["name"]).strip()})
    return root, views, out


def propagate_names(prototypes: list[int], names: list[str], num_prototypes: int) -> dict[str, Any]:
    """Names of prototypes from named members: majority vote per prototype (ties: alphabetically first name).

    Returns:
        ``{"names": {k: name}, "conflicts": {k: {name: votes}}, "votes": {k: {name: votes}}}``.
    """
    vocab = sorted(set(names))
    ids = torch.tensor([vocab.index(n) for n in names], dtype=torch.long)
    clusters = torch.tensor(prototypes, dtype=torch.long)
    res = few_shot_accuracy(clusters, ids, num_clusters=num_prototypes, labelled_indices=torch.arange(len(ids)))
    votes: dict[int, dict[str, int]] = {}
    for k, n in zip(prototypes, names):
        votes.setdefault(k, {}).setdefault(n, 0)
        votes[k][n] += 1
    named = {k: vocab[int(c)] for k, c in enumerate(res["cluster_labels"].tolist()) if c >= 0}
    return {"names": named, "conflicts": {k: v for k, v in votes.items() if len(v) > 1}, "votes": votes}


def run_label(labels: str, run: str | None = None, encoder: str | None = None, detector: str | None = None,
              prototypes: str | None = None, score_threshold: float | None = None) -> dict[str, Any]:
    """Name a few objects (a labels YAML) and propagate the names to the prototypes; store them beside the bank.

    Args:
        labels: the labels YAML (see ``threedq/pipeline/naming.py``: scene, object index or box, name).
        run: a ``threedq em`` work folder (its final encoder, detector and prototype bank).
        encoder, detector, prototypes: override the run's checkpoints (as in ``threedq parse``).
        score_threshold: the detector's threshold for ``object`` indices (default: the hand-on threshold,
            as in ``threedq parse``).

    Returns:
        ``{"names", "conflicts", "unnamed", "objects", "file"}``; the names go to ``prototype_names.json``.
    """
    t0 = time.time()
    root, views, items = load_labels(labels)
    artifacts = resolve_run(run, encoder, detector, prototypes)
    parser = SceneParser(artifacts, score_threshold=score_threshold)
    by_scene: dict[str, list[int]] = {}
    for i, it in enumerate(items):
        by_scene.setdefault(it["scene"], []).append(i)
    protos: list[int] = [-1] * len(items)
    matched: list[dict[str, Any]] = [{} for _ in items]
    for scene, idx in by_scene.items():
        src = root / scene
        rec = load_scene(src)
        v = check_views(views, rec, str(src))
        detected = parse_records(parser, [rec], [v])[0]["objects"]
        given = [i for i in idx if "box" in items[i]]
        boxes = np.array([items[i]["box"] for i in given], np.float32).reshape(-1, 6)
        on_boxes = parse_records(parser, [rec], [v], boxes=[(boxes, np.ones(len(given), np.float32))])[0]["objects"]
        for i in idx:
            if "box" in items[i]:
                o = on_boxes[given.index(i)]
            else:
                j = items[i]["object"]
                if j >= len(detected):
                    raise SceneValidationError(str(labels), f"labels[{i}].object", f"{scene} has {len(detected)} "
                                               f"detected object(s) (threedq parse lists them), not {j + 1}")
                o = detected[j]
            protos[i] = o["prototype"]
            matched[i] = {"scene": scene, "name": items[i]["name"], "box": o["box"], "prototype": o["prototype"],
                          "yaw_deg": o["yaw_deg"], "similarity": o["similarity"]}
    K = int(parser.bank.prototypes.shape[0])
    prop = propagate_names(protos, [it["name"] for it in items], K)
    active = [int(k) for k in parser.bank.active.nonzero().flatten().tolist()]
    unnamed = [k for k in active if k not in prop["names"]]
    doc = {"bank": parser.fingerprint, "prototypes": str(artifacts.prototypes), "labels": str(labels),
           "names": {str(k): n for k, n in sorted(prop["names"].items())},
           "conflicts": {str(k): v for k, v in sorted(prop["conflicts"].items())}, "unnamed": unnamed,
           "objects": matched}
    path = names_path(artifacts.prototypes)
    atomic_write_json(path, doc)
    for k, v in sorted(prop["conflicts"].items()):
        print(f"threedq label: conflict: prototype C{k} has members named "
              + ", ".join(f"{n} x{c}" for n, c in v.items()) + f" -> {prop['names'][k]}")
    for k, n in sorted(prop["names"].items()):
        print(f"threedq label: C{k} = {n}")
    print(f"threedq label: {len(items)} object(s) named, {len(prop['names'])} of {len(active)} prototypes named, "
          f"{len(prop['conflicts'])} conflict(s), {len(unnamed)} unnamed; wrote {path} "
          f"({time.time() - t0:.1f} s)")
    return {**doc, "file": str(path)}
