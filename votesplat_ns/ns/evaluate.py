"""``votesplat eval --load-config outputs/.../config.yml`` loads the run (``ns/run.load_run``: nerfstudio
``eval_setup``'s steps on a safely read config), reads the run's instances exactly as the instance export does
(``ns/run_instances.py``: the same record, computed once per checkpoint and settings), renders instance-id maps
of the dataset's held-out views and scores them against the
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
  ``votesplat synth`` (see :func:`surface_labels`): its mean is mapped back from nerfstudio's
  normalised frame to the dataset's world frame with the run's ``dataparser_transforms.json``, and
  takes the label of the nearest solid if it lies inside a closed one or within
  ``surface_tolerance_px`` pixels (at the typical camera distance) of its surface. A Gaussian off every
  solid (a floater), and every Gaussian of a dataset without that geometry, takes the majority label under
  the projected mean in the training views where the mean is not hidden behind the GT depth
  (:func:`projected_majority_labels`): what the views see it as. An object that fewer than two training views show cannot
  be found from them; its Gaussians stay out of the 3D scores and ``gaussian_gt.unseen_objects``
  lists it.

* What a user sees (:func:`~votesplat_ns.eval.ground_truth.score_level`): per GT object the 3D
  completeness and purity over Gaussians and their means, list precision (instances matched at
  Gaussian IoU >= 0.5 over all instances), 3D AP@50 (instances ranked by their ``confidence``,
  else by size), and the object-removal check (:mod:`votesplat_ns.eval.removal`): each object's
  3D-matched instance is deleted and the held-out views rendered again; ``ghost_percent`` is the
  share of the object's GT pixels that its leftover Gaussians still cover (per object and the
  mean; ``ghost_matched_percent``, the mean over the objects that the 3D assignment gives an
  instance, at any IoU, leaves out those without one, which show whole). It costs (objects + 1)
  renders per held-out view and level; ``ghost_check=False`` skips it.

Output folder: ``metrics.json`` (atomic; per level the scores, ``per_view`` the PSNR and verdict of
each view) and ``comparison_<level>.png`` (GT | prediction per view, a matched prediction shown in
its GT instance's colour), plus a short table and the flagged views on stdout.
The ground truth and the scores of a level come from ``eval/ground_truth.py``; this module loads the run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.clustering import DEFAULT_MAX_POINTS, ClusteringOptions
from votesplat_ns.core.instances import render_id_maps
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.eval.evaluation import (
    DEFAULT_MAX_PSNR_DROP_DB,
    DEFAULT_MIN_GAIN_DB,
    check_reconstruction,
    flat_image_psnr,
    psnr,
    save_comparison_png,
)
from votesplat_ns.eval.ground_truth import (
    GroundTruthDataset,
    gaussian_ground_truth,
    points_to_dataset_frame,
    read_dataparser_transform,
    score_level,
    write_json_atomic,
)
from votesplat_ns.eval.removal import ghost_fractions, mean_ghost_percent
from votesplat_ns.ns.run import dataset_views, load_run, run_dataset, use_dataset
from votesplat_ns.ns.run_config import load_run_config
from votesplat_ns.ns.run_instances import InstanceSettings, run_instances

METRICS_NAME = "metrics.json"
METRICS_FORMAT = "votesplat-eval"
METRICS_VERSION = 3  # 2: per_view PSNR, reconstruction check, *_valid_views scores; 3: object scores, ghosts
DEFAULT_OUTPUT_FOLDER = "votesplat_eval"
ViewSplit = Literal["eval", "train", "all"]


# ----------------------------------------------------------------------------- rendering


def render_rgb_psnr(model, dataset, index: int) -> Tuple[float, float]:
    """(PSNR, flat-image PSNR) of the model's RGB render of ``dataset`` view ``index``.

    The render and the target are the ones nerfstudio's splatfacto eval compares: the model's
    ``get_outputs_for_camera`` and the dataset image composited over the render's background.
    """
    camera = dataset.cameras[index : index + 1]
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera)
        target = model.composite_with_background(
            model.get_gt_img(dataset.get_image_float32(index)), outputs["background"]
        )
    rendered = outputs["rgb"].detach().float().cpu().numpy()
    target = target.detach().float().cpu().numpy()
    return psnr(rendered, target), flat_image_psnr(target)


# ----------------------------------------------------------------------------- nerfstudio glue


def load_votesplat_config(config_path: Union[str, Path]):
    """The run's TrainerConfig; a clear error for a missing file, another method or no checkpoint."""
    config_path = Path(config_path)
    config = load_run_config(config_path)
    method = getattr(config, "method_name", None)
    if method is None:
        raise ValueError(f"{config_path} is not a nerfstudio config.yml (no method_name)")
    if method != "votesplat":
        raise ValueError(
            f"{config_path} is a {method!r} run; votesplat eval scores votesplat runs (train with ns-train votesplat)"
        )
    checkpoints = sorted(config_path.parent.joinpath(config.relative_model_dir).glob("step-*.ckpt"))
    if not checkpoints:
        raise ValueError(
            f"no checkpoint in {config_path.parent / config.relative_model_dir}; the run saved no model yet"
        )
    return config


def _views_of(dataset) -> List[PinholeView]:
    """The dataset's views named by image file name; pinhole cameras only."""
    distortion = dataset.cameras.distortion_params
    for index, filename in enumerate(dataset.image_filenames):
        if distortion is not None and bool(torch.any(distortion[index] != 0)):
            raise ValueError(
                f"view {Path(filename).name} has lens distortion; votesplat eval supports undistorted (pinhole) datasets"
            )
    return [dataclasses.replace(view, name=Path(view.name).name) for view in dataset_views(dataset)]


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


def _levels_to_score(
    model_levels: Sequence[str], gt_levels: Sequence[str], level: Optional[str], gt_level: Optional[str]
) -> List[Tuple[str, str]]:
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
        raise ValueError(
            f"the dataset has no {target!r} ground truth (it has {list(gt_levels)}); pass --gt-level {gt_levels[0]}"
        )
    return [(level, target)]


def select_views(
    kind: ViewSplit, eval_views: Callable[[], List[PinholeView]], train_views: Callable[[], List[PinholeView]]
) -> List[PinholeView]:
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
    gaussian_ids_override: Optional[Callable[[TrainedScene, Dict[str, np.ndarray]], Dict[str, np.ndarray]]] = None,
    mask_check: bool = True,
    mask_check_options: Optional[Dict[str, object]] = None,
    cluster_options: Optional[Dict[str, object]] = None,
    log: Optional[Callable[[str], None]] = print,
    ghost_check: bool = True,
) -> EvaluationResult:
    """Score a votesplat run (see the module doc); writes metrics.json and comparison PNGs.

    ``gaussian_ids_override(scene, gt_per_gaussian) -> {level: ids}`` replaces the clustered ids
    (0..K-1, -1 = none) before rendering; tests use it to render the GT itself. ``mask_check``
    checks the instances against the training masks as ``ns-export votesplat-instances`` does
    (``mask_check_options``: keyword arguments of ``regroup_with_masks``); ``cluster_options`` are further keyword
    arguments of ``cluster_levels`` (benchmark variants). The instances are the run's record
    (:func:`~votesplat_ns.ns.run_instances.run_instances`), computed and kept if it is missing or stale;
    ``log`` gets its one-line messages. ``ghost_check`` runs the object-removal check (module doc).
    """
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
    # a dataset that moved names --data, one that is not a dataset is said before any model is built
    use_dataset(config, Path(data) if data is not None else None, load_config, "--load-config")
    data_path = run_dataset(config)  # --data when given: use_dataset pointed the config at it
    if data_path is None:
        raise ValueError("the run's config names no dataset (pipeline.datamanager.data); pass --data")
    dataset = GroundTruthDataset.open(data_path)
    output_dir = Path(output_dir) if output_dir is not None else load_config.parent / DEFAULT_OUTPUT_FOLDER
    if output_dir.exists() and not output_dir.is_dir():
        raise ValueError(f"output_dir {output_dir} is a file; pass a folder path (it is created if missing)")
    transform, scale = read_dataparser_transform(load_config)

    pipeline, scene, step = load_run(load_config, test_mode="test", data=Path(data) if data is not None else None)
    pairs = _levels_to_score(scene.level_names, dataset.levels, level, gt_level)

    datamanager = pipeline.datamanager
    chosen = select_views(
        views, lambda: _views_of(datamanager.eval_dataset), lambda: _views_of(datamanager.train_dataset)
    )
    # nerfstudio loads the "test" split for evaluation; votesplat synth writes it equal to val_filenames
    held_out = {Path(p).name for p in dataset.meta.get("test_filenames") or dataset.meta.get("val_filenames") or []}
    if views == "eval" and held_out and {v.name for v in chosen} != held_out:
        raise ValueError(
            f"nerfstudio's eval split {sorted(v.name for v in chosen)} is not the dataset's held-out views {sorted(held_out)}; "
            "check the run's dataparser settings (eval_mode)"
        )
    sources = _view_sources(datamanager)
    rgb = [render_rgb_psnr(pipeline.model, *sources[v.name]) for v in chosen]
    check = check_reconstruction([p for p, _ in rgb], [f for _, f in rgb], max_psnr_drop_db, min_gain_db)

    instance_set = run_instances(
        scene,
        load_config.parent,
        InstanceSettings.make(
            ClusteringOptions(
                min_cluster_size=min_cluster_size, min_samples=min_samples, max_points=max_points, seed=seed
            ),
            mask_check,
            mask_check_options=mask_check_options,
            cluster_options=cluster_options,
        ),
        pipeline,
        rasterize_fn=rasterize,
        log=log,
    )
    means_world = points_to_dataset_frame(scene.means, transform, scale)
    gt_gaussians, gt_info = gaussian_ground_truth(
        dataset,
        means_world,
        sorted({gt for _, gt in pairs}),
        method=gaussian_gt,
        surface_tolerance_px=surface_tolerance_px,
    )
    predicted = {name: instance_set.level(name).ids for name, _ in pairs}
    confidence = {name: instance_set.level(name).confidence for name, _ in pairs}
    if gaussian_ids_override is not None:
        overridden = gaussian_ids_override(scene, {name: gt_gaussians[gt] for name, gt in pairs})
        predicted.update(overridden)
        confidence.update({name: None for name in overridden})  # ranked by size (score_level)

    output_dir.mkdir(parents=True, exist_ok=True)
    levels_out: Dict[str, dict] = {}
    maps: Dict[str, Tuple[List[np.ndarray], List[np.ndarray]]] = {}
    for name, gt in pairs:
        gt_maps = [dataset.labels(v.name, gt) for v in chosen]
        sizes = [(m.shape[0], m.shape[1]) for m in gt_maps]
        pred_maps = render_id_maps(scene, predicted[name], chosen, rasterize, sizes, min_weight)
        result = score_level(
            gt_maps,
            pred_maps,
            gt_gaussians[gt],
            predicted[name],
            dataset.named_ids(gt),
            iou_threshold,
            view_ok=check.ok.tolist(),
            confidence=confidence[name],
        )
        if ghost_check:
            add_ghost_check(result, scene, gt_gaussians[gt], predicted[name], chosen, gt_maps, rasterize)
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
        "num_gaussians": scene.num_gaussians,
        "min_weight": min_weight,
        "iou_threshold": iou_threshold,
        "gaussian_gt": gt_info,
        "reconstruction": check.to_dict(),
        "per_view": check.per_view(v.name for v in chosen),
        "summary": {name: {k: levels_out[name].get(k) for k in SUMMARY_KEYS} for name in levels_out},
        "levels": levels_out,
    }
    write_json_atomic(output_dir / METRICS_NAME, metrics)
    return EvaluationResult(metrics, output_dir, format_table(metrics), maps)


def add_ghost_check(result: dict, scene: TrainedScene, gt_labels, pred_ids, views, gt_maps, rasterize_fn) -> None:
    """Run the object-removal check of one level and add it to ``score_level``'s ``result``.

    Each GT object carried by some Gaussian loses the Gaussians of its 3D match
    (``scores_3d.per_gt_match``; nothing when it has none); ``per_instance`` gains
    ``ghost_percent`` and ``shown_before_percent``, the level ``ghost_percent`` (their mean over
    objects with GT pixels, None if none), ``ghost_objects`` (how many were checked) and
    ``ghost_matched_percent`` (the mean over those with a match, whose instance is removed).
    """
    keep = scene.finite()
    add_ghost_check_on(result, scene.gaussians(keep)[:4], keep, gt_labels, pred_ids, views, gt_maps, rasterize_fn)


def add_ghost_check_on(result: dict, gaussians, keep, gt_labels, pred_ids, views, gt_maps, rasterize_fn) -> None:
    """:func:`add_ghost_check` on Gaussians given as arrays: ``gaussians`` (means, quats, scales, opacities), the
    activated tensors of the Gaussians where ``keep`` [N] is true (benchmarks/replay_rules.py replays with it)."""
    means, quats, scales, opacities = gaussians
    pred_kept = np.asarray(pred_ids)[keep]
    removed = {}
    for key, match in result["scores_3d"]["per_gt_match"].items():
        removed[int(key)] = None if match is None else np.flatnonzero(pred_kept == int(match))
    ghosts = ghost_fractions(
        rasterize_fn, means, quats, scales, opacities, np.asarray(gt_labels)[keep], removed, views, gt_maps
    )
    for entry in result["per_instance"]:
        ghost = ghosts.get(entry["id"])
        entry["ghost_percent"] = _percent(None if ghost is None else ghost["ghost_fraction"])
        entry["shown_before_percent"] = _percent(None if ghost is None else ghost["shown_before"])
    result["ghost_percent"] = mean_ghost_percent(ghosts)
    result["ghost_objects"] = sum(g["ghost_fraction"] is not None for g in ghosts.values())
    # the mean over the objects that have an instance to remove: an object without one shows whole
    result["ghost_matched_percent"] = mean_ghost_percent({g: v for g, v in ghosts.items() if removed[g] is not None})


def _percent(fraction: Optional[float]) -> Optional[float]:
    return None if fraction is None else 100.0 * fraction


SUMMARY_KEYS = (
    "miou",
    "precision",
    "recall",
    "f1",
    "purity",
    "completeness",
    "num_predicted_instances",
    "miou_valid_views",
    "precision_valid_views",
    "recall_valid_views",
    "num_valid_views",
    "mean_completeness_3d",
    "mean_purity_3d",
    "list_precision",
    "num_predicted",
    "num_gt_objects",
    "ap50_3d",
    "ghost_percent",
    "ghost_matched_percent",
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
    rows += [
        "",
        "What a user sees (over Gaussians; matched = one-to-one at Gaussian IoU >= 0.5; ghost = % of an object's pixels left after removing its instance):",
        "| level | completeness/object | purity/object | list precision | #objects | #instances | AP@50 | ghost % | ghost % of objects with an instance |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, level in metrics["levels"].items():
        ghost, matched = level.get("ghost_percent"), level.get("ghost_matched_percent")
        rows.append(
            f"| {name} | {level['mean_completeness_3d']:.3f} | {_fmt(level['mean_purity_3d'])} | {level['list_precision']:.3f} | "
            f"{level['num_gt_objects']} | {level['num_predicted']} | {_fmt(level['ap50_3d'])} | {'-' if ghost is None else f'{ghost:.1f}'} | "
            f"{'-' if matched is None else f'{matched:.1f}'} |"
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
        f"  {view['name']}: PSNR {_fmt_db(view['psnr'])} dB, flat image {_fmt_db(view['flat_psnr'])} dB"
        for view in flagged
    ]
    return "\n".join(rows + [line] + details)


def _fmt_db(value: Optional[float]) -> str:
    return "-" if value is None else f"{value:.2f}"  # null: an infinite or NaN PSNR


def _fmt_rule(value: Optional[float]) -> str:
    return "off" if value is None else f"{value:g}"
