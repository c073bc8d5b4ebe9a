"""``threedq view``: a finished run, or a parse folder, as one Rerun recording (native viewer, web viewer or ``.rrd``).

It reads a ``threedq em`` run's ``metrics.json`` (Table 3), each ``rNN_eval``'s ``config.yaml`` and
``objects_test.json`` with the boxes file it read, and the dataset; or a ``threedq parse`` folder's ``summary.json``
and ``<scene>.json`` files (as round 0). Entity paths (``round`` is a sequence timeline)::

    scenes/<scene>                     Transform3D: the scene's place in a grid of scenes
    scenes/<scene>/points, cameras     Points3D fused from every view inside the scene bounds; LineStrips3D frusta
    scenes/<scene>/ground_truth        Boxes3D labelled with the category (where the scene has labels)
    scenes/<scene>/detections, yaw     Boxes3D per round "p07 0.98" coloured by prototype (none: grey); Arrows3D yaw
    prototypes/pNN                     Transform3D: the prototype's place in a grid of prototypes
    prototypes/pNN/members, template   Points3D per round: members turned into the prototype's pose; voxels at least
                                       half of them occupy
    metrics/<name>                     Scalars per round (the run's Table 3)

Convention: positions in metres in each scene's world frame R (z up) shifted by its grid place; an object's yaw
``R = -10 a mod 360`` degrees (``a`` the rotation search's index): turning the object by ``10 a`` degrees
counter-clockwise about +z aligns it with its prototype.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import yaml
from tqdm import tqdm

from threedq.data.draw import distinct_colour
from threedq.errors import InputError
from threedq.geometry.point_cloud import fuse_views, points_in_aabb
from threedq.pipeline.run_layout import RunLayout
from threedq.scene import INDEX_NAME, SceneValidationError, load_index, load_scene

__all__ = ["RunView", "SceneObjects", "read_parse_folder", "read_run", "record", "run_view"]

#: Table 3's numeric fields that are settings or counts rather than metrics.
_NOT_METRICS = ("round", "k", "pool")
_GREY = (150, 150, 150)
_TEMPLATE_VOXEL = 0.03


@dataclass
class SceneObjects:
    """The boxes of one scene in one round: ``aabb`` ``[N, 6]``, ``score`` ``[N]``, ``prototype`` ``[N]`` (-1: none)
    and ``angle_index`` ``[N]`` (-1: none)."""

    aabb: np.ndarray
    score: np.ndarray
    prototype: np.ndarray
    angle_index: np.ndarray


@dataclass
class RunView:
    """What a recording shows: the scenes (dataset folder and files), the objects of each round per scene, the
    prototypes' names, the metrics per round and the yaw steps of the rotation search."""

    data_dir: Path
    scenes: list[str]
    rounds: dict[int, dict[str, SceneObjects]]
    metrics: dict[int, dict[str, float]] = field(default_factory=dict)
    names: dict[int, str] = field(default_factory=dict)
    num_angles: int = 36
    category_names: list[str] = field(default_factory=list)
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None


def _read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: not found ({what})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({what}): {e}") from None


def _find_data_dir(given: str | Path | None, written: str | None, run: Path, source: Path) -> Path:
    """The dataset folder: ``given``, else the one ``source`` names, read from the working folder or above the run."""
    if given is not None:
        d = Path(given)
        if not (d / INDEX_NAME).is_file():
            raise InputError(f"data_dir: {d} holds no {INDEX_NAME}")
        return d
    if not written:
        raise InputError(f"{source}: field 'data.init_args.data_dir' is missing; give --data_dir")
    for base in (Path.cwd(), *run.resolve().parents):
        if (base / written / INDEX_NAME).is_file():
            return base / written
    raise InputError(f"{source}: field 'data.init_args.data_dir': {written} is not found from here or above the "
                     f"run; give --data_dir")


def _boxes_of(run: Path, written: str, split: str, source: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{scene file: (aabb, scores)}`` of the boxes file an evaluation read, found in ``run`` by its folder name."""
    path = Path(written.replace("{split}", split))
    local = run / path.parent.name / path.name
    path = local if local.is_file() else path
    try:
        with np.load(path, allow_pickle=False) as z:
            scenes, counts, aabb, scores = z["scenes"], z["counts"], z["aabb"], z["scores"]
    except FileNotFoundError:
        raise InputError(f"{source}: field 'data.init_args.boxes': {path} is not found") from None
    except (KeyError, ValueError, OSError) as e:
        raise InputError(f"{path}: not a boxes file (scenes, counts, aabb, scores): {e}") from None
    out, start = {}, 0
    for s, n in zip(scenes.tolist(), counts.tolist()):
        out[s] = (aabb[start : start + n].astype(np.float64), scores[start : start + n].astype(np.float64))
        start += n
    return out


def _round_objects(run: Path, eval_dir: Path, split: str) -> tuple[dict[str, SceneObjects], str | None, int]:
    """One round's boxes per scene, with the prototype and yaw of those its evaluation assigned."""
    cfg_path = eval_dir / "config.yaml"
    try:
        init = (yaml.safe_load(cfg_path.read_text()) or {})["data"]["init_args"]
    except FileNotFoundError:
        raise InputError(f"{cfg_path}: not found (the evaluation's settings)") from None
    except (KeyError, TypeError, yaml.YAMLError) as e:
        raise InputError(f"{cfg_path}: field 'data.init_args': unreadable ({e})") from None
    doc = _read_json(eval_dir / f"objects_{split}.json", "the evaluation's objects")
    assigned: dict[str, dict[tuple[float, ...], tuple[int, int]]] = {}
    for o in doc.get("objects", []):
        key = tuple(round(float(x), 4) for x in o["box"])
        assigned.setdefault(o["scene"], {})[key] = (int(o["prototype"]), int(o["angle_index"]))
    given = init.get("boxes")
    given = given if given and "{split}" in str(given) else None
    boxes = _boxes_of(run, given, split, cfg_path) if given else {}
    scenes = sorted(set(boxes) | set(assigned))
    out = {}
    for s in scenes:
        aabb, score = boxes.get(s, (np.zeros((0, 6)), np.zeros(0)))
        found = assigned.get(s, {})
        if not given:
            aabb = np.array([list(k) for k in found] or np.zeros((0, 6)), dtype=np.float64).reshape(-1, 6)
            score = np.ones(len(aabb))
        pa = np.array([found.get(tuple(round(float(x), 4) for x in b), (-1, -1)) for b in aabb], dtype=np.int64)
        pa = pa.reshape(-1, 2)
        out[s] = SceneObjects(aabb, score, pa[:, 0], pa[:, 1])
    return out, init.get("data_dir"), int(doc.get("num_angles", 36))


def read_run(run: str | Path, data_dir: str | Path | None = None, split: str = "test") -> RunView:
    """The rounds of a ``threedq em`` run that have an evaluation (``rNN_eval``), each with its boxes and
    assignments, and the run's Table 3."""
    layout = RunLayout(Path(run))
    if not layout.work.is_dir():
        raise InputError(f"run: {layout.work} is not a folder")
    rounds_found = [r for r in layout.rounds("eval") if (layout.round(r, "eval") / f"objects_{split}.json").is_file()]
    if not rounds_found:
        raise InputError(f"run: {layout.work} has no finished round (no rNN_eval/objects_{split}.json); run "
                         f"'threedq em' to the end of round 0 first")
    rounds, written, num_angles = {}, None, 36
    for r in rounds_found:
        rounds[r], written_r, num_angles = _round_objects(layout.work, layout.round(r, "eval"), split)
        written = written or written_r
    d = _find_data_dir(data_dir, written, layout.work, layout.round(rounds_found[-1], "eval") / "config.yaml")
    metrics: dict[int, dict[str, float]] = {}
    if (layout.work / "metrics.json").is_file():
        for row in _read_json(layout.work / "metrics.json", "the run's metrics").get("table3", []):
            metrics[int(row["round"])] = {k: float(v) for k, v in row.items() if k not in _NOT_METRICS
                                          and isinstance(v, (int, float)) and not isinstance(v, bool)}
    index = load_index(d)
    scenes = sorted(set().union(*(set(o) for o in rounds.values())) | set(index.files(split)))
    return RunView(d, scenes, rounds, metrics, {}, num_angles, list(index.categories), index.scene_bounds)


def read_parse_folder(folder: str | Path) -> RunView:
    """The objects of a ``threedq parse`` folder (its ``summary.json`` and ``<scene>.json``) as round 0."""
    folder = Path(folder)
    summary = _read_json(folder / "summary.json", "a parse folder's summary")
    objects: dict[str, SceneObjects] = {}
    names: dict[int, str] = {}
    roots = set()
    for entry in summary.get("files", []):
        doc = _read_json(folder / entry["json"], "a parsed scene")
        obs = doc.get("objects", [])
        scene = Path(doc["scene"])
        roots.add(scene.parent)
        for o in obs:
            if o.get("name"):
                names[int(o["prototype"])] = o["name"]
        objects[str(scene)] = SceneObjects(np.array([o["box"] for o in obs], dtype=np.float64).reshape(-1, 6),
                                           np.array([o["score"] for o in obs], dtype=np.float64),
                                           *(np.array([o[k] for o in obs], dtype=np.int64)
                                             for k in ("prototype", "angle_index")))
    if not objects:
        raise InputError(f"{folder / 'summary.json'}: field 'files': no parsed scene")
    return RunView(Path("/"), sorted(objects), {0: objects}, {}, names, 36, [])


def _frusta(K: np.ndarray, world_T_cam: np.ndarray, hw: tuple[int, int], depth: float = 0.15) -> list[np.ndarray]:
    """Each view's frustum as one line strip (apex, 4 image corners at ``depth``, back)."""
    h, w = hw
    strips = []
    for k, T in zip(K, world_T_cam):
        uv = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
        rays = np.linalg.solve(k.astype(np.float64), np.c_[uv, np.ones(4)].T).T
        corners = rays / rays[:, 2:] * depth
        world = (T[:3, :3] @ corners.T).T + T[:3, 3]
        apex = T[:3, 3]
        strips.append(np.array([apex, world[0], world[1], apex, world[2], world[3], apex, world[0], world[3],
                                world[2], world[1]], dtype=np.float32))
    return strips


def member_mask(points: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """``[N]`` bool: an object's points, those in its box above its floor (1 cm over the box's bottom)."""
    return points_in_aabb(points, aabb) & (points[:, 2] > aabb[2] + 0.01)


def aligned_member_points(points: np.ndarray, aabb: np.ndarray, angle_index: int, num_angles: int,
                          mask: np.ndarray | None = None) -> np.ndarray:
    """An object's points (:func:`member_mask`, or ``mask`` when given) relative to the box's bottom centre, turned by
    ``360 a / num_angles`` degrees counter-clockwise about +z: into its prototype's pose."""
    inside = points[member_mask(points, aabb) if mask is None else mask]
    centre = np.array([(aabb[0] + aabb[3]) / 2, (aabb[1] + aabb[4]) / 2, aabb[2]])
    t = 2 * math.pi * angle_index / num_angles
    rot = np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]])
    return ((inside - centre) @ rot.T).astype(np.float32)


def template_voxels(members: list[np.ndarray], voxel: float = _TEMPLATE_VOXEL) -> np.ndarray:
    """``[T, 3]`` centres of the voxels that at least half of the members (aligned point sets) occupy."""
    counts: dict[tuple[int, int, int], int] = {}
    for pts in members:
        for cell in {tuple(c) for c in np.floor(pts / voxel).astype(np.int64).tolist()}:
            counts[cell] = counts.get(cell, 0) + 1
    need = max(1, math.ceil(len(members) / 2))
    cells = np.array([c for c, n in counts.items() if n >= need], dtype=np.float64).reshape(-1, 3)
    return ((cells + 0.5) * voxel).astype(np.float32)


def _label(k: int, score: float, names: dict[int, str]) -> str:
    if k < 0:
        return f"{score:.2f}"
    return f"{names[k]} (p{k:02d}) {score:.2f}" if k in names else f"p{k:02d} {score:.2f}"


def _grid_place(i: int, n: int, spacing: float) -> list[float]:
    cols = max(1, math.ceil(math.sqrt(n)))
    return [float((i % cols) * spacing), float(-(i // cols) * spacing), 0.0]


def _blueprint() -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="/scenes", name="scenes"),
        rrb.Vertical(rrb.Spatial3DView(origin="/prototypes", name="prototypes"),
                     rrb.TimeSeriesView(origin="/metrics", name="metrics per round")),
        column_shares=[3, 2]))  # fmt: skip


def record(view: RunView, rec: Any, points_per_scene: int = 6000, voxel_size: float = 0.02,
           max_scenes: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Log ``view`` into the Rerun recording stream ``rec``; returns counts (scenes, points, boxes per round)."""
    import rerun as rr

    scenes = view.scenes[:max_scenes] if max_scenes else view.scenes
    rec.send_blueprint(_blueprint())
    spacing = 0.0
    members: dict[int, dict[int, list[tuple[np.ndarray, np.ndarray]]]] = {r: {} for r in view.rounds}
    counts: dict[str, Any] = {"scenes": 0, "points": 0, "boxes": {r: 0 for r in view.rounds}}
    loaded = []
    for s in tqdm(scenes, desc="threedq view: scenes", disable=not progress, dynamic_ncols=True):
        path = view.data_dir / s
        try:
            loaded.append((s, load_scene(path, validate=False)))
        except (SceneValidationError, OSError) as e:
            print(f"threedq view: {e}; scene left out", file=sys.stderr)
    for _, recd in loaded:
        pts = recd.world_T_cam[:, :3, 3]
        spacing = max(spacing, float(np.ptp(pts[:, 0])), float(np.ptp(pts[:, 1])))
    spacing = max(spacing + 0.5, 2.0)
    for i, (s, recd) in enumerate(loaded):
        name = Path(s).stem
        base = f"scenes/{name}"
        rec.log(base, rr.Transform3D(translation=_grid_place(i, len(loaded), spacing)), static=True)
        region = None if view.bounds is None else np.r_[view.bounds[0], view.bounds[1]]
        points, colours = fuse_views(recd.rgb, recd.depth, recd.K, recd.world_T_cam, voxel_size, points_per_scene, i,
                                     region)
        rec.log(f"{base}/points", rr.Points3D(points, colors=colours, radii=rr.Radius.ui_points(2.0)), static=True)
        rec.log(f"{base}/cameras", rr.LineStrips3D(_frusta(recd.K, recd.world_T_cam, recd.image_size),
                                                   colors=[(170, 170, 170)], radii=rr.Radius.ui_points(0.5)),
                static=True)
        counts["scenes"] += 1
        counts["points"] += int(points.shape[0])
        if recd.boxes is not None and len(recd.boxes):
            b = np.asarray(recd.boxes, dtype=np.float64)
            cats = [view.category_names[c] if 0 <= c < len(view.category_names) else str(c) for c in recd.categories]
            rec.log(f"{base}/ground_truth", rr.Boxes3D(
                centers=b[:, :3], half_sizes=b[:, 3:6] / 2, labels=cats, colors=[(255, 255, 255)],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(y)) for y in b[:, 6]]),
                static=True)  # fmt: skip
        for r, per_scene in view.rounds.items():
            rec.set_time("round", sequence=r)
            obj = per_scene.get(s) or per_scene.get(str(view.data_dir / s))
            if obj is None or len(obj.aabb) == 0:
                for part in ("detections", "yaw"):
                    rec.log(f"{base}/{part}", rr.Clear(recursive=False))
                continue
            a = obj.aabb
            centre, half = (a[:, :3] + a[:, 3:]) / 2, (a[:, 3:] - a[:, :3]) / 2
            colours_k = [distinct_colour(int(k)) if k >= 0 else _GREY for k in obj.prototype]
            labels = [_label(int(k), float(sc), view.names) for k, sc in zip(obj.prototype, obj.score)]
            rec.log(f"{base}/detections", rr.Boxes3D(centers=centre, half_sizes=half, labels=labels, colors=colours_k))
            has = obj.prototype >= 0
            yaw = -2 * np.pi * obj.angle_index[has] / view.num_angles
            length = np.maximum(half[has, :2].max(1), 0.05)
            vec = np.stack([np.cos(yaw) * length, np.sin(yaw) * length, np.zeros_like(yaw)], 1)
            top = centre[has] + np.c_[np.zeros((int(has.sum()), 2)), half[has, 2]]
            rec.log(f"{base}/yaw", rr.Arrows3D(origins=top, vectors=vec,
                                              colors=[c for c, h in zip(colours_k, has) if h]))
            counts["boxes"][r] += len(a)
            for n in np.flatnonzero(has):
                mask = member_mask(points, a[n])
                if mask.any():
                    pts_n = aligned_member_points(points, a[n], int(obj.angle_index[n]), view.num_angles, mask)
                    members[r].setdefault(int(obj.prototype[n]), []).append((pts_n, colours[mask]))
        rec.reset_time()
    ids = sorted(set().union(*(set(m) for m in members.values())))
    for k in ids:
        rec.log(f"prototypes/p{k:02d}", rr.Transform3D(translation=_grid_place(k, ids[-1] + 1, 0.8)), static=True)
    for r in view.rounds:
        rec.set_time("round", sequence=r)
        for k in ids:
            if k not in members[r]:
                rec.log(f"prototypes/p{k:02d}/members", rr.Clear(recursive=False))
                rec.log(f"prototypes/p{k:02d}/template", rr.Clear(recursive=False))
        for k in sorted(members[r]):
            base = f"prototypes/p{k:02d}"
            pts = [m[0] for m in members[r][k]]
            label = f"{view.names[k]} (p{k:02d})" if k in view.names else f"p{k:02d}"
            rec.log(f"{base}/template", rr.Points3D(template_voxels(pts), colors=[distinct_colour(k)],
                                                    radii=_TEMPLATE_VOXEL / 2, labels=[f"{label}: {len(pts)} objects"]))
            rec.log(f"{base}/members", rr.Points3D(np.concatenate(pts), colors=np.concatenate(
                [m[1] for m in members[r][k]]), radii=rr.Radius.ui_points(1.5)))
        for name, value in view.metrics.get(r, {}).items():
            rec.log(f"metrics/{name}", rr.Scalars(value))
    rec.reset_time()
    return counts


def run_view(run: str, save: str | None = None, serve: bool = False, port: int = 9090, data_dir: str | None = None,
             split: str = "test", max_scenes: int | None = None, points_per_scene: int = 6000, voxel_size: float = 0.02,
             progress: bool = True) -> dict[str, Any]:
    """Look at a run in 3D: its scenes, every round's detections with prototype and yaw, the prototypes, the metrics.

    Args:
        run: a ``threedq em`` work folder, or a ``threedq parse`` output folder (it holds ``summary.json``).
        save: write the recording to this ``.rrd`` file (open it with ``rerun FILE``) instead of opening a viewer.
        serve: serve the web viewer on ``port`` and print its address (until interrupted).
        port: the web viewer's port with ``serve``.
        data_dir: the dataset folder (default: the one the run's evaluation read).
        split: the split whose scenes are shown (a run's).
        max_scenes: show only the first scenes (default: all of the split).
        points_per_scene: the most points of each scene's fused cloud.
        voxel_size: the voxel edge (metres) the fused cloud is thinned on.
        progress: show a progress bar.

    Returns:
        counts: scenes, points, boxes per round, seconds, and the file written (with ``save``).
    """
    try:
        import rerun as rr
    except ImportError:
        raise InputError("threedq view needs rerun-sdk: pip install 'threedq[view]'") from None
    if save and serve:
        raise InputError("save, serve: give one of them (a file, or the web viewer)")
    if max_scenes is not None and max_scenes < 1:
        raise InputError(f"max_scenes: expected at least 1, got {max_scenes}")
    if points_per_scene < 1 or not voxel_size > 0:
        raise InputError("points_per_scene, voxel_size: expected a positive count and edge")
    t0 = time.time()
    folder = Path(run)
    view = read_parse_folder(folder) if (folder / "summary.json").is_file() else read_run(folder, data_dir, split)
    rec = rr.RecordingStream("threedq", recording_id=f"threedq-view-{folder.resolve().name}")
    rec.set_log_time_enabled(False)
    url = None
    if save:
        out = Path(save)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(out.name + ".partial")
        rec.save(tmp)
    elif serve:
        grpc = rec.serve_grpc()
        rr.serve_web_viewer(web_port=port, open_browser=False, connect_to=grpc)
        url = f"http://localhost:{port}/?url={quote(grpc, safe='')}"
    else:
        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise InputError("no display for Rerun's native viewer (DISPLAY and WAYLAND_DISPLAY are unset): write a "
                             "file with --save run.rrd, or serve the web viewer with --serve true")
        try:
            rec.spawn()
        except Exception as e:  # noqa: BLE001 - no display, no viewer binary: one line and the alternatives
            raise InputError(f"could not start Rerun's viewer ({e}); write a file with --save run.rrd, or serve "
                             f"the web viewer with --serve true") from None
    counts = record(view, rec, points_per_scene, voxel_size, max_scenes, progress)
    rec.flush()
    if save:
        rec.disconnect()
        tmp.replace(out)
        counts.update(file=str(out), megabytes=round(out.stat().st_size / 2**20, 2))
    counts["seconds"] = round(time.time() - t0, 2)
    boxes = ", ".join(f"round {r}: {n}" for r, n in counts["boxes"].items())
    where = (f"wrote {out} ({counts['megabytes']} MB)" if save
             else f"web viewer at {url}" if serve else "sent to the viewer")
    print(f"threedq view: {counts['scenes']} scene(s), {counts['points']} points, boxes {boxes}; {where} "
          f"in {counts['seconds']} s")
    if serve:
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass
    return counts
