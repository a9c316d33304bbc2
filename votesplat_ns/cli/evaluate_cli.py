"""``votesplat-eval`` and ``votesplat-noisy-masks``: score a VoteSplat run on a synthetic scene.

``votesplat-eval --load-config outputs/.../config.yml`` loads the run (nerfstudio ``eval_setup``),
clusters its votes exactly as the instance export does (``cluster_levels`` with the export's
defaults), renders instance-id maps of the dataset's held-out views and scores them against the
dataset's exact label images:

* 2D (per vote level with a ground truth of the same name, ``instance`` / ``part``):
  :func:`~votesplat_ns.eval.evaluation.match_instances` over all chosen views jointly (mIoU, precision
  and recall at IoU 0.5). Views are the pipeline's own cameras (nerfstudio's split, orientation and
  scale), so they are exactly the frames nerfstudio would render; the GT label image of a view is
  found through its transforms.json frame (``<level>_mask_path``) by image file name.
* Reconstruction check: each scored view is also rendered in RGB by the model itself (as
  nerfstudio's eval renders it) and its PSNR against the dataset image is recorded;
  :func:`~votesplat_ns.eval.evaluation.check_reconstruction` flags views where the reconstruction failed
  (far below the run's median PSNR, or no better than a flat image of the view's mean colour). Every
  2D score is reported over all views and again over the valid views only (``*_valid_views``),
  so a broken render shows as what it is instead of silently lowering the instance score.
* 3D: :func:`~votesplat_ns.eval.evaluation.gaussian_purity` of the per-Gaussian instance ids. The GT
  label of a Gaussian comes from the scene's exact geometry when the dataset was written by
  ``votesplat-synth`` (see :func:`surface_labels`): its mean is mapped back from nerfstudio's
  normalised frame to the dataset's world frame with the run's ``dataparser_transforms.json``, and
  takes the label of the nearest surface if that surface lies within ``surface_tolerance_px``
  pixels (at the typical camera distance). Otherwise it falls back to the majority label under the
  projected mean in the training views where the mean is not hidden behind the GT depth
  (:func:`projected_majority_labels`).

Output folder: ``metrics.json`` (atomic; per level the scores, ``per_view`` the PSNR and verdict of
each view) and ``comparison_<level>.png`` (GT | prediction per view, a matched prediction shown in
its GT instance's colour), plus a short table and the flagged views on stdout.

``votesplat-noisy-masks --data <dataset> --output <folder>`` writes the dataset's GT label images
corrupted by :class:`~votesplat_ns.eval.mask_noise.MaskNoise` in the folder mask source's layout
(``<folder>/<level>/<image_stem>.png``), to train with
``--pipeline.datamanager.mask-source folder --pipeline.datamanager.mask-folder <folder>`` and
measure how VoteSplat copes with imperfect SAM masks.

The scoring helpers at the top need only numpy/torch; nerfstudio is imported inside the glue
functions.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView, viewmat_from_camera_to_world
from votesplat_ns.cli.cli_errors import VoteSplatInputError
from votesplat_ns.core.clustering import DEFAULT_MAX_POINTS, cluster_levels
from votesplat_ns.eval.evaluation import (
    DEFAULT_MAX_PSNR_DROP_DB,
    DEFAULT_MIN_GAIN_DB,
    check_reconstruction,
    flat_image_psnr,
    gaussian_purity,
    match_instances,
    psnr,
    save_comparison_png,
)
from votesplat_ns.core.instances import render_instance_ids
from votesplat_ns.eval.mask_noise import MaskNoise
from votesplat_ns.core.mask_sources import read_label_png
from votesplat_ns.core.ply_io import atomic_write, make_temp_dir, temp_sibling

METRICS_NAME = "metrics.json"
METRICS_FORMAT = "votesplat-eval"
METRICS_VERSION = 2  # 2: per_view PSNR, reconstruction check, *_valid_views scores
NOISE_MANIFEST_NAME = "noise.json"
DEFAULT_OUTPUT_FOLDER = "votesplat_eval"
DATAPARSER_TRANSFORMS_NAME = "dataparser_transforms.json"
DEPTH_UNIT_METRES = 1e-3
GT_LEVELS = ("instance", "part")
ViewSplit = Literal["eval", "train", "all"]


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
        raise ValueError(f"{path} not found; it is written by ns-train next to config.yml (evaluate a complete run folder)")
    data = json.loads(path.read_text(encoding="utf-8"))
    return np.asarray(data["transform"], dtype=np.float64), float(data["scale"])


# ----------------------------------------------------------------------------- GT per Gaussian


def surface_labels(scene, points_world, level: str, tolerance: float) -> np.ndarray:
    """Exact GT label per point from the scene's geometry: the label of the nearest surface.

    The candidates are every object part (label: its instance id at level ``instance``, its part
    id at level ``part``) and the background pieces (label 0). A point farther than
    ``tolerance`` (world units) from every surface, e.g. a floater, gets 0.
    """
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
    finite = np.isfinite(points).all(axis=1)
    if not finite.any() or not owners:
        return labels
    distances = np.stack([scene.part_surface_distance(part, points[finite]) for _, part in owners], axis=1)
    nearest = distances.argmin(axis=1)
    ids = np.array([label for label, _ in owners], dtype=np.int64)[nearest]
    close = distances[np.arange(len(nearest)), nearest] <= tolerance
    labels[np.flatnonzero(finite)] = np.where(close, ids, 0)
    return labels


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
            raise ValueError(f"{path} not found; point at a dataset folder written by votesplat-synth")
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
                "evaluate on a synthetic dataset written by votesplat-synth"
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
        from votesplat_ns.eval.synthetic.render import scene_from_dataset

        try:
            return scene_from_dataset(self.meta)
        except Exception:  # not a votesplat-synth dataset, or another generator version
            return None


def gaussian_ground_truth(
    dataset: GroundTruthDataset,
    means_world: np.ndarray,
    levels: Sequence[str],
    method: Literal["auto", "geometry", "projection"] = "auto",
    surface_tolerance_px: float = 3.0,
) -> Tuple[Dict[str, np.ndarray], Dict[str, object]]:
    """GT label per Gaussian for each level (means in the dataset's world frame) and how it was made."""
    from votesplat_ns.eval.synthetic.render import read_views

    meta, views = read_views(dataset.root)
    train = set(dataset.train_names())
    train_views = [v for v in views if v.name in train]
    centres = [entry["centre"] for entry in meta.get("instances", []) if "centre" in entry]
    targets = np.asarray(centres) if centres else np.zeros((1, 3))
    footprint = pixel_footprint([v.c2w[:3, 3] for v in train_views], targets, float(views[0].K[0, 0]))
    scene = dataset.scene() if method in ("auto", "geometry") else None
    if method == "geometry" and scene is None:
        raise ValueError(
            f"the scene of {dataset.root} cannot be rebuilt (not written by this votesplat-synth version); "
            "use --gaussian-gt projection"
        )
    info: Dict[str, object] = {"pixel_footprint": footprint}
    labels: Dict[str, np.ndarray] = {}
    if scene is not None:
        tolerance = surface_tolerance_px * footprint
        info.update(method="geometry", surface_tolerance=tolerance, surface_tolerance_px=surface_tolerance_px)
        for level in levels:
            labels[level] = surface_labels(scene, means_world, level, tolerance)
    else:
        info.update(method="projection", depth_tolerance=footprint, num_views=len(train_views))
        for level in levels:
            labelled = [LabelledView(v.viewmat, v.K, dataset.labels(v.name, level), dataset.depth(v.name)) for v in train_views]
            labels[level] = projected_majority_labels(means_world, labelled, depth_tolerance=footprint)
    info["fraction_on_objects"] = {level: float((labels[level] > 0).mean()) if len(labels[level]) else 0.0 for level in levels}
    return labels, info


# ----------------------------------------------------------------------------- scoring


@dataclass
class GaussianScene:
    """Activated Gaussians (nerfstudio frame) with their votes, as the renderer and clustering need them."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    scales: torch.Tensor  # [N, 3], exp'd
    opacities: torch.Tensor  # [N], sigmoid'd
    vote_offsets: np.ndarray  # [N, L, 3]
    vote_support: np.ndarray  # [N, L]
    level_names: Tuple[str, ...]

    @classmethod
    def from_model(cls, model) -> "GaussianScene":
        params = getattr(model, "gauss_params", None)
        if params is None or "vote_offsets" not in params or "vote_support" not in params:
            raise ValueError("the checkpoint has no vote_offsets / vote_support: evaluate a run trained with ns-train votesplat")
        levels = getattr(getattr(model, "config", None), "vote_levels", None)
        offsets = params["vote_offsets"].detach()
        if levels is None:
            levels = tuple(f"level_{i}" for i in range(offsets.shape[1]))
        return cls(
            means=params["means"].detach().float(),
            quats=params["quats"].detach().float(),
            scales=torch.exp(params["scales"].detach().float()),
            opacities=torch.sigmoid(params["opacities"].detach().float()).reshape(-1),
            vote_offsets=offsets.float().cpu().numpy(),
            vote_support=params["vote_support"].detach().float().cpu().numpy(),
            level_names=tuple(str(level) for level in levels),
        )

    @property
    def finite(self) -> torch.Tensor:
        ok = torch.isfinite(self.means).all(1) & torch.isfinite(self.quats).all(1) & torch.isfinite(self.scales).all(1)
        return ok & torch.isfinite(self.opacities)


def render_id_maps(
    scene: GaussianScene,
    gaussian_ids,
    views: Sequence[PinholeView],
    rasterize_fn: Callable[..., tuple],
    out_sizes: Optional[Sequence[Tuple[int, int]]] = None,
    min_weight: float = 0.5,
) -> List[np.ndarray]:
    """Instance-id map per view (int64, -1 = none), rendered at ``out_sizes`` (H, W) if given.

    Rendering at another size scales the intrinsics, which is exact in the continuous pixel frame.
    """
    keep = scene.finite
    ids = torch.as_tensor(np.asarray(gaussian_ids), device=scene.means.device).long()[keep]
    maps = []
    for index, view in enumerate(views):
        height, width = out_sizes[index] if out_sizes is not None else (view.height, view.width)
        K = view.K.clone().float()
        K[0] *= width / view.width
        K[1] *= height / view.height
        id_map = render_instance_ids(
            rasterize_fn,
            scene.means[keep],
            scene.quats[keep],
            scene.scales[keep],
            scene.opacities[keep],
            ids,
            view.viewmat.float().to(scene.means.device),
            K.to(scene.means.device),
            int(width),
            int(height),
            min_weight=min_weight,
        )
        maps.append(id_map.cpu().numpy())
    return maps


def render_rgb_psnr(model, dataset, index: int) -> Tuple[float, float]:
    """(PSNR, flat-image PSNR) of the model's RGB render of ``dataset`` view ``index``.

    The render and the target are the ones nerfstudio's splatfacto eval compares: the model's
    ``get_outputs_for_camera`` and the dataset image composited over the render's background.
    """
    camera = dataset.cameras[index : index + 1]
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera)
        target = model.composite_with_background(model.get_gt_img(dataset.get_image_float32(index)), outputs["background"])
    rendered = outputs["rgb"].detach().float().cpu().numpy()
    target = target.detach().float().cpu().numpy()
    return psnr(rendered, target), flat_image_psnr(target)


def score_level(
    gt_maps: Sequence[np.ndarray],
    pred_maps: Sequence[np.ndarray],
    gt_gaussians: np.ndarray,
    pred_gaussians: np.ndarray,
    names: Optional[Dict[int, str]] = None,
    iou_threshold: float = 0.5,
    view_ok: Optional[Sequence[bool]] = None,
) -> dict:
    """2D and 3D scores of one level. Predicted ids are 0..K-1 with -1 = none (clustering's ids).

    The scorer treats ids <= 0 as "none", so predictions are shifted by one before scoring; the
    reported ``matched_prediction`` is the clustering's own id again. The 2D scores are repeated
    over the views where ``view_ok`` is true (default: all) as ``miou_valid_views``,
    ``precision_valid_views``, ``recall_valid_views``, ``f1_valid_views`` (None when those views
    show no GT instance) and ``num_valid_views``.
    """
    shifted_maps = [np.asarray(m).astype(np.int64) + 1 for m in pred_maps]
    gt_maps = [np.asarray(m).astype(np.int64) for m in gt_maps]
    scores2d = match_instances(gt_maps, shifted_maps, iou_threshold=iou_threshold)
    scores3d = gaussian_purity(np.asarray(pred_gaussians).astype(np.int64) + 1, np.asarray(gt_gaussians).astype(np.int64))
    names = dict(names or {})
    gt_area = {int(g): 0 for g in scores2d.gt_ids}
    for m in gt_maps:
        values, counts = np.unique(m[m > 0], return_counts=True)
        for v, c in zip(values.tolist(), counts.tolist()):
            gt_area[v] = gt_area.get(v, 0) + c
    on_gt = np.bincount(np.asarray(gt_gaussians).astype(np.int64))
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
                "completeness_3d": scores3d.per_gt_completeness.get(gid),
            }
        )
    pred_count = int(np.asarray(pred_gaussians).max()) + 1 if np.size(pred_gaussians) else 0
    two_d = scores2d.to_dict()
    two_d["matches"] = {k: (None if v is None else int(v) - 1) for k, v in scores2d.matches.items()}
    three_d = scores3d.to_dict()
    three_d["per_cluster_purity"] = {str(int(k) - 1): v for k, v in scores3d.per_cluster_purity.items()}
    three_d["cluster_majority"] = {str(int(k) - 1): v for k, v in scores3d.cluster_majority.items()}
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
        "miou_valid_views": None if valid_scores is None else valid_scores.miou,
        "precision_valid_views": None if valid_scores is None else valid_scores.precision,
        "recall_valid_views": None if valid_scores is None else valid_scores.recall,
        "f1_valid_views": None if valid_scores is None else valid_scores.f1,
        "num_valid_views": len(valid),
        "scores_2d": two_d,
        "scores_3d": three_d,
        "per_instance": per_instance,
    }


# ----------------------------------------------------------------------------- atomic files


def write_json_atomic(path: Union[str, Path], data: dict) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as handle:
        handle.write(json.dumps(data, indent=2) + "\n")
    return path


# ----------------------------------------------------------------------------- nerfstudio glue


def load_votesplat_config(config_path: Union[str, Path]):
    """The run's TrainerConfig; a clear error for a missing file, another method or no checkpoint."""
    import yaml

    config_path = Path(config_path)
    if not config_path.is_file():
        raise ValueError(f"{config_path} not found; pass the config.yml of a votesplat run (outputs/<name>/votesplat/<time>/config.yml)")
    try:
        config = yaml.load(config_path.read_text(encoding="utf-8"), Loader=yaml.Loader)
    except Exception as err:
        raise ValueError(f"{config_path} is not a nerfstudio config.yml ({type(err).__name__}: {err})") from None
    method = getattr(config, "method_name", None)
    if method is None:
        raise ValueError(f"{config_path} is not a nerfstudio config.yml (no method_name)")
    if method != "votesplat":
        raise ValueError(f"{config_path} is a {method!r} run; votesplat-eval scores votesplat runs (train with ns-train votesplat)")
    checkpoints = sorted(config_path.parent.joinpath(config.relative_model_dir).glob("step-*.ckpt"))
    if not checkpoints:
        raise ValueError(f"no checkpoint in {config_path.parent / config.relative_model_dir}; the run saved no model yet")
    return config


def _dataset_of(config) -> Path:
    datamanager = config.pipeline.datamanager
    data = getattr(datamanager, "data", None) or getattr(config, "data", None) or getattr(datamanager.dataparser, "data", None)
    if data is None:
        raise ValueError("the run's config names no dataset (pipeline.datamanager.data); pass --data")
    return Path(data)


def _views_of(dataset) -> List[PinholeView]:
    cameras = dataset.cameras
    views = []
    for index, filename in enumerate(dataset.image_filenames):
        camera = cameras[index : index + 1]
        distortion = camera.distortion_params
        if distortion is not None and bool(torch.any(distortion != 0)):
            raise ValueError(f"view {Path(filename).name} has lens distortion; votesplat-eval supports undistorted (pinhole) datasets")
        views.append(
            PinholeView(
                name=Path(filename).name,
                viewmat=viewmat_from_camera_to_world(camera.camera_to_worlds[0].float()),
                K=camera.get_intrinsics_matrices()[0].float(),
                width=int(camera.width.item()),
                height=int(camera.height.item()),
            )
        )
    return views


def _view_sources(datamanager) -> Dict[str, tuple]:
    """Image file name -> (nerfstudio dataset, index), held-out views first (as select_views orders them)."""
    sources: Dict[str, tuple] = {}
    for dataset in (datamanager.eval_dataset, datamanager.train_dataset):
        for index, filename in enumerate(dataset.image_filenames):
            sources.setdefault(Path(filename).name, (dataset, index))
    return sources


def _check_reconstruction_options(max_psnr_drop_db: float, min_gain_db: float) -> None:
    if np.isnan(max_psnr_drop_db) or not max_psnr_drop_db > 0:
        raise VoteSplatInputError(f"--max-psnr-drop-db must be > 0 dB (inf turns the rule off), got {max_psnr_drop_db}")
    if np.isnan(min_gain_db) or min_gain_db == float("inf"):
        raise VoteSplatInputError(f"--min-gain-db must be a number of dB (-inf turns the rule off), got {min_gain_db}")


def _levels_to_score(model_levels: Sequence[str], gt_levels: Sequence[str], level: Optional[str], gt_level: Optional[str]) -> List[Tuple[str, str]]:
    if level is None:
        if gt_level is not None:
            raise ValueError("--gt-level needs --level (the model level to compare with it)")
        pairs = [(name, name) for name in model_levels if name in gt_levels]
        if not pairs:
            raise ValueError(
                f"none of the model's vote levels {list(model_levels)} has a ground truth of the same name "
                f"(the dataset has {list(gt_levels)}); pass --level <model level> --gt-level instance"
            )
        return pairs
    if level not in model_levels:
        raise ValueError(f"unknown vote level {level!r}; this model has levels {list(model_levels)}")
    target = gt_level or level
    if target not in gt_levels:
        raise ValueError(f"the dataset has no {target!r} ground truth (it has {list(gt_levels)}); pass --gt-level {gt_levels[0]}")
    return [(level, target)]


def select_views(kind: ViewSplit, eval_views: Callable[[], List[PinholeView]], train_views: Callable[[], List[PinholeView]]) -> List[PinholeView]:
    """The views of a split: held-out ("eval"), training ("train") or both ("all", held-out first, no repeats)."""
    if kind not in ("eval", "train", "all"):
        raise ValueError(f"views must be 'eval', 'train' or 'all' (got {kind!r})")
    chosen: List[PinholeView] = list(eval_views()) if kind in ("eval", "all") else []
    if kind in ("train", "all"):
        seen = {v.name for v in chosen}
        chosen += [v for v in train_views() if v.name not in seen]
    if not chosen:
        raise ValueError(f"the run's dataset has no {kind} views to evaluate")
    return chosen


@dataclass
class EvaluationResult:
    metrics: dict
    output_dir: Path
    table: str
    # level -> (GT label maps, rendered id maps with -1 = none), one per scored view in metrics["view_names"] order
    maps: Dict[str, Tuple[List[np.ndarray], List[np.ndarray]]] = dataclasses.field(default_factory=dict)


def evaluate_run(
    load_config: Union[str, Path],
    output_dir: Optional[Union[str, Path]] = None,
    level: Optional[str] = None,
    gt_level: Optional[str] = None,
    views: ViewSplit = "eval",
    data: Optional[Union[str, Path]] = None,
    min_cluster_size: Optional[int] = None,
    min_samples: Optional[int] = None,
    max_points: int = DEFAULT_MAX_POINTS,
    seed: int = 0,
    min_weight: float = 0.5,
    gaussian_gt: Literal["auto", "geometry", "projection"] = "auto",
    surface_tolerance_px: float = 3.0,
    iou_threshold: float = 0.5,
    max_psnr_drop_db: float = DEFAULT_MAX_PSNR_DROP_DB,
    min_gain_db: float = DEFAULT_MIN_GAIN_DB,
    gaussian_ids_override: Optional[Callable[[GaussianScene, Dict[str, np.ndarray]], Dict[str, np.ndarray]]] = None,
) -> EvaluationResult:
    """Score a votesplat run (see the module doc); writes metrics.json and comparison PNGs.

    ``gaussian_ids_override(scene, gt_per_gaussian) -> {level: ids}`` replaces the clustered ids
    (0..K-1, -1 = none) before rendering; tests use it to render the GT itself.
    """
    from nerfstudio.utils.eval_utils import eval_setup

    from votesplat_ns.ns.rasterizer import rasterize

    if views not in ("eval", "train", "all"):
        raise ValueError(f"views must be 'eval', 'train' or 'all' (got {views!r})")
    if not 0.0 < min_weight <= 1.0:
        raise ValueError(f"min_weight must be in (0, 1] (got {min_weight})")
    if not surface_tolerance_px > 0:
        raise ValueError(f"surface_tolerance_px must be > 0 (got {surface_tolerance_px})")
    _check_reconstruction_options(max_psnr_drop_db, min_gain_db)
    load_config = Path(load_config)
    config = load_votesplat_config(load_config)
    data_path = Path(data) if data is not None else _dataset_of(config)
    dataset = GroundTruthDataset.open(data_path)
    output_dir = Path(output_dir) if output_dir is not None else load_config.parent / DEFAULT_OUTPUT_FOLDER
    if output_dir.exists() and not output_dir.is_dir():
        raise ValueError(f"output_dir {output_dir} is a file; pass a folder path (it is created if missing)")
    transform, scale = read_dataparser_transform(load_config)

    def update(cfg):
        if data is not None:
            cfg.data = data_path
            cfg.pipeline.datamanager.data = data_path
        return cfg

    _, pipeline, _, step = eval_setup(load_config, test_mode="test", update_config_callback=update)
    scene = GaussianScene.from_model(pipeline.model)
    pairs = _levels_to_score(scene.level_names, dataset.levels, level, gt_level)

    datamanager = pipeline.datamanager
    chosen = select_views(
        views, lambda: _views_of(datamanager.eval_dataset), lambda: _views_of(datamanager.train_dataset)
    )
    # nerfstudio loads the "test" split for evaluation; votesplat-synth writes it equal to val_filenames
    held_out = {Path(p).name for p in dataset.meta.get("test_filenames") or dataset.meta.get("val_filenames") or []}
    if views == "eval" and held_out and {v.name for v in chosen} != held_out:
        raise ValueError(
            f"nerfstudio's eval split {sorted(v.name for v in chosen)} is not the dataset's held-out views {sorted(held_out)}; "
            "check the run's dataparser settings (eval_mode)"
        )
    sources = _view_sources(datamanager)
    rgb = [render_rgb_psnr(pipeline.model, *sources[v.name]) for v in chosen]
    check = check_reconstruction([p for p, _ in rgb], [f for _, f in rgb], max_psnr_drop_db, min_gain_db)

    instance_set = cluster_levels(
        scene.means.cpu().numpy(),
        scene.vote_offsets,
        scene.vote_support,
        scene.level_names,
        min_cluster_size=min_cluster_size,
        min_samples=min_samples,
        max_points=max_points,
        seed=seed,
    )
    means_world = points_to_dataset_frame(scene.means.cpu().numpy(), transform, scale)
    gt_gaussians, gt_info = gaussian_ground_truth(
        dataset, means_world, sorted({gt for _, gt in pairs}), method=gaussian_gt, surface_tolerance_px=surface_tolerance_px
    )
    predicted = {name: instance_set.level(name).ids for name, _ in pairs}
    if gaussian_ids_override is not None:
        predicted.update(gaussian_ids_override(scene, {name: gt_gaussians[gt] for name, gt in pairs}))

    output_dir.mkdir(parents=True, exist_ok=True)
    levels_out: Dict[str, dict] = {}
    maps: Dict[str, Tuple[List[np.ndarray], List[np.ndarray]]] = {}
    for name, gt in pairs:
        gt_maps = [dataset.labels(v.name, gt) for v in chosen]
        pred_maps = render_id_maps(scene, predicted[name], chosen, rasterize, [m.shape for m in gt_maps], min_weight)
        result = score_level(
            gt_maps, pred_maps, gt_gaussians[gt], predicted[name], dataset.named_ids(gt), iou_threshold, view_ok=check.ok.tolist()
        )
        picture = output_dir / f"comparison_{name}.png"
        save_comparison_png(gt_maps, [m + 1 for m in pred_maps], picture, scale=2)
        result.update(gt_level=gt, comparison_png=picture.name, clustering=instance_set.level(name).clustering)
        levels_out[name] = result
        maps[name] = (gt_maps, pred_maps)

    metrics = {
        "format": METRICS_FORMAT,
        "version": METRICS_VERSION,
        "config": str(load_config),
        "step": int(step),
        "dataset": str(dataset.root),
        "views": views,
        "view_names": [v.name for v in chosen],
        "num_gaussians": int(scene.means.shape[0]),
        "min_weight": min_weight,
        "iou_threshold": iou_threshold,
        "gaussian_gt": gt_info,
        "reconstruction": check.to_dict(),
        "per_view": check.per_view(v.name for v in chosen),
        "summary": {name: {k: levels_out[name][k] for k in SUMMARY_KEYS} for name in levels_out},
        "levels": levels_out,
    }
    write_json_atomic(output_dir / METRICS_NAME, metrics)
    return EvaluationResult(metrics, output_dir, format_table(metrics), maps)


SUMMARY_KEYS = (
    "miou", "precision", "recall", "f1", "purity", "completeness", "num_predicted_instances",
    "miou_valid_views", "precision_valid_views", "recall_valid_views", "num_valid_views",
)


def _fmt(value: Optional[float]) -> str:
    return "-" if value is None else f"{value:.3f}"


def format_table(metrics: dict) -> str:
    """The summary: scores over all views and over the views whose reconstruction is ok, then the flagged views."""
    num_views = len(metrics["view_names"])
    rows = [
        "| level | views | mIoU | precision | recall | valid views | mIoU valid | precision valid | recall valid | purity | completeness | #GT | #pred |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, level in metrics["levels"].items():
        num_gt = level["scores_2d"]["num_gt"]
        rows.append(
            f"| {name} | {metrics['views']} ({num_views}) | {level['miou']:.3f} | {level['precision']:.3f} | {level['recall']:.3f} | "
            f"{level['num_valid_views']}/{num_views} | {_fmt(level['miou_valid_views'])} | {_fmt(level['precision_valid_views'])} | "
            f"{_fmt(level['recall_valid_views'])} | {level['purity']:.3f} | {level['completeness']:.3f} | {num_gt} | {level['num_predicted_instances']} |"
        )
    check = metrics["reconstruction"]
    median = check["median_psnr"]
    flagged = [view for view in metrics["per_view"] if not view["reconstruction_ok"]]
    line = (
        f"reconstruction check: median RGB PSNR {'-' if median is None else f'{median:.2f}'} dB; "
        f"{len(flagged)} of {num_views} views flagged "
        f"(PSNR more than {_fmt_rule(check['max_psnr_drop_db'])} dB below the median "
        f"or less than {_fmt_rule(check['min_gain_db'])} dB above a flat image of the view's mean colour)"
    )
    details = [
        f"  {view['name']}: PSNR {_fmt_db(view['psnr'])} dB, flat image {_fmt_db(view['flat_psnr'])} dB" for view in flagged
    ]
    return "\n".join(rows + [line] + details)


def _fmt_db(value: Optional[float]) -> str:
    return "-" if value is None else f"{value:.2f}"  # null: an infinite or NaN PSNR


def _fmt_rule(value: Optional[float]) -> str:
    return "off" if value is None else f"{value:g}"


@dataclass
class EvaluateVoteSplat:
    """Score a VoteSplat run's instances against a synthetic dataset's exact labels (2D mIoU,
    precision/recall at IoU 0.5 on the held-out views; 3D per-Gaussian purity). Each view's RGB PSNR
    flags views where the reconstruction itself failed; the 2D scores are also given over the valid views."""

    load_config: Path
    """Path to the run's config.yml."""
    output_dir: Optional[Path] = None
    """Folder for metrics.json and the comparison PNGs (default: <run folder>/votesplat_eval)."""
    level: Optional[str] = None
    """Model vote level to score (default: every level with a ground truth of the same name: instance, part)."""
    gt_level: Optional[str] = None
    """Ground truth to compare --level with (instance or part; default: the level's own name)."""
    views: ViewSplit = "eval"
    """Views to score: the held-out views (eval), the training views (train) or both (all)."""
    data: Optional[Path] = None
    """Dataset folder, if it moved since training (default: the one in the config)."""
    min_cluster_size: Optional[int] = None
    """Smallest instance, in Gaussians (default as the export: 0.05 percent of the foreground, at least 10)."""
    min_samples: Optional[int] = None
    """HDBSCAN min_samples (default as the export)."""
    seed: int = 0
    """Seed of the clustering subsample."""
    min_weight: float = 0.5
    """A pixel shows an instance if that instance makes up at least this share of the pixel."""
    gaussian_gt: Literal["auto", "geometry", "projection"] = "auto"
    """GT label per Gaussian: scene geometry (exact, needs votesplat-synth's generator) or the majority label in the training views."""
    surface_tolerance_px: float = 3.0
    """geometry: a Gaussian farther than this many pixels (at the median camera distance) from every surface is background."""
    max_psnr_drop_db: float = DEFAULT_MAX_PSNR_DROP_DB
    """Reconstruction check: a view whose RGB PSNR is more than this many dB below the median of the scored views
    is a failed reconstruction (6 dB = four times the squared error); inf turns this rule off."""
    min_gain_db: float = DEFAULT_MIN_GAIN_DB
    """Reconstruction check: a view whose RGB PSNR is less than this many dB above that of a flat image of the view's
    mean colour is a failed reconstruction (e.g. a wall of floaters; 2 dB: squared error above 63% of the flat
    image's); -inf turns this rule off."""

    def main(self) -> None:
        try:
            result = evaluate_run(
                self.load_config,
                self.output_dir,
                level=self.level,
                gt_level=self.gt_level,
                views=self.views,
                data=self.data,
                min_cluster_size=self.min_cluster_size,
                min_samples=self.min_samples,
                seed=self.seed,
                min_weight=self.min_weight,
                gaussian_gt=self.gaussian_gt,
                surface_tolerance_px=self.surface_tolerance_px,
                max_psnr_drop_db=self.max_psnr_drop_db,
                min_gain_db=self.min_gain_db,
            )
        except ValueError as err:
            print(f"votesplat-eval: error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        print(result.table)
        print(f"wrote {result.output_dir / METRICS_NAME}")


def entrypoint() -> None:
    """Console script ``votesplat-eval``."""
    import tyro

    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(tyro.conf.FlagConversionOff[EvaluateVoteSplat]).main()


# ----------------------------------------------------------------------------- noisy masks


def write_noisy_masks(
    data: Union[str, Path],
    output: Union[str, Path],
    noise: MaskNoise,
    levels: Sequence[str] = GT_LEVELS,
    overwrite: bool = False,
) -> Path:
    """GT label images with ``noise`` applied, as ``<output>/<level>/<image_stem>.png`` (+ noise.json).

    Every frame of the dataset is written (view index = frame order in transforms.json, so the
    noise of a view is reproducible); each level gets its own seed (``noise.seed + level index``).
    The folder is built beside ``output`` and renamed into place; an existing ``output`` is
    replaced only with ``overwrite`` and only if it holds a previous noisy-mask folder.
    """
    from votesplat_ns.eval.synthetic.render import write_png

    dataset = GroundTruthDataset.open(data)
    levels = tuple(levels)
    missing = [level for level in levels if level not in dataset.levels]
    if missing:
        raise ValueError(f"dataset {dataset.root} has no {missing} ground truth (it has {list(dataset.levels)})")
    if not levels:
        raise ValueError("pass at least one level (instance, part)")
    output = Path(output)
    if output.exists():
        if not output.is_dir():
            raise ValueError(f"{output} is a file; pass a folder path")
        if any(output.iterdir()):
            if not (output / NOISE_MANIFEST_NAME).is_file():
                raise ValueError(f"{output} is a non-empty folder that is not a noisy-mask folder; choose a new or empty folder")
            if not overwrite:
                raise ValueError(f"{output} already holds noisy masks; pass --overwrite to replace them")
    if output.resolve() == dataset.root.resolve() or dataset.root.resolve() in output.resolve().parents:
        raise ValueError(f"{output} lies inside the dataset {dataset.root}; write the noisy masks outside it")
    output.parent.mkdir(parents=True, exist_ok=True)
    staging = make_temp_dir(output, ".partial")
    try:
        changed = {level: 0 for level in levels}
        for level_index, level in enumerate(levels):
            level_noise = dataclasses.replace(noise, seed=int(noise.seed) + level_index)
            for view_index, name in enumerate(dataset.frames):
                clean = dataset.labels(name, level)
                noisy = level_noise.apply(clean.astype(np.int64), view_index=view_index)
                if noisy.max(initial=0) > np.iinfo(np.uint16).max:
                    raise ValueError(f"view {name} has more than 65535 masks after noise")
                changed[level] += int(not np.array_equal(noisy, clean))
                write_png(staging / level / f"{Path(name).stem}.png", noisy.astype(np.uint16))
        manifest = {
            "format": "votesplat-noisy-masks",
            "dataset": str(dataset.root),
            "levels": list(levels),
            "noise": dataclasses.asdict(noise),
            "level_seeds": {level: int(noise.seed) + i for i, level in enumerate(levels)},
            "num_views": len(dataset.frames),
            "views_changed": changed,
        }
        write_json_atomic(staging / NOISE_MANIFEST_NAME, manifest)
        if output.exists():
            old = temp_sibling(output, ".old")
            output.rename(old)
            staging.rename(output)
            shutil.rmtree(old, ignore_errors=True)
        else:
            staging.rename(output)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return output


@dataclass
class WriteNoisyMasks:
    """Write a synthetic dataset's GT masks with seeded SAM-like errors (split, merge, boundary jitter,
    drop) as a folder mask source: train with --pipeline.datamanager.mask-source folder
    --pipeline.datamanager.mask-folder <output>."""

    data: Path
    """Dataset folder with GT masks (written by votesplat-synth)."""
    output: Path
    """Folder to write (<output>/<level>/<image_stem>.png)."""
    split_rate: float = 0.15
    """Probability that a mask is cut in two (over-segmentation)."""
    merge_rate: float = 0.1
    """Probability that a mask absorbs a neighbouring mask (under-segmentation)."""
    jitter_rate: float = 0.5
    """Probability that a mask's boundary grows or shrinks by 1..max-jitter-px pixels."""
    drop_rate: float = 0.05
    """Probability that a mask is missing."""
    max_jitter_px: int = 2
    merge_max_gap_px: int = 2
    seed: int = 0
    levels: Tuple[str, ...] = GT_LEVELS
    """Levels to write (each needs <level>_mask_path in transforms.json)."""
    overwrite: bool = False
    """Replace a previous noisy-mask folder at --output."""

    def noise(self) -> MaskNoise:
        return MaskNoise(
            split_rate=self.split_rate,
            merge_rate=self.merge_rate,
            jitter_rate=self.jitter_rate,
            drop_rate=self.drop_rate,
            max_jitter_px=self.max_jitter_px,
            merge_max_gap_px=self.merge_max_gap_px,
            seed=self.seed,
        )

    def main(self) -> None:
        try:
            out = write_noisy_masks(self.data, self.output, self.noise(), self.levels, self.overwrite)
        except ValueError as err:
            print(f"votesplat-noisy-masks: error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        manifest = json.loads((out / NOISE_MANIFEST_NAME).read_text(encoding="utf-8"))
        print(
            f"wrote noisy masks for {manifest['num_views']} views, levels {manifest['levels']} to {out}; train with "
            f"--pipeline.datamanager.mask-source folder --pipeline.datamanager.mask-folder {out}"
        )


def noisy_masks_entrypoint() -> None:
    """Console script ``votesplat-noisy-masks``."""
    import tyro

    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(tyro.conf.FlagConversionOff[WriteNoisyMasks]).main()


if __name__ == "__main__":
    entrypoint()
