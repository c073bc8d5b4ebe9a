"""``threedq parse``: parse scenes a trained run has never seen; write JSON + PNG per scene (paper Sec. 4.5, Fig. 4).

The parsing and its conventions: :mod:`threedq.pipeline.parse`; the renders: :mod:`threedq.pipeline.renders`.
"""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import yaml
from jsonargparse.typing import NonNegativeInt, PositiveInt
from tqdm import tqdm

from threedq.atomic_io import atomic_write_bytes, atomic_write_json
from threedq.data.box_files import load_boxes_file
from threedq.data.view_colour import apply_gains
from threedq.datamodules.scene_folder import sensor_corrections
from threedq.errors import InputError
from threedq.locks import hold_folder
from threedq.pipeline.parse import (
    SceneParser,
    check_views,
    find_scenes,
    load_names,
    load_or_make_appearance,
    parse_figure,
    parse_records,
    resolve_run,
    scene_targets,
)
from threedq.pipeline.renders import load_view_decoder, prototype_gallery, replaced_render
from threedq.pipeline.run_layout import RunLayout
from threedq.scene import SceneRecord, SceneValidationError, load_scene

if TYPE_CHECKING:
    from torch import Tensor

    from threedq.stages.viewpred import ViewPrediction

__all__ = ["run_parse"]


def _png(path: Path, img: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", img[:, :, ::-1])
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, png.tobytes())


def _scene_name(file: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(Path(file).with_suffix("")))


def _run_data_args(run: str | Path | None) -> dict[str, Any]:
    """The ``data.init_args`` of a ``threedq em`` run's final quantizer's saved config (``{}`` without one)."""
    if run is None:
        return {}
    layout = RunLayout(Path(run))
    done = layout.rounds("quantizer")
    cfg = layout.round(done[-1], "quantizer") / "config.yaml" if done else None
    if cfg is None or not cfg.is_file():
        return {}
    data = (yaml.safe_load(cfg.read_text()) or {}).get("data") or {}
    return data.get("init_args") or {}


def spread_views(num_views: int, n: int) -> list[int]:
    """``n`` view indices spread evenly over ``num_views`` views (first and last included; all when at most ``n``)."""
    if num_views <= n:
        return list(range(num_views))
    return sorted({round(i * (num_views - 1) / (n - 1)) for i in range(n)}) if n > 1 else [0]


def _view_decoder(artifacts: Any) -> Any:
    """The run's view decoder, for ``renders``."""
    if artifacts.viewpred is None:
        raise FileNotFoundError("renders: the run has no view-prediction checkpoint (00_viewpred) to decode with")
    return load_view_decoder(artifacts.viewpred)


def _load_batch(root: Path, batch: list[str], views: list[int] | int,
                box_sets: dict[str, tuple[np.ndarray, np.ndarray]] | None, boxes: str | None, failed: list[str],
                align_floor: bool = False) -> tuple[list[SceneRecord], list[list[int]], list[str]]:
    """Load a batch of scene files and check their input views (a list, or a number ``n``: :func:`spread_views`).

    A scene that cannot be loaded, whose views are out of range, or that ``box_sets`` does not cover is skipped, its
    one-line reason appended to ``failed`` and printed. ``align_floor``: poses corrected by the floor.

    Returns:
        The loaded records, their chosen view indices and the files they came from (``batch`` order).
    """
    recs, chosen, ok_files = [], [], []
    for f in batch:
        src = root / f
        try:
            if box_sets is not None and f not in box_sets:
                raise SceneValidationError(str(boxes), f, "the boxes file has no boxes for this scene")
            rec = load_scene(src)
            if align_floor:
                rec.world_T_cam, gains = sensor_corrections(src, rec)
                rec.rgb = apply_gains(rec.rgb, gains)
            chosen.append(check_views(spread_views(rec.num_views, views) if isinstance(views, int) else list(views),
                                      rec, str(src)))
            recs.append(rec)
            ok_files.append(f)
        except (SceneValidationError, ValueError, OSError) as e:
            failed.append(str(e).splitlines()[0] if str(e) else f"{src}: {type(e).__name__}")
            print(f"threedq parse: skipped {failed[-1]}", file=sys.stderr)
    return recs, chosen, ok_files


def _write_pictures(outp: Path, name: str, rec: SceneRecord, v: list[int], doc: dict[str, Any], features: Tensor,
                    parser: SceneParser, appearance: dict[str, Tensor] | None, names: dict[int, str],
                    decoder: ViewPrediction | None, pictures: bool, gallery_done: bool) -> bool:
    """Write ``<name>.png`` (with ``pictures``), and with a ``decoder`` ``gallery.png`` (unless ``gallery_done``) and
    ``<name>_replaced.png``; returns whether ``gallery.png`` is written by now."""
    if pictures:
        _png(outp / f"{name}.png", parse_figure(rec, v, doc, parser, appearance))
    if decoder is not None:
        if not gallery_done:
            _png(outp / "gallery.png", prototype_gallery(parser, decoder, rec, appearance, names, view=v[0]))
            gallery_done = True
        others = [i for i in range(rec.num_views) if i not in v]
        if others:
            _png(outp / f"{name}_replaced.png", replaced_render(parser, decoder, rec, doc, features, others[0]))
    return gallery_done


def _write_summary(outp: Path, files: list[str], parsed: list[dict[str, Any]], failed: list[str],
                   names: dict[int, str], t0: float, models: dict[str, Any]) -> dict[str, Any]:
    """Write ``outp/summary.json``, print a one-line account of the run and return the summary."""
    summary = {"scenes": len(files), "parsed": len(parsed), "failed": failed,
               "objects": sum(p["objects"] for p in parsed), "named_prototypes": len(names),
               "seconds": round(time.time() - t0, 2), "models": models, "files": parsed}
    atomic_write_json(outp / "summary.json", summary)
    print(f"threedq parse: {len(parsed)} of {len(files)} scene(s) parsed, {summary['objects']} object(s), "
          f"{len(failed)} failed; wrote {outp}")
    return summary


def run_parse(scenes: str, out: str, run: str | None = None, encoder: str | None = None, detector: str | None = None,
              prototypes: str | None = None, views: list[int] | None = None, split: str | None = None,
              boxes: str | None = None, score_threshold: float | None = None, precision: str = "fp32",
              batch_size: PositiveInt = 4, pictures: bool = True, renders: bool = False,
              appearance_scenes: NonNegativeInt = 100, sensor_captures: bool | None = None, view: bool = False,
              progress: bool = True) -> dict[str, Any]:
    """Parse scenes with a trained run: boxes, prototype id (C), yaw (R), similarity and name per object.

    Args:
        scenes: one scene ``.npz``, a dataset folder with ``index.json``, or a folder of ``.npz`` files (import a
            capture first: ``threedq data import --format F SRC --out D``).
        out: output folder: ``<scene>.json`` and ``<scene>.png`` per scene, ``summary.json``.
        run: a ``threedq em`` work folder (its final encoder, detector and prototype bank).
        encoder: overrides the run's encoder of the prototypes (a stage checkpoint).
        detector: overrides the run's detector (a detector or self-labelling checkpoint).
        prototypes: overrides the run's prototype bank (a quantizer checkpoint).
        views: the views that are inputs, the same for every scene (negative counts from the end); default: as many
            as the run's prototype bank was fitted on (its final quantizer's ``num_input_views``: 1 for the embedded
            data, 3 for the shape-only data and scene folders, ``threedq.pipeline.presets``), spread evenly over each
            scene's views (view 0 alone for one).
        split: with a dataset folder, parse only this split.
        boxes: a boxes file (``{scene file: (aabb, scores)}``, the layout of ``detections_<split>.npz``; scene files
            relative to the dataset folder) whose boxes are matched instead of the detector's.
        score_threshold: objectness of the boxes kept (default: the detector's hand-on threshold).
        precision: ``fp32`` or ``bf16`` (autocast of the encoder and detector; ``docs/benchmarks.md``: faster,
            and the same prototype and yaw for >= 99% of objects on the embedded data).
        batch_size: scenes encoded together.
        pictures: write ``<scene>.png``.
        renders: also write ``gallery.png`` (every prototype decoded by the run's view decoder at 4 azimuths) and
            per scene ``<scene>_replaced.png`` (a view that was not an input: real, decoded, and decoded with the
            objects replaced by their prototypes at the inferred yaw).
        appearance_scenes: training scenes used once to picture the prototypes in the bird's-eye view (0: none).
        sensor_captures: correct each scene's poses and colours by the floor its views see first, as a DataModule
            reading sensor captures does (:func:`~threedq.datamodules.scene_folder.sensor_corrections`); default: as
            the run's data was read (its final quantizer's ``config.yaml``), else off.
        view: open the parse in Rerun's viewer when done (:func:`threedq.pipeline.view.run_view`; ``threedq view
            --run OUT --save FILE`` writes it to a file instead).
        progress: show a progress bar.

    Returns:
        the summary (also written as ``summary.json``): scenes parsed, failed (one line each), objects, seconds.
    """
    if views is not None and not views:
        raise InputError("views: expected at least one view index")
    outp = Path(out)
    if outp.exists() and not outp.is_dir():
        raise InputError(f"out: {outp} exists and is not a folder")
    artifacts = resolve_run(run, encoder, detector, prototypes)
    run_data = _run_data_args(run)
    sensor_captures = bool(run_data.get("sensor_captures", False)) if sensor_captures is None else sensor_captures
    chosen_views: list[int] | int = list(views) if views is not None else int(run_data.get("num_input_views", 1))
    root, files = find_scenes(scenes, split)
    parser = SceneParser(artifacts, score_threshold=score_threshold, precision=precision)
    names = load_names(artifacts.prototypes, parser.bank)
    box_sets = load_boxes_file(boxes) if boxes else None
    appearance = load_or_make_appearance(parser, appearance_scenes, progress) if pictures or renders else None
    decoder = _view_decoder(artifacts) if renders else None
    with hold_folder(outp):
        outp.mkdir(parents=True, exist_ok=True)
        failed: list[str] = []
        parsed: list[dict[str, Any]] = []
        gallery_done = False
        t0 = time.time()
        bar = tqdm(total=len(files), desc="threedq parse", unit="scene", disable=not progress, dynamic_ncols=True)
        for s in range(0, len(files), batch_size):
            recs, chosen, ok_files = _load_batch(root, files[s : s + batch_size], chosen_views, box_sets, boxes,
                                                 failed, sensor_captures)
            given = None if box_sets is None else [box_sets[f] for f in ok_files]
            targets = scene_targets(parser, recs, sensor_captures) if given is None else None
            results = parse_records(parser, recs, chosen, names, batch_size, given, targets)
            for f, rec, v, res in zip(ok_files, recs, chosen, results):
                features = res.pop("_features")
                doc = {"scene": str(root / f), **res, "models": artifacts.to_dict(),
                       "score_threshold": parser.score_threshold}
                name = _scene_name(f)
                atomic_write_json(outp / f"{name}.json", doc)
                gallery_done = _write_pictures(outp, name, rec, v, doc, features, parser, appearance, names, decoder,
                                               pictures, gallery_done)
                parsed.append({"scene": str(root / f), "json": f"{name}.json", "objects": len(doc["objects"])})
            bar.update(len(files[s : s + batch_size]))
        bar.close()
        summary = _write_summary(outp, files, parsed, failed, names, t0, artifacts.to_dict())
    if view and parsed:
        from threedq.pipeline.view import run_view

        run_view(str(outp), progress=progress)
    return summary
