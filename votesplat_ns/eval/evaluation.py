"""Instance segmentation scores against exact ground truth (numpy/scipy; Pillow only to save pictures).

Label conventions
-----------------
* Ground-truth instance maps: integer [H,W] per view, 0 = background, k > 0 = instance k. Ids are
  the same instance in every view (as in the synthetic datasets).
* Predicted instance maps: integer [H,W] per view; any id <= 0 (0 or -1, e.g. HDBSCAN noise) means
  "no instance". A predicted id is one instance across all views.

2D score (:func:`match_instances`): IoU between every GT and predicted instance is computed over all
views jointly (pixel counts summed over views), GT and predictions are matched one-to-one by the
Hungarian method maximising total IoU (``scipy.optimize.linear_sum_assignment``), a pair with IoU 0
counts as unmatched, and:

* per-GT IoU: IoU with its match, 0 if unmatched; mIoU = mean over GT instances present in the maps;
* true positive: a matched pair with IoU >= ``iou_threshold`` (0.5 by default);
  precision = TP / #predicted instances (0 when nothing is predicted), recall = TP / #GT instances.

3D score (:func:`gaussian_purity`): from per-Gaussian predicted ids and the GT instance each Gaussian
lies on (0 = none/background, supplied by the caller).

What a user sees (:func:`object_scores`, over Gaussians, the same inputs): an exported instance is
one entry in the instance list, one click target, one PLY. A GT object is *matched* when the
one-to-one (Hungarian) assignment on Gaussian-set IoU pairs it with an instance at IoU >= 0.5, so
a fragment of an object is never matched. List precision = matched instances / all predicted
instances; 3D AP@50 ranks the instances by a confidence (ScanNet-style, see :func:`average_precision_3d`).

Reconstruction check (:func:`check_reconstruction`): an instance score is only meaningful where the
render shows the scene. A view whose RGB render failed (e.g. a wall of floaters in front of the
camera) is flagged from its PSNR, with two scale-free rules (both in dB, i.e. ratios of squared
errors, so they mean the same for any image brightness or contrast):

* far below the run: PSNR more than ``max_psnr_drop_db`` (6 dB: four times the squared error) below
  the median PSNR of the checked views. The median ignores failures as long as fewer than half of
  the views fail;
* no better than a flat picture: PSNR less than ``min_gain_db`` (2 dB: a squared error above 63% of
  a flat image's) above the PSNR that the view's own mean colour, painted over the whole frame,
  reaches (:func:`flat_image_psnr`, the best any constant image can do). This one needs no other
  view, so it holds even when every view fails.

Measured on the bundled demo's short CPU run (held-out views at 20-23 dB, 3.8-5.0 dB above a flat
image), with a wall of grey floaters rendered in front of a held-out camera: covering 20% of the
view leaves 0.5-2.2 dB above a flat image, 30% -0.3-1.3 dB, the whole view -2.5 dB; the PSNR drop
of a whole-view wall is 6.5-7.4 dB there, and grows with the quality of the run. An absolute PSNR
floor cannot tell a wall from a scene: a flat grey image alone reaches 12-16 dB on the demo's views.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from votesplat_ns.core.ply_io import atomic_write


def _as_views(maps, what: str) -> list:
    if isinstance(maps, np.ndarray):
        if maps.ndim == 2:
            maps = [maps]
        elif maps.ndim == 3:
            maps = list(maps)
        else:
            raise ValueError(f"{what}: expected [H,W] per view or [V,H,W], got an array of shape {maps.shape}")
    views = [np.asarray(m) for m in maps]
    if not views:
        raise ValueError(f"{what}: no views given; pass at least one [H,W] map")
    for i, view in enumerate(views):
        if view.ndim != 2:
            raise ValueError(f"{what}: view {i} has shape {view.shape}; each view must be a 2D [H,W] id map")
        if not (np.issubdtype(view.dtype, np.integer) or view.dtype == np.bool_):
            raise ValueError(
                f"{what}: view {i} has dtype {view.dtype}; instance maps must be integer ids (cast with .astype(int))"
            )
    return views


def _check_pairs(gt_views: list, pred_views: list) -> None:
    if len(gt_views) != len(pred_views):
        raise ValueError(
            f"{len(gt_views)} ground-truth views but {len(pred_views)} predicted views; pass one prediction per GT view"
        )
    for i, (g, p) in enumerate(zip(gt_views, pred_views)):
        if g.shape != p.shape:
            raise ValueError(
                f"view {i}: ground truth is {g.shape} but prediction is {p.shape}; resize the prediction (nearest) first"
            )


@dataclass(frozen=True)
class Contingency:
    gt_ids: np.ndarray  # [G] instance ids present in the ground truth
    pred_ids: np.ndarray  # [P] instance ids present in the prediction
    intersection: np.ndarray  # [G,P] pixels, summed over views
    gt_area: np.ndarray  # [G]
    pred_area: np.ndarray  # [P]

    @property
    def iou(self) -> np.ndarray:
        union = self.gt_area[:, None] + self.pred_area[None, :] - self.intersection
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(union > 0, self.intersection / np.maximum(union, 1), 0.0)


def contingency(gt_maps, pred_maps) -> Contingency:
    """Pixel overlap counts between GT ids (> 0) and predicted ids (> 0) summed over all views."""
    gt_views, pred_views = _as_views(gt_maps, "gt_maps"), _as_views(pred_maps, "pred_maps")
    _check_pairs(gt_views, pred_views)
    for i, g in enumerate(gt_views):
        if g.size and g.min() < 0:
            raise ValueError(
                f"gt_maps: view {i} has negative ids; ground truth uses 0 for background and k > 0 for instances"
            )
    pair_counts: Dict[Tuple[int, int], int] = {}
    gt_area: Dict[int, int] = {}
    pred_area: Dict[int, int] = {}
    for g, p in zip(gt_views, pred_views):
        g = g.astype(np.int64).ravel()
        p = np.where(p > 0, p, 0).astype(np.int64).ravel()
        for ids, areas in ((g, gt_area), (p, pred_area)):
            counts = np.bincount(ids) if ids.size and ids.max() < 2**24 else None
            if counts is None:
                values, counts = np.unique(ids[ids > 0], return_counts=True)
            else:
                values = np.nonzero(counts)[0]
                values, counts = values[values > 0], counts[values[values > 0]]
            for v, c in zip(values.tolist(), counts.tolist()):
                areas[v] = areas.get(v, 0) + c
        both = (g > 0) & (p > 0)
        if both.any():
            stride = int(p.max()) + 1
            keys, counts = np.unique(g[both] * stride + p[both], return_counts=True)
            for key, c in zip(keys.tolist(), counts.tolist()):
                pair = divmod(key, stride)
                pair_counts[pair] = pair_counts.get(pair, 0) + c
    gt_ids = np.array(sorted(gt_area), dtype=np.int64)
    pred_ids = np.array(sorted(pred_area), dtype=np.int64)
    g_index = {v: i for i, v in enumerate(gt_ids.tolist())}
    p_index = {v: i for i, v in enumerate(pred_ids.tolist())}
    inter = np.zeros((len(gt_ids), len(pred_ids)), dtype=np.int64)
    for (gi, pi), c in pair_counts.items():
        inter[g_index[gi], p_index[pi]] = c
    return Contingency(
        gt_ids,
        pred_ids,
        inter,
        np.array([gt_area[v] for v in gt_ids.tolist()], dtype=np.int64),
        np.array([pred_area[v] for v in pred_ids.tolist()], dtype=np.int64),
    )


@dataclass(frozen=True)
class InstanceScores:
    gt_ids: np.ndarray
    pred_ids: np.ndarray
    iou: np.ndarray  # [G,P] joint IoU over all views
    matches: Dict[int, Optional[int]]  # GT id -> matched predicted id, None if unmatched
    per_gt_iou: Dict[int, float]
    miou: float
    precision: float
    recall: float
    f1: float
    true_positives: int
    iou_threshold: float

    def to_dict(self) -> dict:
        return {
            "miou": self.miou,
            "precision": self.precision,
            "recall": self.recall,
            "f1": self.f1,
            "true_positives": self.true_positives,
            "num_gt": int(len(self.gt_ids)),
            "num_pred": int(len(self.pred_ids)),
            "iou_threshold": self.iou_threshold,
            "per_gt_iou": {str(k): v for k, v in self.per_gt_iou.items()},
            "matches": {str(k): v for k, v in self.matches.items()},
        }


def match_instances(gt_maps, pred_maps, iou_threshold: float = 0.5) -> InstanceScores:
    """Hungarian matching on joint multi-view IoU; mIoU, precision and recall (see module docstring)."""
    if not 0.0 < iou_threshold <= 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1] (got {iou_threshold})")
    table = contingency(gt_maps, pred_maps)
    if len(table.gt_ids) == 0:
        raise ValueError("the ground-truth maps contain no instance (all 0); nothing to score against")
    iou = table.iou
    matches: Dict[int, Optional[int]] = {int(g): None for g in table.gt_ids}
    per_gt = {int(g): 0.0 for g in table.gt_ids}
    tp = 0
    if len(table.pred_ids):
        rows, cols = linear_sum_assignment(iou, maximize=True)
        for r, c in zip(rows, cols):
            if iou[r, c] <= 0.0:
                continue
            g, p = int(table.gt_ids[r]), int(table.pred_ids[c])
            matches[g] = p
            per_gt[g] = float(iou[r, c])
            tp += int(iou[r, c] >= iou_threshold)
    num_gt, num_pred = len(table.gt_ids), len(table.pred_ids)
    precision = tp / num_pred if num_pred else 0.0
    recall = tp / num_gt
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return InstanceScores(
        gt_ids=table.gt_ids,
        pred_ids=table.pred_ids,
        iou=iou,
        matches=matches,
        per_gt_iou=per_gt,
        miou=float(np.mean(list(per_gt.values()))),
        precision=float(precision),
        recall=float(recall),
        f1=float(f1),
        true_positives=tp,
        iou_threshold=float(iou_threshold),
    )


@dataclass(frozen=True)
class GaussianScores:
    """Cluster quality of per-Gaussian instance ids.

    * ``purity``: over Gaussians with a predicted id > 0, the fraction whose GT label (0 included, so
      background swept into a cluster counts against it) is the majority GT label of their cluster;
      equal to the mean per-Gaussian purity, i.e. cluster purities weighted by cluster size.
    * ``completeness``: over Gaussians on a GT instance (> 0), the fraction that sit in the predicted
      cluster holding most of their instance (unassigned Gaussians count as misses).
    * ``miou_3d``: mean over GT instances of the Gaussian-set IoU with its Hungarian match (0 if none).
    * ``assigned_fraction``: fraction of GT-instance Gaussians that got a predicted id > 0.

    Per GT object (the labels > 0 that some Gaussian carries):

    * ``per_gt_completeness``: the fraction of its Gaussians in the cluster holding most of them;
      ``mean_completeness`` is its plain mean over objects (``completeness`` weights by size).
    * ``per_gt_match``: the cluster the Hungarian assignment on Gaussian-set IoU gives it (any IoU
      > 0; None if none), with that IoU in ``per_gt_iou``.
    * ``per_gt_purity``: of the Gaussians of that matched cluster, the fraction whose GT label is
      this object, i.e. how much of what a user selects is the object; None for an object without
      a match, and ``mean_purity`` is the mean over the matched objects (None if there are none).
    """

    purity: float
    completeness: float
    miou_3d: float
    assigned_fraction: float
    per_cluster_purity: Dict[int, float] = field(default_factory=dict)
    cluster_majority: Dict[int, int] = field(default_factory=dict)
    per_gt_completeness: Dict[int, float] = field(default_factory=dict)
    per_gt_match: Dict[int, Optional[int]] = field(default_factory=dict)
    per_gt_iou: Dict[int, float] = field(default_factory=dict)
    per_gt_purity: Dict[int, Optional[float]] = field(default_factory=dict)

    @property
    def mean_completeness(self) -> float:
        values = list(self.per_gt_completeness.values())
        return float(np.mean(values)) if values else 0.0

    @property
    def mean_purity(self) -> Optional[float]:
        values = [v for v in self.per_gt_purity.values() if v is not None]
        return float(np.mean(values)) if values else None

    def to_dict(self) -> dict:
        return {
            "purity": self.purity,
            "completeness": self.completeness,
            "miou_3d": self.miou_3d,
            "assigned_fraction": self.assigned_fraction,
            "mean_completeness": self.mean_completeness,
            "mean_purity": self.mean_purity,
            "per_cluster_purity": {str(k): v for k, v in self.per_cluster_purity.items()},
            "cluster_majority": {str(k): v for k, v in self.cluster_majority.items()},
            "per_gt_completeness": {str(k): v for k, v in self.per_gt_completeness.items()},
            "per_gt_match": {str(k): v for k, v in self.per_gt_match.items()},
            "per_gt_iou": {str(k): v for k, v in self.per_gt_iou.items()},
            "per_gt_purity": {str(k): v for k, v in self.per_gt_purity.items()},
        }


def gaussian_purity(pred_ids, gt_ids) -> GaussianScores:
    """3D score from predicted per-Gaussian ids (<= 0 = unassigned) and GT per-Gaussian instances (0 = none)."""
    pred = np.asarray(pred_ids)
    gt = np.asarray(gt_ids)
    if pred.ndim != 1 or gt.ndim != 1 or pred.shape != gt.shape:
        raise ValueError(f"pred_ids and gt_ids must be 1D arrays of equal length (got {pred.shape} and {gt.shape})")
    for name, arr in (("pred_ids", pred), ("gt_ids", gt)):
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{name} has dtype {arr.dtype}; per-Gaussian ids must be integers")
    if pred.size == 0:
        raise ValueError("no Gaussians given; pred_ids and gt_ids are empty")
    if gt.min() < 0:
        raise ValueError("gt_ids has negative values; use 0 for Gaussians on no instance")
    pred = np.where(pred > 0, pred, 0).astype(np.int64)
    gt = gt.astype(np.int64)
    # one contingency table: rows = unassigned (row 0) + predicted clusters, columns = GT labels (0 included)
    clusters, row = np.unique(pred, return_inverse=True)
    labels, col = np.unique(gt, return_inverse=True)
    if clusters[0] != 0:
        clusters, row = np.concatenate([[0], clusters]), row + 1
    if len(labels) == 0 or labels[0] != 0:
        labels, col = np.concatenate([[0], labels]), col + 1
    table = np.bincount(row.ravel() * len(labels) + col.ravel(), minlength=len(clusters) * len(labels))
    table = table.reshape(len(clusters), len(labels))
    assigned_rows, object_cols = table[1:], table[:, 1:]
    cluster_ids, gt_instances = clusters[1:].tolist(), labels[1:].tolist()

    per_cluster, majority = {}, {}
    for i, c in enumerate(cluster_ids):
        j = int(np.argmax(assigned_rows[i]))
        per_cluster[c] = float(assigned_rows[i, j] / assigned_rows[i].sum())
        majority[c] = int(labels[j])
    num_assigned = int(assigned_rows.sum())
    purity = float(assigned_rows.max(axis=1).sum() / num_assigned) if num_assigned else 0.0

    inter = object_cols[1:].T  # [GT instances, clusters]
    sizes = object_cols.sum(axis=0)  # every Gaussian on the instance, assigned or not
    best = inter.max(axis=1) if len(cluster_ids) else np.zeros(len(gt_instances), dtype=np.int64)
    per_gt = {g: float(best[k] / sizes[k]) for k, g in enumerate(gt_instances)}
    completeness = float(best.sum() / sizes.sum()) if len(gt_instances) else 0.0
    miou_3d = 0.0
    match: Dict[int, Optional[int]] = {g: None for g in gt_instances}
    match_iou = {g: 0.0 for g in gt_instances}
    match_purity: Dict[int, Optional[float]] = {g: None for g in gt_instances}
    if len(gt_instances) and len(cluster_ids):
        cluster_sizes = assigned_rows.sum(axis=1)
        union = sizes[:, None] + cluster_sizes[None, :] - inter
        iou = inter / np.maximum(union, 1)
        rows, cols = linear_sum_assignment(iou, maximize=True)
        miou_3d = float(iou[rows, cols].sum() / len(gt_instances))
        for r, c in zip(rows.tolist(), cols.tolist()):
            if inter[r, c] > 0:
                g = gt_instances[r]
                match[g], match_iou[g] = int(cluster_ids[c]), float(iou[r, c])
                match_purity[g] = float(inter[r, c] / cluster_sizes[c])
    on_object = int(sizes.sum())
    assigned_fraction = float(inter.sum() / on_object) if on_object else 0.0
    return GaussianScores(
        purity, completeness, miou_3d, assigned_fraction, per_cluster, majority, per_gt, match, match_iou, match_purity
    )


def _gaussian_iou_table(pred_ids, gt_ids) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted ids [P] > 0, GT ids [G] > 0, IoU [G,P] of their Gaussian sets) from per-Gaussian ids."""
    pred = np.asarray(pred_ids)
    gt = np.asarray(gt_ids)
    if pred.ndim != 1 or gt.ndim != 1 or pred.shape != gt.shape:
        raise ValueError(f"pred_ids and gt_ids must be 1D arrays of equal length (got {pred.shape} and {gt.shape})")
    for name, arr in (("pred_ids", pred), ("gt_ids", gt)):
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{name} has dtype {arr.dtype}; per-Gaussian ids must be integers")
    if gt.size and gt.min() < 0:
        raise ValueError("gt_ids has negative values; use 0 for Gaussians on no instance")
    pred = np.where(pred > 0, pred, 0).astype(np.int64)
    gt = gt.astype(np.int64)
    clusters = np.unique(pred[pred > 0])
    objects = np.unique(gt[gt > 0])
    row = np.searchsorted(objects, gt)
    col = np.searchsorted(clusters, pred)
    both = (gt > 0) & (pred > 0)
    inter = np.zeros((len(objects), len(clusters)), dtype=np.int64)
    np.add.at(inter, (row[both], col[both]), 1)
    gt_size = np.array([(gt == g).sum() for g in objects.tolist()], dtype=np.int64)
    pred_size = np.array([(pred == c).sum() for c in clusters.tolist()], dtype=np.int64)
    union = gt_size[:, None] + pred_size[None, :] - inter
    return clusters, objects, inter / np.maximum(union, 1)


def average_precision_3d(pred_ids, gt_ids, confidence: Dict[int, float], iou_threshold: float = 0.5) -> dict:
    """ScanNet-style AP over Gaussians: rank, match greedily, integrate the precision/recall curve.

    ``confidence`` maps every predicted id > 0 to its score. Instances are taken in order of
    decreasing confidence (ties: smaller id first); each is a true positive if the GT object it
    overlaps most (Gaussian-set IoU) among the objects not yet taken reaches ``iou_threshold``,
    which it then takes; otherwise a false positive. With recall r_k = TP_k / #objects and
    precision p_k = TP_k / k after the k-th instance, the curve is made monotone (p at r is the
    best precision at any recall >= r) and AP is the area under it, sum_k (r_k - r_{k-1}) p_k.
    Returns ``ap`` (0 when nothing is predicted; None when there is no GT object), ``precision``
    and ``recall`` (the curve in ranking order) and ``order`` (the ranked ids).
    """
    if not 0.0 < iou_threshold <= 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1] (got {iou_threshold})")
    clusters, objects, iou = _gaussian_iou_table(pred_ids, gt_ids)
    missing = [c for c in clusters.tolist() if c not in confidence]
    if missing:
        raise ValueError(f"no confidence for predicted instances {missing[:5]}; give one per predicted id")
    order = sorted(range(len(clusters)), key=lambda c: (-float(confidence[int(clusters[c])]), int(clusters[c])))
    taken = np.zeros(len(objects), dtype=bool)
    hits = []
    for c in order:
        candidates = np.where(taken, -1.0, iou[:, c]) if len(objects) else np.zeros(0)
        best = int(np.argmax(candidates)) if len(objects) else -1
        hit = best >= 0 and candidates[best] >= iou_threshold
        if hit:
            taken[best] = True
        hits.append(hit)
    tp = np.cumsum(hits, dtype=np.float64)
    precision = tp / np.arange(1, len(hits) + 1) if hits else np.zeros(0)
    recall = tp / len(objects) if len(objects) else np.zeros(len(hits))
    ap: Optional[float] = None
    if len(objects):
        envelope = np.maximum.accumulate(precision[::-1])[::-1] if hits else np.zeros(0)
        steps = np.diff(np.concatenate([[0.0], recall]))
        ap = float((steps * envelope).sum())
    return {
        "ap": ap,
        "precision": precision.tolist(),
        "recall": recall.tolist(),
        "order": [int(clusters[c]) for c in order],
    }


@dataclass(frozen=True)
class ObjectScores:
    """The instance list as a user sees it (module doc): matches at Gaussian-set IoU >= the threshold."""

    num_predicted: int
    num_gt: int
    num_matched: int
    list_precision: float  # matched / predicted instances (0 when nothing is predicted)
    ap: Optional[float]  # 3D AP at the threshold; None without GT objects
    matches: Dict[int, Optional[int]]  # GT id -> predicted id matched at >= threshold, None if none
    iou_threshold: float

    def to_dict(self) -> dict:
        return {
            "num_predicted": self.num_predicted,
            "num_gt": self.num_gt,
            "num_matched": self.num_matched,
            "list_precision": self.list_precision,
            "ap": self.ap,
            "iou_threshold": self.iou_threshold,
            "matches": {str(k): v for k, v in self.matches.items()},
        }


def object_scores(pred_ids, gt_ids, confidence: Dict[int, float], iou_threshold: float = 0.5) -> ObjectScores:
    """List precision and 3D AP of per-Gaussian predicted ids (> 0 = an instance) against GT labels (> 0 = an object).

    A GT object and an instance are matched when the Hungarian assignment maximising total
    Gaussian-set IoU pairs them at IoU >= ``iou_threshold``; every other instance (a fragment, a
    floater, a merge that lost its pair) lowers the list precision. ``confidence`` (predicted id
    -> score) ranks the instances for :func:`average_precision_3d`.
    """
    if not 0.0 < iou_threshold <= 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1] (got {iou_threshold})")
    clusters, objects, iou = _gaussian_iou_table(pred_ids, gt_ids)
    matches: Dict[int, Optional[int]] = {int(g): None for g in objects.tolist()}
    if len(objects) and len(clusters):
        for r, c in zip(*linear_sum_assignment(iou, maximize=True)):
            if iou[r, c] >= iou_threshold:
                matches[int(objects[r])] = int(clusters[c])
    matched = sum(v is not None for v in matches.values())
    ap = average_precision_3d(pred_ids, gt_ids, confidence, iou_threshold)["ap"]
    return ObjectScores(
        num_predicted=len(clusters),
        num_gt=len(objects),
        num_matched=matched,
        list_precision=matched / len(clusters) if len(clusters) else 0.0,
        ap=ap,
        matches=matches,
        iou_threshold=float(iou_threshold),
    )


# --------------------------------------------------------------------------------------------
# reconstruction check

DEFAULT_MAX_PSNR_DROP_DB = 6.0
DEFAULT_MIN_GAIN_DB = 2.0


def _rgb_pair(prediction, target) -> Tuple[np.ndarray, np.ndarray]:
    prediction, target = np.asarray(prediction, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if prediction.shape != target.shape:
        raise ValueError(
            f"prediction is {prediction.shape} but the target image is {target.shape}; render at the image's size"
        )
    if target.ndim not in (2, 3) or target.size == 0:
        raise ValueError(f"images must be [H,W] or [H,W,C] with pixels, got shape {target.shape}")
    return prediction, target


def psnr(prediction, target, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all pixels and channels (inf for identical images)."""
    prediction, target = _rgb_pair(prediction, target)
    mse = float(np.mean((prediction - target) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(data_range**2 / mse))


def flat_image_psnr(target, data_range: float = 1.0) -> float:
    """PSNR of the best constant image: ``target``'s own mean colour everywhere (10 log10(range^2 / variance))."""
    _, target = _rgb_pair(target, target)
    mean = target.reshape(-1, target.shape[-1]).mean(axis=0) if target.ndim == 3 else target.mean()
    return psnr(np.broadcast_to(mean, target.shape), target, data_range)


@dataclass(frozen=True)
class ReconstructionCheck:
    """Per view PSNR, flat-image PSNR and verdict (see the module doc), with the rule's settings."""

    psnr: np.ndarray  # [V] dB
    flat_psnr: np.ndarray  # [V] dB
    ok: np.ndarray  # [V] bool, False = the reconstruction failed in this view
    median_psnr: float
    max_psnr_drop_db: float
    min_gain_db: float

    @property
    def num_valid(self) -> int:
        return int(self.ok.sum())

    def to_dict(self) -> dict:
        return {
            "rule": "flagged if psnr < median_psnr - max_psnr_drop_db or psnr < flat_psnr + min_gain_db",
            "median_psnr": _json_number(self.median_psnr),
            "max_psnr_drop_db": _json_number(self.max_psnr_drop_db),
            "min_gain_db": _json_number(self.min_gain_db),
            "num_views": int(len(self.ok)),
            "num_valid_views": self.num_valid,
        }

    def per_view(self, names) -> List[dict]:
        """One JSON entry per view: name, psnr, flat_psnr (null for an infinite PSNR) and reconstruction_ok."""
        names = list(names)
        if len(names) != len(self.ok):
            raise ValueError(f"{len(names)} view names for {len(self.ok)} checked views")
        return [
            {
                "name": str(name),
                "psnr": _json_number(self.psnr[i]),
                "flat_psnr": _json_number(self.flat_psnr[i]),
                "reconstruction_ok": bool(self.ok[i]),
            }
            for i, name in enumerate(names)
        ]


def _json_number(value: float) -> Optional[float]:
    """JSON has no inf/nan: a non-finite float (e.g. the PSNR of a perfect render) is written as null."""
    return float(value) if np.isfinite(value) else None


def check_reconstruction(
    psnrs,
    flat_psnrs,
    max_psnr_drop_db: float = DEFAULT_MAX_PSNR_DROP_DB,
    min_gain_db: float = DEFAULT_MIN_GAIN_DB,
) -> ReconstructionCheck:
    """Flag views whose render failed (module doc). ``inf`` / ``-inf`` turn the first / second rule off.

    A view with a NaN PSNR (a render with NaN pixels) is flagged and left out of the median.
    """
    values = np.asarray(psnrs, dtype=np.float64).reshape(-1)
    flat = np.asarray(flat_psnrs, dtype=np.float64).reshape(-1)
    if values.shape != flat.shape or values.size == 0:
        raise ValueError(f"need one PSNR and one flat-image PSNR per view (got {values.size} and {flat.size})")
    if np.isnan(max_psnr_drop_db) or not max_psnr_drop_db > 0:
        raise ValueError(f"max_psnr_drop_db must be > 0 dB, inf for no limit (got {max_psnr_drop_db})")
    if np.isnan(min_gain_db) or min_gain_db == float("inf"):
        raise ValueError(f"min_gain_db must be a number of dB, -inf for no limit (got {min_gain_db})")
    known = ~np.isnan(values)
    median = float(np.median(values[known])) if known.any() else float("nan")
    with np.errstate(invalid="ignore"):
        ok = known & ~(values < median - max_psnr_drop_db) & ~(values - flat < min_gain_db)
    return ReconstructionCheck(values, flat, ok, median, float(max_psnr_drop_db), float(min_gain_db))


# --------------------------------------------------------------------------------------------
# pictures


def instance_palette(count: int, saturation: float = 0.75, value: float = 0.95, offset: float = 0.0) -> np.ndarray:
    """[count,3] uint8 colours with well-spread hues (golden-ratio steps); entry 0 is black."""
    colours = np.zeros((max(count, 1), 3), dtype=np.uint8)
    for k in range(1, count):
        hue = (offset + k * 0.618033988749895) % 1.0
        colours[k] = np.round(np.array(colorsys.hsv_to_rgb(hue, saturation, value)) * 255)
    return colours


def _colourise(ids: np.ndarray, colour_of: Dict[int, np.ndarray]) -> np.ndarray:
    out = np.zeros(ids.shape + (3,), dtype=np.uint8)
    for value, colour in colour_of.items():
        out[ids == value] = colour
    return out


def save_comparison_png(gt_maps, pred_maps, path, scale: int = 1, gap: int = 4) -> Path:
    """One row per view: GT instances | predicted instances, written atomically as a PNG.

    A predicted instance matched to a GT instance (see :func:`match_instances`) takes that GT
    instance's colour, so a correct prediction looks identical to the GT; unmatched predictions get
    duller colours of their own; "none" is black.
    """
    from PIL import Image

    gt_views, pred_views = _as_views(gt_maps, "gt_maps"), _as_views(pred_maps, "pred_maps")
    _check_pairs(gt_views, pred_views)
    if scale < 1 or gap < 0:
        raise ValueError(f"scale must be >= 1 and gap >= 0 (got scale={scale}, gap={gap})")
    table = contingency(gt_views, pred_views)
    matches: Dict[int, int] = {}
    if len(table.gt_ids) and len(table.pred_ids):
        iou = table.iou
        for r, c in zip(*linear_sum_assignment(iou, maximize=True)):
            if iou[r, c] > 0:
                matches[int(table.pred_ids[c])] = int(table.gt_ids[r])
    gt_palette = instance_palette(len(table.gt_ids) + 1)
    gt_colour = {int(g): gt_palette[i + 1] for i, g in enumerate(table.gt_ids)}
    spare = instance_palette(len(table.pred_ids) + 1, saturation=0.45, value=0.6, offset=0.31)
    pred_colour = {
        int(p): gt_colour[matches[int(p)]] if int(p) in matches else spare[i + 1] for i, p in enumerate(table.pred_ids)
    }
    rows = []
    for g, p in zip(gt_views, pred_views):
        left = _colourise(g, gt_colour)
        right = _colourise(np.where(p > 0, p, 0), pred_colour)
        sep = np.full((g.shape[0], gap, 3), 255, dtype=np.uint8)
        rows.append(np.concatenate([left, sep, right], axis=1))
    width = max(r.shape[1] for r in rows)
    padded = []
    for i, r in enumerate(rows):
        if r.shape[1] < width:
            r = np.concatenate([r, np.full((r.shape[0], width - r.shape[1], 3), 255, np.uint8)], axis=1)
        padded.append(r)
        if i < len(rows) - 1:
            padded.append(np.full((gap, width, 3), 255, dtype=np.uint8))
    picture = np.concatenate(padded, axis=0)
    if scale > 1:
        picture = picture.repeat(scale, axis=0).repeat(scale, axis=1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as handle:  # the user's umask, as every file we write
        Image.fromarray(picture).save(handle, format="PNG")
    return path
