"""A LightningDataModule over a folder of canonical scene records: ``<data_dir>/index.json`` (categories, symmetry,
scene bounds, scenes with their split) and ``<data_dir>/<split>/scene_*.npz`` for ``train``, ``val``, ``test``.

Each sample is one scene: ``num_input_views`` input views, then ``num_target_views`` distinct target views, and the
scene's objects padded to ``max_objects`` with a mask. Frame R is the record's world frame (metres, z up, centred).
"""

from __future__ import annotations

import os
import zipfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import lightning as L
import numpy as np
import torch
from jsonargparse.typing import NonNegativeInt, PositiveInt
from torch.utils.data import DataLoader, Dataset

from threedq.argtypes import UnitIoU
from threedq.boxes import boxes_to_aabb
from threedq.data.box_files import load_boxes_file
from threedq.data.proposal_cache import propose_dataset
from threedq.data.samplers import ContiguousDistributedSampler, EpochShuffleSampler
from threedq.metrics.detection import assign_detections
from threedq.data.view_colour import apply_gains, floor_colour_gains
from threedq.geometry.floor_alignment import align_to_floor
from threedq.proposals import ProposalParams
from threedq.scene import DatasetIndex, SceneRecord, SceneValidationError, load_index, load_scene

__all__ = ["SceneDataset", "SceneFolderDataModule", "detections_as_objects", "fixed_views"]

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class _SceneViews:
    """The views of one sample and the scene's objects, as read from its record."""

    rgb: np.ndarray  # [S, H, W, 3] uint8
    depth: np.ndarray  # [S, H, W] float32
    K: np.ndarray  # [S, 3, 3] float32
    world_T_cam: np.ndarray  # [S, 4, 4] float32
    view_ids: np.ndarray  # [S] int64
    instance: np.ndarray | None  # [S, H, W]
    boxes: np.ndarray  # [M, 7]
    categories: np.ndarray  # [M]

    @property
    def nbytes(self) -> int:
        arrays = (self.rgb, self.depth, self.K, self.world_T_cam, self.instance, self.boxes, self.categories)
        return sum(a.nbytes for a in arrays if a is not None)


class _ViewCache:
    """A process-wide LRU of the fixed views of scenes already read, keyed with the file's size and modification time;
    ``THREEDQ_VIEW_CACHE_MB`` (default 1024, 0 = off) caps its size."""

    def __init__(self) -> None:
        self._items: OrderedDict[tuple, _SceneViews] = OrderedDict()
        self.nbytes = 0

    @property
    def limit(self) -> int:
        return int(float(os.environ.get("THREEDQ_VIEW_CACHE_MB", "1024")) * 2**20)

    def get(self, key: tuple) -> _SceneViews | None:
        v = self._items.get(key)
        if v is not None:
            self._items.move_to_end(key)
        return v

    def put(self, key: tuple, v: _SceneViews) -> None:
        limit = self.limit
        if v.nbytes > limit or key in self._items:
            return
        self._items[key] = v
        self.nbytes += v.nbytes
        while self.nbytes > limit:
            _, old = self._items.popitem(last=False)
            self.nbytes -= old.nbytes


_VIEW_CACHE = _ViewCache()
#: the pseudo-boxes of clean renders: every second view, a voxel seen by 2 views, a fixed 1.5 cm ground margin
RENDER_PROPOSALS = ProposalParams(view_stride=2)
#: the pseudo-boxes of sensor captures: floor-corrected poses, a voxel seen by 3 views, a per-scene ground margin
SENSOR_PROPOSALS = ProposalParams(view_stride=2, min_views=3, ground_margin=None, min_ground_margin=0.015,
                                  align_floor=True)
#: (resolved path, mtime, size) -> a scene's floor-aligned poses ``[V, 4, 4]`` and colour gains ``[V, 3]`` (a few KB)
_SENSOR_CORRECTIONS: dict[tuple[str, int, int], tuple[np.ndarray, np.ndarray]] = {}


def sensor_corrections(path: Path, rec: SceneRecord) -> tuple[np.ndarray, np.ndarray]:
    """A scene's poses corrected by its floor (:func:`~threedq.geometry.floor_alignment.align_to_floor`) and each
    view's colour gains from that floor (:func:`~threedq.data.view_colour.floor_colour_gains`), once per scene file
    and process."""
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _SENSOR_CORRECTIONS:
        poses = align_to_floor(rec.depth, rec.K, rec.world_T_cam).world_T_cam
        _SENSOR_CORRECTIONS[key] = poses, floor_colour_gains(rec.rgb, rec.depth, rec.K, poses)
    return _SENSOR_CORRECTIONS[key]


def _cores(most: int) -> int:
    """The CPU cores this process may run on (its affinity where the OS says), at most ``most``."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, min(n, most))


def fixed_views(seed: int, i: int, num_views: int, need: int) -> np.ndarray:
    """The views a fixed-view :class:`SceneDataset` reads for its ``i``-th scene: ``need`` distinct views of
    ``num_views`` drawn from ``(seed, i)``, inputs first."""
    return np.random.default_rng([seed, i]).permutation(num_views)[:need]


class SceneDataset(Dataset):
    """Scenes of one split; item ``i`` is a dict of tensors (see :meth:`__getitem__`).

    Args:
        root: dataset folder holding ``index.json``.
        index: the parsed index.
        split: ``train``, ``val`` or ``test``.
        num_input_views: input views per sample (>= 1).
        num_target_views: target views per sample (>= 0), distinct from the inputs.
        max_objects: objects are padded to this many; a scene with more is an error.
        random_views: draw views at random per call (training) instead of a fixed per-scene choice.
        seed: seed of the fixed per-scene view choice.
        box_sets: ``{scene file -> (aabb [P,6], scores [P])}`` boxes to use instead of the GT (``None``: GT boxes).
        match_iou: a box takes the category and oriented box of the GT object it matches at this IoU.
        keep_unmatched: keep boxes that match no GT object (category -1); ``False`` keeps only matched ones.
        max_boxes: boxes per scene are padded to this many when ``box_sets`` is given (highest scores kept).
        align_floor: correct each scene's poses by the floor its views see, and each view's colours by that floor's
            (:func:`sensor_corrections`).
    """

    def __init__(
        self, root: str | Path, index: DatasetIndex, split: str, num_input_views: int = 1, num_target_views: int = 1,
        max_objects: int = 3, random_views: bool = False, seed: int = 0,
        box_sets: dict[str, tuple[np.ndarray, np.ndarray]] | None = None, match_iou: float = 0.5,
        keep_unmatched: bool = True, max_boxes: int = 8, align_floor: bool = False,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
        if num_input_views < 1:
            raise ValueError(f"num_input_views: expected >= 1, got {num_input_views}")
        if num_target_views < 0:
            raise ValueError(f"num_target_views: expected >= 0, got {num_target_views}")
        self.root = Path(root)
        self.index = index
        self.split = split
        self.files = index.files(split)
        self.num_input_views = num_input_views
        self.num_target_views = num_target_views
        self.max_objects = max_objects
        self.random_views = random_views
        self.seed = seed
        if box_sets is not None:
            missing = [f for f in self.files if f not in box_sets]
            if missing:
                raise ValueError(f"box_sets: no boxes for {len(missing)} scene(s) of split {split!r}, "
                                 f"e.g. {missing[0]}")
            if max_boxes < 1:
                raise ValueError(f"max_boxes: expected >= 1, got {max_boxes}")
        self.box_sets = box_sets
        self.match_iou = match_iou
        self.keep_unmatched = keep_unmatched
        self.max_boxes = max_boxes
        self.align_floor = bool(align_floor)

    def __len__(self) -> int:
        return len(self.files)

    def _choose_views(self, i: int, num_views: int, path: Path, epoch: int | None = None) -> np.ndarray:
        need = self.num_input_views + self.num_target_views
        if need > num_views:
            raise SceneValidationError(str(path), "rgb",
                                       f"sample needs {need} distinct views but the scene has {num_views}")
        if self.random_views:
            if epoch is not None:  # drawn by an EpochShuffleSampler: the same views in any process or worker
                return np.random.default_rng([self.seed, i, epoch, 1]).permutation(num_views)[:need]
            # torch's global generator: seeded by seed_everything (and per worker by Lightning)
            return torch.randperm(num_views)[:need].numpy()
        return fixed_views(self.seed, i, num_views, need)

    def __getitem__(self, i: int | tuple[int, int]) -> dict[str, Any]:
        """One scene: ``i`` is its index, or ``(index, epoch)`` from an
        :class:`~threedq.data.samplers.EpochShuffleSampler` (random views then drawn from ``(seed, index, epoch)``).

        Returns:
            ``rgb`` [S,3,H,W] float in [0,1]; ``depth`` [S,H,W] metres (0 invalid); ``K`` [S,3,3]; ``R_T_cam``
            [S,4,4]; ``instance`` [S,H,W] long (only if the record has masks); ``view_ids`` [S]; ``boxes`` [M,7]
            oriented, ``aabb`` [M,6] ``(xmin..zmax)``, ``categories`` [M] long (-1 pad), ``box_mask`` [M] bool, M =
            ``max_objects``; ``scene_index`` long; ``num_input_views`` long (the first views are inputs, the rest
            targets); ``gt_aabb`` [G,6] and ``gt_mask`` [G] the GT. With ``box_sets``, the box fields describe the
            given boxes (M = ``max_boxes``, :func:`detections_as_objects`) and ``box_scores`` [M] their scores.

        Convention: frame R = the record's world frame (metres, z up); OpenCV camera axes.
        """
        i, epoch = (int(i[0]), int(i[1])) if isinstance(i, (tuple, list)) else (i, None)
        path = self.root / self.files[i]
        v = self._views(i, path, epoch)
        M = self.max_objects
        n = len(v.boxes)
        boxes = np.zeros((M, 7), np.float32)
        boxes[:n] = v.boxes
        aabb = np.zeros((M, 6), np.float32)
        aabb[:n] = boxes_to_aabb(v.boxes.astype(np.float64))
        cats = np.full((M,), -1, np.int64)
        cats[:n] = v.categories
        out: dict[str, Any] = {
            "rgb": torch.from_numpy(v.rgb).permute(0, 3, 1, 2).float().div_(255.0),
            "depth": torch.from_numpy(v.depth.copy()), "K": torch.from_numpy(v.K.copy()),
            "R_T_cam": torch.from_numpy(v.world_T_cam.copy()), "view_ids": torch.from_numpy(v.view_ids.copy()),
            "boxes": torch.from_numpy(boxes), "aabb": torch.from_numpy(aabb), "categories": torch.from_numpy(cats),
            "box_mask": torch.arange(M) < n, "scene_index": torch.tensor(i, dtype=torch.long),
            "num_input_views": torch.tensor(self.num_input_views, dtype=torch.long),
        }
        out["gt_aabb"], out["gt_mask"] = out["aabb"], out["box_mask"]
        if self.box_sets is not None:
            out.update(detections_as_objects(*self.box_sets[self.files[i]], v.boxes, v.categories, self.match_iou,
                                             self.keep_unmatched, self.max_boxes))
        if v.instance is not None:
            out["instance"] = torch.from_numpy(v.instance.astype(np.int64))
        return out

    def _views(self, i: int, path: Path, epoch: int | None) -> _SceneViews:
        """The chosen views of scene ``i`` and its objects: read and validated from ``path``, or, for a fixed view
        choice, from :data:`_VIEW_CACHE`."""
        bounds, ncat = self.index.scene_bounds, len(self.index.categories)
        key = None
        if not self.random_views:
            try:
                st = path.stat()
                key = (str(path.resolve()), st.st_mtime_ns, st.st_size, repr(bounds), ncat, self.seed, i,
                       self.num_input_views + self.num_target_views, self.max_objects, self.align_floor)
            except OSError:
                key = None  # load_scene names the missing file
            hit = _VIEW_CACHE.get(key) if key is not None else None
            if hit is not None:
                return hit
        rec = load_scene(path, bounds=bounds, num_categories=ncat)
        if rec.num_objects > self.max_objects:
            raise SceneValidationError(str(path), "boxes",
                                       f"{rec.num_objects} objects but max_objects is {self.max_objects}")
        views = self._choose_views(i, rec.num_views, path, epoch)
        poses, gains = sensor_corrections(path, rec) if self.align_floor else (rec.world_T_cam, None)
        v = _SceneViews(
            rgb=rec.rgb[views] if gains is None else apply_gains(rec.rgb[views], gains[views]),
            depth=rec.depth[views].astype(np.float32), K=rec.K[views].astype(np.float32),
            world_T_cam=poses[views].astype(np.float32), view_ids=views.astype(np.int64),
            instance=None if rec.instance is None else rec.instance[views], boxes=rec.boxes, categories=rec.categories,
        )
        if key is not None:
            _VIEW_CACHE.put(key, v)
        return v


def detections_as_objects(
    aabb: np.ndarray, scores: np.ndarray, gt_boxes: np.ndarray, gt_categories: np.ndarray, match_iou: float = 0.5,
    keep_unmatched: bool = True, max_boxes: int = 8,
) -> dict[str, torch.Tensor]:
    """Turn a scene's detected (or proposed) boxes into the object fields of a sample: the ``max_boxes`` highest
    scores, matched to the GT by the mAP's rule (:func:`threedq.metrics.detection.assign_detections` at
    ``match_iou``); a matched box carries that object's category and oriented box (for the metrics only).

    Args:
        aabb ``[P, 6]``, scores ``[P]``: the boxes; gt_boxes ``[G, 7]``, gt_categories ``[G]``: the scene's GT.

    Returns:
        ``aabb`` [M,6], ``boxes`` [M,7], ``categories`` [M] (-1 unmatched or pad), ``box_mask`` [M] bool,
        ``box_scores`` [M], ``box_matched`` [M] bool, M = ``max_boxes``.
    """
    M = max_boxes
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")[:M]
    aabb = np.asarray(aabb, np.float32).reshape(-1, 6)[order]
    scores = np.asarray(scores, np.float32).reshape(-1)[order]
    gt_aabb = boxes_to_aabb(np.asarray(gt_boxes, np.float64).reshape(-1, 7)).astype(np.float32)
    match = assign_detections(*(torch.from_numpy(a) for a in (aabb, scores, gt_aabb)), match_iou).numpy()
    keep = np.ones(len(aabb), bool) if keep_unmatched else match >= 0
    idx = np.nonzero(keep)[0]
    out_aabb = np.zeros((M, 6), np.float32)
    out_boxes = np.zeros((M, 7), np.float32)
    out_cats = np.full((M,), -1, np.int64)
    out_scores = np.zeros((M,), np.float32)
    out_matched = np.zeros((M,), bool)
    n = len(idx)
    out_aabb[:n], out_scores[:n] = aabb[idx], scores[idx]
    for j, d in enumerate(idx):
        if match[d] >= 0:
            out_boxes[j] = gt_boxes[match[d]]
            out_cats[j] = gt_categories[match[d]]
            out_matched[j] = True
    return {"aabb": torch.from_numpy(out_aabb), "boxes": torch.from_numpy(out_boxes),
            "categories": torch.from_numpy(out_cats), "box_mask": torch.arange(M) < n,
            "box_scores": torch.from_numpy(out_scores), "box_matched": torch.from_numpy(out_matched)}


class SceneFolderDataModule(L.LightningDataModule):
    """Any folder of canonical scene records (see the module docstring for the tree).

    Args:
        data_dir: the dataset folder.
        batch_size: scenes per batch.
        num_workers: DataLoader worker processes.
        num_input_views: input views per sample.
        num_target_views: held-out target views per sample (view prediction).
        max_objects: objects per scene are padded to this many.
        seed: seed of the fixed view choice of val/test samples.
        boxes: the samples' object boxes: ``"gt"``, ``"proposals"`` (label-free pseudo-boxes, cached in
            ``<data_dir>/proposals/<split>.npz``) or a box file path with ``{split}`` in it.
        match_iou: IoU at which a proposed/detected box is matched to a GT object (metrics only).
        max_boxes: proposed/detected boxes per scene (highest scores kept).
        train_random_views: draw the train split's views at random per epoch (else the fixed per-scene choice).
        proposal_workers: processes computing a split's pseudo-boxes (``None``: one per usable CPU core, at most 8).
        sensor_captures: poses and colours corrected by the floor and pseudo-boxes with :data:`SENSOR_PROPOSALS`
            (sensor data).

    With boxes other than GT, the train split keeps every box; val and test keep only the boxes matched to a GT object.
    """

    #: the stage configs that serve this kind of data (threedq.pipeline.presets)
    PRESETS: ClassVar[dict[str, str]] = {"detector": "stages/detector_scene.yaml",
                                         "mining": "stages/mining_occupancy_pairs.yaml",
                                         "quantizer": "stages/quantizer_multiview.yaml"}

    def __init__(
        self, data_dir: str = "data/scenes", batch_size: PositiveInt = 2, num_workers: NonNegativeInt = 0,
        num_input_views: PositiveInt = 1, num_target_views: NonNegativeInt = 1, max_objects: PositiveInt = 3,
        seed: int = 0, boxes: str = "gt", match_iou: UnitIoU = 0.5, max_boxes: PositiveInt = 8,
        train_random_views: bool = True, proposal_workers: PositiveInt | None = None, sensor_captures: bool = True,
    ) -> None:
        super().__init__()
        self.sensor_captures = bool(sensor_captures)
        if boxes not in ("gt", "proposals") and "{split}" not in boxes:
            raise ValueError(f"boxes: expected 'gt', 'proposals' or a path containing '{{split}}', got {boxes!r}")
        self.boxes = boxes
        self.match_iou = match_iou
        self.max_boxes = max_boxes
        self.train_random_views = bool(train_random_views)
        self.proposal_workers = proposal_workers if proposal_workers is not None else _cores(8)
        self.data_dir = Path(data_dir)
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.num_input_views = num_input_views
        self.num_target_views = num_target_views
        self.max_objects = max_objects
        self.seed = seed
        self._index: DatasetIndex | None = None
        self.datasets: dict[str, SceneDataset] = {}

    @property
    def index(self) -> DatasetIndex:
        if self._index is None:
            self._index = load_index(self.data_dir)
        return self._index

    @property
    def num_classes(self) -> int:
        """The dataset's category count (``index.json``); the CLI links it to a stage's ``num_classes``."""
        return len(self.index.categories)

    @property
    def symmetry_order(self) -> list[int]:
        """Per category, its yaw symmetry order (``index.json``); the CLI links it to a stage's ``symmetry_order``."""
        return [int(o) for o in self.index.symmetry_order]

    def setup(self, stage: str | None = None) -> None:
        for split in SPLITS:
            if split not in self.datasets and self.index.files(split):
                random_views = split == "train" and self.train_random_views
                self.datasets[split] = self._dataset(split, self.num_target_views, random_views, True)

    def box_sets(self, split: str) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
        """The proposed/detected boxes of a split per scene file (``None`` for GT boxes)."""
        if self.boxes == "gt":
            return None
        if self.boxes == "proposals":
            return self.pseudo_boxes(split)
        return load_boxes_file(self.boxes.format(split=split))

    def pseudo_boxes(self, split: str, progress: bool = False) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The label-free pseudo-boxes (:mod:`threedq.proposals`) of a split per scene file, cached in
        ``<data_dir>/proposals/<split>.npz``."""
        cache = self.data_dir / "proposals" / f"{split}.npz"
        params = SENSOR_PROPOSALS if self.sensor_captures else RENDER_PROPOSALS
        return propose_dataset(self.data_dir, split, cache, params=params, progress=progress,
                               workers=self.proposal_workers)

    def fixed_view_dataset(self, split: str, gallery: bool = False, with_boxes: bool = True) -> SceneDataset:
        """A dataset over one split of every scene's fixed input views; ``gallery``: plus the scene's next fixed view;
        ``with_boxes``: the samples carry this DataModule's ``boxes`` (else the GT boxes)."""
        return self._dataset(split, 1 if gallery else 0, False, with_boxes)

    def _dataset(self, split: str, num_target_views: int, random_views: bool, with_boxes: bool) -> SceneDataset:
        return SceneDataset(
            self.data_dir, self.index, split, num_input_views=self.num_input_views, num_target_views=num_target_views,
            max_objects=self.max_objects, random_views=random_views, seed=self.seed,
            box_sets=self.box_sets(split) if with_boxes else None, match_iou=self.match_iou,
            keep_unmatched=split == "train", max_boxes=self.max_boxes, align_floor=self.sensor_captures,
        )  # fmt: skip

    def box_extents(self, split: str = "train") -> np.ndarray:
        """``[N, 3]`` extents (x, y, z; metres) of the object boxes a split's samples carry: the GT boxes' hulls, or
        each scene's ``max_boxes`` highest-scoring proposed/detected boxes."""
        sets = self.box_sets(split)
        if sets is not None:
            pairs = [sets[f] for f in self.index.files(split) if f in sets]
            order = [np.argsort(-np.asarray(sc).reshape(-1), kind="stable")[: self.max_boxes] for _, sc in pairs]
            rows = [np.asarray(a, np.float64).reshape(-1, 6)[o] for (a, _), o in zip(pairs, order, strict=True)]
        else:
            rows = []
            for f in self.index.files(split):
                path = self.data_dir / f
                try:
                    with np.load(path, allow_pickle=False) as npz:
                        boxes = np.asarray(npz["boxes"], np.float64).reshape(-1, 7)
                except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError) as e:
                    raise SceneValidationError(str(path), "boxes", f"cannot be read: {e}") from e
                rows.append(boxes_to_aabb(boxes))
        aabb = np.concatenate(rows) if rows else np.zeros((0, 6))
        return aabb[:, 3:] - aabb[:, :3]

    def describe_boxes(self, split: str = "train") -> str:
        """Where a split's boxes come from, for messages: ``<data_dir> (split train, boxes='proposals')``."""
        return f"{self.data_dir} (split {split}, boxes={self.boxes!r})"

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        if split not in self.datasets:
            self.setup()
        if split not in self.datasets:
            raise SceneValidationError(str(self.data_dir / "index.json"), "scenes", f"no scenes in split {split!r}")
        dataset = self.datasets[split]
        if shuffle:  # by (seed, epoch), the same in one process or many (threedq.data.samplers)
            sampler: Any = EpochShuffleSampler(dataset, seed=self.seed)
        elif torch.distributed.is_available() and torch.distributed.is_initialized():
            sampler = ContiguousDistributedSampler(dataset)  # each sample once, in the one-process order
        else:
            sampler = None
        return DataLoader(dataset, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers,
                          persistent_workers=self.num_workers > 0, drop_last=False)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)

    predict_dataloader = test_dataloader
