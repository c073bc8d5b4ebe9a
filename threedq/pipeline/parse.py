"""Scene parsing with a trained run (paper Sec. 4.5, Fig. 4); the command is :mod:`threedq.pipeline.parse_command`.

Per scene: encode the input view(s), detect 3D boxes (the run's final detector at its hand-on threshold), crop each
box out of the prototypes' feature space and match it against every prototype at every yaw. Per object: box, score,
prototype id ``C``, yaw ``R``, similarity, ``yaw_confidence`` (best similarity minus the best more than 30 degrees
away) and a name when the prototypes were named (``threedq label``). :func:`resolve_run` finds the newest finished
round's parts in a ``threedq em`` folder (:class:`~threedq.pipeline.run_layout.RunLayout`).

Convention: boxes in frame R, the record's world frame (metres, z up), axis-aligned
``(xmin, ymin, zmin, xmax, ymax, zmax)``; with an imported capture (``meta.canonical_T_capture``) each object
also gets ``capture_T_box`` in the capture's own frame. ``angle_index`` ``a`` is the search's: rotating the
object by ``10 a`` degrees counter-clockwise aligns it with its prototype; ``yaw_deg`` is the object's yaw
relative to its prototype's canonical pose, ``-10 a mod 360`` (the paper's "R": the prototype turned by ``R``
degrees counter-clockwise about +z looks like the object).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import yaml
from torch import Tensor
from tqdm import tqdm

from threedq.atomic_io import atomic_write_bytes
from threedq.data.draw import crop_birds_eye, distinct_colour, draw_boxes
from threedq.data.formats.normalise import boxes_to_capture_frame
from threedq.datamodules.scene_folder import RENDER_PROPOSALS, SENSOR_PROPOSALS
from threedq.errors import InputError
from threedq.geometry import crop_boxes, rotate_yaw, unproject_rgbd_occupied, yaw_angles
from threedq.pipeline.run_layout import RunLayout
from threedq.proposals import propose_boxes
from threedq.quantization.prototypes import PrototypeBank, prototype_crops
from threedq.quantization.rotation_search import yaw_confidence
from threedq.scene import INDEX_NAME, SceneRecord, SceneValidationError, load_index, load_scene
from threedq.stages.base import EncoderStage, stage_arguments
from threedq.stages.checkpoint import (
    DEFAULT_GRID,
    checkpoint_hparams,
    checkpoint_state,
    encoder_state_from_checkpoint,
    load_checkpoint,
)
from threedq.stages.detector import Detector
from threedq.stages.quantizer import bank_occupancy_floor, load_bank_state

__all__ = ["RunArtifacts", "check_views", "prototype_top_view", "SceneParser", "find_scenes", "load_names",
           "names_path", "parse_records", "resolve_run", "scene_batch"]

NAMES_FILE = "prototype_names.json"
APPEARANCE_FILE = "prototype_appearance.pt"


@dataclass(frozen=True)
class RunArtifacts:
    """The checkpoints a parse uses (see the module docstring)."""

    encoder: Path
    detector: Path
    prototypes: Path
    viewpred: Path | None = None
    run: Path | None = None

    def to_dict(self) -> dict[str, str | None]:
        return {k: (None if v is None else str(v)) for k, v in self.__dict__.items()}


def resolve_run(run: str | Path | None = None, encoder: str | Path | None = None, detector: str | Path | None = None,
                prototypes: str | Path | None = None) -> RunArtifacts:
    """The final encoder, detector and prototype bank of a ``threedq em`` run folder (explicit paths win).

    Raises:
        FileNotFoundError: a part is neither given nor found (the message names the run folder and the part).
    """
    r = Path(run) if run is not None else None
    if r is not None and not r.is_dir():
        raise FileNotFoundError(f"run: no such folder: {r}")
    layout = RunLayout(r) if r is not None else None

    def need(part: str, given: str | Path | None, found: Path | None, what: str) -> Path:
        if given is not None:
            p = Path(given)
            if not p.is_file():
                raise FileNotFoundError(f"{part}: no such file: {p}")
            return p
        if found is None:
            where = f"run {r}" if r is not None else "no --run given"
            raise FileNotFoundError(f"{part}: {where}: no finished {what}; give --{part}")
        return found

    bank = need("prototypes", prototypes, layout.final_quantizer() if layout else None,
                "quantizer stage (rNN_quantizer)")
    det = need("detector", detector, layout.final_detector() if layout else None,
               "detector (02_detector or rNN_self_labelling)")
    enc = Path(encoder) if encoder is not None else bank
    if not enc.is_file():
        raise FileNotFoundError(f"encoder: no such file: {enc}")
    vp = layout.viewpred_checkpoint() if layout else None
    return RunArtifacts(encoder=enc, detector=det, prototypes=bank, viewpred=vp, run=r)


def names_path(prototypes: str | Path) -> Path:
    """Where the names of a prototype bank are stored: beside its checkpoint."""
    return Path(prototypes).parent / NAMES_FILE


def bank_fingerprint(bank: PrototypeBank) -> str:
    """A short hash of the bank's prototypes (names and appearances are refused for another bank)."""
    h = hashlib.sha256()
    h.update(bank.prototypes.detach().cpu().contiguous().numpy().tobytes())
    h.update(bank.active.cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def load_names(prototypes: str | Path, bank: PrototypeBank | None = None) -> dict[int, str]:
    """``{prototype id: name}`` stored by ``threedq label`` beside ``prototypes`` ({} when none)."""
    p = names_path(prototypes)
    if not p.is_file():
        return {}
    try:
        obj = json.loads(p.read_text())
        names = {int(k): str(v) for k, v in obj["names"].items()}
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise InputError(f"{p}: field 'names': unreadable ({type(e).__name__}: {e})") from e
    if bank is not None and obj.get("bank") != bank_fingerprint(bank):
        raise InputError(f"{p}: field 'bank': these names belong to another prototype bank; run threedq label again")
    return names


def _checked_grid(a: dict[str, Any], b: dict[str, Any], pa: Path, pb: Path) -> None:
    for k in DEFAULT_GRID:
        va, vb = a.get(k), b.get(k)
        if va is not None and vb is not None and list(np.atleast_1d(va)) != list(np.atleast_1d(vb)):
            raise InputError(f"{pb}: field '{k}': {vb} differs from {pa}'s {va}: the checkpoints come from other grids")


class SceneParser(torch.nn.Module):
    """The run's detector, encoder and prototype bank, ready to parse batches of scenes.

    Args:
        artifacts: from :func:`resolve_run`.
        score_threshold: objectness of the boxes kept (default: the detector's hand-on threshold).
        precision: ``"fp32"`` or ``"bf16"`` (autocast of the encoder and the detector head; crops and the rotation
            search stay fp32).
    """

    def __init__(self, artifacts: RunArtifacts, score_threshold: float | None = None, precision: str = "fp32") -> None:
        super().__init__()
        if precision not in ("fp32", "bf16"):
            raise InputError(f"precision: expected 'fp32' or 'bf16', got {precision!r}")
        self.precision = precision
        self.artifacts = artifacts
        det_hp, q_hp = checkpoint_hparams(artifacts.detector), checkpoint_hparams(artifacts.prototypes)
        _checked_grid(q_hp, det_hp, artifacts.prototypes, artifacts.detector)
        names = set(stage_arguments(Detector)) - {"encoder_ckpt"}
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in det_hp.items() if k in names}
        kw.update(channels_last=True, freeze_encoder=True, image_every_n_steps=0,
                  anchor_size=load_checkpoint(artifacts.detector).anchor)
        self.detector = Detector(**kw)
        state = checkpoint_state(artifacts.detector)
        part = {k: v for k, v in state.items() if k.startswith(("encoder.", "head."))}
        if not any(k.startswith("head.") for k in part):
            raise InputError(f"{artifacts.detector}: field 'state_dict': no 'head.*' weights (not a detector "
                             "checkpoint)")
        missing, _ = self.detector.load_state_dict(part, strict=False)
        missing = [k for k in missing if k.startswith(("encoder.", "head."))]
        if missing:
            raise InputError(f"{artifacts.detector}: field 'state_dict': missing {missing[0]} "
                             f"(and {len(missing) - 1} more)")
        for k in ("num_prototypes", "crop_size", "num_angles"):
            if k not in q_hp:
                raise InputError(f"{artifacts.prototypes}: field 'hyper_parameters.{k}': missing (not a quantizer "
                                 "checkpoint)")
        self.bank = PrototypeBank(q_hp["num_prototypes"], self.detector.feature_dim, q_hp["crop_size"],
                                  q_hp["num_angles"], q_hp.get("init_threshold", 0.8),
                                  q_hp.get("search_method", "fast"))
        load_bank_state(self.bank, str(artifacts.prototypes))
        if self.bank.num_active == 0:
            raise InputError(f"{artifacts.prototypes}: field 'bank.active': the bank has no prototype")
        enc = encoder_state_from_checkpoint(artifacts.encoder)
        own = self.detector.encoder.state_dict()
        same = own.keys() == enc.keys() and all(torch.equal(own[k], enc[k].to(own[k].dtype)) for k in own)
        #: the encoder of the prototypes when it is not the detector's (None: one encoding serves both)
        self.q_stage: EncoderStage | None = None
        if not same:
            g = {k: (tuple(v) if isinstance(v, list) else v) for k, v in self.detector.grid_fields.items()}
            self.q_stage = EncoderStage(**g, freeze_encoder=True, channels_last=True)
            try:
                self.q_stage.encoder.load_state_dict(enc)
            except RuntimeError as e:
                raise InputError(f"{artifacts.encoder}: field 'state_dict': does not fit the grid ({e})") from e
        self.score_threshold = float(det_hp.get("score_threshold", 0.9) if score_threshold is None else score_threshold)
        self.crop_size = int(q_hp["crop_size"])
        self.num_angles = int(q_hp["num_angles"])
        #: the bank's crop weighting (:func:`~threedq.quantization.prototypes.prototype_crops`; None: plain cosine)
        self.occupancy_floor = bank_occupancy_floor(artifacts.prototypes)
        self.fingerprint = bank_fingerprint(self.bank)
        self.eval()

    @property
    def device(self) -> torch.device:
        return self.bank.prototypes.device

    @torch.no_grad()
    def forward(self, batch: dict[str, Tensor], boxes: list[tuple[Tensor, Tensor]] | None = None,
                targets: list[tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, Any]:
        """Parse a batch of scenes (:func:`scene_batch` layout: ``rgb`` ``[B, V, 3, H, W]``, ``depth``, ``K``,
        ``R_T_cam``; all V views are inputs).

        Args:
            batch: the scenes.
            boxes: per scene ``(aabb [P, 6], scores [P])`` to match instead of the detector's boxes.
            targets: per scene ``(aabb [Q, 6], scores [Q])`` the detections are refined against instead of the
                input views' pseudo-boxes (a ``refine_to: scene`` detector: :func:`scene_targets`).

        Returns:
            per scene lists: ``aabb`` ``[P, 6]``, ``score`` ``[P]``, ``prototype`` ``[P]``, ``angle`` ``[P]``,
            ``similarity`` ``[P]``, ``yaw_confidence`` ``[P]`` (:func:`yaw_margin_steps`); and ``features``
            ``[B, C, Z', Y', X']`` (the prototypes' feature space),
            ``timings`` (seconds per part).
        """
        t: dict[str, float] = {}
        t0 = time.perf_counter()
        rgb, depth, K, pose = (batch[k].to(self.device) for k in ("rgb", "depth", "K", "R_T_cam"))
        det = self.detector
        B, V = rgb.shape[:2]
        views = (rgb.flatten(0, 1), depth.flatten(0, 1), K.flatten(0, 1), pose.flatten(0, 1))
        if V == 1:  # no multi-view aggregation, so no 'seen' mask: gather the image at occupied voxels only
            x = unproject_rgbd_occupied(*views, det.grid)
            seen = x[:, :1]
        else:
            x, seen = det.encoder_input(*views)
        t["unproject"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        amp = torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16")
        with amp:
            feats = det.encode_input(x, seen, V)
        t["encode"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if boxes is None:
            with amp:
                logits, box = det.head(feats)
            dets = det.detect(logits.float(), box.float(), self.score_threshold, views=(depth, K, pose),
                              targets=targets)
        else:
            dets = [{"boxes": torch.as_tensor(a, dtype=torch.float32).reshape(-1, 6).to(feats.device),
                     "scores": torch.as_tensor(sc, dtype=torch.float32).reshape(-1).to(feats.device)}
                    for a, sc in boxes]
        t["detect"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if self.q_stage is None:
            q_feats = feats
        else:
            with amp:
                q_feats = self.q_stage.encode_input(x, seen, V)
        q_feats = q_feats.float()
        t["encode_prototype_space"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        P = max([d["boxes"].shape[0] for d in dets] + [1])
        aabb = feats.new_zeros(B, P, 6)
        mask = torch.zeros(B, P, dtype=torch.bool, device=feats.device)
        for b, d in enumerate(dets):
            n = d["boxes"].shape[0]
            aabb[b, :n], mask[b, :n] = d["boxes"], True
        region = aabb  # each box's own region, as the bank's crops were cut
        crops = crop_boxes(q_feats, region, det.feature_grid, self.crop_size, mask=mask)
        if self.occupancy_floor is not None:  # the input occupancy (union over the views) weights the crops
            occ = x[:, :1].reshape(B, V, 1, *x.shape[2:]).amax(1)
            crops = prototype_crops(crops, crop_boxes(occ, region, det.grid, self.crop_size, mask=mask),
                                    self.occupancy_floor)
        t["crop"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if crops.shape[0]:
            res = self.bank.assign(crops)
            proto, angle, sim = res.prototype, res.angle, res.score
            margin = yaw_confidence(res, yaw_margin_steps(self.num_angles))
        else:
            proto = angle = torch.zeros(0, dtype=torch.long, device=feats.device)
            sim = margin = feats.new_zeros(0)
        t["search"] = time.perf_counter() - t0
        counts = mask.sum(1).tolist()
        split = lambda x: list(torch.split(x.cpu(), counts))  # noqa: E731
        return {"aabb": [d["boxes"].cpu() for d in dets], "score": [d["scores"].cpu() for d in dets],
                "prototype": split(proto), "angle": split(angle), "similarity": split(sim.float()),
                "yaw_confidence": split(margin.float()), "features": q_feats, "timings": t}


def yaw_margin_steps(num_angles: int) -> int:
    """The yaw steps within 30 degrees of the chosen one, which ``yaw_confidence`` counts as the same pose."""
    return max(1, round(num_angles * 30 / 360))


def find_scenes(scenes: str | Path, split: str | None = None) -> tuple[Path, list[str]]:
    """The scene files to parse: ``(root, files relative to root)``.

    ``scenes`` is one ``.npz``, a dataset folder with ``index.json`` (every scene, or those of ``split``), or a
    folder of ``.npz`` files (searched recursively; ``proposals/`` and ``boxes/`` folders are skipped).
    """
    p = Path(scenes)
    if p.is_file():
        return p.parent, [p.name]
    if not p.is_dir():
        raise FileNotFoundError(f"scenes: no such file or folder: {p}")
    if (p / INDEX_NAME).is_file():
        index = load_index(p)
        files = index.files(split) if split else [s["file"] for s in index.scenes]
    else:
        files = sorted(str(f.relative_to(p)) for f in p.rglob("*.npz")
                       if not {"proposals", "boxes"} & set(f.relative_to(p).parts[:-1]))
    if not files:
        raise FileNotFoundError(f"scenes: no scene files in {p}" + (f" (split {split!r})" if split else ""))
    return p, files


def scene_batch(records: list[SceneRecord], views: list[list[int]]) -> dict[str, Tensor]:
    """Stack the chosen views of records of one image size into a parse batch (see :meth:`SceneParser.forward`)."""
    rv = list(zip(records, views))
    return {"rgb": torch.stack([torch.from_numpy(r.rgb[v]).permute(0, 3, 1, 2).float().div_(255.0) for r, v in rv]),
            **{k: torch.stack([torch.from_numpy(getattr(r, a)[v].astype(np.float32)) for r, v in rv])
               for k, a in (("depth", "depth"), ("K", "K"), ("R_T_cam", "world_T_cam"))}}


def check_views(views: list[int], record: SceneRecord, source: str) -> list[int]:
    bad = [v for v in views if not -record.num_views <= v < record.num_views]
    if bad:
        raise SceneValidationError(source, "views",
                                   f"view {bad[0]} asked for but the scene has {record.num_views} views")
    return [v % record.num_views for v in views]


def scene_targets(parser: SceneParser, records: list[SceneRecord], sensor_captures: bool,
                  ) -> list[tuple[np.ndarray, np.ndarray]] | None:  # fmt: skip
    """Per record, the label-free pseudo-boxes fused over all its views that a ``refine_to: scene`` detector refines
    against (the parameters a scene-folder DataModule's ``pseudo_boxes`` uses for renders or sensor captures); ``None``
    for a detector that refines against its input views."""
    if parser.detector.hparams.get("refine_to") != "scene":
        return None
    params = asdict(SENSOR_PROPOSALS if sensor_captures else RENDER_PROPOSALS)
    fg = parser.detector.feature_grid
    return [propose_boxes(r, bounds=(fg.bounds_min, fg.bounds_max), **params) for r in records]


def parse_records(parser: SceneParser, records: list[SceneRecord], views: list[list[int]],
                  names: dict[int, str] | None = None, batch_size: int = 4,
                  boxes: list[tuple[np.ndarray, np.ndarray]] | None = None,
                  targets: list[tuple[np.ndarray, np.ndarray]] | None = None) -> list[dict[str, Any]]:
    """Parse in-memory records (views per record); returns one JSON-ready dict per record (see :func:`run_parse`).

    ``boxes`` (per record ``(aabb [P, 6], scores [P])``) replaces the detector's boxes; ``targets`` (the same
    layout, :func:`scene_targets`) are what its detections are refined against. Records of one image size and number
    of input views are batched ``batch_size`` at a time.
    """
    names = names or {}
    out: list[dict[str, Any] | None] = [None] * len(records)
    groups: dict[tuple, list[int]] = {}
    for i, (r, v) in enumerate(zip(records, views)):
        groups.setdefault((r.image_size, len(v)), []).append(i)
    yaw = yaw_angles(parser.num_angles, dtype=torch.float64)
    for idx in groups.values():
        for s in range(0, len(idx), batch_size):
            chunk = idx[s : s + batch_size]
            given = None if boxes is None else [boxes[i] for i in chunk]
            snap = None if targets is None else [targets[i] for i in chunk]
            res = parser(scene_batch([records[i] for i in chunk], [views[i] for i in chunk]), given, snap)
            for j, i in enumerate(chunk):
                out[i] = _scene_json(records[i], views[i], res, j, yaw, names)
                out[i]["_features"] = res["features"][j : j + 1]
    return out  # type: ignore[return-value]


def _scene_json(rec: SceneRecord, views: list[int], res: dict[str, Any], j: int, yaw: Tensor,
                names: dict[int, str]) -> dict[str, Any]:
    aabb = res["aabb"][j].double().numpy()
    objects = []
    c_T = rec.meta.get("canonical_T_capture") if isinstance(rec.meta, dict) else None
    for n in range(aabb.shape[0]):
        a, k = int(res["angle"][j][n]), int(res["prototype"][j][n])
        obj: dict[str, Any] = {
            "box": [round(float(x), 5) for x in aabb[n]],
            "center": [round(float(x), 5) for x in (aabb[n, :3] + aabb[n, 3:]) / 2],
            "size": [round(float(x), 5) for x in aabb[n, 3:] - aabb[n, :3]],
            "score": round(float(res["score"][j][n]), 5), "prototype": k, "angle_index": a,
            "yaw_deg": round((-math.degrees(float(yaw[a]))) % 360.0, 3),
            "similarity": round(float(res["similarity"][j][n]), 5),
            "yaw_confidence": round(float(res["yaw_confidence"][j][n]), 5), "name": names.get(k)}
        if c_T is not None:
            box7 = np.array([[*obj["center"], *obj["size"], 0.0]])
            obj["capture_T_box"] = np.round(boxes_to_capture_frame(box7, np.asarray(c_T))[0][0], 6).tolist()
        objects.append(obj)
    return {"input_views": list(views), "frame": "R (the record's world frame: metres, z up)", "objects": objects}


def _appearance_raw(parser: SceneParser, appearance: dict[str, Tensor] | None, k: int) -> Tensor | None:
    if appearance is None or k >= appearance["count"].shape[0] or appearance["count"][k] == 0:
        return None
    return appearance["raw"][k]


def prototype_top_view(raw: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Bird's-eye picture of a mean raw crop ``[4, s, s, s]`` (``cat[occ, occ * rgb]`` averaged over members).

    Returns the ``[s, s, 3]`` float RGB picture (y up; occupancy rescaled by its maximum, colour ``rgb / occ``) and
    the ``[s, s]`` mask of columns holding a voxel above half the maximum occupancy.
    """
    occ = raw[0].clamp_min(0)
    occ_n = occ / occ.max().clamp_min(1e-6)
    rgb = raw[1:4] / occ.clamp_min(1e-6)
    pic = crop_birds_eye(torch.cat([occ_n[None], rgb]), background=0.0)
    mask = (occ_n > 0.5).any(0).flip(0).numpy()
    return pic, mask


def birds_eye_panel(rec: SceneRecord, views: list[int], parse: dict[str, Any], parser: SceneParser,
                    appearance: dict[str, Tensor] | None, size: int) -> np.ndarray:
    """Bird's-eye view of the scene's input grid (top colour of the occupied voxels) with each object's prototype
    drawn at its yaw inside the object's footprint, its footprint outline and its label (``[size, size, 3]`` uint8).

    Convention: x to the right, y up; the prototype's picture is the mean of its members' raw crops in canonical
    pose (``prototype_appearance``), turned by the object's ``yaw_deg``.
    """
    det = parser.detector
    b = scene_batch([rec], [views])
    with torch.no_grad():
        x, _ = det.encoder_input(*(b[k][0].to(parser.device) for k in ("rgb", "depth", "K", "R_T_cam")))
    raw = x.amax(0)  # [4, Z, Y, X]
    img = (crop_birds_eye(raw, background=0.08) * 255).astype(np.uint8)  # [Y, X, 3], y up
    g = det.grid
    scale = size / max(img.shape[:2])
    img = cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)), interpolation=cv2.INTER_NEAREST)
    img = (img.astype(np.float32) * 0.6).astype(np.uint8)
    H, W = img.shape[:2]
    lo, hi = np.array(g.bounds_min), np.array(g.bounds_max)

    def px(xw: float, yw: float) -> tuple[float, float]:
        return (xw - lo[0]) / (hi[0] - lo[0]) * W, (hi[1] - yw) / (hi[1] - lo[1]) * H

    yaw = yaw_angles(parser.num_angles)
    for o in parse["objects"]:
        x0, y0 = px(o["box"][0], o["box"][4])
        x1, y1 = px(o["box"][3], o["box"][1])
        c0, r0, c1, r1 = (int(round(v)) for v in (x0, y0, x1, y1))
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, W), min(r1, H)
        col = distinct_colour(o["prototype"] + 1)
        proto = _appearance_raw(parser, appearance, o["prototype"])
        if proto is not None and c1 > c0 + 1 and r1 > r0 + 1:
            turned = rotate_yaw(proto[None].float(), -yaw[o["angle_index"]][None])[0]
            pic, has = prototype_top_view(turned)
            pic = cv2.resize(pic, (c1 - c0, r1 - r0), interpolation=cv2.INTER_NEAREST)
            has = cv2.resize(has.astype(np.uint8), (c1 - c0, r1 - r0), interpolation=cv2.INTER_NEAREST) > 0
            region = img[r0:r1, c0:c1]
            region[has] = (np.clip(pic[has], 0, 1) * 255).astype(np.uint8)
        cv2.rectangle(img, (c0, r0), (max(c0, c1 - 1), max(r0, r1 - 1)), col, 1, cv2.LINE_AA)
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        ang = math.radians(o["yaw_deg"])  # the prototype's +x axis, turned like the object
        L = 0.5 * min(x1 - x0, y1 - y0)
        cv2.arrowedLine(img, (int(cx), int(cy)), (int(cx + L * math.cos(ang)), int(cy - L * math.sin(ang))), col, 1,
                        cv2.LINE_AA, tipLength=0.3)
        text = f"C{o['prototype']} R{o['yaw_deg']:.0f}" + (f" {o['name']}" if o.get("name") else "")
        cv2.putText(img, text, (c0, max(r0 - 3, 9)), cv2.FONT_HERSHEY_SIMPLEX, 0.33, col, 1, cv2.LINE_AA)
    out = np.zeros((size, max(W, size), 3), np.uint8)
    out[:H, :W] = img
    return out


def parse_figure(rec: SceneRecord, views: list[int], parse: dict[str, Any], parser: SceneParser,
                 appearance: dict[str, Tensor] | None = None) -> np.ndarray:
    """The input view with the projected boxes labelled "C12 R40 name", beside the bird's-eye panel (RGB uint8)."""
    v = views[0]
    objs = parse["objects"]
    boxes = np.array([[*o["center"], *o["size"], 0.0] for o in objs], np.float64).reshape(-1, 7)
    labels = [f"C{o['prototype']} R{o['yaw_deg']:.0f}" + (f" {o['name']}" if o.get("name") else "") for o in objs]
    H = rec.image_size[0]
    up = max(1, int(math.ceil(384 / H)))
    left = draw_boxes(rec.rgb[v], boxes, labels, rec.K[v], rec.world_T_cam[v],
                      colour=[distinct_colour(o["prototype"] + 1) for o in objs], upscale=up, heading=False)
    right = birds_eye_panel(rec, views, parse, parser, _none_if_empty(appearance), left.shape[0])
    gap = np.full((left.shape[0], 6, 3), 255, np.uint8)
    return np.concatenate([left, gap, right], axis=1)


def _none_if_empty(appearance: dict[str, Tensor] | None) -> dict[str, Tensor] | None:
    return appearance if appearance is not None and int(appearance["count"].sum()) > 0 else None


@torch.no_grad()
def prototype_appearance(parser: SceneParser, root: Path, files: list[str], views: list[int], progress: bool = True,
                         batch_size: int = 4) -> dict[str, Tensor]:
    """What each prototype looks like: the mean raw crop (``cat[occ, occ * rgb]``) of the objects the parser finds
    in ``files`` and assigns to it, each turned into the prototype's canonical pose (for pictures only).

    Returns:
        ``raw`` ``[K, 4, s, s, s]``, ``count`` ``[K]``, ``size`` ``[K, 3]`` mean box size (metres), ``bank``
        (the bank's fingerprint, as a uint8 tensor).
    """
    K, s = parser.bank.prototypes.shape[0], parser.crop_size
    acc = torch.zeros(K, 4, s, s, s)
    count = torch.zeros(K)
    size = torch.zeros(K, 3)
    yaw = yaw_angles(parser.num_angles)
    det = parser.detector
    for i in tqdm(range(0, len(files), batch_size), desc="prototype appearance", disable=not progress, leave=False):
        recs = []
        for f in files[i : i + batch_size]:
            try:
                recs.append(load_scene(root / f))
            except (SceneValidationError, OSError, ValueError):
                continue
        if not recs:
            continue
        by_size: dict[tuple, list[SceneRecord]] = {}
        for r in recs:
            by_size.setdefault(r.image_size, []).append(r)
        for group in by_size.values():
            vs = [[v % r.num_views for v in views] for r in group]
            b = scene_batch(group, vs)
            res = parser(b)
            B, V = b["rgb"].shape[:2]
            x, _ = det.encoder_input(*(b[k].flatten(0, 1).to(parser.device)
                                       for k in ("rgb", "depth", "K", "R_T_cam")))
            raw_grid = x.view(B, V, *x.shape[1:]).amax(1)
            for j in range(B):
                if res["aabb"][j].shape[0] == 0:
                    continue
                region = res["aabb"][j][None].to(raw_grid)
                raw = crop_boxes(raw_grid[j : j + 1], region, det.grid, s)[0].cpu()
                aligned = rotate_yaw(raw, yaw[res["angle"][j]])
                for n, k in enumerate(res["prototype"][j].tolist()):
                    acc[k] += aligned[n]
                    count[k] += 1
                    size[k] += res["aabb"][j][n, 3:] - res["aabb"][j][n, :3]
    has = count > 0
    acc[has] /= count[has].view(-1, 1, 1, 1, 1)
    size[has] /= count[has, None]
    return {"raw": acc, "count": count, "size": size,
            "bank": torch.tensor(list(parser.fingerprint.encode()), dtype=torch.uint8)}


def _training_scenes(artifacts: RunArtifacts) -> tuple[Path, list[str]] | None:
    """The training split the prototypes were fitted on (from the quantizer's ``config.yaml``), if it is there."""
    cfg = artifacts.prototypes.parent.parent / "config.yaml"
    if not cfg.is_file():
        return None
    try:
        data_dir = yaml.safe_load(cfg.read_text())["data"]["init_args"]["data_dir"]
    except (KeyError, TypeError, yaml.YAMLError):
        return None
    for base in (Path.cwd(), *(artifacts.run.resolve().parents if artifacts.run else ())):
        d = base / data_dir
        if (d / INDEX_NAME).is_file():
            try:
                files = load_index(d).files("train")
            except (SceneValidationError, ValueError, OSError):
                return None
            return (d, files) if files else None
    return None


def load_or_make_appearance(parser: SceneParser, max_scenes: int = 100,
                            progress: bool = True) -> dict[str, Tensor] | None:
    """The cached ``prototype_appearance.pt`` beside the bank, made from up to ``max_scenes`` training scenes when
    missing or made for another bank (None when the training data cannot be found, or ``max_scenes`` is 0)."""
    if max_scenes <= 0:
        return None
    path = parser.artifacts.prototypes.parent / APPEARANCE_FILE
    if path.is_file():
        try:
            app = torch.load(path, map_location="cpu", weights_only=True)
            if bytes(app["bank"].tolist()).decode() == parser.fingerprint:
                return app
        except Exception:  # noqa: BLE001 - a stale or broken cache is rebuilt
            pass
    train = _training_scenes(parser.artifacts)
    if train is None:
        print("threedq parse: the prototypes' training scenes are not at hand: the bird's-eye view draws no "
              "prototype pictures", file=sys.stderr)
        return None
    root, files = train
    step = max(1, len(files) // max_scenes)
    app = prototype_appearance(parser, root, files[::step][:max_scenes], [0], progress=progress)
    buf = io.BytesIO()
    torch.save(app, buf)
    atomic_write_bytes(path, buf.getvalue())
    return app
