"""Correspondence learning (paper Sec. 3.3, Table 2): fine-tune the shared encoder by metric learning.

One stage, three sources of positive pairs (``source``), all trained with InfoNCE at temperature 0.07:

* ``vc`` (the paper's rgbocc+VC): the same world point inside an object box, seen through two disjoint view
  sets of one scene (the sample's first ``num_input_views`` views and the next as many, both lifted into frame
  R); ``voxels_per_object`` points per box; negatives are the other points of the batch (in-batch InfoNCE,
  both sides trained).
* ``vc_moco`` (rgbocc+VC*): the same pairs; the second view set goes through the momentum key encoder
  (``moco.encoder_k``), negatives come from the queue (``moco.queue``, ``[Q, D]``).
* ``mined`` (ours, supplement "3D correspondence mining"): every ``refresh_every`` steps a pool of
  ``target_pool`` object crops (``crop_size^3``) is cut from random training scenes with the current encoder
  (eval mode, no gradient, float32, each scene's fixed input views; by default only boxes that the pseudo-boxes of
  the input views and of the whole scene's views vouch for: ``pool_min_observed_iou``, ``pool_min_scene_iou``), and
  the first ``query_pool`` of them are mined against the rest
  (:func:`threedq.contrastive.mine_correspondences`: object-level rotation-max retrieval, the query patch
  searched over each target's patch grid at ``num_angles`` yaws, verification by the context ring at
  Manhattan distance ``context_distance``); the ``keep`` best verified pairs are kept. That is the paper's miner,
  ``candidates_from: "features"``; by default (issue #63) the input crops propose the pairs instead
  (``candidates_from: "input"``, :func:`input_pairs`: the pool's mutual nearest neighbours by input agreement over
  every yaw, the learned features choosing none), and the miner and its settings are not used. With ``positives:
  patches`` (the paper's; the default is ``occupancy``, below) each pair gives 8 positives: the corners of a
  ``2 * corner_offset``-voxel cube around the match in the query crop, each paired with its best-matching voxel
  within ``+-corner_search`` voxels of the expected place in the target rotated onto the query (keys computed at
  the refresh). A training step draws ``pairs_per_step`` pairs, re-encodes
  their query scenes with the encoder being trained (the loader's batch is not used) and takes InfoNCE of
  the query corners against their keys, with the queue as negatives. The queue is primed at the first refresh
  with random voxels of the pool, so the first steps do not contrast against random vectors.
  With ``view_positives > 0`` (issue #30's object-level multi-view positive, not in the paper) the step also
  takes, for every object box of its query scenes, ``view_positives`` random voxels of the object's crop: each
  voxel's feature from the input views is paired with the same voxel (the same world point: the poses are known)
  of the crop encoded from a second, disjoint view set of that scene (the data's ``num_target_views`` views after
  the input ones, drawn at random like them) by the momentum key encoder (``moco.encoder_k``, which the mined
  source otherwise leaves unused), in the same queue, weighted by ``view_weight``: the same object seen from
  elsewhere must keep its features. It is ``vc_moco``'s positive, restricted to the mined scenes and added to the
  mined pairs; the key encoder's pass costs about a third more per step.

Mining diagnostics (GT categories and yaws are used for measuring only): each refresh logs the number of
pairs, the fraction whose two objects share a category, and the median error of the implied relative yaw on
same-category pairs of asymmetric categories, and writes ``mining/refresh_<step>.json`` and a picture of the
best pairs (``mining/refresh_<step>.png``) under the run's log folder.

View prediction as a regulariser (``view_prediction_weight > 0``, issue #30's lever, not in the paper): the step
adds ``view_prediction_weight`` x the view-prediction loss (:class:`~threedq.stages.viewpred.ViewPredictionObjective`:
RGB of a target view decoded from the grid, and occupancy with raycast free space) on the first of its query
scenes, so the fine-tuning cannot forget what view prediction taught (off, the mined encoder's decoder RGB L1 goes
0.0415 -> 0.0938 in 100 steps, ``docs/studies/mining.md``). The decoder, the occupancy head and their settings come from
``encoder_ckpt`` (view prediction's, or an earlier round's mining checkpoint trained with the term, which carries
them on) and train along; the data must give target views (``num_target_views >= 1``). Off by default: the
measurement is in ``docs/studies/mining.md``. ``correspondence_weight: 0`` with it is the control arm: the same
stage, scenes and pairs, with view prediction alone training the encoder (docs/studies/mined-pairs.md).
``view_prediction_rgb: false`` keeps only the loss's occupancy term (no decoder pass, the decoder carried on
untrained): the term keeps shape when it trains the encoder from the start (docs/studies/shape.md), but as the
regulariser at weight 1 it does not (docs/studies/mined-pairs.md).

A projection head (``projection_dim``, MoCo v2's, not in the paper): the queue's InfoNCE (the mined pairs, the view
positives, the prototype positives, ``vc_moco``'s) is taken on ``Linear(C, C)``, ReLU, ``Linear(C, projection_dim)`` of
the features, L2-normalised; keys and the queue (which keeps the unit feature vectors) go through the head as it is
at the step, without gradient. The grid's features, which retrieval, the miner and the quantizer use, are the head's
input: the invariances the pairs teach may settle in the head. The head trains at its own constant ``projection_lr``
and is carried to the next EM round by the checkpoint (``projection.*``; a fresh head when ``encoder_ckpt`` has
none). Off by default (the paper's InfoNCE on the features): it holds the embedded rounds back and lets the shape-only
ones fall a little less, the trade the view-prediction keepers make (``docs/studies/mined-pairs.md``).

Positives that are shape agreements by construction (``positives: occupancy``, issue #63's lever, not in the paper):
the miner is asked for ``shape_oversample`` x ``keep`` pairs; each is re-posed on its two objects' input occupancy
(:func:`shape_agreement`) and the ``keep`` that agree best are kept, with positives at cells both objects occupy at
that yaw, keyed by the turned target's feature at the same cell (:func:`shape_cells`), instead of the corners of the
patch match keyed by the features. The default since issue #63's twenty-first session (``"patches"`` is the
paper's): over 2 seeds on each of two CPU types it lifts the embedded rounds' category retrieval and pose and the
shape-only clustering, and lowers same-object identity; the embedded clustering is equal within the seeds' spread;
it costs a few seconds a refresh (``docs/studies/mined-pairs.md``, "Positives that are shape agreements by
construction" and the sections after it).

The prototypes as positives (``prototype_weight > 0``, issue #63's lever, not in the paper): at each refresh the
prototype bank of ``bank_ckpt`` (``threedq em`` hands over the bank the pool's encoder was last quantized with)
assigns every pool object a prototype and a yaw; each kept pair's query corners get a second key, the same cells of
their object's prototype turned onto the object (:func:`prototype_keys`), in the same queue, weighted by
``prototype_weight``. Off by default: it lifts the rounds' category retrieval and lowers the loop's Hungarian
accuracy (``docs/studies/mined-pairs.md``, "The prototypes as positives").

Convention: frame R metres, z up; crops ``[N, C, Z, Y, X]``; yaw counter-clockwise seen from above, index
``b`` meaning ``2 pi b / num_angles``; the mined yaw rotates the TARGET crop onto the query.
"""

from __future__ import annotations

import copy
import json
import math
import time
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import default_collate

from threedq.atomic_io import atomic_write_text
from threedq.box_refinement import observed_boxes
from threedq.boxes import best_aabb_iou
from threedq.contrastive import MomentumContrast, calibrate_context_cosine, info_nce_streamed, mine_correspondences
from threedq.errors import InputError
from threedq.geometry import crop_boxes, rotate_yaw
from threedq.metrics import RetrievalPrecisionAtK
from threedq.nets import OccupancyHead, ViewDecoder, balanced_occupancy_loss
from threedq.quantization.prototypes import PrototypeBank, assign_chunked, prototype_crops
from threedq.stages.base import EncoderStage, SplitEvaluation
from threedq.stages.checkpoint import checkpoint_hparams, load_checkpoint, require_stage
from threedq.stages.quantizer import bank_occupancy_floor, load_bank_state
from threedq.stages.viewpred import ViewPredictionObjective, view_prediction_checkpoint
from threedq.viz.features import mined_pairs_figure
from threedq.viz.png import write_png

__all__ = ["Mining", "corner_offsets", "corner_keys", "crop_voxels", "implied_yaw_error_deg", "oracle_pairs",
           "shape_agreement", "shape_cells", "spread_candidates"]

SOURCES = ("vc", "vc_moco", "mined")
ORACLES = ("gt", "gt_category", "mined_gt_filtered")


def corner_offsets(corner_offset: int = 4, patch: int = 2, device: torch.device | str | None = None) -> Tensor:
    """``[8, 3]`` long ``(dz, dy, dx)`` offsets from a patch start to the corners of a cube centred on the patch.

    The cube's corners sit ``corner_offset - 0.5`` voxels (for ``patch=2``) from the patch centre along each
    axis: offsets ``(patch // 2) - corner_offset`` and ``(patch // 2) + corner_offset - 1`` (``-3`` and ``4`` by
    default, the corners of an 8^3 cube).
    """
    lo, hi = patch // 2 - corner_offset, patch // 2 + corner_offset - 1
    vals = torch.tensor([lo, hi], device=device)
    return torch.cartesian_prod(vals, vals, vals)


def corner_keys(
    query_crop: Tensor, query_pos: Tensor, target_aligned: Tensor, target_pos_aligned: Tensor,
    offsets: Tensor, search: int = 1,
) -> tuple[Tensor, Tensor]:
    """Hard positives of one verified match: query corners and their best matches in the aligned target.

    Args:
        query_crop: ``[C, S, S, S]``; query_pos: ``[3]`` long patch start of the match in the query.
        target_aligned: ``[C, S, S, S]`` the target rotated onto the query; target_pos_aligned ``[3]`` long.
        offsets: ``[P, 3]`` long, from :func:`corner_offsets`.
        search: the key is the voxel of highest cosine to the query corner within ``+-search`` voxels (per axis)
            of the expected place ``target_pos_aligned + offset``.

    Returns:
        ``query_voxels`` ``[P, 3]`` long (clamped into the crop) and ``keys`` ``[P, C]`` L2-normalised.
    """
    size = torch.tensor(query_crop.shape[1:], device=query_crop.device)
    qv = torch.minimum((query_pos + offsets).clamp_min(0), size - 1)
    expected = target_pos_aligned + offsets  # [P, 3]
    r = torch.arange(-search, search + 1, device=query_crop.device)
    neigh = torch.cartesian_prod(r, r, r)  # [G, 3]
    cand = torch.minimum((expected[:, None] + neigh[None]).clamp_min(0), size - 1)  # [P, G, 3]
    qf = F.normalize(query_crop[:, qv[:, 0], qv[:, 1], qv[:, 2]].T, dim=1)  # [P, C]
    tf = F.normalize(target_aligned[:, cand[..., 0], cand[..., 1], cand[..., 2]].permute(1, 2, 0), dim=2)  # [P, G, C]
    best = torch.einsum("pc,pgc->pg", qf, tf).argmax(dim=1)
    return qv, tf[torch.arange(tf.shape[0]), best]


def prototype_keys(prototypes: Tensor, angle: Tensor, voxels: Tensor, num_angles: int) -> tuple[Tensor, Tensor]:
    """Prototype positives: the features of each object's prototype, turned into the object's frame, at its voxels.

    Args:
        prototypes: ``[P, C, S, S, S]`` the prototype each object is assigned to (its crop, as the bank holds it).
        angle: ``[P]`` long yaw steps of the assignment ("object o has yaw a": ``rotate_yaw(o, a)`` lies on its
            prototype).
        voxels: ``[P, V, 3]`` long ``(z, y, x)`` cells of the objects' crops.
        num_angles: yaw steps in a full turn.

    Returns:
        ``keys`` ``[P, V, C]`` L2-normalised (zero where the turned prototype is empty: its cell came from outside
        the crop) and ``valid`` ``[P, V]`` bool, where the prototype has a feature.

    Convention: yaw as in :func:`~threedq.geometry.rotate_yaw` (about the crop's vertical axis, through its centre);
    the prototype is turned by ``-a``, the object is not touched.
    """
    P = prototypes.shape[0]
    if P == 0:
        return prototypes.new_zeros(0, voxels.shape[1], prototypes.shape[1]), voxels.new_zeros(0, voxels.shape[1],
                                                                                               dtype=torch.bool)
    turned = rotate_yaw(prototypes, -angle.to(prototypes.dtype) * (2 * math.pi / num_angles))
    f = turned[torch.arange(P, device=voxels.device)[:, None], :, voxels[..., 0], voxels[..., 1], voxels[..., 2]]
    valid = f.norm(dim=2) > 1e-6
    return F.normalize(f, dim=2), valid


def prototype_purity(prototype: Tensor, labels: Tensor, query_index: Tensor) -> float:
    """GT measure of the prototype positives (measuring only): over the labelled queries, the mean share of the other
    labelled pool objects in the query's prototype that have the query's label (NaN where no query has such a
    neighbour). ``prototype``, ``labels`` ``[N]`` (label -1: no GT object); ``query_index`` ``[P]``."""
    shares = []
    for q in query_index.tolist():
        if int(labels[q]) < 0:
            continue
        mates = (prototype == prototype[q]) & (labels >= 0)
        mates[q] = False
        if mates.any():
            shares.append(float((labels[mates] == labels[q]).float().mean()))
    return sum(shares) / len(shares) if shares else float("nan")


def shape_agreement(query_occ: Tensor, target_occ: Tensor, num_angles: int, chunk: int = 64
                    ) -> tuple[Tensor, Tensor]:
    """How well each pair's two objects agree in shape: the cosine of the query's input occupancy crop with the
    target's, rotated onto it, at the yaw where it is highest (exact: every yaw step by :func:`rotate_yaw`).

    Args:
        query_occ: ``[P, 1, s, s, s]`` occupancy crops (any non-negative weights); target_occ: the same, pairwise.
        num_angles: yaw steps in a full turn.
        chunk: pairs rotated at once.

    Returns:
        ``cos`` ``[P]`` (0 where a crop is empty) and ``yaw`` ``[P]`` long, the step ``b`` whose rotation of the target
        by ``2 pi b / num_angles`` lies best on the query (the mined yaw's convention); ties go to the lowest ``b``.

    Convention: as the miner's: yaw about the crop's vertical axis through its centre, counter-clockwise seen from
    above; crops ``[Z, Y, X]``.
    """
    P, A = query_occ.shape[0], num_angles
    cos = query_occ.new_zeros(P)
    yaw = torch.zeros(P, dtype=torch.long, device=query_occ.device)
    angles = torch.arange(A, device=query_occ.device, dtype=query_occ.dtype) * (2 * math.pi / A)
    for s in range(0, P, chunk):
        q = F.normalize(query_occ[s:s + chunk].flatten(1), dim=1)  # [n, V]
        t = rotate_yaw(target_occ[s:s + chunk], angles.expand(q.shape[0], A))  # [n, A, 1, s, s, s]
        t = F.normalize(t.flatten(2), dim=2)  # [n, A, V]
        c = torch.einsum("nv,nav->na", q, t)
        cos[s:s + chunk], yaw[s:s + chunk] = c.max(dim=1)
    return cos, yaw


def pool_shape_agreement(occ: Tensor, num_angles: int, chunk: int = 128) -> Tensor:
    """:func:`shape_agreement` of every box of a pool with every other: ``S[n, m]``, the cosine of crop ``n`` with
    crop ``m`` turned onto it, at the yaw where it is highest. One rotation per crop and yaw, then one product per
    chunk of targets: ``N^2 A V`` multiply-adds (512 crops of ``16^3`` at 36 yaws: about a second on 2 cores).

    Args:
        occ: ``[N, C, s, s, s]`` occupancy crops (any non-negative weights; more channels: one cosine over all of
            them). num_angles: yaw steps in a full turn.
        chunk: target crops rotated at once (memory ``chunk * num_angles * C * s^3`` floats).

    Returns:
        ``[N, N]`` cosines (0 where a crop is empty); row: the query, column: the target.

    Convention: as :func:`shape_agreement`'s: yaw about the crop's vertical axis through its centre, crops
    ``[Z, Y, X]``.
    """
    N, A = occ.shape[0], num_angles
    q = F.normalize(occ.flatten(1), dim=1)  # [N, C s^3]
    out = occ.new_zeros(N, N)
    angles = torch.arange(A, device=occ.device, dtype=occ.dtype) * (2 * math.pi / A)
    for s in range(0, N, chunk):
        t = rotate_yaw(occ[s:s + chunk], angles.expand(min(chunk, N - s), A))  # [n, A, C, s, s, s]
        t = F.normalize(t.flatten(2), dim=2)  # [n, A, C s^3]
        out[:, s:s + chunk] = torch.einsum("nv,mav->nma", q, t).amax(dim=2)
    return out


def mutual_pool_neighbours(similarity: Tensor, exclude: Tensor, k: int) -> Tensor:
    """``[N, N]`` bool: ``n`` and ``m`` are each among the other's ``k`` most similar (excluded pairs never count;
    ties go to the lower index, :func:`torch.topk`'s order). Not :func:`threedq.contrastive.mutual_neighbours`,
    which takes a query x target matrix, ranks both sides by the same entry and counts ties at the ``k``-th value:
    here the matrix is the pool against itself and not symmetric (``S[n, m]`` turns ``m`` onto ``n``), so ``n``'s
    neighbours are ranked by row ``n`` and ``m``'s by row ``m``, exactly ``k`` each.

    Args:
        similarity: ``[N, N]``; exclude: ``[N, N]`` bool (e.g. the same scene, the box itself); k: >= 1.
    """
    sim = similarity.masked_fill(exclude, float("-inf"))
    k = min(k, sim.shape[1])
    near = torch.zeros_like(exclude)
    near.scatter_(1, sim.topk(k, dim=1).indices, True)
    return near & near.T & ~exclude


def input_pairs(crops: Tensor, scene: Tensor, n_q: int, k: int, num_angles: int) -> dict[str, Tensor]:
    """Candidate pairs from the input crops alone (``candidates_from: occupancy`` or ``input``): every pair of mutual
    ``k`` nearest neighbours by :func:`pool_shape_agreement` (other scenes only) whose query is one of the first
    ``n_q`` boxes, best agreement first.

    Args:
        crops: ``[N, C, s, s, s]`` input crops (occupancy, or occupancy and colour; non-negative); scene: ``[N]``
            long scene of each box; n_q: queries; k: >= 1; num_angles: yaw steps in a full turn.

    Returns:
        The keys of :func:`~threedq.contrastive.mine_correspondences` the stage reads: ``query_index``,
        ``target_index``, ``yaw`` ``[P]`` long (the agreement's step, :func:`shape_agreement`'s convention),
        ``score`` ``[P]`` (the agreement), ``query_pos``, ``target_pos``, ``target_pos_aligned`` ``[P, 3]`` long
        (zeros: no patch match).
    """
    sim = pool_shape_agreement(crops, num_angles)
    mutual = mutual_pool_neighbours(sim, scene[:, None] == scene[None, :], k)[:n_q]
    qi, ti = mutual.nonzero(as_tuple=True)
    order = torch.sort(sim[qi, ti], descending=True, stable=True).indices
    qi, ti = qi[order], ti[order]
    _, yaw = shape_agreement(crops[qi], crops[ti], num_angles)
    zeros = qi.new_zeros(qi.numel(), 3)
    return {"query_index": qi, "target_index": ti, "yaw": yaw, "score": sim[qi, ti],
            "query_pos": zeros, "target_pos": zeros.clone(), "target_pos_aligned": zeros.clone()}


def shape_cells(query_occ: Tensor, target_occ_aligned: Tensor, count: int,
                generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Where a pair's positives go when they are to be shape agreements by construction: ``count`` cells drawn where
    both objects have input occupancy once the target is turned onto the query (weight: the product of the two).

    Args:
        query_occ: ``[P, 1, s, s, s]``; target_occ_aligned: ``[P, 1, s, s, s]`` the target's, rotated onto the query.
        count: cells per pair, drawn without replacement.
        generator: the draw's generator (CPU).

    Returns:
        ``cells`` ``[P', count]`` long flat indices ``z * s * s + y * s + x`` (:func:`crop_voxels`' order) and ``valid``
        ``[P]`` bool: the pairs with at least ``count`` cells of shared occupancy (the ``P'`` returned, in order).
    """
    w = (query_occ * target_occ_aligned).flatten(1).clamp_min(0)  # [P, s^3]
    valid = (w > 0).sum(dim=1) >= count
    if not valid.any():
        return w.new_zeros(0, count, dtype=torch.long), valid
    return torch.multinomial(w[valid].float().cpu(), count, replacement=False, generator=generator).to(w.device), valid


def recolour_scenes(rgb: Tensor, strength: float) -> Tensor:
    """One random colour transform per scene, the same for all of its views: kornia's ``ColorJitter`` at
    brightness, contrast and saturation ``0.4 * strength`` (MoCo v2's at 1) and hue ``0.5 * strength`` (any hue at 1).

    Args:
        rgb: ``[B, S, 3, H, W]`` in [0, 1], ``S`` views of each of ``B`` scenes.
        strength: in [0, 1]; 0 returns ``rgb`` itself.

    Returns:
        ``[B, S, 3, H, W]`` in [0, 1]. Draws from torch's global generator (a seed reproduces it).

    Convention: RGB channel order; the transform acts on colour only, never on pixel positions, so depth, poses
    and boxes stay valid.
    """
    if not strength:
        return rgb
    from kornia.augmentation import ColorJitter  # the package's augmentation import is slow; only when asked

    jitter = ColorJitter(0.4 * strength, 0.4 * strength, 0.4 * strength, 0.5 * strength, same_on_batch=True, p=1.0)
    return torch.stack([jitter(scene.float()).clamp(0, 1).to(rgb.dtype) for scene in rgb])


def gt_box_iou(batch: dict[str, Any]) -> Tensor:
    """``[N]`` for the batch's valid boxes (``box_mask`` order): the highest 3D IoU with a GT object box of its scene
    (``gt_aabb``/``gt_mask``; measuring only: the pair diagnostics' looser "on an object"); NaN where the batch
    carries no GT boxes, 0 where the scene has none."""
    mask = batch["box_mask"]
    if "gt_aabb" not in batch or "gt_mask" not in batch:
        return torch.full((int(mask.sum()),), float("nan"), device=mask.device)
    gt, gt_mask = batch["gt_aabb"], batch["gt_mask"]
    return torch.cat([best_aabb_iou(batch["aabb"][i][mask[i]].float(), gt[i][gt_mask[i]].float())
                      for i in range(mask.shape[0])])


def cap_pairs_per_box(query_index: Tensor, target_index: Tensor, cap: int) -> Tensor:
    """``[P]`` bool: walking the pairs in the given (rank) order, keep a pair only while each of its two boxes is in
    fewer than ``cap`` kept pairs (as query or target). A box whose crop agrees with many (a thin object, a part
    cut short) then cannot take most of a refresh's pairs.

    Args:
        query_index, target_index: ``[P]`` pool indices of each pair's boxes, best pair first. cap: >= 1.
    """
    used: dict[int, int] = {}
    keep = torch.zeros(query_index.numel(), dtype=torch.bool, device=query_index.device)
    for n, (q, t) in enumerate(zip(query_index.tolist(), target_index.tolist())):
        if used.get(q, 0) < cap and used.get(t, 0) < cap:
            keep[n] = True
            used[q] = used.get(q, 0) + 1
            used[t] = used.get(t, 0) + 1
    return keep


def oracle_pairs(labels: Tensor, scene: Tensor, yaw: Tensor, n_q: int, per_query: int, count: int, num_angles: int,
                 generator: torch.Generator | None = None) -> dict[str, Tensor]:
    """A diagnostic that uses labels (``oracle_pairs: "gt"``; never for a real run): the pairs a perfect miner would
    give, to tell what the learning makes of right pairs from what the miner gives it. Each of the first ``n_q`` pool
    boxes that matches a GT object is paired with up to ``per_query`` boxes of other scenes whose GT object is of the
    same category (drawn at random), at the GT relative yaw. The pairs are interleaved (every query's first target,
    then every query's second, ...) and cut at ``count``.

    Args:
        labels: ``[N]`` long GT category of each pool box (-1: no GT object); scene: ``[N]`` long scene of each box;
        yaw: ``[N]`` GT yaw (radians) of each box's object; n_q: queries (the first boxes); per_query, count: >= 1;
        num_angles: yaw steps in a full turn; generator: the draw's generator (CPU).

    Returns:
        The keys of :func:`~threedq.contrastive.mine_correspondences` the stage reads: ``query_index``,
        ``target_index``, ``yaw`` ``[P]`` long (the step nearest to ``query_yaw - target_yaw``), ``score`` ``[P]``
        (ones), ``query_pos``, ``target_pos`` and ``target_pos_aligned`` ``[P, 3]`` long (zeros: no patch match).

    Convention: the mined yaw's: ``rotate_yaw(target, 2 pi yaw / num_angles)`` turns the target onto the query.
    """
    q_list, t_list = [labels.new_zeros(0, dtype=torch.long).cpu()], [labels.new_zeros(0, dtype=torch.long).cpu()]
    lab, sc = labels.cpu(), scene.cpu()
    for i in range(min(n_q, lab.numel())):
        if lab[i] < 0:
            continue
        cand = ((lab == lab[i]) & (sc != sc[i])).nonzero().flatten()
        cand = cand[torch.randperm(cand.numel(), generator=generator)[:per_query]]
        q_list.append(torch.full_like(cand, i))
        t_list.append(cand)
    qi, ti = torch.cat(q_list), torch.cat(t_list)
    order = spread_candidates(qi, per_query, count)  # every query's first target before any second one
    qi, ti = qi[order].to(labels.device), ti[order].to(labels.device)
    step = 2 * math.pi / num_angles
    b = torch.round(torch.remainder((yaw[qi] - yaw[ti]).double(), 2 * math.pi) / step).long() % num_angles
    zeros = qi.new_zeros(qi.numel(), 3)
    return {"query_index": qi, "target_index": ti, "yaw": b, "score": yaw.new_ones(qi.numel()),
            "query_pos": zeros, "target_pos": zeros.clone(), "target_pos_aligned": zeros.clone()}


def spread_candidates(query_index: Tensor, per_query: int, count: int) -> Tensor:
    """Indices of the candidate pairs that spread over the queries: each query's first ``per_query`` pairs (in the
    given rank order), every query's best before any query's second (round-robin, ties in rank order), cut at
    ``count``. The globally most similar pairs otherwise crowd onto the queries with the nearest neighbours.

    Args:
        query_index: ``[P]`` pool index of each pair's query, best pair first. per_query, count: >= 1.

    Returns:
        ``[P']`` long indices into the pairs, ``P' <= min(count, P)``, in the new order.
    """
    P = query_index.numel()
    if P == 0:
        return torch.zeros(0, dtype=torch.long, device=query_index.device)
    order = torch.sort(query_index, stable=True).indices  # pairs grouped by query, rank order within a query
    q = query_index[order]
    start = torch.ones_like(q, dtype=torch.bool)
    start[1:] = q[1:] != q[:-1]
    group_start = torch.cummax(torch.where(start, torch.arange(P, device=q.device), 0), dim=0).values
    rank = torch.empty_like(order)
    rank[order] = torch.arange(P, device=q.device) - group_start  # each pair's rank among its query's pairs
    pos = torch.arange(P, device=q.device)
    keep = (rank < per_query).nonzero().flatten()
    return keep[torch.sort(rank[keep] * P + pos[keep], stable=True).indices][:count]


def take_pairs(mined: dict[str, Any], idx: Tensor) -> dict[str, Any]:
    """The pairs ``idx`` of a :func:`~threedq.contrastive.mine_correspondences` result (its per-pair ``[P, ...]``
    tensors indexed, the rest kept)."""
    n = mined["query_index"].shape[0]
    return {k: v[idx] if isinstance(v, Tensor) and v.shape[:1] == (n,) else v for k, v in mined.items()}


def crop_voxels(crops: Tensor, idx: Tensor) -> Tensor:
    """The L2-normalised features ``[N, V, C]`` of crops ``[N, C, s, s, s]`` at flat cell indices ``idx`` ``[N, V]``
    (row-major over ``(z, y, x)``, i.e. ``z * s * s + y * s + x``): the view-contrastive positives' queries and keys."""
    flat = crops.flatten(2)  # [N, C, s^3]
    return F.normalize(flat.gather(2, idx[:, None].expand(-1, flat.shape[1], -1)).transpose(1, 2), dim=2)


def implied_yaw_error_deg(yaw_index: Tensor, num_angles: int, query_yaw: Tensor, target_yaw: Tensor,
                          symmetry: Tensor) -> Tensor:
    """Error (degrees) of a mined yaw against GT: rotating the target by ``2 pi b / A`` should equal
    ``query_yaw - target_yaw``, modulo the category's symmetry ``2 pi / symmetry``.

    Args:
        yaw_index: ``[P]`` long mined yaw steps; query_yaw, target_yaw: ``[P]`` GT yaws (radians);
        symmetry: ``[P]`` long yaw symmetry order of the category (1 = asymmetric).

    Returns:
        ``[P]`` errors in ``[0, 180 / symmetry]`` degrees.
    """
    period = 2 * math.pi / symmetry.to(torch.float64)
    d = yaw_index.to(torch.float64) * (2 * math.pi / num_angles) - (query_yaw - target_yaw).to(torch.float64)
    d = torch.remainder(d, period)
    return torch.rad2deg(torch.minimum(d, period - d))



class Mining(SplitEvaluation, ViewPredictionObjective, EncoderStage):
    """The correspondence-learning stage (``vc``, ``vc_moco`` or ``mined``; see the module docstring).

    Args:
        **kwargs: the encoder's arguments (``grid_min``, ``grid_max``, ``grid_resolution``, ``feature_dim``,
            ``encoder_channels``, ``feature_stride``, ``encoder_ckpt``, ``freeze_encoder``, ``channels_last``), by keyword: see
            :class:`~threedq.stages.base.EncoderStage` (the encoder comes from view prediction or an earlier
            round, and is fine-tuned).
        source: ``"vc"``, ``"vc_moco"`` or ``"mined"``.
        queue_size: MoCo negatives Q (paper: 100,000).
        momentum: MoCo key-encoder momentum (paper: 0.999).
        temperature: InfoNCE temperature (paper: 0.07).
        lr: Adam learning rate of the fine-tuning.
        crop_size: object crops are ``crop_size^3`` (paper: 16).
        voxels_per_object: ``vc``/``vc_moco``: points sampled per object box (lineage: ~256).
        query_pool: ``mined``: query crops per refresh (paper: 1000; 256 fits the CPU budget: mining costs ~0.2 s
            per query on 2 cores).
        target_pool: ``mined``: crops cut per refresh; queries are the first ``query_pool`` of them, targets all
            of them from other scenes (paper: 1000).
        top_k: targets retrieved per query (paper: 30). This and the miner's settings after ``keep`` up to
            ``retrieval_occupancy_floor`` act on the miner's candidates (``candidates_from: "features"``) only.
        keep: verified pairs kept per refresh (paper: 200).
        num_angles: yaw steps of retrieval and patch search (paper: 36).
        patch: query patch edge in voxels (paper: 2).
        search_grid: patch-grid positions per axis in each target (paper: 4).
        context_distance: Manhattan distance of the context patches (paper: 6).
        min_cosine: cosine at which a context patch counts as found; ``None`` calibrates it per refresh as the
            ``context_quantile`` quantile, over random patch pairs of different pool crops, of the best cosine
            within +-1 voxel (on view-prediction features any fixed threshold up to ~0.95 passes every context
            patch).
        context_quantile: the quantile of that calibration.
        min_score: verification score (fraction of context found) a pair needs.
        corner_offset: positives are the corners of a ``2 * corner_offset`` cube around the match (lineage: 8^3).
        corner_search: each corner's key is its best match within ``+-corner_search`` voxels (lineage: 3^3).
        yaw_window: search the query patch only within this many yaw steps of the object-level retrieval's yaw
            (``None``: all yaws, as the paper; see :func:`~threedq.contrastive.mine_correspondences`; 1 keeps the
            patch yaw consistent with the object's: mined pairs of one category 0.29 -> 0.33, yaw error 69 -> 12 deg).
        rank_by: which verified pairs are kept: ``"score"`` (verification score, the paper's) or
            ``"retrieval"`` (object-level similarity among the verified ones; with the context quantile, pairs of one
            category 0.43 -> 0.69, ``configs/stages/mining.yaml``).
        csls_k: retrieve the targets and rank the pairs by CSLS scores over ``csls_k`` neighbours instead of the plain
            rotation-max cosine (:func:`~threedq.contrastive.csls_scores`: a box close to every other, such as
            empty floor or a near-duplicate, loses its lead; not in the paper). None: the cosine, the paper's.
        mutual_k: retrieve only mutual ``mutual_k``-nearest neighbours by the plain rotation-max cosine
            (:func:`~threedq.contrastive.mutual_neighbours`; not in the paper): fewer targets to match; with
            ``csls_k: 10`` it kept the same pairs at about half the mining time. None: every target, the paper's.
        retrieval_occupancy_floor: run the object-level retrieval (targets, the ranking's similarity, the yaw of
            ``yaw_window``) on the pool's crops weighted by their input occupancy with this floor, the similarity
            the quantizer's prototypes use (:func:`~threedq.quantization.prototypes.prototype_crops`; not in the
            paper); patches are matched and verified on the plain crops. None: the plain crops, the paper's. 0.2
            (the quantizer's floor) is the default since issue #63's twenty-first session: with the occupancy
            positives it lifts the shape-only rounds' retrieval (2 seeds, round 4 paper protocol +0.030) at about
            the embedded rounds' (-0.007; Hungarian +0.002), docs/studies/mined-pairs.md.
        refresh_every: steps between pool refreshes (the first is at step 0; lineage: 200).
        pairs_per_step: mined pairs (query scenes encoded) per training step.
        view_positives: ``mined``: per object box of the step's query scenes, voxels whose input-view feature is
            contrasted with the same voxel seen from a second view set by the key encoder (0: off, the paper's
            mined source alone; needs the data's ``num_target_views >= num_input_views``).
        view_weight: ``mined``: weight of that multi-view term in the loss.
        view_prediction_weight: ``mined``: weight of the view-prediction loss kept as a regulariser (0: off; see the
            module docstring; needs an ``encoder_ckpt`` that carries the decoder, and ``num_target_views >= 1``).
        view_prediction_rgb: with ``view_prediction_weight > 0``: keep the whole view-prediction loss (true, default)
            or only its occupancy term (false: ``occ_weight`` x the balanced occupancy loss with raycast free space,
            the term that keeps shape when it trains from the start, docs/studies/shape.md): the decoder is then
            neither run nor trained, and is carried on unchanged in the checkpoint for the next round. Not in the
            paper. At weight 1 it keeps no shape on the shape-only data and lifts the embedded few-shot accuracy
            (docs/studies/mined-pairs.md): off.
        correspondence_weight: ``mined``: weight of the mined pairs' InfoNCE (default 1, the paper's only term). 0
            leaves the pairs mined and enqueued but out of the loss: an ablation, allowed only where another term
            (``view_prediction_weight``, ``prototype_weight`` or ``view_positives``) trains the encoder.
        pool_batch_size: scenes encoded at once while cutting the pool.
        pool_min_observed_iou: ``mined``: a box enters the pool only when the geometry of its scene's input views
            vouches for it: its 3D IoU with one of those views' label-free pseudo-boxes
            (:func:`~threedq.box_refinement.observed_boxes`, observed surface above the fitted ground, the boxes the
            detector snaps to) reaches this value (default 0.5). ``None``: every box of the split (the paper's pool,
            which on detected boxes also holds boxes on empty floor, whose crops are the most alike). Label-free; a
            departure from the paper (docs/studies/mined-pairs.md, "The object check alone").
        pool_min_scene_iou: ``mined``: a box enters the pool only when the geometry of its whole training scene
            vouches for it too: its 3D IoU with one of the label-free pseudo-boxes fused over the scene's views (the
            DataModule's ``pseudo_boxes``: observed surface above the fitted ground over every second view, what the
            detector's warm start learns from, cached per split) reaches this value. The input view's check above
            passes boxes cut short to the part of an object one view sees (the detector snaps to that view's
            surface); the fused views see most of each object, so this check drops them (default 0.7; ``None``:
            off). Label-free: the views are the training scene's own, which view prediction learns from. Not in the
            paper (docs/studies/mined-pairs.md, "The scene's views vouch for the box").
        bank_ckpt: ``mined``: the prototype bank the pool's encoder was last quantized with (a quantizer
            checkpoint; ``threedq em`` passes the previous round's, round 1 gets round 0's), for
            ``verify_by_prototypes`` and ``prototype_weight``.
        verify_by_prototypes: ``mined``: keep only mined pairs whose two objects the bank assigns to one prototype
            at yaws that agree with the pair's mined yaw (within ``prototype_yaw_window`` steps): the quantizer
            vouches for the pair's category and pose (a departure from the paper, whose pairs are verified by
            context patches alone). The miner is asked for ``prototype_oversample`` x ``keep`` pairs and the best
            ``keep`` that pass are kept. Needs ``bank_ckpt``; label-free.
        prototype_yaw_window: the largest disagreement, in yaw steps, between the mined yaw and the one the two
            prototype assignments imply.
        prototype_weight: ``mined``: weight of a second positive for each mined pair's query voxels: the same cells
            of the prototype the bank (``bank_ckpt``) assigns the query object to, turned to the object's frame by
            its assigned yaw, against the same queue of negatives (0: off, the paper's). The quantizer feeding the
            correspondence learner, so that objects move towards their prototype; a departure from the paper
            (docs/studies/mined-pairs.md, "The prototypes as positives"). Needs ``bank_ckpt``; label-free.
        prototype_oversample: see ``verify_by_prototypes``.
        positives: ``mined``: what each kept pair teaches. ``"patches"`` (the paper's): the 8 corners around the
            verified patch match, each keyed by its best-matching target voxel (``corner_offset``, ``corner_search``):
            the features vouch for the correspondence. ``"occupancy"`` (not in the paper): the miner is asked for
            ``shape_oversample`` x ``keep`` pairs; each pair's yaw is re-found on the two objects' input occupancy
            (:func:`shape_agreement`, 3^3-dilated crops, every yaw step), the ``keep`` pairs whose occupancy agrees
            best are kept, and their positives are 8 cells where both objects are occupied at that yaw, each keyed
            by the target's feature at the same cell (:func:`shape_cells`): the geometry vouches for the
            correspondence, so the positives are shape agreements by construction. Label-free; the default.
        shape_oversample: see ``positives``.
        max_pairs_per_box: with ``positives: occupancy``: walking the ranked pairs, a box takes part in at most this
            many kept pairs, as query or target (:func:`cap_pairs_per_box`); ``None`` (default): no cap. Crops
            that agree with many others (thin objects, parts cut short) otherwise take a large share of a
            refresh's pairs. Label-free; not in the paper (docs/studies/mined-pairs.md, "Pairs per box").
        negatives: ``mined``: what the InfoNCE contrasts the positives with. ``"queue"`` (MoCo's, the paper's): the
            queue of past keys; it is primed with random voxels of the first refresh's pool and every step's keys
            are enqueued after the loss. ``"pool"`` (not in the paper): random voxels of the latest refresh's pool,
            drawn afresh at every refresh; the step's keys are not enqueued. The keys are the features of the
            parts the pairs put in correspondence, mostly on objects of the queries' categories, and each pair is
            drawn ``refresh_every * pairs_per_step / keep`` times a refresh on average (2 by default), so in MoCo's
            queue later queries meet them (their own pair's earlier keys among them) as negatives: false negatives
            at the highest cosines, which the temperature turns into the largest pushes. Label-free. Measured on
            the shape-only data (seed 0, both kinds of positives) it changes nothing: the queue's keys are not what
            lowers those rounds (docs/studies/mined-pairs.md): off.
        candidates_per_query: ``mined``: the candidates handed to the ranking (``keep`` x ``shape_oversample`` with
            the occupancy positives) are each query's best ``candidates_per_query`` verified pairs, every query's
            best before any query's second (:func:`spread_candidates`), instead of the globally most similar pairs
            (``None``, the paper's). Default 2: with ``candidates_from`` other than ``"features"``, each query's two
            best mutual neighbours. Label-free; not in the paper: with the most similar pairs the pairs
            crowd onto the queries whose neighbours are nearest, and pairs of one category drawn across the pool
            are what raises the rounds (docs/studies/mined-pairs.md, "Pairs from GT").
        occupancy_mutual_k: ``mined`` with the occupancy positives: keep only the verified candidate pairs whose two
            boxes are each among the other's ``k`` best matches of the pool (other scenes) by input-occupancy shape
            agreement over every yaw (:func:`pool_shape_agreement`, :func:`mutual_pool_neighbours`), in the miner's
            rank order, then cut at ``keep`` (no shape oversampling: the check is the shape ranking). ``None``:
            every candidate, the ``shape_oversample`` x ``keep`` most similar, ranked by shape agreement. Label-free;
            not in the paper (it mines with the learned features alone): the features' nearest neighbours and the
            input geometry's must agree, and a pair need not be the pool's most similar one to be kept. With
            ``candidates_per_query`` the pairs spread over the queries. Costs one ``N x N`` agreement per refresh.
            On the shape-only data (2 seeds) it makes the pairs purer and the rounds lower: the features propose
            pairs only within the categories they already match (docs/studies/mined-pairs.md, "The input proposes
            the pairs"). Default 10, the ``k`` of the default ``candidates_from: input``.
        candidates_from: ``mined`` with ``occupancy_mutual_k``: ``"features"`` (the paper's): the candidates
            are the miner's verified pairs by the learned features, checked by the input geometry. ``"occupancy"``:
            the candidates are the mutual neighbours of the input occupancy crops themselves (every such pair with a
            query among the first ``query_pool`` boxes, best agreement first; :func:`input_pairs`); ``"input"``: the
            same on the whole unprojected input crop, occupancy and colour (``cat[occ, occ * rgb]``, each channel
            with the 3^3 dilation). The learned features then choose no pair. Label-free; a departure from the
            paper: the input proposes the pairs, the features learn from them. ``"occupancy"`` (with k = 10, as
            ``stages/mining_occupancy_pairs.yaml`` sets) raises every round on data whose categories are shapes
            and joins colours of one shape where colour is part of the category (2 seeds each, same study).
            ``"input"`` (default since issue #63's twenty-eighth session; k = 10, two candidates per query): pairs
            on two GT objects 0.97-0.99 of every refresh at 4-6 deg on both data sets, one category 0.73 on the
            embedded data (the features' 0.56-0.76) and 0.92 on the shape-only data; round 4 at or above the
            features' candidates (embedded paper protocol 0.517 vs 0.508, round 3 at round 0 + 0.051; shape-only
            0.449 vs 0.445), Hungarian 0.587 vs 0.595 on the embedded data (2 seeds each, AMD EPYC).
        oracle_pairs: a diagnostic that uses labels, never for a real run (default ``None``: the miner's pairs).
            ``"gt"``: each refresh's candidate pairs come from GT instead of the miner (:func:`oracle_pairs`: boxes
            on GT objects of one category, in other scenes, drawn at random), ranked by the occupancy positives'
            shape agreement and posed at the GT relative yaw. ``"gt_category"``: the same pairs, posed at the shape
            agreement's yaw (the stage's own posing). ``"mined_gt_filtered"``: the miner's candidates, less those
            not on two GT objects of one category, then the stage's ranking and posing. Everything else (pool,
            checks, InfoNCE, queue, rate) is the stage's own, so runs with them tell what the learning makes of
            right pairs and which of their properties it needs (docs/studies/mined-pairs.md, "Pairs from GT").
        colour_jitter: ``mined``: recolour each step's query scenes at random (:func:`recolour_scenes`, one
            transform per scene, ``0`` off: the paper's, default). The keys were encoded at the refresh from the
            targets' own colours, so a positive cannot be matched by colour: a test of whether the miner teaches
            the colour of the pairs' objects rather than their shape (on data whose instances are coloured at
            random, the pairs of one colour are the most similar, and the negatives differ in colour). Label-free;
            not in the paper (MoCo v2 jitters the colours of its views; docs/studies/mined-pairs.md).
        round_lr: the learning rate across EM rounds: ``"constant"`` (``lr`` in every round, the paper's) or
            ``"harmonic"`` (default; ``lr / em_round``: the decreasing step of stochastic-approximation EM, so that
            later rounds refine the encoder rather than move it as far again; a departure from the paper, see
            docs/studies/mined-pairs.md). Outside ``threedq em`` (``em_round`` 1) both are ``lr``.
        em_round: the EM round this stage runs in (``threedq em`` sets it; 1 outside the loop).
        seed: seed of the pool draws (offset by the refresh count and the process rank).
        retrieval_k: K of the validation/test precision@K.
        symmetry_order: per category, its yaw symmetry order, for the mined pairs' yaw-error diagnostics only (the
            threedq CLI links it from the dataset's ``index.json``; ``None``: not scored by symmetry).

    Convention: see the module docstring.
    """

    def __init__(
        self,
        *,
        source: Literal["vc", "vc_moco", "mined"] = "mined",
        queue_size: int = 100_000,
        momentum: float = 0.999,
        temperature: float = 0.07,
        lr: float = 1e-4,
        crop_size: int = 16,
        voxels_per_object: int = 256,
        query_pool: int = 256,
        target_pool: int = 512,
        top_k: int = 30,
        keep: int = 200,
        num_angles: int = 36,
        patch: int = 2,
        search_grid: int = 4,
        context_distance: int = 6,
        min_cosine: float | None = None,
        context_quantile: float = 0.95,
        min_score: float = 0.5,
        corner_offset: int = 4,
        corner_search: int = 1,
        yaw_window: int | None = 1,
        rank_by: Literal["score", "retrieval"] = "retrieval",
        csls_k: int | None = None,
        mutual_k: int | None = None,
        retrieval_occupancy_floor: float | None = 0.2,
        refresh_every: int = 100,
        pairs_per_step: int = 4,
        view_positives: int = 0,
        view_weight: float = 1.0,
        view_prediction_weight: float = 0.0,
        view_prediction_rgb: bool = True,
        correspondence_weight: float = 1.0,
        projection_dim: int | None = None,
        projection_lr: float = 1e-3,
        pool_batch_size: int = 4,
        pool_min_observed_iou: float | None = 0.5,
        pool_min_scene_iou: float | None = 0.7,
        bank_ckpt: str | None = None,
        verify_by_prototypes: bool = False,
        prototype_yaw_window: int = 2,
        prototype_oversample: int = 4,
        prototype_weight: float = 0.0,
        positives: Literal["patches", "occupancy"] = "occupancy",
        shape_oversample: int = 4,
        max_pairs_per_box: int | None = None,
        negatives: Literal["queue", "pool"] = "queue",
        oracle_pairs: Literal["gt", "gt_category", "mined_gt_filtered"] | None = None,
        candidates_per_query: int | None = 2,
        occupancy_mutual_k: int | None = 10,
        candidates_from: Literal["features", "occupancy", "input"] = "input",
        colour_jitter: float = 0.0,
        round_lr: Literal["constant", "harmonic"] = "harmonic",
        em_round: int = 1,
        seed: int = 0,
        retrieval_k: int = 10,
        symmetry_order: list[int] | None = None,
            **kwargs: Any,
    ) -> None:
        if source not in SOURCES:
            raise ValueError(f"source: expected one of {SOURCES}, got {source!r}")
        if kwargs.get("freeze_encoder"):
            raise ValueError("freeze_encoder: the mining stage fine-tunes the encoder; it cannot be frozen")
        for name, v in (("voxels_per_object", voxels_per_object), ("query_pool", query_pool),
                        ("target_pool", target_pool), ("keep", keep), ("refresh_every", refresh_every),
                        ("pairs_per_step", pairs_per_step), ("pool_batch_size", pool_batch_size),
                        ("top_k", top_k), ("crop_size", crop_size)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        if isinstance(view_positives, bool) or not isinstance(view_positives, int) or view_positives < 0:
            raise ValueError(f"view_positives: expected an int >= 0, got {view_positives!r}")
        if view_positives and source != "mined":
            raise ValueError(f"view_positives: the multi-view positive is a term of the mined source; source "
                             f"{source!r} has its own view pairs (voxels_per_object)")
        if isinstance(view_weight, bool) or not isinstance(view_weight, (int, float)) or not view_weight > 0:
            raise ValueError(f"view_weight: expected a number > 0, got {view_weight!r}")
        for name, w in (("view_prediction_weight", view_prediction_weight), ("prototype_weight", prototype_weight),
                        ("correspondence_weight", correspondence_weight)):
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not w >= 0:
                raise ValueError(f"{name}: expected a number >= 0, got {w!r}")
        if not correspondence_weight and not (view_prediction_weight or prototype_weight or view_positives):
            raise ValueError("correspondence_weight: 0 leaves the mined source no loss; keep it > 0 or set "
                             "view_prediction_weight, prototype_weight or view_positives")
        if view_prediction_weight and source != "mined":
            raise ValueError(f"view_prediction_weight: the view-prediction regulariser is a term of the mined source, "
                             f"not of source {source!r}")
        if not isinstance(view_prediction_rgb, bool):
            raise ValueError(f"view_prediction_rgb: expected true or false, got {view_prediction_rgb!r}")
        if not view_prediction_rgb and not view_prediction_weight:
            raise ValueError("view_prediction_rgb: false keeps only the occupancy term of the view-prediction "
                             "regulariser, which is off (view_prediction_weight 0); set view_prediction_weight > 0")
        if view_prediction_weight and not kwargs.get("encoder_ckpt"):
            raise ValueError("view_prediction_weight: the regulariser's decoder comes from encoder_ckpt; none given")
        if query_pool > target_pool:
            raise ValueError(f"query_pool: the queries are the first query_pool of the target_pool crops, so "
                             f"query_pool ({query_pool}) must be <= target_pool ({target_pool})")
        if pool_min_observed_iou is not None and (isinstance(pool_min_observed_iou, bool) or not isinstance(
                pool_min_observed_iou, (int, float)) or not 0.0 < pool_min_observed_iou <= 1.0):
            raise ValueError(f"pool_min_observed_iou: expected None or a number in (0, 1], got {pool_min_observed_iou!r}")
        if pool_min_scene_iou is not None and (isinstance(pool_min_scene_iou, bool) or not isinstance(
                pool_min_scene_iou, (int, float)) or not 0.0 < pool_min_scene_iou <= 1.0):
            raise ValueError(f"pool_min_scene_iou: expected None or a number in (0, 1], got {pool_min_scene_iou!r}")
        f = retrieval_occupancy_floor
        if f is not None and (isinstance(f, bool) or not isinstance(f, (int, float)) or not 0.0 <= f < math.inf):
            raise ValueError(f"retrieval_occupancy_floor: expected None or a number >= 0, got {f!r}")
        for name, k in (("csls_k", csls_k), ("mutual_k", mutual_k)):
            if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
                raise ValueError(f"{name}: expected None or an int >= 1, got {k!r}")
        if verify_by_prototypes and not bank_ckpt:
            raise ValueError("verify_by_prototypes: the pairs are verified by a prototype bank; no bank_ckpt given "
                             "(threedq em passes the previous round's; on its own, give --model.init_args.bank_ckpt="
                             "<a quantizer checkpoint of this encoder> or --model.init_args.verify_by_prototypes=false)")
        for name, v, lo in (("prototype_yaw_window", prototype_yaw_window, 0),
                            ("prototype_oversample", prototype_oversample, 1)):
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name}: expected an int >= {lo}, got {v!r}")
        if prototype_weight and source != "mined":
            raise ValueError(f"prototype_weight: the prototype positives are a term of the mined source, not of source "
                             f"{source!r}")
        if prototype_weight and not bank_ckpt:
            raise ValueError("prototype_weight: the positives come from a prototype bank; no bank_ckpt given (threedq "
                             "em passes the previous round's; on its own, give --model.init_args.bank_ckpt=<a "
                             "quantizer checkpoint of this encoder> or --model.init_args.prototype_weight=0)")
        if projection_dim is not None and (isinstance(projection_dim, bool) or not isinstance(projection_dim, int)
                                           or projection_dim < 1):
            raise ValueError(f"projection_dim: expected None or an int >= 1, got {projection_dim!r}")
        if projection_dim is not None and source == "vc":
            raise ValueError("projection_dim: the projection head serves the queue's InfoNCE (source 'mined' or "
                             "'vc_moco'); source 'vc' contrasts in-batch")
        if isinstance(projection_lr, bool) or not isinstance(projection_lr, (int, float)) or not projection_lr > 0:
            raise ValueError(f"projection_lr: expected a number > 0, got {projection_lr!r}")
        if positives not in ("patches", "occupancy"):
            raise ValueError(f"positives: expected 'patches' or 'occupancy', got {positives!r}")
        if isinstance(shape_oversample, bool) or not isinstance(shape_oversample, int) or shape_oversample < 1:
            raise ValueError(f"shape_oversample: expected an int >= 1, got {shape_oversample!r}")
        if max_pairs_per_box is not None and (isinstance(max_pairs_per_box, bool) or not isinstance(
                max_pairs_per_box, int) or max_pairs_per_box < 1):
            raise ValueError(f"max_pairs_per_box: expected None or an int >= 1, got {max_pairs_per_box!r}")
        if max_pairs_per_box is not None and positives != "occupancy":
            raise ValueError(f"max_pairs_per_box: caps the occupancy ranking's pairs (positives: occupancy), not "
                             f"positives {positives!r}")
        if negatives not in ("queue", "pool"):
            raise ValueError(f"negatives: expected 'queue' or 'pool', got {negatives!r}")
        if isinstance(colour_jitter, bool) or not isinstance(colour_jitter, (int, float)) \
                or not 0.0 <= colour_jitter <= 1.0:
            raise ValueError(f"colour_jitter: expected a number in [0, 1], got {colour_jitter!r}")
        if colour_jitter and source != "mined":
            raise ValueError(f"colour_jitter: recolours the mined source's query scenes; source {source!r} has none "
                             f"(use 0)")
        if negatives == "pool" and source != "mined":
            raise ValueError(f"negatives: 'pool' draws the negatives from the mined source's pool; source {source!r} "
                             f"has no pool (use 'queue')")
        cpq = candidates_per_query
        if cpq is not None and (isinstance(cpq, bool) or not isinstance(cpq, int) or cpq < 1):
            raise ValueError(f"candidates_per_query: expected null or an int >= 1, got {candidates_per_query!r}")
        omk = occupancy_mutual_k
        if omk is not None and (isinstance(omk, bool) or not isinstance(omk, int) or omk < 1):
            raise ValueError(f"occupancy_mutual_k: expected null or an int >= 1, got {occupancy_mutual_k!r}")
        if omk is not None and source == "mined" and positives != "occupancy":  # the other sources mine no pairs
            raise ValueError("occupancy_mutual_k: the input crops' mutual neighbours propose or check the mined "
                             f"pairs for the occupancy positives; positives {positives!r} needs the miner's own "
                             "patch matches: set occupancy_mutual_k: null and candidates_from: features (the paper's "
                             "miner), or positives: occupancy")
        if candidates_from not in ("features", "occupancy", "input"):
            raise ValueError(f"candidates_from: expected 'features', 'occupancy' or 'input', got {candidates_from!r}")
        if candidates_from != "features" and omk is None:
            raise ValueError(f"candidates_from: {candidates_from!r} takes the input crops' mutual neighbours as the "
                             "candidates; set occupancy_mutual_k (e.g. 10)")
        if oracle_pairs not in (None, *ORACLES):
            raise ValueError(f"oracle_pairs: expected null or one of {ORACLES}, got {oracle_pairs!r}")
        if oracle_pairs and (source != "mined" or positives != "occupancy"):
            raise ValueError("oracle_pairs: the GT pairs replace the mined source's miner and are posed by the "
                             f"occupancy positives; source {source!r} with positives {positives!r} has no place for "
                             "them (source: mined, positives: occupancy)")
        if positives == "occupancy" and verify_by_prototypes:
            raise ValueError("positives: 'occupancy' ranks the mined pairs by shape agreement; with "
                             "verify_by_prototypes the bank ranks them too: choose one (positives: patches, "
                             "the paper's, to verify by prototypes)")
        if round_lr not in ("constant", "harmonic"):
            raise ValueError(f"round_lr: expected 'constant' or 'harmonic', got {round_lr!r}")
        if isinstance(em_round, bool) or not isinstance(em_round, int) or em_round < 1:
            raise ValueError(f"em_round: expected an int >= 1, got {em_round!r}")
        if min_cosine is not None and not -1.0 <= min_cosine <= 1.0:
            raise ValueError(f"min_cosine: expected None or a number in [-1, 1], got {min_cosine!r}")
        if not 0.0 < context_quantile < 1.0:
            raise ValueError(f"context_quantile: expected a number in (0, 1), got {context_quantile!r}")
        if 2 * corner_offset > crop_size:
            raise ValueError(f"corner_offset: a cube of 2 * {corner_offset} voxels does not fit a crop of {crop_size}")
        super().__init__(**kwargs)
        self.save_hyperparameters()
        self.moco = MomentumContrast(self.encoder, dim=self.feature_dim, queue_size=queue_size, momentum=momentum,
                                     temperature=temperature)
        self.register_buffer("queue_primed", torch.zeros((), dtype=torch.bool))
        self.register_buffer("refreshes", torch.zeros((), dtype=torch.long))
        self.metrics = torch.nn.ModuleDict({
            split: RetrievalPrecisionAtK(k=retrieval_k, num_angles=num_angles) for split in ("val", "test")
        })
        self._pairs: dict[str, Tensor] | None = None
        self._pool_stats = {"boxes": 0, "vouched": 0, "scene_vouched": 0}
        self._scene_boxes: dict[str, Any] | None = None  # the training split's fused pseudo-boxes (pool_min_scene_iou)
        self._candidates = 0
        self._refreshed_at = -1
        self._vp: dict[str, Any] | None = None  # the regulariser's settings (VIEW_PREDICTION_SETTINGS)
        if view_prediction_weight:
            settings, dec, occ = view_prediction_checkpoint(kwargs["encoder_ckpt"])
            self._vp = settings
            self.decoder = ViewDecoder(in_channels=self.feature_dim, num_planes=settings["num_planes"],
                                       pool=settings["pool"])
            self.occ_head = OccupancyHead(in_channels=self.feature_dim)
            for name, module, state in (("decoder", self.decoder, dec), ("occ_head", self.occ_head, occ)):
                try:
                    module.load_state_dict(state)
                except RuntimeError as e:
                    raise InputError(f"{kwargs['encoder_ckpt']}: field '{name}.*': does not fit this "
                                     f"{name}: {str(e).splitlines()[0]}") from e
            if not view_prediction_rgb:  # the occupancy term alone: the decoder is carried, not trained
                self.decoder.requires_grad_(False)
        self.projection: torch.nn.Module | None = None
        if projection_dim is not None:
            self.projection = self._projection_head(self.feature_dim, projection_dim, kwargs.get("encoder_ckpt"))
        self._projected_queue: Tensor | None = None  # the queue through the head, once a step
        # bank_ckpt's bank (for verify_by_prototypes and prototype_weight), not this stage's state: kept out of the
        # module tree (so out of the state_dict, the optimizer and device moves; assign_pool moves it)
        self.__dict__["verify_bank"] = None
        self._bank_floor: float | None = None
        if verify_by_prototypes or prototype_weight:
            self.__dict__["verify_bank"], self._bank_floor = self._load_bank(bank_ckpt, num_angles, crop_size)
        #: per refresh, the diagnostics written to ``mining/refresh_<step>.json``
        self.mining_history: list[dict[str, Any]] = []

    def _load_bank(self, path: str, num_angles: int, crop_size: int) -> tuple[PrototypeBank, float | None]:
        """The prototype bank of quantizer checkpoint ``path`` and its crops' occupancy floor (one-line errors
        naming the file and field)."""
        require_stage(path, "quantizer", "bank_ckpt",
                      "verify_by_prototypes" if self.hparams.verify_by_prototypes else "prototype_weight")
        hp = checkpoint_hparams(path)
        for name, want in (("num_angles", num_angles), ("crop_size", crop_size)):
            if int(hp.get(name, want)) != want:
                raise InputError(f"{path}: field 'hyper_parameters.{name}': the bank has {hp.get(name)}, the "
                                 f"mining stage {want}")
        if (hp.get("crop_shape") or "hull") != "hull":
            raise InputError(f"{path}: field 'hyper_parameters.crop_shape': the mining pool's crops are 'hull' crops; "
                             f"the bank's are {hp.get('crop_shape')!r}")
        bank = PrototypeBank(int(hp["num_prototypes"]), self.feature_dim, crop_size, num_angles)
        try:
            load_bank_state(bank, path)
        except ValueError as e:
            raise InputError(str(e)) from None
        if bank.num_active == 0:
            raise InputError(f"{path}: field 'bank.active': the bank has no prototype")
        return bank, bank_occupancy_floor(path)

    @torch.no_grad()
    def assign_pool(self, pool: dict[str, Tensor]) -> Any:
        """The bank's prototype and yaw of every pool object (a ``RotationSearchResult``; ``[N]`` ``prototype`` and
        ``angle``), on the pool's occupancy-weighted crops as the bank was fitted."""
        assert self.verify_bank is not None
        bank = self.verify_bank.to(pool["features"].device)
        return assign_chunked(bank, prototype_crops(pool["features"], pool["raw"], self._bank_floor))

    @torch.no_grad()
    def prototype_agreement(self, pool: dict[str, Tensor], mined: dict[str, Tensor], assignment: Any = None
                            ) -> Tensor:
        """``[P]`` bool: the bank puts both objects of each mined pair in one prototype, at yaws whose difference is
        the pair's mined yaw within ``prototype_yaw_window`` steps (``assignment``: :meth:`assign_pool`'s, or None to
        compute it).

        Convention: "object o has yaw a" rotates o by ``a`` onto its prototype (the bank's); the mined yaw ``b``
        rotates the target onto the query; so ``rot(q, a_q) ~ rot(t, a_t)`` gives ``b ~ a_t - a_q`` (mod A).
        """
        A = self.hparams.num_angles
        res = assignment if assignment is not None else self.assign_pool(pool)
        qi, ti, b = mined["query_index"], mined["target_index"], mined["yaw"]
        d = torch.remainder(res.angle[ti] - res.angle[qi] - b, A)
        return (res.prototype[qi] == res.prototype[ti]) & (torch.minimum(d, A - d) <= self.hparams.prototype_yaw_window)

    @property
    def vp_settings(self) -> dict[str, Any]:
        if self._vp is None:
            raise RuntimeError("vp_settings: view_prediction_weight is 0; the stage has no view-prediction objective")
        return self._vp

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """With the regulariser on, the checkpoint carries its settings beside the decoder, for the next round."""
        super().on_save_checkpoint(checkpoint)
        if self._vp is not None:
            checkpoint["view_prediction_settings"] = dict(self._vp)

    def _view_prediction_term(self, feats: Tensor, batch: dict[str, Tensor], n_in: int) -> dict[str, Tensor]:
        """The view-prediction loss of the first scene of ``batch`` (its grid ``feats[:1]``, from the first ``n_in``
        views) at predicting its other views; with ``view_prediction_rgb`` false, only its occupancy term
        (``loss`` = ``occ_weight`` x ``occ_loss``, labels from all the scene's views)."""
        if batch["rgb"].shape[1] <= n_in:
            raise ValueError(f"num_target_views: view_prediction_weight > 0 needs target views beside the {n_in} "
                             f"input view(s) of each scene (set the data's num_target_views >= 1)")
        one = {k: batch[k][:1] for k in ("rgb", "depth", "K", "R_T_cam")}
        occ_logits = self.occ_head(feats[:1])
        if self.hparams.view_prediction_rgb:
            return self.view_prediction_loss(feats[:1], occ_logits, one, n_in)
        occ, free = self.occupancy_labels(one["depth"], one["K"], one["R_T_cam"])
        occ_loss = balanced_occupancy_loss(occ_logits, occ, free)
        return {"loss": self.vp_settings["occ_weight"] * occ_loss, "occ_loss": occ_loss}

    # ------------------------------------------------------------------ view-contrastive sources
    def _two_view_sets(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        n = self.input_views(batch)
        S = batch["rgb"].shape[1]
        if S < 2 * n:
            raise ValueError(f"rgb: source {self.hparams.source!r} needs two disjoint sets of {n} views per sample, "
                             f"got {S} views (set the data's num_target_views >= num_input_views)")
        sets = []
        for lo in (0, n):
            sets.append(tuple(batch[k][:, lo:lo + n] for k in ("rgb", "depth", "K", "R_T_cam")))
        return sets[0], sets[1]

    def _object_points(self, feats: Tensor, aabb: Tensor, mask: Tensor, idx: Tensor) -> Tensor:
        """Features ``[P, C]`` at the sampled cells ``idx`` ``[N, V]`` of every valid box's ``crop_size^3`` crop."""
        s = self.hparams.crop_size
        crops = crop_boxes(feats, aabb, self.feature_grid, s, mask=mask)  # [N, C, s, s, s]
        return crop_voxels(crops, idx).flatten(0, 1)

    def _vc_step(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        a, b = self._two_view_sets(batch)
        mask = batch["box_mask"]
        n_obj = int(mask.sum())
        if n_obj == 0:
            return {"loss": None}
        s, V = self.hparams.crop_size, self.hparams.voxels_per_object
        if self.hparams.source == "vc":
            idx = torch.randint(0, s ** 3, (n_obj, min(V, s ** 3)), device=self.device)
            q = self._object_points(self.encode_views(*a), batch["aabb"], mask, idx)
            k = self._object_points(self.encode_views(*b), batch["aabb"], mask, idx)
            logits_neg = q @ k.T  # in-batch: the other points' keys are the negatives
            pos = (q * k).sum(1, keepdim=True)
            off = ~torch.eye(q.shape[0], dtype=torch.bool, device=q.device)
            logits = torch.cat([pos, logits_neg[off].view(q.shape[0], -1)], dim=1) / self.hparams.temperature
            loss = F.cross_entropy(logits, torch.zeros(q.shape[0], dtype=torch.long, device=q.device))
            return {"loss": loss, "positives": q.shape[0], "pos_cos": pos.mean()}
        with torch.no_grad():
            self.moco._momentum_update_key_encoder()
        q, k = self._view_positives(self.encode_views(*a), b, batch, V)
        loss = self._contrast(q, k)
        self._enqueue(k)
        return {"loss": loss, "positives": q.shape[0], "pos_cos": (q * k).sum(1).mean()}

    def _encode_keys(self, rgb: Tensor, depth: Tensor, K: Tensor, pose: Tensor, aabb: Tensor, mask: Tensor,
                     idx: Tensor) -> Tensor:
        """Keys: the second view set through the momentum encoder (eval mode), at the same points as the queries."""
        x, seen = self.encoder_input(rgb.flatten(0, 1), depth.flatten(0, 1), K.flatten(0, 1), pose.flatten(0, 1))
        self.moco.encoder_k.eval()
        feats = self.encode_input(x, seen, rgb.shape[1], encoder=self.moco.encoder_k)
        return self._object_points(feats, aabb, mask, idx)

    @staticmethod
    def _projection_head(channels: int, dim: int, encoder_ckpt: str | None) -> torch.nn.Module:
        """MoCo v2's projection head on voxel features: ``Linear(C, C)``, ReLU, ``Linear(C, dim)``; the weights of
        ``encoder_ckpt``'s head (``projection.*``, an earlier round's mining checkpoint trained with one) when it
        carries one, a fresh head otherwise."""
        head = torch.nn.Sequential(torch.nn.Linear(channels, channels), torch.nn.ReLU(),
                                   torch.nn.Linear(channels, dim))
        ck = load_checkpoint(encoder_ckpt) if encoder_ckpt else None
        carried = ck.prefixed("projection.") if ck is not None and ck.is_lightning else {}
        if carried:
            try:
                head.load_state_dict(carried)
            except RuntimeError as e:
                raise InputError(f"{encoder_ckpt}: field 'projection.*': does not fit a projection head "
                                 f"{channels} -> {channels} -> {dim}: {str(e).splitlines()[0]}") from e
        return head

    def _contrast(self, q: Tensor, k: Tensor) -> Tensor:
        """InfoNCE of queries ``q`` ``[N, C]`` (with gradient) against keys ``k`` ``[N, C]`` and the queue.

        Without a projection head: :meth:`MomentumContrast.loss` on the features themselves (the paper's). With one
        (``projection_dim``), queries, keys and the queue (which keeps the unit feature vectors) go through the
        head and are L2-normalised before the loss, in float32; the keys and the queue without gradient, by the
        head as it is now, so that the negatives stay comparable however the head has moved.
        """
        if self.projection is None:
            return self.moco.loss(q, k)
        head = self.projection
        with torch.no_grad():
            if self._projected_queue is None:
                self._projected_queue = F.normalize(head(self.moco.queue.to(q.dtype)).float(), dim=1)
            kp = F.normalize(head(k.to(q.dtype)).float(), dim=1)
        qp = F.normalize(head(q).float(), dim=1)
        return info_nce_streamed(qp, kp, self._projected_queue, self.moco.temperature)

    def _enqueue(self, k: Tensor) -> None:
        keys = self.all_gather(k.detach())
        self.moco._dequeue_and_enqueue(keys.reshape(-1, k.shape[-1]))
        self._projected_queue = None

    # ------------------------------------------------------------------ mined source
    def _train_dataset(self) -> Any:
        loader = self.trainer.train_dataloader
        ds = getattr(loader, "dataset", None)
        if ds is None:
            raise RuntimeError("mining: the training dataloader has no .dataset to draw the pools from")
        return ds

    def _pool_dataset(self) -> Any:
        """The training split with each scene's fixed input views (the choice val, test and the self-labelling pool
        use) instead of random ones: under ``threedq em`` the pool's crops then come from the feature grids the
        previous round's self-labelling and detector evaluation left in the crop cache for these weights."""
        ds = copy.copy(self._train_dataset())
        if getattr(ds, "random_views", False):
            ds.random_views = False
        return ds

    @torch.no_grad()
    def _cut_pool(self, ds: Any, generator: torch.Generator) -> dict[str, Tensor]:
        """Crops of at least ``target_pool`` objects (or all) from random training scenes, encoder in eval mode,
        in float32 whatever the training precision (the crops the other stages cached are float32)."""
        with torch.autocast(self.device.type, enabled=False):
            return self._cut_pool_fp32(ds, generator)

    def _cut_pool_fp32(self, ds: Any, generator: torch.Generator) -> dict[str, Tensor]:
        was_training = self.encoder.training
        self.encoder.eval()
        want = self.hparams.target_pool
        order = torch.randperm(len(ds), generator=generator).tolist()
        parts: dict[str, list[Tensor]] = {k: [] for k in ("features", "raw", "labels", "yaw", "scene", "slot",
                                                          "gt_iou")}
        got, i = 0, 0
        try:
            while got < want and i < len(order):
                idx = order[i:i + self.hparams.pool_batch_size]
                i += len(idx)
                batch = self._to_device(default_collate([ds[j] for j in idx]))
                c = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
                mask = batch["box_mask"]
                slot = torch.arange(mask.shape[1], device=self.device)[None].expand_as(mask)[mask]
                keep = torch.ones_like(slot, dtype=torch.bool)
                if self.hparams.pool_min_observed_iou is not None:
                    keep = self._observed_iou(batch) >= self.hparams.pool_min_observed_iou
                    self._pool_stats["boxes"] += int(keep.numel())
                    self._pool_stats["vouched"] += int(keep.sum())
                if self.hparams.pool_min_scene_iou is not None:
                    keep &= self._scene_iou(batch, ds) >= self.hparams.pool_min_scene_iou
                    self._pool_stats["scene_vouched"] += int(keep.sum())
                for k, v in (("features", c["features"]), ("raw", c["raw"]), ("labels", c["labels"]),
                             ("yaw", c["boxes"][:, 6]), ("scene", c["scene"]), ("slot", slot),
                             ("gt_iou", gt_box_iou(batch))):
                    parts[k].append(v[keep])
                got += int(keep.sum())
        finally:
            self.encoder.train(was_training)
        out = {k: torch.cat(v)[:want] for k, v in parts.items()}
        return out

    def _observed_iou(self, batch: dict[str, Any]) -> Tensor:
        """``[N]`` for the batch's valid boxes (``box_mask`` order): the highest 3D IoU with a label-free pseudo-box
        of its scene's input views (:func:`~threedq.box_refinement.observed_boxes`, with the feature grid's bounds
        as the detector uses them, so the detector's refinement has usually cached them); 0 where there is none."""
        v = self.input_views(batch)
        fg = self.feature_grid
        out = []
        for i in range(batch["box_mask"].shape[0]):
            boxes = batch["aabb"][i][batch["box_mask"][i]].float().cpu()
            obs, _ = observed_boxes(batch["depth"][i, :v], batch["K"][i, :v], batch["R_T_cam"][i, :v],
                                    (fg.bounds_min, fg.bounds_max))
            out.append(best_aabb_iou(boxes, torch.from_numpy(obs).reshape(-1, 6)))
        return torch.cat(out).to(self.device)

    def _scene_iou(self, batch: dict[str, Any], ds: Any) -> Tensor:
        """``[N]`` for the batch's valid boxes (``box_mask`` order): the highest 3D IoU with a label-free pseudo-box
        fused over the views of its training scene (the DataModule's ``pseudo_boxes("train")``, by the scene's file in
        ``ds.files``); 0 where the scene has none."""
        if self._scene_boxes is None:
            self._scene_boxes = self._scene_pseudo_boxes()
        if not hasattr(ds, "files"):
            raise ValueError(f"pool_min_scene_iou: the pool's dataset ({type(ds).__name__}) names no scene files "
                             f"(.files); set pool_min_scene_iou: null")
        out = []
        for i in range(batch["box_mask"].shape[0]):
            boxes = batch["aabb"][i][batch["box_mask"][i]].float().cpu()
            name = ds.files[int(batch["scene_index"][i])]
            if name not in self._scene_boxes:
                raise ValueError(f"pool_min_scene_iou: the training split's pseudo-boxes have no entry for {name}")
            fused = torch.as_tensor(self._scene_boxes[name][0], dtype=torch.float32).reshape(-1, 6)
            out.append(best_aabb_iou(boxes, fused))
        return torch.cat(out).to(self.device)

    def _scene_pseudo_boxes(self) -> dict[str, Any]:
        """The training split's label-free pseudo-boxes per scene file, fused over its views: the DataModule's
        ``pseudo_boxes("train")`` (computed once per split and cached by it)."""
        dm = getattr(self._trainer, "datamodule", None)
        if dm is None or not callable(getattr(dm, "pseudo_boxes", None)):
            raise ValueError(f"pool_min_scene_iou: the check needs a DataModule with pseudo_boxes(split) (threedq's "
                             f"scene-folder DataModules); got {type(dm).__name__}; set pool_min_scene_iou: null")
        return dm.pseudo_boxes("train")

    def _to_device(self, batch: dict[str, Any]) -> dict[str, Any]:
        return {k: v.to(self.device) if isinstance(v, Tensor) else v for k, v in batch.items()}

    @torch.no_grad()
    def refresh_pairs(self) -> dict[str, Any]:
        """Cut a new pool, mine it, compute the corner keys; log and write the diagnostics. Returns them."""
        hp = self.hparams
        t0 = time.time()
        rank = self.trainer.global_rank if self.trainer is not None else 0
        g = torch.Generator().manual_seed(hp.seed + 1009 * int(self.refreshes) + 7919 * rank)
        self._pool_stats = {"boxes": 0, "vouched": 0, "scene_vouched": 0}
        pool = self._cut_pool(self._pool_dataset(), g)
        feats = pool["features"]
        n_t = feats.shape[0]
        if n_t == 0:
            st = self._pool_stats
            checks = ", ".join(f"{k}={hp[k]}" for k in ("pool_min_observed_iou", "pool_min_scene_iou")
                               if hp[k] is not None)
            seen = (f" (of {st['boxes']} boxes seen, {st['vouched']} vouched for by the input views, "
                    f"{st['scene_vouched']} by the scenes' fused views too)") if hp.pool_min_observed_iou is not None \
                else ""
            raise ValueError(f"mining: the pool of the training split's boxes is empty{seen}: no box to mine pairs from"
                             + (f"; the pool's checks ({checks}) may be too strict for this data: set them to null"
                                if checks else ""))
        n_q = min(hp.query_pool, n_t)
        if not bool(self.queue_primed) or hp.negatives == "pool":
            flat = feats.permute(0, 2, 3, 4, 1).reshape(-1, feats.shape[1])
            pick = torch.randint(0, flat.shape[0], (self.moco.queue.shape[0],), generator=g).to(flat.device)
            self.moco.queue.copy_(F.normalize(flat[pick], dim=1))
            self.queue_primed.fill_(True)
            self._projected_queue = None
        min_cos = hp.min_cosine if hp.min_cosine is not None else calibrate_context_cosine(
            feats, pool["scene"], hp.context_quantile, hp.patch, generator=g)
        exclude = pool["scene"][:n_q, None] == pool["scene"][None, :]
        verify = bool(hp.verify_by_prototypes)
        by_shape = hp.positives == "occupancy"
        assignment = self.assign_pool(pool) if verify or hp.prototype_weight else None
        mined = self.candidate_pairs(pool, n_q, min_cos, exclude, self.candidate_count(), g)
        candidates = int(mined["query_index"].numel())
        if verify:  # the best keep pairs (rank order kept) the bank agrees with
            ok = self.prototype_agreement(pool, mined, assignment).nonzero().flatten()[: hp.keep]
            mined = take_pairs(mined, ok)
        offsets = corner_offsets(hp.corner_offset, hp.patch, device=feats.device)
        if by_shape:
            mined, q_voxels, keys = self._shape_positives(pool, mined, offsets.shape[0], g)
        qi, ti, yaw = mined["query_index"], mined["target_index"], mined["yaw"]
        P = qi.numel()
        if not by_shape:
            angle = yaw.to(feats.dtype) * (2 * math.pi / hp.num_angles)
            q_vox, k_list = [], []
            if P:
                aligned = rotate_yaw(feats[ti], angle)  # [P, C, S, S, S]
                for j in range(P):
                    v, k = corner_keys(feats[qi[j]], mined["query_pos"][j], aligned[j],
                                       mined["target_pos_aligned"][j], offsets, hp.corner_search)
                    q_vox.append(v)
                    k_list.append(k)
            C = feats.shape[1]
            q_voxels = torch.stack(q_vox) if P else offsets.new_zeros(0, 8, 3)
            keys = torch.stack(k_list) if P else feats.new_zeros(0, 8, C)
        self._pairs = {"scene": pool["scene"][qi], "slot": pool["slot"][qi], "query_voxels": q_voxels, "keys": keys}
        if hp.prototype_weight:  # the query object's prototype at the same voxels, turned to the object's yaw
            protos = self.verify_bank.prototypes.to(feats.device, feats.dtype)[assignment.prototype[qi]]
            pk, valid = prototype_keys(protos, assignment.angle[qi], self._pairs["query_voxels"], hp.num_angles)
            self._pairs.update(prototype_keys=pk, prototype_valid=valid)
        self._refreshed_at = self.global_step
        self.refreshes += 1
        self._candidates = candidates
        return self._diagnostics(pool, mined, min_cos, n_q, time.time() - t0, assignment)

    def candidate_count(self) -> int:
        """How many candidate pairs a refresh hands to the bank's check or the shape ranking, which keep ``keep``:
        ``keep`` times ``prototype_oversample`` or ``shape_oversample``; ``keep`` itself with ``occupancy_mutual_k``
        (its check is the shape ranking) or with neither."""
        hp = self.hparams
        if hp.verify_by_prototypes:
            return hp.keep * hp.prototype_oversample
        if hp.positives == "occupancy" and hp.occupancy_mutual_k is None:
            return hp.keep * hp.shape_oversample
        return hp.keep

    def candidate_pairs(self, pool: dict[str, Tensor], n_q: int, min_cos: float, exclude: Tensor, count: int,
                        generator: torch.Generator, occupancy_floor: float | None | str = "hparams",
                        **miner: Any) -> dict[str, Any]:
        """A refresh's candidate pairs, best first, before the bank's check or the shape ranking: the miner's
        ``count`` most similar verified pairs (:func:`~threedq.contrastive.mine_correspondences`), or each query's
        best ``candidates_per_query`` (:func:`spread_candidates`), either of them only those the input geometry's
        mutual neighbours agree with (``occupancy_mutual_k``); or the input crops' mutual pairs themselves
        (``candidates_from``, :func:`input_pairs`); or the pairs of the ``oracle_pairs`` diagnostic.
        ``occupancy_floor`` and ``miner`` (keywords of the miner) override the stage's settings (a probe's)."""
        hp = self.hparams
        feats = pool["features"]
        top_k = min(hp.top_k, feats.shape[0])
        if hp.oracle_pairs in ("gt", "gt_category"):  # a diagnostic with labels: the pairs a perfect miner would give
            return oracle_pairs(pool["labels"], pool["scene"], pool["yaw"], n_q, top_k, count, hp.num_angles, generator)
        spread = hp.candidates_per_query is not None
        checked = hp.occupancy_mutual_k is not None
        if hp.candidates_from != "features":  # the input crops' mutual neighbours, best agreement first
            crops = self._input_occupancy(pool, colour=hp.candidates_from == "input")
            mined = input_pairs(crops, pool["scene"], n_q, hp.occupancy_mutual_k, hp.num_angles)
        else:
            mined = mine_correspondences(
                feats[:n_q], feats, top_k=top_k, keep=n_q * top_k if spread or checked else count, exclude=exclude,
                min_cosine=min_cos, retrieval_crops=self.retrieval_crops(pool, n_q, occupancy_floor),
                **{**self.miner_settings(), **miner},
            )
        if checked and hp.candidates_from == "features":  # the pairs the input geometry's neighbours agree with
            scene = pool["scene"]
            mutual = mutual_pool_neighbours(pool_shape_agreement(self._input_occupancy(pool), hp.num_angles),
                                            scene[:, None] == scene[None, :], hp.occupancy_mutual_k)
            ok = mutual[mined["query_index"], mined["target_index"]].nonzero().flatten()
            mined = take_pairs(mined, ok if spread else ok[:count])
        if spread:  # every query's best pairs before any query's next ones
            mined = take_pairs(mined, spread_candidates(mined["query_index"], hp.candidates_per_query, count))
        elif hp.candidates_from != "features":  # the best agreements
            mined = take_pairs(mined, torch.arange(min(count, mined["query_index"].numel()), device=feats.device))
        if hp.oracle_pairs == "mined_gt_filtered":  # a diagnostic with labels: the miner's pairs, made pure
            lq, lt = pool["labels"][mined["query_index"]], pool["labels"][mined["target_index"]]
            mined = take_pairs(mined, ((lq == lt) & (lq >= 0)).nonzero().flatten())
        return mined

    @staticmethod
    def _input_occupancy(pool: dict[str, Tensor], colour: bool = False) -> Tensor:
        """``[N, 1, s, s, s]`` the pool crops' input occupancy, the surface and the cells next to it (a 3^3 max): what
        the shape agreement of the occupancy positives compares. ``colour``: ``[N, 4, s, s, s]``, the whole input
        crop ``cat[occ, occ * rgb]`` dilated alike (what ``candidates_from: input`` compares)."""
        raw = pool["raw"] if colour else pool["raw"][:, :1]
        return F.max_pool3d(raw.float(), kernel_size=3, stride=1, padding=1)

    def _shape_positives(self, pool: dict[str, Tensor], mined: dict[str, Tensor], count: int,
                         generator: torch.Generator) -> tuple[dict[str, Tensor], Tensor, Tensor]:
        """``positives: occupancy``: the ``keep`` mined pairs whose objects' input occupancy agrees best, each at the
        yaw of that agreement, and their positives (:func:`shape_agreement`, :func:`shape_cells`). Returns the kept
        pairs (``mined``'s keys, ``yaw`` replaced, ``shape_cosine`` added), their query cells ``[P, count, 3]`` and
        keys ``[P, count, C]``."""
        hp = self.hparams
        qi, ti = mined["query_index"], mined["target_index"]
        occ = self._input_occupancy(pool)
        cos, yaw = shape_agreement(occ[qi], occ[ti], hp.num_angles)
        if hp.oracle_pairs == "gt":  # ranked by shape agreement all the same, posed at the GT yaw
            yaw = mined["yaw"]
        order = torch.sort(cos, descending=True, stable=True).indices
        t_occ = rotate_yaw(occ[ti[order]], yaw[order].to(occ.dtype) * (2 * math.pi / hp.num_angles))
        cells, valid = shape_cells(occ[qi[order]], t_occ, count, generator)
        order = order[valid]
        if hp.max_pairs_per_box is not None:
            spread = cap_pairs_per_box(qi[order], ti[order], hp.max_pairs_per_box)
            order, cells = order[spread], cells[spread]
        pick, cells = order[: hp.keep], cells[: hp.keep]
        feats = pool["features"]
        aligned = rotate_yaw(feats[ti[pick]], yaw[pick].to(feats.dtype) * (2 * math.pi / hp.num_angles))
        keys = crop_voxels(aligned, cells)  # [P, count, C]
        vox = torch.stack(torch.unravel_index(cells, occ.shape[2:]), dim=-1)  # [P, count, 3]
        out = take_pairs(mined, pick)
        out["yaw"], out["shape_cosine"] = yaw[pick], cos[pick]
        # the pictures mark one positive cell, the same cell of both crops once the target is turned onto the query
        out["query_pos"], out["target_pos_aligned"] = vox[:, 0], vox[:, 0]
        return out, vox, keys

    def retrieval_crops(self, pool: dict[str, Tensor], n_q: int,
                        occupancy_floor: float | None | str = "hparams") -> tuple[Tensor, Tensor] | None:
        """The crops the object-level retrieval of a refresh runs on (``mine_correspondences``' ``retrieval_crops``):
        None (the pool's feature crops, the paper's) without ``retrieval_occupancy_floor``, else the pool's crops
        weighted by their input occupancy at that floor (:func:`~threedq.quantization.prototypes.prototype_crops`,
        the similarity the quantizer's prototypes use), as (the first ``n_q``, all). ``occupancy_floor`` overrides
        the hyperparameter (a probe's setting)."""
        floor = self.hparams.retrieval_occupancy_floor if occupancy_floor == "hparams" else occupancy_floor
        if floor is None:
            return None
        w = prototype_crops(pool["features"], pool["raw"], float(floor))
        return w[:n_q], w

    def miner_settings(self) -> dict[str, Any]:
        """The keywords of :func:`~threedq.contrastive.mine_correspondences` this stage's hyperparameters set (all but
        the pool-dependent ``top_k``, ``keep``, ``exclude`` and ``min_cosine``)."""
        hp = self.hparams
        return {"num_angles": hp.num_angles, "patch": hp.patch, "grid": hp.search_grid,
                "context_distance": hp.context_distance, "min_score": hp.min_score, "yaw_window": hp.yaw_window,
                "rank_by": hp.rank_by, "csls_k": hp.csls_k, "mutual_k": hp.mutual_k}

    def pair_measures(self, pool: dict[str, Tensor], mined: dict[str, Tensor]) -> dict[str, Any]:
        """GT measures of mined pairs (measuring only): ``same_category`` among the ``labelled_pairs`` (both boxes
        match a GT object; detected boxes may not), and, where the data names symmetries, the median implied yaw error
        ``yaw_median_err_deg`` over the ``yaw_pairs`` same-category pairs of asymmetric categories, and
        ``yaw_sym_median_err_deg`` over the ``yaw_sym_pairs`` of every category of finite symmetry order (each modulo
        its period: more pairs, a steadier median). A key is absent where it has no pair."""
        qi, ti = mined["query_index"], mined["target_index"]
        lq, lt = pool["labels"][qi], pool["labels"][ti]
        labelled = (lq >= 0) & (lt >= 0)
        same = (lq == lt) & labelled
        out: dict[str, Any] = {"same_category": float(same.sum() / labelled.sum()) if labelled.any() else float("nan"),
                               "labelled_pairs": int(labelled.sum())}
        iou = pool.get("gt_iou")
        if iou is not None and iou.numel() and not bool(torch.isnan(iou).any()):
            # the looser "on an object": both boxes overlap a GT object at IoU >= 0.25 (mAP@0.25's threshold), which
            # counts boxes cut short on thin or half-seen objects
            out["pairs_on_objects_iou25"] = int(((iou[qi] >= 0.25) & (iou[ti] >= 0.25)).sum())
        sym = self._symmetry()
        if sym is not None and same.any():
            s = sym.to(qi.device)[lq.clamp_min(0)]
            for key, use in (("yaw", same & (s == 1)), ("yaw_sym", same & (s >= 1))):
                if use.any():
                    err = implied_yaw_error_deg(mined["yaw"][use], self.hparams.num_angles, pool["yaw"][qi][use],
                                                pool["yaw"][ti][use], s[use])
                    out[f"{key}_median_err_deg"] = float(err.median())
                    out[f"{key}_pairs"] = int(use.sum())
        return out

    def _diagnostics(self, pool: dict[str, Tensor], mined: dict[str, Tensor], min_cos: float, n_q: int,
                     seconds: float, assignment: Any = None) -> dict[str, Any]:
        hp = self.hparams
        qi = mined["query_index"]
        measures = self.pair_measures(pool, mined)
        info: dict[str, Any] = {
            "step": int(self.global_step), "refresh": int(self.refreshes), "pool_objects": int(pool["features"].shape[0]),
            "queries": n_q, "pairs": int(qi.numel()), "min_cosine": round(min_cos, 4),
            "score_mean": float(mined["score"].mean()) if qi.numel() else float("nan"),
            # how widely the pairs spread over the pool (a box in many pairs is a hub of the ranking)
            "distinct_queries": int(qi.unique().numel()), "distinct_targets": int(mined["target_index"].unique().numel()),
            "distinct_boxes": int(torch.cat([qi, mined["target_index"]]).unique().numel()),
            "same_category": measures["same_category"],
            "labelled_pairs": measures["labelled_pairs"],
            **({"pairs_on_objects_iou25": measures["pairs_on_objects_iou25"]}
               if "pairs_on_objects_iou25" in measures else {}),
            # the pool's boxes that match a GT object (measuring only)
            "pool_on_objects": float((pool["labels"] >= 0).float().mean()) if pool["labels"].numel() else float("nan"),
            "seconds": round(seconds, 1),
        }
        if hp.occupancy_mutual_k is not None:  # the candidates the input geometry's mutual neighbours agreed with
            info["occupancy_mutual_k"] = hp.occupancy_mutual_k
            info["candidates_from"] = hp.candidates_from
        if hp.oracle_pairs:  # the diagnostic: the report says these pairs came from labels
            info["oracle_pairs"] = hp.oracle_pairs
        if hp.verify_by_prototypes:  # the pairs mined before the bank's check (prototype_oversample x keep at most)
            info["prototype_candidates"] = self._candidates
        if hp.positives == "occupancy":  # the pairs mined before the shape ranking, and the kept pairs' agreement
            info["shape_candidates"] = self._candidates
            info["shape_cosine_mean"] = float(mined["shape_cosine"].mean()) if qi.numel() else float("nan")
        if hp.prototype_weight and assignment is not None:  # GT, measuring only
            info["prototype_positive_purity"] = prototype_purity(assignment.prototype, pool["labels"], qi)
        if hp.pool_min_observed_iou is not None:  # boxes looked at, and those the input views' geometry vouched for
            info["pool_boxes_seen"] = self._pool_stats["boxes"]
            info["pool_vouched"] = self._pool_stats["vouched"]
        if hp.pool_min_scene_iou is not None:  # of those, the ones the fused views of their scene vouched for too
            info["pool_scene_vouched"] = self._pool_stats["scene_vouched"]
        info.update({k: v for k, v in measures.items() if k.startswith("yaw")})
        self.mining_history.append(info)
        if self.trainer is not None:
            self.log_dict({f"mining/{k}": float(v) for k, v in info.items()
                           if k in ("pairs", "same_category", "yaw_median_err_deg", "min_cosine", "seconds")},
                          rank_zero_only=True)
            if self.trainer.is_global_zero:
                self._write_diagnostics(info, pool, mined)
        return info

    def _symmetry(self) -> Tensor | None:
        sym = self.hparams.symmetry_order
        return None if sym is None else torch.tensor(list(sym), dtype=torch.long)

    def _write_diagnostics(self, info: dict[str, Any], pool: dict[str, Tensor], mined: dict[str, Tensor]) -> None:
        out = self.run_dir / "mining"
        name = f"refresh_{info['step']:06d}"
        atomic_write_text(out / f"{name}.json", json.dumps(info, indent=1) + "\n")
        P = mined["query_index"].numel()
        if P == 0:
            return
        # the best 6 pairs of the refresh and its worst 4 (the kept pairs are in rank order)
        pick = torch.cat([torch.arange(min(6, P)), torch.arange(min(max(6, P - 4), P), P)])
        pick = pick.to(mined["query_index"].device)
        qi, ti, yaw = mined["query_index"][pick], mined["target_index"][pick], mined["yaw"][pick]
        angle = yaw.to(pool["raw"].dtype) * (2 * math.pi / self.hparams.num_angles)
        aligned = rotate_yaw(pool["raw"][ti], angle)
        lab = pool["labels"]

        def verdict(q: int, t: int) -> str:  # GT, for measuring only
            if q < 0 or t < 0:
                return "off an object" if (q < 0) != (t < 0) else "off objects"
            return "same category" if q == t else "other category"

        score = mined.get("shape_cosine", mined["score"])  # what ranked the kept pairs
        captions = [f"{'best' if int(j) < 6 else 'worst'} {int(j) + 1}: {float(score[j]):.2f}, "
                    f"{int(yaw[n]) * 360 // self.hparams.num_angles} deg, {verdict(int(lab[qi[n]]), int(lab[ti[n]]))}"
                    for n, j in enumerate(pick.tolist())]  # at most 40 characters (the figure's caption bar)
        img = mined_pairs_figure(pool["raw"][qi], aligned, mined["query_pos"][pick], mined["target_pos_aligned"][pick],
                                 captions, self.hparams.patch)
        write_png(out / f"{name}.png", img)

    def _mined_step(self) -> dict[str, Any]:
        hp = self.hparams
        if self._pairs is None or (self.global_step % hp.refresh_every == 0 and self.global_step != self._refreshed_at):
            self.refresh_pairs()
        pairs = self._pairs
        P = pairs["scene"].numel()
        if P == 0:
            return {"loss": None}
        pick = torch.randperm(P)[: hp.pairs_per_step].to(pairs["scene"].device)
        scenes = pairs["scene"][pick]
        uniq, inv = scenes.unique(return_inverse=True)
        ds = self._train_dataset()
        batch = self._to_device(default_collate([ds[int(s)] for s in uniq.tolist()]))
        if hp.colour_jitter:
            batch["rgb"] = recolour_scenes(batch["rgb"], hp.colour_jitter)
        v = self.input_views(batch)
        feats = self.encode_views(*(batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam")))
        crops = crop_boxes(feats, batch["aabb"], self.feature_grid, hp.crop_size)  # [B, M, C, s, s, s]
        qv = pairs["query_voxels"][pick]  # [n, 8, 3]
        sel = crops[inv, pairs["slot"][pick]]  # [n, C, s, s, s]
        n = sel.shape[0]
        q = sel[torch.arange(n, device=sel.device)[:, None], :, qv[..., 0], qv[..., 1], qv[..., 2]]  # [n, 8, C]
        q = F.normalize(q.reshape(-1, q.shape[-1]), dim=1)
        k = pairs["keys"][pick].reshape(-1, q.shape[-1]).to(q.dtype)
        with torch.no_grad():
            self.moco._momentum_update_key_encoder()
        if hp.correspondence_weight:
            loss = self._contrast(q, k)
            if hp.correspondence_weight != 1:
                loss = loss * hp.correspondence_weight
        else:  # the ablation: the pairs are mined and enqueued, the other terms train
            loss = q.new_zeros(())
        out = {"positives": q.shape[0], "pos_cos": (q * k).sum(1).mean()}
        if hp.prototype_weight:
            valid = pairs["prototype_valid"][pick].reshape(-1)
            if valid.any():
                pk = pairs["prototype_keys"][pick].reshape(-1, q.shape[-1]).to(q.dtype)[valid]
                loss = loss + hp.prototype_weight * self._contrast(q[valid], pk)
                out.update(prototype_positives=int(valid.sum()), prototype_pos_cos=(q[valid] * pk).sum(1).mean())
        if hp.view_positives:
            qv_, kv_ = self._view_positives(feats, self._two_view_sets(batch)[1], batch, hp.view_positives)
            if qv_.shape[0]:
                loss = loss + hp.view_weight * self._contrast(qv_, kv_)
                out.update(view_positives=qv_.shape[0], view_pos_cos=(qv_ * kv_).sum(1).mean())
                k = torch.cat([k, kv_.to(k.dtype)])
        if hp.view_prediction_weight:
            vp = self._view_prediction_term(feats, batch, v)
            loss = loss + hp.view_prediction_weight * vp["loss"]
            out.update(vp_loss=vp["loss"].detach(), vp_occ=vp["occ_loss"].detach())
            if "l1" in vp:
                out.update(vp_l1=vp["l1"].detach())
        if hp.negatives == "queue":
            self._enqueue(k)
        if not loss.requires_grad:  # correspondence_weight 0 and no other term had anything this step
            return {"loss": None}
        return {"loss": loss, **out}

    def _view_positives(self, feats: Tensor, second: tuple[Tensor, ...], batch: dict[str, Tensor], count: int
                        ) -> tuple[Tensor, Tensor]:
        """View-contrastive positives (``vc_moco``, and the mined source's ``view_positives``): queries ``[P, C]``
        (``feats``, the input views, with gradient) and keys ``[P, C]`` (the same voxels of the same boxes encoded
        from the ``second`` view set by the momentum encoder, no gradient); ``P = count`` x the valid boxes."""
        mask = batch["box_mask"]
        n_obj, s = int(mask.sum()), self.hparams.crop_size
        if n_obj == 0:
            return feats.new_zeros(0, feats.shape[1]), feats.new_zeros(0, feats.shape[1])
        idx = torch.randint(0, s ** 3, (n_obj, min(count, s ** 3)), device=self.device)
        q = self._object_points(feats, batch["aabb"], mask, idx)
        with torch.no_grad():
            k = self._encode_keys(*second, batch["aabb"], mask, idx)
        return q, k

    # ------------------------------------------------------------------ Lightning hooks
    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor | None:
        r = self._mined_step() if self.hparams.source == "mined" else self._vc_step(batch)
        if r["loss"] is None:
            return None  # no objects / no verified pairs: skip the step
        self.log_dict({"train/loss": r["loss"], "train/pos_cos": r["pos_cos"],
                       "train/positives": float(r["positives"])}, prog_bar=True, batch_size=1)
        if "vp_loss" in r:
            self.log_dict({"train/vp_loss": r["vp_loss"], "train/vp_occ": r["vp_occ"],
                           **({"train/vp_l1": r["vp_l1"]} if "vp_l1" in r else {})}, batch_size=1)
        if "prototype_pos_cos" in r:
            self.log_dict({"train/prototype_pos_cos": r["prototype_pos_cos"],
                           "train/prototype_positives": float(r["prototype_positives"])}, batch_size=1)
        if "view_pos_cos" in r:
            self.log_dict({"train/view_pos_cos": r["view_pos_cos"],
                           "train/view_positives": float(r["view_positives"])}, batch_size=1)
        return r["loss"]

    def _eval_step(self, batch: dict[str, Tensor], split: str) -> None:
        crops = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
        if crops["features"].shape[0]:
            keep = crops["labels"] >= 0
            self.metrics[split].update(crops["features"][keep], crops["labels"][keep])

    def _eval_epoch_end(self, split: str) -> None:
        m = self.metrics[split]
        if m.crops:
            n = sum(c.shape[0] for c in m.crops) if isinstance(m.crops, list) else m.crops.shape[0]
            if n > self.hparams.retrieval_k:
                self.log(f"{split}/precision_at_{self.hparams.retrieval_k}", m.compute(), prog_bar=True)
        m.reset()

    def configure_optimizers(self) -> torch.optim.Optimizer:
        params = [p for p in self.encoder.parameters() if p.requires_grad]
        if self._vp is not None:  # the regulariser's occupancy head (and, with its RGB term, decoder) train along
            params += [p for p in (*self.decoder.parameters(), *self.occ_head.parameters()) if p.requires_grad]
        groups: list[dict[str, Any]] = [{"params": params}]
        if self.projection is not None:  # the head, at its own constant rate: it starts afresh and has few steps
            groups.append({"params": list(self.projection.parameters()), "lr": self.hparams.projection_lr})
        return torch.optim.Adam(groups, lr=self.round_learning_rate)

    @property
    def round_learning_rate(self) -> float:
        """The learning rate of this round: ``lr``, or ``lr / em_round`` under ``round_lr: harmonic``."""
        hp = self.hparams
        return hp.lr / hp.em_round if hp.round_lr == "harmonic" else hp.lr

