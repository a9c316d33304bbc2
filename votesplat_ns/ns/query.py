"""Text query, click and the LERF-OVS protocol on a :class:`~votesplat_ns.ns.selection.QueryScene` (paper §3.4).

How a query is answered. The instance ids of the Gaussians are rendered into id maps of training
views, each instance's crops of the training images are encoded with CLIP and averaged
(:func:`~votesplat_ns.core.semantics.instance_features`), and the text is ranked against them by
LERF relevancy (:func:`~votesplat_ns.core.semantics.query_text`). The features are cached beside
the run (``<run>/votesplat_query/instance_features_<level>.npz``) with the encoder and a
fingerprint of the Gaussians, instances and views that made them; a cache made differently is rebuilt.

Masks. The mask of a selection in a view is OpenGaussian's LERF-OVS rule, used by ``query`` and
``query-eval`` alike: render only the selected Gaussians and keep pixels whose accumulated opacity
exceeds 0.7 (:func:`~votesplat_ns.eval.lerf_ovs.silhouette_mask`). It ignores occluders, like the benchmark.

Pixel coordinates (``click --x --y``) are continuous in the training image of that view at its
stored resolution: pixel column c spans [c, c + 1), so x = 64 and x = 64.7 both hit column 64.
"""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.cameras import scaled_view
from votesplat_ns.core.ply_io import atomic_write, write_gaussian_table
from votesplat_ns.core.semantics import (
    DEFAULT_NEGATIVES,
    ClipEncoder,
    EncoderProtocol,
    InstanceFeatures,
    instance_features,
    isolate,
    query_text,
    remove,
    select_instances,
)
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.eval.lerf_ovs import SILHOUETTE_THRESHOLD, LabelFrame, SceneScore, evaluate_scene, silhouette_mask
from votesplat_ns.ns.selection import QueryScene, evenly_spaced

DEFAULT_CLIP_MODEL = "ViT-B-16"
# LERF and LangSplat use this open_clip tag; named in the "no checkpoint" message.
PREFERRED_PRETRAINED_TAG = "laion2b_s34b_b88k"
QUERY_FOLDER_NAME = "votesplat_query"
FEATURES_FILE_TEMPLATE = "instance_features_{level}.npz"
# Bumped when the meaning of the cache fingerprint changes, so old caches are rebuilt.
FEATURE_CACHE_VERSION = 1


# ----------------------------------------------------------------------------- encoder


def expected_checkpoint_file(model_name: str) -> str:
    """Where open_clip's pretrained weights for ``model_name`` come from, for error messages."""
    try:
        import open_clip

        tags = list(open_clip.list_pretrained_tags_by_model(model_name))
    except Exception:  # an unknown name is reported by ClipEncoder itself
        tags = []
    if not tags:
        return f"the open_clip weights file for {model_name!r}"
    tag = PREFERRED_PRETRAINED_TAG if PREFERRED_PRETRAINED_TAG in tags else tags[0]
    config = open_clip.get_pretrained_cfg(model_name, tag)
    if config.get("hf_hub"):
        return f"open_clip_pytorch_model.bin of hf-hub {config['hf_hub'].rstrip('/')} (open_clip {model_name!r}, tag {tag!r})"
    if config.get("url"):
        return f"{config['url'].rsplit('/', 1)[-1]} from {config['url']} (open_clip {model_name!r}, tag {tag!r})"
    return f"the open_clip weights file for {model_name!r} (tag {tag!r})"


def make_encoder(
    clip_model: str = DEFAULT_CLIP_MODEL,
    clip_checkpoint: Optional[Path] = None,
    clip_random_init: bool = False,
    device: Union[str, torch.device, None] = None,
) -> ClipEncoder:
    """The CLIP encoder the CLI options describe; never downloads anything."""
    device = device if device is not None else ("cuda" if torch.cuda.is_available() else "cpu")
    if clip_random_init:
        if clip_checkpoint is not None:
            raise ValueError("--clip-random-init and --clip-checkpoint exclude each other; pass one of them")
        return ClipEncoder.random_init(clip_model, device=device)
    if clip_checkpoint is None:
        raise ValueError(
            f"no CLIP checkpoint given: pass --clip-checkpoint /path/to/the weights, expected "
            f"{expected_checkpoint_file(clip_model)}; nothing is downloaded "
            "(--clip-random-init runs with random weights, for testing the wiring only)"
        )
    return ClipEncoder.from_checkpoint(clip_model, clip_checkpoint, device=device)


# ----------------------------------------------------------------------------- instance features


@dataclass
class FeatureOptions:
    """How instance features are made from training views."""

    feature_views: Optional[int] = 64
    """Training views (evenly spaced) whose crops are encoded; 0 or None: all."""
    feature_width: int = 512
    """Views are rendered and cropped at most this wide (pixels)."""
    min_pixels: int = 64
    """An instance enters a view's features only if its id map covers this many pixels there."""
    crop_mode: Literal["masked_bbox", "bbox"] = "masked_bbox"
    """masked_bbox: pixels of the box outside the instance are blacked out; bbox: kept as context."""


def features_cache_path(scene: QueryScene, cache_dir: Optional[Path] = None) -> Path:
    folder = Path(cache_dir) if cache_dir is not None else (scene.run_dir or Path(".")) / QUERY_FOLDER_NAME
    level = re.sub(r"[^A-Za-z0-9_.-]+", "_", scene.level.name)
    return folder / FEATURES_FILE_TEMPLATE.format(level=level)


def scene_instance_features(
    scene: QueryScene,
    encoder: EncoderProtocol,
    options: FeatureOptions = FeatureOptions(),
    cache_path: Optional[Path] = None,
    log=print,
) -> Tuple[InstanceFeatures, bool]:
    """Per-instance CLIP features of ``scene``; read from ``cache_path`` when it was made the same way.

    Returns the features and whether they came from the cache. A missing, unreadable or differently
    made cache is (re)built and saved there.
    """
    views = evenly_spaced(len(scene.train_views), options.feature_views)
    if not views:
        raise ValueError("the run has no training views to compute instance features from")
    scene_key = dict(
        scene.fingerprint(), views=views, feature_width=int(options.feature_width), cache_version=FEATURE_CACHE_VERSION
    )
    if cache_path is not None and Path(cache_path).is_file():
        reason = None
        try:
            cached = InstanceFeatures.load(
                cache_path, encoder=encoder, crop_mode=options.crop_mode, min_pixels=options.min_pixels
            )
            if cached.config.get("scene") != json.loads(json.dumps(scene_key)):
                reason = "the Gaussians, instances or views changed"
        except ValueError as error:
            reason = str(error)
        if reason is None:
            return cached, True
        log(f"Rebuilding instance features ({reason})")
    images, maps = [], []
    for index in views:
        camera = scene.train_camera(index, max_width=options.feature_width)
        images.append(scene.train_image(index, camera))
        maps.append(scene.id_map(camera))
    features = instance_features(images, maps, encoder, min_pixels=options.min_pixels, crop_mode=options.crop_mode)
    if len(features) == 0:
        raise ValueError(
            f"no instance covers {options.min_pixels} pixels in any of the {len(views)} training views; "
            "lower --min-pixels or raise --feature-width"
        )
    features.config["scene"] = scene_key
    if cache_path is not None:
        features.save(cache_path)
    return features, False


# ----------------------------------------------------------------------------- files


def _write_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue())


def write_json(path: Path, data: Mapping[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as handle:
        handle.write((json.dumps(data, indent=2) + "\n").encode("utf-8"))


def _rgba(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    stacked = np.concatenate([rgb, alpha[..., None]], axis=-1)
    return (np.clip(stacked, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def write_selection_views(scene: QueryScene, keep: np.ndarray, views: Sequence[int], output_dir: Path) -> List[str]:
    """For each training view: ``mask_VVVV.png`` (acc > 0.7 of the kept Gaussians) and ``render_VVVV.png`` (RGBA)."""
    written = []
    for index in views:
        camera = scene.train_camera(index)
        rgb, alpha = scene.render(keep, camera)
        mask = silhouette_mask(alpha, SILHOUETTE_THRESHOLD)
        _write_png(output_dir / f"mask_{index:04d}.png", mask.astype(np.uint8) * 255)
        _write_png(output_dir / f"render_{index:04d}.png", _rgba(rgb, alpha))
        written += [f"mask_{index:04d}.png", f"render_{index:04d}.png"]
    return written


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text.strip()).strip("_").lower()[:60] or "query"


# ----------------------------------------------------------------------------- query / click / eval


def run_query(
    scene: QueryScene,
    text: str,
    encoder: EncoderProtocol,
    output_dir: Optional[Path] = None,
    views: Optional[Sequence[int]] = None,
    top_k: int = 5,
    threshold: Optional[float] = None,
    negatives: Sequence[str] = DEFAULT_NEGATIVES,
    feature_options: FeatureOptions = FeatureOptions(),
    cache_path: Optional[Path] = None,
    log=print,
) -> Dict[str, Any]:
    """Rank the instances for ``text``, print the top ``top_k``, write masks and renders of the selection.

    Selection: the best instance, or with ``threshold`` every instance with relevancy >= threshold.
    ``views`` are training view indices (default: 4 evenly spaced). Returns what ranking.json holds.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(
            f'the text query is empty ({text!r}); pass the words to look for, e.g. votesplat query ... "red mug"'
        )
    if top_k < 1:
        raise ValueError(f"--top-k must be >= 1, got {top_k}")
    views = list(evenly_spaced(len(scene.train_views), 4) if views is None else views)
    for index in views:
        scene.train_camera(index)  # range check before any work
    features, cached = scene_instance_features(scene, encoder, feature_options, cache_path, log)
    ranked = query_text(text, features, encoder, negatives=negatives)
    selected = select_instances(ranked, threshold)
    counts = scene.instance_counts()
    log(
        f"{'features from cache' if cached else 'features computed'}: {len(features)} of {scene.level.num_instances} "
        f"instances at level {scene.level.name!r}"
    )
    log(f"Query {text!r}: top {min(top_k, len(ranked))} of {len(ranked)} instances")
    log(f"{'rank':>4}  {'id':>5}  {'relevancy':>9}  {'gaussians':>9}")
    for rank, (instance_id, relevancy) in enumerate(ranked[:top_k], start=1):
        mark = "  *" if instance_id in selected else ""
        log(f"{rank:>4}  {instance_id:>5}  {relevancy:>9.4f}  {counts[instance_id]:>9}{mark}")
    output_dir = (
        Path(output_dir) if output_dir is not None else (scene.run_dir or Path(".")) / QUERY_FOLDER_NAME / _slug(text)
    )
    if output_dir.exists() and not output_dir.is_dir():
        raise ValueError(f"output_dir {output_dir} is a file; pass a folder path")
    files: List[str] = []
    if selected:
        files = write_selection_views(scene, scene.selection_mask(selected), views, output_dir)
        log(f"Selected instance(s) {selected}; wrote {len(views)} mask(s) and render(s) to {output_dir}")
    else:
        log(f"No instance reaches relevancy {threshold}; nothing selected")
    result = {
        "query": text,
        "level": scene.level.name,
        "instances": scene.instances_source,
        "encoder": dict(encoder.config),
        "negatives": list(negatives),
        "threshold": threshold,
        "ranking": [{"id": i, "relevancy": r, "gaussians": counts[i]} for i, r in ranked],
        "selected": selected,
        "views": views,
        "mask_rule": f"accumulated opacity of the selected Gaussians alone > {SILHOUETTE_THRESHOLD}",
        "files": files,
        "features_from_cache": cached,
    }
    write_json(output_dir / "ranking.json", result)
    return result


def run_click(
    scene: QueryScene,
    view: int,
    x: float,
    y: float,
    output_dir: Path,
    mode: Literal["isolate", "remove"] = "isolate",
    log=print,
) -> Dict[str, Any]:
    """Select the instance under pixel (x, y) of training view ``view``; write its PLY and a render.

    ``isolate`` writes ``instance_<id>.ply`` (the instance alone), ``remove`` writes
    ``scene_without_<id>.ply`` (the scene without it); ``render_VVVV.png`` shows that PLY's
    Gaussians from the clicked view and ``click.json`` records the selection.
    """
    if mode not in ("isolate", "remove"):
        raise ValueError(f"mode must be 'isolate' or 'remove', got {mode!r}")
    camera = scene.train_camera(view)
    if not (0 <= x < camera.width and 0 <= y < camera.height):  # NaN fails too
        raise VoteSplatInputError(
            f"--x {x} --y {y} is outside training view {view}, which is {camera.width}x{camera.height} pixels; "
            f"give --x in [0, {camera.width}) and --y in [0, {camera.height})"
        )
    output_dir = Path(output_dir)
    if output_dir.exists() and not output_dir.is_dir():
        raise ValueError(f"output_dir {output_dir} is a file; pass a folder path")
    instance_id = scene.instance_at(view, x, y)
    if instance_id is None:
        raise ValueError(
            f"no instance under pixel ({x}, {y}) of view {view} (background, or no instance makes up most of that pixel); "
            "click on an object"
        )
    keep = np.asarray((isolate if mode == "isolate" else remove)(scene.level.ids, instance_id), dtype=bool)
    name = f"instance_{instance_id}.ply" if mode == "isolate" else f"scene_without_{instance_id}.ply"
    output_dir.mkdir(parents=True, exist_ok=True)
    written = write_gaussian_table(output_dir / name, scene.vertex_rows(), select=keep)
    rgb, alpha = scene.render(keep, camera)
    render_name = f"render_{view:04d}.png"
    _write_png(output_dir / render_name, _rgba(rgb, alpha))
    result = {
        "view": int(view),
        "image": camera.name,
        "x": float(x),
        "y": float(y),
        "level": scene.level.name,
        "instance_id": int(instance_id),
        "instance_gaussians": int(scene.level.counts[instance_id]),
        "mode": mode,
        "ply": name,
        "ply_count": int(written.size),
        "render": render_name,
    }
    write_json(output_dir / "click.json", result)
    log(
        f"View {view}, pixel ({x}, {y}): instance {instance_id} of level {scene.level.name!r} "
        f"({result['instance_gaussians']} Gaussians); {mode}: wrote {name} ({written.size} Gaussians) and {render_name} to {output_dir}"
    )
    return result


def evaluate_queries(
    scene: QueryScene,
    frames: Sequence[LabelFrame],
    encoder: EncoderProtocol,
    threshold: Optional[float] = None,
    negatives: Sequence[str] = DEFAULT_NEGATIVES,
    feature_options: FeatureOptions = FeatureOptions(),
    cache_path: Optional[Path] = None,
    queries: Optional[Mapping[str, str]] = None,
    scene_name: str = "",
    log=print,
) -> Tuple[SceneScore, Dict[str, List[int]]]:
    """LERF-OVS protocol on labelled frames of this run's images (OpenGaussian's rule, see lerf_ovs).

    Per frame and category: select instances by text, render only them at the label's resolution,
    accumulated opacity > 0.7 is the predicted mask, IoU against the merged polygons. Returns the
    scores and, per query text, the selected instance ids.
    """
    for frame in frames:  # fail on an unknown image before any work
        scene.camera_for_image(frame.name)
    features, _ = scene_instance_features(scene, encoder, feature_options, cache_path, log)
    selections: Dict[str, List[int]] = {}

    def predict(frame: LabelFrame, text: str):
        if text not in selections:
            selections[text] = select_instances(query_text(text, features, encoder, negatives=negatives), threshold)
        if not selections[text]:
            return None
        camera = scaled_view(scene.camera_for_image(frame.name), width=frame.width, height=frame.height)
        _, alpha = scene.render(scene.selection_mask(selections[text]), camera)
        return silhouette_mask(alpha, SILHOUETTE_THRESHOLD)

    score = evaluate_scene(frames, predict, queries=queries, scene=scene_name)
    return score, selections
