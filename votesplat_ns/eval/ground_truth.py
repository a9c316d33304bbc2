"""Exact ground truth of a synthetic dataset (written by ``votesplat synth``) and the scores of one level.

:class:`GroundTruthDataset` reads a dataset's transforms.json and label images; the GT label of a
Gaussian comes from the scene's exact geometry (:func:`surface_labels`) or, failing that, from the
majority label under its projected mean (:func:`projected_majority_labels`), which also labels the Gaussians
that lie on no solid (floaters: what the training views see them as); see :func:`gaussian_ground_truth`.
:func:`score_level` turns rendered id maps and per-Gaussian ids into the 2D and 3D scores of ``votesplat eval``.
Pure numpy/torch.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple, Union

import numpy as np

from votesplat_ns.core.image_files import read_label_png
from votesplat_ns.core.instances import size_confidence
from votesplat_ns.core.ply_io import atomic_write
from votesplat_ns.eval.evaluation import gaussian_purity, match_instances, object_scores

DATAPARSER_TRANSFORMS_NAME = "dataparser_transforms.json"
DEPTH_UNIT_METRES = 1e-3
GT_LEVELS = ("instance", "part")
# A GT object (or part) that fewer training views than this show cannot be found from them: no
# mask ever separates it (fruit inside a closed box, the underside of a mug). Its Gaussians are
# left out of the 3D scores (label -1) and the object is listed as unseen instead.
MIN_TRAINING_VIEWS_SCORED = 2
NOT_SCORED = -1


def mask_key(level: str) -> str:
    """transforms.json frame key of a level's label image (as the dataset mask source reads it)."""
    return f"{level}_mask_path"


# ----------------------------------------------------------------------------- frames


def points_to_dataset_frame(points, transform, scale: float) -> np.ndarray:
    """Undo nerfstudio's dataparser transform: p_world = R^T (p / scale - t).

    nerfstudio maps a dataset point p to ``scale * (R p + t)`` with ``transform = [R | t]`` (3x4,
    R a rotation) and ``scale`` as saved in ``dataparser_transforms.json``.
    """
    points = np.asarray(points, dtype=np.float64)
    transform = np.asarray(transform, dtype=np.float64)
    if transform.shape == (4, 4):
        transform = transform[:3]
    if transform.shape != (3, 4):
        raise ValueError(f"dataparser transform must be 3x4 (or 4x4), got {transform.shape}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"dataparser scale must be a positive number, got {scale}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {points.shape}")
    rotation, translation = transform[:, :3], transform[:, 3]
    return (points / scale - translation) @ rotation


def read_dataparser_transform(config_path: Union[str, Path]) -> Tuple[np.ndarray, float]:
    """(transform [3,4], scale) from the ``dataparser_transforms.json`` next to a run's config.yml."""
    path = Path(config_path).parent / DATAPARSER_TRANSFORMS_NAME
    if not path.is_file():
        raise ValueError(
            f"{path} not found; it is written by ns-train next to config.yml (evaluate a complete run folder)"
        )
    data = json.loads(path.read_text(encoding="utf-8"))
    return np.asarray(data["transform"], dtype=np.float64), float(data["scale"])


# ----------------------------------------------------------------------------- GT per Gaussian


def surface_labels(scene, points_world, level: str, tolerance: float) -> np.ndarray:
    """Exact GT label per point from the scene's geometry: the label of the nearest solid.

    The candidates are every object part (label: its instance id at level ``instance``, its part
    id at level ``part``) and the background pieces (label 0). A point inside a closed primitive
    (a box, a full sweep of a closed profile) is at distance 0 from it: splatting fills solids
    with Gaussians that a removal of the object must take along. A point farther than
    ``tolerance`` (world units) from every solid, e.g. a floater, gets 0 (:func:`solid_labels` says which).
    """
    return solid_labels(scene, points_world, level, tolerance)[0]


def solid_labels(scene, points_world, level: str, tolerance: float) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`surface_labels`, and which finite points lie farther than ``tolerance`` from every solid (bool [N])."""
    if level not in GT_LEVELS:
        raise ValueError(f"no geometric ground truth for level {level!r}; use one of {list(GT_LEVELS)}")
    if not tolerance > 0:
        raise ValueError(f"tolerance must be > 0 (got {tolerance})")
    points = np.asarray(points_world, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {points.shape}")
    owners = [(obj.id if level == "instance" else part.id, part) for obj in scene.objects for part in obj.parts]
    owners += [(0, part) for part in scene.background]
    labels = np.zeros(len(points), dtype=np.int64)
    off_solids = np.zeros(len(points), dtype=bool)
    finite = np.isfinite(points).all(axis=1)
    if not finite.any() or not owners:
        return labels, off_solids
    distances = np.stack([scene.part_solid_distance(part, points[finite]) for _, part in owners], axis=1)
    nearest = distances.argmin(axis=1)
    ids = np.array([label for label, _ in owners], dtype=np.int64)[nearest]
    close = distances[np.arange(len(nearest)), nearest] <= tolerance
    labels[np.flatnonzero(finite)] = np.where(close, ids, 0)
    off_solids[np.flatnonzero(finite)] = ~close
    return labels, off_solids


@dataclass
class LabelledView:
    """A dataset view with exact labels: OpenCV world-to-camera, intrinsics, label image, depth."""

    viewmat: np.ndarray  # [4, 4], in the frame of the points it is used with
    K: np.ndarray  # [3, 3] for the label image's resolution
    labels: np.ndarray  # [H, W] int, 0 = background
    depth: Optional[np.ndarray] = None  # [H, W] camera z, 0 = no surface


def projected_majority_labels(points, views: Sequence[LabelledView], depth_tolerance: float = 0.01) -> np.ndarray:
    """GT label per point: the most frequent label under its projected position over ``views``.

    A view counts only if the point projects inside it, in front of the camera and, where the
    view has depth, not more than ``depth_tolerance`` (plus 1 percent of the depth) behind the
    visible surface, so occluders do not lend their label. Ties go to the smaller label; a
    point seen by no view gets 0.
    """
    points = np.asarray(points, dtype=np.float64)
    if not views:
        raise ValueError("projected_majority_labels needs at least one labelled view")
    max_label = max(int(v.labels.max()) for v in views)
    counts = np.zeros((len(points), max_label + 1), dtype=np.int64)
    finite = np.isfinite(points).all(axis=1)
    safe = np.where(finite[:, None], points, 0.0)
    for view in views:
        height, width = view.labels.shape
        cam = safe @ view.viewmat[:3, :3].T + view.viewmat[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = view.K[0, 0] * cam[:, 0] / z + view.K[0, 2]
            v = view.K[1, 1] * cam[:, 1] / z + view.K[1, 2]
        ok = finite & (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        col = np.clip(np.floor(np.nan_to_num(u)).astype(np.int64), 0, width - 1)
        row = np.clip(np.floor(np.nan_to_num(v)).astype(np.int64), 0, height - 1)
        if view.depth is not None:
            surface = view.depth[row, col]
            ok &= (surface <= 0) | (z <= surface + depth_tolerance + 0.01 * surface)
        index = np.flatnonzero(ok)
        np.add.at(counts, (index, view.labels[row[index], col[index]].astype(np.int64)), 1)
    labels = counts.argmax(axis=1)
    labels[counts.sum(axis=1) == 0] = 0
    return labels.astype(np.int64)


def pixel_footprint(camera_centres, targets, focal_length: float) -> float:
    """World size of one pixel at the median distance from the cameras to the targets."""
    centres = np.asarray(camera_centres, dtype=np.float64).reshape(-1, 3)
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    distance = np.linalg.norm(centres[:, None, :] - targets[None, :, :], axis=-1)
    return float(np.median(distance) / focal_length)


# ----------------------------------------------------------------------------- the dataset


@dataclass
class GroundTruthDataset:
    """A dataset's transforms.json, its frames by image file name, and the GT levels it has."""

    root: Path
    meta: dict
    frames: Dict[str, dict]
    levels: Tuple[str, ...]

    @classmethod
    def open(cls, data: Union[str, Path]) -> "GroundTruthDataset":
        data = Path(data)
        path = data if data.suffix == ".json" else data / "transforms.json"
        if not path.is_file():
            raise ValueError(f"{path} not found; point at a dataset folder written by votesplat synth")
        meta = json.loads(path.read_text(encoding="utf-8"))
        frames: Dict[str, dict] = {}
        for frame in meta.get("frames", []):
            name = Path(frame["file_path"]).name
            if name in frames:
                raise ValueError(f"{path} lists two frames named {name}; frame file names must be unique")
            frames[name] = frame
        levels = tuple(level for level in GT_LEVELS if frames and all(mask_key(level) in f for f in frames.values()))
        if "instance" not in levels:
            raise ValueError(
                f"dataset {path.parent} has no ground-truth masks (its frames lack 'instance_mask_path'); "
                "evaluate on a synthetic dataset written by votesplat synth"
            )
        return cls(path.parent.resolve(), meta, frames, levels)

    def frame(self, image_name: str) -> dict:
        frame = self.frames.get(Path(image_name).name)
        if frame is None:
            raise ValueError(f"image {image_name} is not a frame of {self.root / 'transforms.json'}")
        return frame

    def labels(self, image_name: str, level: str) -> np.ndarray:
        return read_label_png(self.root / self.frame(image_name)[mask_key(level)])

    def depth(self, image_name: str) -> Optional[np.ndarray]:
        frame = self.frame(image_name)
        if "depth_file_path" not in frame:
            return None
        return read_label_png(self.root / frame["depth_file_path"]).astype(np.float64) * DEPTH_UNIT_METRES

    def train_names(self) -> List[str]:
        listed = self.meta.get("train_filenames")
        names = [Path(p).name for p in listed] if listed else list(self.frames)
        return [n for n in names if n in self.frames]

    def named_ids(self, level: str) -> Dict[int, str]:
        """GT id -> human-readable name ("grey mug", "grey mug / handle")."""
        names: Dict[int, str] = {}
        for entry in self.meta.get("instances", []):
            if level == "instance":
                names[int(entry["id"])] = str(entry.get("name", entry["id"]))
            else:
                for part in entry.get("parts", []):
                    names[int(part["id"])] = f"{entry.get('name', entry['id'])} / {part.get('name', part['id'])}"
        return names

    def scene(self):
        """The generating scene (exact geometry) or None when it cannot be rebuilt."""
        from votesplat_ns.eval.synthetic.dataset_files import scene_from_dataset

        try:
            return scene_from_dataset(self.meta)
        except Exception:  # not a votesplat synth dataset, or another generator version
            return None


def gaussian_ground_truth(
    dataset: GroundTruthDataset,
    means_world: np.ndarray,
    levels: Sequence[str],
    method: Literal["auto", "geometry", "projection"] = "auto",
    surface_tolerance_px: float = 3.0,
) -> Tuple[Dict[str, np.ndarray], Dict[str, object]]:
    """GT label per Gaussian for each level (means in the dataset's world frame) and how it was made.

    Labels: the object (or part) id, 0 for none, :data:`NOT_SCORED` (-1) for the Gaussians of an
    object that fewer than :data:`MIN_TRAINING_VIEWS_SCORED` training views show (listed in
    ``info["unseen_objects"]``); :func:`score_level` leaves those out of the 3D scores.

    With the scene's geometry, a Gaussian within ``surface_tolerance_px`` pixel footprints of a solid takes that
    solid's label; one farther from every solid (a floater: a dark or shiny surface reconstructed thick in depth,
    fuzz in front of an object) takes what the training views see it as, the majority label under its projection
    (:func:`projected_majority_labels`, occluded views left out), 0 where no view sees it. A floater that the
    views show over an object renders as that object: removing the object must take it, or it stays behind as a
    ghost of it. ``info["off_solids"]`` counts them per level, ``info["off_solids_on_objects"]`` those labelled
    an object."""
    from votesplat_ns.eval.synthetic.dataset_files import read_views

    means_world = np.asarray(means_world, dtype=np.float64)
    meta, views = read_views(dataset.root)
    train = set(dataset.train_names())
    train_views = [v for v in views if v.name in train]
    centres = [entry["centre"] for entry in meta.get("instances", []) if "centre" in entry]
    targets = np.asarray(centres) if centres else np.zeros((1, 3))
    footprint = pixel_footprint([v.c2w[:3, 3] for v in train_views], targets, float(views[0].K[0, 0]))
    scene = dataset.scene() if method in ("auto", "geometry") else None
    if method == "geometry" and scene is None:
        raise ValueError(
            f"the scene of {dataset.root} cannot be rebuilt (not written by this votesplat synth version); "
            "use --gaussian-gt projection"
        )
    info: Dict[str, object] = {"pixel_footprint": footprint}
    labels: Dict[str, np.ndarray] = {}

    def labelled(level: str) -> List[LabelledView]:
        return [LabelledView(v.viewmat, v.K, dataset.labels(v.name, level), dataset.depth(v.name)) for v in train_views]

    if scene is not None:
        tolerance = surface_tolerance_px * footprint
        info.update(method="geometry", surface_tolerance=tolerance, surface_tolerance_px=surface_tolerance_px)
        off_counts: Dict[str, int] = {}
        off_on_objects: Dict[str, int] = {}
        for level in levels:
            labels[level], off = solid_labels(scene, means_world, level, tolerance)
            if off.any():
                labels[level][off] = projected_majority_labels(
                    means_world[off], labelled(level), depth_tolerance=footprint
                )
            off_counts[level] = int(off.sum())
            off_on_objects[level] = int((labels[level][off] > 0).sum())
        info.update(off_solids=off_counts, off_solids_on_objects=off_on_objects)
    else:
        info.update(method="projection", depth_tolerance=footprint, num_views=len(train_views))
        for level in levels:
            labels[level] = projected_majority_labels(means_world, labelled(level), depth_tolerance=footprint)
    unseen: Dict[str, List[int]] = {}
    for level in levels:
        shown = training_view_counts(dataset, level)
        present = np.unique(labels[level][labels[level] > 0])
        unseen[level] = [int(g) for g in present if shown.get(int(g), 0) < MIN_TRAINING_VIEWS_SCORED]
        labels[level] = np.where(np.isin(labels[level], unseen[level]), NOT_SCORED, labels[level])
    info["unseen_objects"] = unseen
    info["min_training_views_scored"] = MIN_TRAINING_VIEWS_SCORED
    info["fraction_on_objects"] = {
        level: float((labels[level] > 0).mean()) if len(labels[level]) else 0.0 for level in levels
    }
    return labels, info


def training_view_counts(dataset: GroundTruthDataset, level: str) -> Dict[int, int]:
    """GT id -> how many training views' label images show it (at least one pixel)."""
    counts: Dict[int, int] = {}
    for name in dataset.train_names():
        for gid in np.unique(dataset.labels(name, level)).tolist():
            counts[int(gid)] = counts.get(int(gid), 0) + 1
    return counts


# ----------------------------------------------------------------------------- scoring


def score_level(
    gt_maps: Sequence[np.ndarray],
    pred_maps: Sequence[np.ndarray],
    gt_gaussians: np.ndarray,
    pred_gaussians: np.ndarray,
    names: Optional[Dict[int, str]] = None,
    iou_threshold: float = 0.5,
    view_ok: Optional[Sequence[bool]] = None,
    confidence: Union[Sequence[float], np.ndarray, None] = None,
) -> dict:
    """2D and 3D scores of one level. Predicted ids are 0..K-1 with -1 = none (clustering's ids).

    The scorer treats ids <= 0 as "none", so predictions are shifted by one before scoring; the
    reported ``matched_prediction`` is the clustering's own id again. The 2D scores are repeated
    over the views where ``view_ok`` is true (default: all) as ``miou_valid_views``,
    ``precision_valid_views``, ``recall_valid_views``, ``f1_valid_views`` (None when those views
    show no GT instance) and ``num_valid_views``.

    What a user sees, over Gaussians (:func:`~votesplat_ns.eval.evaluation.object_scores`):
    ``mean_completeness_3d`` and ``mean_purity_3d`` (means over GT objects of the per-object
    values in ``per_instance``), ``list_precision`` (instances matched at Gaussian IoU >=
    ``iou_threshold`` / all instances), ``num_predicted`` and ``num_gt_objects``, and ``ap50_3d``
    (3D AP at ``iou_threshold``, instances ranked by ``confidence`` [K], per clustering id; None:
    :func:`~votesplat_ns.core.instances.size_confidence` of the ids, ``confidence_source`` says
    which).
    """
    shifted_maps = [np.asarray(m).astype(np.int64) + 1 for m in pred_maps]
    gt_maps = [np.asarray(m).astype(np.int64) for m in gt_maps]
    scores2d = match_instances(gt_maps, shifted_maps, iou_threshold=iou_threshold)
    gt_all = np.asarray(gt_gaussians).astype(np.int64)
    pred_ids = np.asarray(pred_gaussians).astype(np.int64)
    if gt_all.shape != pred_ids.shape:
        raise ValueError(f"gt_gaussians has shape {gt_all.shape} but pred_gaussians {pred_ids.shape}")
    scored = gt_all != NOT_SCORED  # the Gaussians of objects no training view shows stay out
    gt_scored, pred_scored = gt_all[scored], pred_ids[scored]
    scores3d = gaussian_purity(pred_scored + 1, gt_scored)
    pred_count = int(pred_ids.max()) + 1 if pred_ids.size else 0
    if confidence is None:
        counts = np.bincount(pred_ids[pred_ids >= 0], minlength=max(pred_count, 0))
        confidence_values, confidence_source = size_confidence(counts, int((pred_ids >= 0).sum())), "size"
    else:
        confidence_values, confidence_source = np.asarray(confidence, dtype=np.float64).reshape(-1), "instances"
        if confidence_values.shape[0] < pred_count:
            raise ValueError(
                f"confidence has {confidence_values.shape[0]} entries for {pred_count} predicted instances"
            )
    objects = object_scores(
        pred_scored + 1,
        gt_scored,
        {k + 1: float(confidence_values[k]) for k in range(max(pred_count, 0))},
        iou_threshold,
    )
    listed = int(np.unique(pred_ids[pred_ids >= 0]).size)
    if listed > objects.num_predicted:  # instances made only of unscored Gaussians are still listed
        objects = replace(objects, num_predicted=listed, list_precision=objects.num_matched / listed)
    names = dict(names or {})
    gt_area = {int(g): 0 for g in scores2d.gt_ids}
    for m in gt_maps:
        values, counts = np.unique(m[m > 0], return_counts=True)
        for v, c in zip(values.tolist(), counts.tolist()):
            gt_area[v] = gt_area.get(v, 0) + c
    on_gt = np.bincount(gt_all[gt_all > 0]) if (gt_all > 0).any() else np.zeros(1, dtype=np.int64)
    all_ids = sorted(set(names) | set(gt_area) | {int(g) for g in np.flatnonzero(on_gt) if g > 0})
    per_instance = []
    for gid in all_ids:
        matched = scores2d.matches.get(gid)
        per_instance.append(
            {
                "id": gid,
                "name": names.get(gid, str(gid)),
                "visible": gid in gt_area,
                "pixels": int(gt_area.get(gid, 0)),
                "iou": scores2d.per_gt_iou.get(gid) if gid in gt_area else None,
                "matched_prediction": None if matched is None else int(matched) - 1,
                "gaussians": int(on_gt[gid]) if gid < len(on_gt) else 0,
                "scored_3d": gid in scores3d.per_gt_completeness,
                "completeness_3d": scores3d.per_gt_completeness.get(gid),
                "purity_3d": scores3d.per_gt_purity.get(gid),
                "iou_3d": scores3d.per_gt_iou.get(gid),
                "matched_instance_3d": _unshift(scores3d.per_gt_match.get(gid)),
                "matched_at_threshold_3d": _unshift(objects.matches.get(gid)),
            }
        )
    two_d = scores2d.to_dict()
    two_d["matches"] = {k: (None if v is None else int(v) - 1) for k, v in scores2d.matches.items()}
    three_d = scores3d.to_dict()
    three_d["per_cluster_purity"] = {str(int(k) - 1): v for k, v in scores3d.per_cluster_purity.items()}
    three_d["cluster_majority"] = {str(int(k) - 1): v for k, v in scores3d.cluster_majority.items()}
    three_d["per_gt_match"] = {str(k): _unshift(v) for k, v in scores3d.per_gt_match.items()}
    objects_out = objects.to_dict()
    objects_out["matches"] = {str(k): _unshift(v) for k, v in objects.matches.items()}
    if view_ok is not None and len(view_ok) != len(gt_maps):
        raise ValueError(f"view_ok has {len(view_ok)} entries for {len(gt_maps)} views")
    valid = [i for i in range(len(gt_maps)) if view_ok is None or view_ok[i]]
    valid_scores = None
    if any((gt_maps[i] > 0).any() for i in valid):
        valid_scores = match_instances([gt_maps[i] for i in valid], [shifted_maps[i] for i in valid], iou_threshold)
    return {
        "miou": scores2d.miou,
        "precision": scores2d.precision,
        "recall": scores2d.recall,
        "f1": scores2d.f1,
        "purity": scores3d.purity,
        "completeness": scores3d.completeness,
        "miou_3d": scores3d.miou_3d,
        "num_predicted_instances": max(pred_count, 0),
        "mean_completeness_3d": scores3d.mean_completeness,
        "mean_purity_3d": scores3d.mean_purity,
        "list_precision": objects.list_precision,
        "num_predicted": objects.num_predicted,
        "num_gt_objects": objects.num_gt,
        "ap50_3d": objects.ap,
        "confidence_source": confidence_source,
        "miou_valid_views": None if valid_scores is None else valid_scores.miou,
        "precision_valid_views": None if valid_scores is None else valid_scores.precision,
        "recall_valid_views": None if valid_scores is None else valid_scores.recall,
        "f1_valid_views": None if valid_scores is None else valid_scores.f1,
        "num_valid_views": len(valid),
        "scores_2d": two_d,
        "scores_3d": three_d,
        "objects_3d": objects_out,
        "per_instance": per_instance,
    }


def _unshift(value: Optional[int]) -> Optional[int]:
    """A scorer id (clustering id + 1) back to the clustering's id; None stays None."""
    return None if value is None else int(value) - 1


def write_json_atomic(path: Union[str, Path], data: dict) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as handle:
        handle.write(json.dumps(data, indent=2) + "\n")
    return path
