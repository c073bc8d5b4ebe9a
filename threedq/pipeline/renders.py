"""Neural renders of prototypes through the view decoder (paper Fig. 3b and supplement; ``threedq parse --renders``).

:func:`prototype_gallery` decodes each prototype alone, standing at the grid centre in a box of its members' mean size
inside an empty scene's encoding, from 4 azimuths; :func:`replaced_render` decodes a parsed scene with every object's
box filled with its prototype at the inferred yaw, beside the real view and the decode of the unmodified grid. The
decoder is view prediction's (``00_viewpred``).

Convention: frame R metres, z up; yaw counter-clockwise about +z; cameras OpenCV, ``world_T_cam``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from threedq.errors import InputError
from threedq.geometry import paste_boxes, rotate_yaw, yaw_angles
from threedq.pipeline.parse import SceneParser, prototype_top_view, scene_batch
from threedq.scene import SceneRecord
from threedq.stages.base import stage_arguments
from threedq.stages.checkpoint import checkpoint_hparams, checkpoint_state
from threedq.stages.viewpred import ViewPrediction

__all__ = ["load_view_decoder", "orbit_poses", "prototype_gallery", "replaced_render"]


def load_view_decoder(path: str | Path) -> ViewPrediction:
    """The view-prediction stage of a checkpoint (decoder weights loaded; its encoder is not used here)."""
    hp = checkpoint_hparams(path)
    names = set(stage_arguments(ViewPrediction)) - {"encoder_ckpt"}
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in hp.items() if k in names}
    vp = ViewPrediction(**{**kw, "channels_last": True, "image_every_n_steps": 0})
    state = {k: v for k, v in checkpoint_state(path).items() if k.startswith("decoder.")}
    if not state:
        raise InputError(f"{path}: field 'state_dict': no 'decoder.*' weights (not a view-prediction checkpoint)")
    missing, _ = vp.load_state_dict(state, strict=False)
    if [k for k in missing if k.startswith("decoder.")]:
        raise InputError(f"{path}: field 'state_dict': the decoder's weights are incomplete")
    return vp.eval()


def orbit_poses(world_T_cam: np.ndarray, centre: tuple[float, float], azimuths_deg: list[float]) -> np.ndarray:
    """``world_T_cam`` turned about the vertical axis through ``centre`` (x, y) by each azimuth: ``[A, 4, 4]``."""
    out = []
    for a in azimuths_deg:
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = np.array(centre) - T[:2, :2] @ np.array(centre)
        out.append(T @ np.asarray(world_T_cam, np.float64))
    return np.stack(out).astype(np.float32)


def _u8(img: Tensor, size: tuple[int, int]) -> np.ndarray:
    a = ((img.detach().float().cpu() + 0.5).clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    return cv2.resize(a, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)


def _text(img: np.ndarray, text: str, y: int = 11) -> None:
    cv2.putText(img, text, (3, y), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 2, cv2.LINE_AA)
    cv2.putText(img, text, (3, y), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)


@torch.no_grad()
def empty_features(parser: SceneParser) -> Tensor:
    """The prototypes' encoder's features of an empty scene (all-zero input): ``[1, C, Z', Y', X']``."""
    stage = parser.q_stage or parser.detector
    x = torch.zeros(1, 4, *stage.grid.volume_shape, device=parser.device)
    return stage.encode_input(x, torch.ones_like(x[:, :1]), 1)


@torch.no_grad()
def prototype_gallery(parser: SceneParser, decoder: ViewPrediction, reference: SceneRecord,
                      appearance: dict[str, Tensor] | None, names: dict[int, str] | None = None, azimuths: int = 4,
                      max_prototypes: int = 16, tile: int = 112, view: int = 0, zoom: float = 2.0) -> np.ndarray:
    """The gallery: one row per prototype, the most populated first, with its mean member from above (RGB uint8).

    Args:
        reference: a scene whose view ``view`` gives the camera (intrinsics, distance, elevation) and image size.
        zoom: focal lengths are multiplied by this (the principal point stays), so the prototype fills more of it.
        appearance: ``prototype_appearance`` (member counts, mean sizes and raw crops); None: every active
            prototype in a box of the detector's anchor size, no raw picture.
    """
    names = names or {}
    bank, fg = parser.bank, parser.detector.feature_grid
    active = bank.active.nonzero().flatten().tolist()
    counts = appearance["count"] if appearance is not None else torch.zeros(bank.prototypes.shape[0])
    order = sorted(active, key=lambda k: (-float(counts[k]), k))[:max_prototypes]
    base = empty_features(parser)
    cx, cy = ((fg.bounds_min[0] + fg.bounds_max[0]) / 2, (fg.bounds_min[1] + fg.bounds_max[1]) / 2)
    poses = torch.from_numpy(orbit_poses(reference.world_T_cam[view], (cx, cy),
                                         [360.0 * i / azimuths for i in range(azimuths)]))
    K = torch.from_numpy(reference.K[view].astype(np.float32))
    K[0, 0], K[1, 1] = K[0, 0] * zoom, K[1, 1] * zoom
    H, W = reference.image_size
    anchor = parser.detector.anchor.cpu()
    rows = []
    for k in order:
        size = appearance["size"][k] if appearance is not None and counts[k] > 0 else anchor
        z0 = max(0.0, fg.bounds_min[2])
        box = torch.tensor([cx - size[0] / 2, cy - size[1] / 2, z0, cx + size[0] / 2, cy + size[1] / 2, z0 + size[2]])
        feats = paste_boxes(base, bank.prototypes[k][None, None].to(base), box[None, None].to(base), fg)
        feats = torch.nn.functional.normalize(feats, dim=1, eps=1e-6)
        pred = decoder.predict_view(feats.expand(azimuths, -1, -1, -1, -1), K.expand(azimuths, 3, 3).to(base),
                                    poses.to(base), (H, W))
        tiles = [_u8(p, (tile, tile * W // H)) for p in pred]
        if appearance is not None and counts[k] > 0:
            pic, _ = prototype_top_view(appearance["raw"][k].float())
            tiles.append(cv2.resize((pic * 255).astype(np.uint8), (tile, tile), interpolation=cv2.INTER_NEAREST))
        label = (f"C{k}" + (f" n={int(counts[k])}" if appearance is not None else "")
                 + (f" {names[k]}" if k in names else ""))
        _text(tiles[0], label)
        sep = np.full((tile, 3, 3), 255, np.uint8)
        rows.append(np.concatenate([t for tl in tiles for t in (tl, sep)][:-1], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 3), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    head = np.full((16, width, 3), 255, np.uint8)
    cv2.putText(head, f"prototypes decoded at {azimuths} azimuths" + (" | mean member, canonical pose, from above"
                if appearance is not None else ""), (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1,
                cv2.LINE_AA)
    return np.concatenate([head, *rows], axis=0)


@torch.no_grad()
def replaced_render(parser: SceneParser, decoder: ViewPrediction, rec: SceneRecord, parse: dict[str, Any],
                    features: Tensor, target_view: int, tile: int = 192) -> np.ndarray:
    """Real target view | decode of the scene's grid | decode with every object replaced by its prototype (RGB).

    Args:
        parse: the scene's parse (``objects`` with ``box``, ``prototype``, ``angle_index``).
        features: ``[1, C, Z', Y', X']`` the scene's features in the prototypes' space (from the parse).
        target_view: a view of ``rec`` that was not an input.
    """
    objs = parse["objects"]
    fg = parser.detector.feature_grid
    feats = features.to(parser.device)
    if objs:
        yaw = yaw_angles(parser.num_angles, device=feats.device)
        protos = parser.bank.prototypes[[o["prototype"] for o in objs]]
        turned = rotate_yaw(protos, -yaw[[o["angle_index"] for o in objs]])
        boxes = torch.tensor([o["box"] for o in objs], dtype=feats.dtype, device=feats.device)
        replaced = paste_boxes(feats, turned[None].to(feats), boxes[None], fg)
        replaced = torch.nn.functional.normalize(replaced, dim=1, eps=1e-6)
    else:
        replaced = feats
    b = scene_batch([rec], [[target_view]])
    K, pose = b["K"][:, 0].to(feats), b["R_T_cam"][:, 0].to(feats)
    H, W = rec.image_size
    pred = decoder.predict_view(torch.cat([feats, replaced]), K.expand(2, 3, 3), pose.expand(2, 4, 4), (H, W))
    size = (tile, tile * W // H)
    real = cv2.resize(rec.rgb[target_view], (size[1], size[0]), interpolation=cv2.INTER_AREA)
    tiles = [real, _u8(pred[0], size), _u8(pred[1], size)]
    for t, name in zip(tiles, (f"real view {target_view}", "decoded scene", "objects -> prototypes")):
        _text(t, name)
    sep = np.full((size[0], 3, 3), 255, np.uint8)
    return np.concatenate([tiles[0], sep, tiles[1], sep, tiles[2]], axis=1)
