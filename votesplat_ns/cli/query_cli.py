"""``votesplat`` console script: text and click selection on a trained VoteSplat run (paper §3.4).

    votesplat query --load-config RUN/config.yml "red mug" [--clip-model ViT-B-16 --clip-checkpoint W.bin]
                    [--level instance] [--instances EXPORT_DIR] [--views 0 3 5] [--output-dir D] [--top-k 5]
    votesplat click --load-config RUN/config.yml --view 3 --x 64 --y 50 [--isolate | --remove] --output-dir D
    votesplat query-eval --load-config RUN/config.yml --labels LABEL_DIR [--output results.json]
    votesplat write-labels --scene SCENE_DIR --output-dir LABEL_DIR [--frames frame_00005.png ...]

How a query is answered. The run's 3D votes are clustered into instances with the same defaults
as ``votesplat-export`` (or an export's ``instance_ids.npz`` is reused with ``--instances``). The
instance ids of the Gaussians are rendered into id maps of training views
(:func:`~votesplat_ns.core.instances.render_instance_ids`), each instance's crops of the training images
are encoded with CLIP and averaged (:func:`~votesplat_ns.core.semantics.instance_features`), and the text
is ranked against them by LERF relevancy (:func:`~votesplat_ns.core.semantics.query_text`). The
features are cached beside the run (``<run>/votesplat_query/instance_features_<level>.npz``) with
the encoder and a fingerprint of the Gaussians, instances and views that made them; a cache made
differently is rebuilt.

Masks. The mask of a selection in a view is OpenGaussian's LERF-OVS rule, used by ``query`` and
``query-eval`` alike: render only the selected Gaussians and keep pixels whose accumulated opacity
exceeds 0.7 (:func:`~votesplat_ns.eval.lerf_ovs.silhouette_mask`). It ignores occluders, like the benchmark.

Pixel coordinates (``click --x --y``) are continuous in the training image of that view at its
stored resolution: pixel column c spans [c, c + 1), so x = 64 and x = 64.7 both hit column 64.

nerfstudio is imported only inside functions, so ``import votesplat_ns.cli.query_cli`` stays cheap.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import re
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import tyro
from typing_extensions import Annotated

from votesplat_ns.core.cameras import PinholeView, scaled_view, viewmat_from_camera_to_world
from votesplat_ns.cli.cli_errors import check_writable_folder, load_run, one_line_errors, writing_into
from votesplat_ns.core.clustering import cluster_levels
from votesplat_ns.core.instances import InstanceSet, LevelInstances, render_instance_ids, vote_level_index
from votesplat_ns.eval.lerf_ovs import (
    SILHOUETTE_THRESHOLD,
    LabelFrame,
    SceneScore,
    evaluate_scene,
    frame_from_masks,
    load_scene_labels,
    silhouette_mask,
    write_label_frame,
)
from votesplat_ns.core.ply_io import atomic_write, gaussian_vertex_table, write_gaussian_table
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

DEFAULT_CLIP_MODEL = "ViT-B-16"
# LERF and LangSplat use this open_clip tag; named in the "no checkpoint" message.
PREFERRED_PRETRAINED_TAG = "laion2b_s34b_b88k"
QUERY_FOLDER_NAME = "votesplat_query"
FEATURES_FILE_TEMPLATE = "instance_features_{level}.npz"
# Bumped when the meaning of the cache fingerprint changes, so old caches are rebuilt.
FEATURE_CACHE_VERSION = 1
# Rendered instance id maps a QueryScene keeps (repeated clicks and feature rebuilds reuse them).
ID_MAPS_KEPT = 8


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


def make_encoder(clip_model: str = DEFAULT_CLIP_MODEL, clip_checkpoint: Optional[Path] = None,
                 clip_random_init: bool = False, device: Union[str, torch.device, None] = None) -> ClipEncoder:
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


# ----------------------------------------------------------------------------- loaded run


@dataclass
class ClusteringOptions:
    """The HDBSCAN settings the query commands expose; the rest keep ``cluster_levels``' defaults (votesplat-export's)."""

    min_cluster_size: Optional[int] = None
    min_samples: Optional[int] = None
    seed: int = 0


def _sha256(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(str((array.dtype.str, array.shape)).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


class QueryScene:
    """A trained run ready for selection: its Gaussians, the instances of one level, its cameras.

    Build it with :meth:`from_config` (loads the checkpoint through nerfstudio) or directly from
    parameters and cameras (tests, other front ends). ``params`` is export's ``_Params``;
    ``train_views``/``eval_views`` are lists of ``(PinholeView, image_loader)`` where
    ``image_loader()`` returns the view's image as [H, W, 3] uint8 at the camera's resolution.
    """

    def __init__(self, params, level: LevelInstances, train_views: Sequence[Tuple[PinholeView, Any]],
                 eval_views: Sequence[Tuple[PinholeView, Any]] = (), run_dir: Optional[Path] = None,
                 device: Union[str, torch.device] = "cpu", rasterize_mode: str = "classic",
                 instances_source: str = "clustered") -> None:
        self.params = params
        self.level = level
        self.train_views = list(train_views)
        self.eval_views = list(eval_views)
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.device = torch.device(device)
        self.rasterize_mode = rasterize_mode
        self.instances_source = instances_source
        n = params.means.shape[0]
        if level.ids.shape != (n,):
            raise ValueError(f"instance ids cover {level.ids.shape[0]} Gaussians but the model has {n}")
        finite = np.isfinite(params.means).all(1) & np.isfinite(params.log_scales).all(1) & np.isfinite(params.quats).all(1)
        finite &= np.isfinite(params.opacity_logits) & np.isfinite(params.sh_dc).all(1)
        if params.sh_rest is not None:
            finite &= np.isfinite(params.sh_rest).reshape(n, -1).all(1)
        # The rasteriser refuses non-finite input; such Gaussians are invisible anyway.
        self.finite = finite
        tensor = lambda a: torch.as_tensor(np.ascontiguousarray(a[finite]), dtype=torch.float32, device=self.device)  # noqa: E731
        self.means = tensor(params.means)
        self.quats = tensor(params.quats)
        self.scales = torch.exp(tensor(params.log_scales))
        self.opacities = torch.sigmoid(tensor(params.opacity_logits))
        dc = tensor(params.sh_dc)[:, None, :]
        self.colors = torch.cat([dc, tensor(params.sh_rest)], dim=1) if params.sh_rest is not None else dc
        self.sh_degree = int(round(math.sqrt(self.colors.shape[1]))) - 1
        self.ids = torch.as_tensor(level.ids[finite], dtype=torch.long, device=self.device)
        self._table: Optional[np.ndarray] = None
        self._id_maps: "OrderedDict[tuple, np.ndarray]" = OrderedDict()

    # ------------------------------------------------------------------ loading
    @classmethod
    def from_config(cls, load_config: Path, level: Optional[str] = None, instances: Optional[Path] = None,
                    clustering: Optional[ClusteringOptions] = None) -> "QueryScene":
        """Load a run's checkpoint (nerfstudio eval_setup, errors as one line) and get the instances of ``level``."""
        from votesplat_ns.ns.export import _read_params

        load_config = Path(load_config)
        _, pipeline, _, _ = load_run(load_config)
        model = pipeline.model
        params = _read_params(model, None, None)
        device = params_device(model)
        level_instances, source = instances_of_level(params, level, instances, clustering or ClusteringOptions())
        datamanager = pipeline.datamanager
        train_views = dataset_views(datamanager, "train")
        eval_views = dataset_views(datamanager, "eval")
        rasterize_mode = getattr(getattr(model, "config", None), "rasterize_mode", "classic")
        return cls(params, level_instances, train_views, eval_views, run_dir=load_config.parent, device=device,
                   rasterize_mode=rasterize_mode, instances_source=source)

    # ------------------------------------------------------------------ cameras
    def train_camera(self, index: int, max_width: Optional[int] = None) -> PinholeView:
        if not isinstance(index, (int, np.integer)) or not 0 <= index < len(self.train_views):
            raise ValueError(
                f"view {index} is out of range: this run has {len(self.train_views)} training views "
                f"(pass --view/--views between 0 and {len(self.train_views) - 1})"
            )
        camera = self.train_views[index][0]
        return camera if max_width is None else scaled_view(camera, max_width)

    def train_image(self, index: int, camera: Optional[PinholeView] = None) -> np.ndarray:
        """The training image of view ``index`` as uint8 [H, W, 3], area-resized to ``camera``'s size."""
        full_camera = self.train_camera(index)
        image = np.asarray(self.train_views[index][1]())
        if image.shape[:2] != (full_camera.height, full_camera.width):
            raise ValueError(
                f"training image {full_camera.name} is {image.shape[1]}x{image.shape[0]} but its camera is "
                f"{full_camera.width}x{full_camera.height}; check the dataset"
            )
        if camera is not None and (camera.width, camera.height) != (full_camera.width, full_camera.height):
            resized = torch.nn.functional.interpolate(
                torch.from_numpy(image).permute(2, 0, 1)[None].float(), size=(camera.height, camera.width), mode="area"
            )[0].permute(1, 2, 0)
            image = resized.round().clamp(0, 255).to(torch.uint8).numpy()
        return image

    def camera_for_image(self, name: str) -> PinholeView:
        """The camera of the training or evaluation image whose file stem equals ``name``'s."""
        stem = Path(name).stem
        for camera, _ in self.train_views + self.eval_views:
            if Path(camera.name).stem == stem:
                return camera
        known = [Path(camera.name).name for camera, _ in self.train_views + self.eval_views]
        raise ValueError(
            f"no training or evaluation image named like {name!r} in this run (it has {len(known)} images, e.g. "
            f"{known[:3]}); the labels must belong to the run's dataset"
        )

    # ------------------------------------------------------------------ rendering
    def instance_counts(self) -> Dict[int, int]:
        return {i: int(c) for i, c in enumerate(self.level.counts)}

    def id_map(self, camera: PinholeView) -> np.ndarray:
        """Rendered instance id map [H, W] int32 (-1 = none) of ``camera`` (the last few are kept)."""
        from votesplat_ns.ns.rasterizer import rasterize

        key = (camera.width, camera.height, camera.viewmat.cpu().numpy().tobytes(), camera.K.cpu().numpy().tobytes())
        if key in self._id_maps:
            self._id_maps.move_to_end(key)
            return self._id_maps[key]
        id_map = render_instance_ids(
            rasterize, self.means, self.quats, self.scales, self.opacities, self.ids,
            camera.viewmat.to(self.device), camera.K.to(self.device), camera.width, camera.height,
            rasterize_mode=self.rasterize_mode,
        ).to(torch.int32).cpu().numpy()
        id_map.setflags(write=False)
        self._id_maps[key] = id_map
        while len(self._id_maps) > ID_MAPS_KEPT:
            self._id_maps.popitem(last=False)
        return id_map

    def instance_at(self, view: int, x: float, y: float) -> Optional[int]:
        """The instance under continuous pixel (x, y) of training view ``view`` (None: background)."""
        from votesplat_ns.core.semantics import click_select

        return click_select(self.id_map(self.train_camera(view)), float(x), float(y))

    @torch.no_grad()
    def render(self, keep: np.ndarray, camera: PinholeView) -> Tuple[np.ndarray, np.ndarray]:
        """RGB [H, W, 3] in [0, 1] (black background) and accumulated opacity [H, W] of the kept Gaussians."""
        from votesplat_ns.ns.rasterizer import rasterize

        keep = torch.as_tensor(np.asarray(keep, dtype=bool)[self.finite], device=self.device)
        if not bool(keep.any()):
            return np.zeros((camera.height, camera.width, 3), np.float32), np.zeros((camera.height, camera.width), np.float32)
        colors, alphas, _ = rasterize(
            self.means[keep], self.quats[keep], self.scales[keep], self.opacities[keep], self.colors[keep],
            camera.viewmat.to(self.device)[None].float(), camera.K.to(self.device)[None].float(),
            int(camera.width), int(camera.height), sh_degree=self.sh_degree, rasterize_mode=self.rasterize_mode,
        )
        return colors[0].clamp(0, 1).cpu().numpy(), alphas[0, ..., 0].cpu().numpy()

    def selection_mask(self, selected: Sequence[int]) -> np.ndarray:
        """[N] bool over all Gaussians of the model: members of the selected instances."""
        return np.asarray(isolate(self.level.ids, list(selected)), dtype=bool)

    def vertex_table(self) -> np.ndarray:
        if self._table is None:
            p = self.params
            self._table = gaussian_vertex_table(p.means, p.sh_dc, p.sh_rest, p.opacity_logits, p.log_scales, p.quats)
        return self._table

    def fingerprint(self) -> Dict[str, Any]:
        """What the instance features of this scene depend on, besides encoder and views."""
        p = self.params
        return {
            "gaussians_sha256": _sha256(p.means.astype(np.float32), p.opacity_logits.astype(np.float32),
                                        p.log_scales.astype(np.float32), p.quats.astype(np.float32)),
            "instance_ids_sha256": _sha256(self.level.ids.astype(np.int64)),
            "level": self.level.name,
            "num_gaussians": int(p.means.shape[0]),
        }


def params_device(model) -> torch.device:
    if hasattr(model, "gauss_params"):
        return next(iter(model.gauss_params.values())).device
    return torch.device("cpu")


def instances_of_level(params, level: Optional[str], instances_dir: Optional[Path],
                       clustering: ClusteringOptions) -> Tuple[LevelInstances, str]:
    """The instances of one vote level: read from an export folder, or clustered now (export defaults)."""
    names = params.level_names
    n = params.means.shape[0]
    if instances_dir is not None:
        instance_set = InstanceSet.load(instances_dir)
        if instance_set.num_gaussians != n:
            raise ValueError(
                f"the export in {instances_dir} has {instance_set.num_gaussians} Gaussians but this run's checkpoint "
                f"has {n}; export again from this checkpoint or drop --instances"
            )
        chosen = instance_set.level(level)
        source = f"export {instances_dir}"
    else:
        index = vote_level_index(names, level)
        # Levels are clustered independently, so clustering only the asked level gives the same ids.
        chosen = cluster_levels(
            params.means, params.vote_offsets[:, index:index + 1], params.vote_support[:, index:index + 1], (names[index],),
            min_cluster_size=clustering.min_cluster_size, min_samples=clustering.min_samples, seed=clustering.seed,
        ).levels[0]
        source = "clustered"
    if chosen.num_instances == 0:
        raise ValueError(
            f"vote level {chosen.name!r} has no instances (no foreground Gaussians, or all votes were noise); "
            "check that the run trained with the vote loss, or lower --min-cluster-size"
        )
    return chosen, source


def dataset_views(datamanager, split: Literal["train", "eval"]) -> List[Tuple[PinholeView, Any]]:
    """Cameras and lazy uint8 image loaders of a nerfstudio full-image datamanager's split.

    Images of distorted cameras are taken from nerfstudio's undistorted cache, whose loading also
    rewrites the cameras' intrinsics, so image and camera always agree.
    """
    dataset = datamanager.train_dataset if split == "train" else datamanager.eval_dataset
    if dataset is None:
        return []
    cameras = dataset.cameras
    distorted = cameras.distortion_params is not None and bool((cameras.distortion_params != 0).any())
    if distorted:
        cache = datamanager.cached_train if split == "train" else datamanager.cached_eval
        cameras = dataset.cameras

        def loader(index: int):
            return lambda: _uint8_image(cache[index]["image"])
    else:

        def loader(index: int):
            return lambda: _uint8_image(dataset.get_data(index, image_type="uint8")["image"])

    views = []
    for index in range(len(dataset)):
        camera = cameras[index]
        K = camera.get_intrinsics_matrices().reshape(3, 3).float().clone()
        view = PinholeView(viewmat_from_camera_to_world(camera.camera_to_worlds.reshape(3, 4).float()), K,
                          int(camera.width.item()), int(camera.height.item()), str(dataset.image_filenames[index]))
        views.append((view, loader(index)))
    return views


def _uint8_image(image) -> np.ndarray:
    image = image.detach().cpu() if torch.is_tensor(image) else torch.as_tensor(np.asarray(image))
    image = image[..., :3]
    if image.dtype != torch.uint8:
        image = (image.float().clamp(0, 1) * 255).round().to(torch.uint8)
    return image.numpy()


def evenly_spaced(count: int, limit: Optional[int]) -> List[int]:
    """Up to ``limit`` indices spread evenly over range(count) (all when limit is None or 0)."""
    if not limit or limit >= count:
        return list(range(count))
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, limit)})


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


def scene_instance_features(scene: QueryScene, encoder: EncoderProtocol, options: FeatureOptions = FeatureOptions(),
                            cache_path: Optional[Path] = None, log=print) -> Tuple[InstanceFeatures, bool]:
    """Per-instance CLIP features of ``scene``; read from ``cache_path`` when it was made the same way.

    Returns the features and whether they came from the cache. A missing, unreadable or differently
    made cache is (re)built and saved there.
    """
    views = evenly_spaced(len(scene.train_views), options.feature_views)
    if not views:
        raise ValueError("the run has no training views to compute instance features from")
    scene_key = dict(scene.fingerprint(), views=views, feature_width=int(options.feature_width),
                     cache_version=FEATURE_CACHE_VERSION)
    if cache_path is not None and Path(cache_path).is_file():
        reason = None
        try:
            cached = InstanceFeatures.load(cache_path, encoder=encoder, crop_mode=options.crop_mode, min_pixels=options.min_pixels)
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


def _write_json(path: Path, data: Mapping[str, Any]) -> None:
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


def run_query(scene: QueryScene, text: str, encoder: EncoderProtocol, output_dir: Optional[Path] = None,
              views: Optional[Sequence[int]] = None, top_k: int = 5, threshold: Optional[float] = None,
              negatives: Sequence[str] = DEFAULT_NEGATIVES, feature_options: FeatureOptions = FeatureOptions(),
              cache_path: Optional[Path] = None, log=print) -> Dict[str, Any]:
    """Rank the instances for ``text``, print the top ``top_k``, write masks and renders of the selection.

    Selection: the best instance, or with ``threshold`` every instance with relevancy >= threshold.
    ``views`` are training view indices (default: 4 evenly spaced). Returns what ranking.json holds.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"the text query is empty ({text!r}); pass the words to look for, e.g. votesplat query ... \"red mug\"")
    if top_k < 1:
        raise ValueError(f"--top-k must be >= 1, got {top_k}")
    views = list(evenly_spaced(len(scene.train_views), 4) if views is None else views)
    for index in views:
        scene.train_camera(index)  # range check before any work
    features, cached = scene_instance_features(scene, encoder, feature_options, cache_path, log)
    ranked = query_text(text, features, encoder, negatives=negatives)
    selected = select_instances(ranked, threshold)
    counts = scene.instance_counts()
    log(f"{'features from cache' if cached else 'features computed'}: {len(features)} of {scene.level.num_instances} "
        f"instances at level {scene.level.name!r}")
    log(f"Query {text!r}: top {min(top_k, len(ranked))} of {len(ranked)} instances")
    log(f"{'rank':>4}  {'id':>5}  {'relevancy':>9}  {'gaussians':>9}")
    for rank, (instance_id, relevancy) in enumerate(ranked[:top_k], start=1):
        mark = "  *" if instance_id in selected else ""
        log(f"{rank:>4}  {instance_id:>5}  {relevancy:>9.4f}  {counts[instance_id]:>9}{mark}")
    output_dir = Path(output_dir) if output_dir is not None else (scene.run_dir or Path(".")) / QUERY_FOLDER_NAME / _slug(text)
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
    _write_json(output_dir / "ranking.json", result)
    return result


def run_click(scene: QueryScene, view: int, x: float, y: float, output_dir: Path,
              mode: Literal["isolate", "remove"] = "isolate", log=print) -> Dict[str, Any]:
    """Select the instance under pixel (x, y) of training view ``view``; write its PLY and a render.

    ``isolate`` writes ``instance_<id>.ply`` (the instance alone), ``remove`` writes
    ``scene_without_<id>.ply`` (the scene without it); ``render_VVVV.png`` shows that PLY's
    Gaussians from the clicked view and ``click.json`` records the selection.
    """
    if mode not in ("isolate", "remove"):
        raise ValueError(f"mode must be 'isolate' or 'remove', got {mode!r}")
    camera = scene.train_camera(view)
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
    written = write_gaussian_table(output_dir / name, scene.vertex_table(), select=keep)
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
    _write_json(output_dir / "click.json", result)
    log(f"View {view}, pixel ({x}, {y}): instance {instance_id} of level {scene.level.name!r} "
        f"({result['instance_gaussians']} Gaussians); {mode}: wrote {name} ({written.size} Gaussians) and {render_name} to {output_dir}")
    return result


def evaluate_queries(scene: QueryScene, frames: Sequence[LabelFrame], encoder: EncoderProtocol,
                     threshold: Optional[float] = None, negatives: Sequence[str] = DEFAULT_NEGATIVES,
                     feature_options: FeatureOptions = FeatureOptions(), cache_path: Optional[Path] = None,
                     queries: Optional[Mapping[str, str]] = None, scene_name: str = "", log=print) -> Tuple[SceneScore, Dict[str, List[int]]]:
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


# ----------------------------------------------------------------------------- labels for synthetic scenes


def write_scene_labels(scene_dir: Path, output_dir: Path, frames: Optional[Sequence[str]] = None) -> List[Path]:
    """LERF-OVS label files for a scene with ground-truth instance masks (our synthetic scenes).

    Reads ``transforms.json``: object names from ``instances`` (``{id, name}``; objects sharing a
    name form one category) and each frame's ``instance_mask_path`` (uint16 PNG, 0 = background).
    ``frames`` are image file names (default: the scene's evaluation frames, else every frame).
    Writes ``<image stem>.json`` per frame (objects not visible in a frame are not labelled) and
    returns the paths.
    """
    from PIL import Image

    scene_dir = Path(scene_dir)
    transforms_path = scene_dir / "transforms.json" if scene_dir.is_dir() else scene_dir
    if not transforms_path.is_file():
        raise ValueError(f"{transforms_path} not found; pass a scene folder with transforms.json")
    scene_dir = transforms_path.parent
    meta = json.loads(transforms_path.read_text())
    objects = meta.get("instances")
    if not objects:
        raise ValueError(f"{transforms_path} lists no 'instances' with names; labels need the objects' names")
    names = {int(entry["id"]): str(entry["name"]) for entry in objects}
    by_name = {Path(frame["file_path"]).name: frame for frame in meta.get("frames", [])}
    if frames is None:
        frames = (meta.get("votesplat_synthetic") or {}).get("eval_frames") or [
            Path(p).name for p in meta.get("test_filenames") or meta.get("val_filenames") or []
        ] or sorted(by_name)
    written = []
    for frame_name in frames:
        frame = by_name.get(Path(frame_name).name)
        if frame is None:
            raise ValueError(f"frame {frame_name!r} is not in {transforms_path}; pass image file names such as {sorted(by_name)[:2]}")
        if "instance_mask_path" not in frame:
            raise ValueError(f"frame {frame_name!r} of {transforms_path} has no instance_mask_path; labels need ground-truth masks")
        label_image = np.asarray(Image.open(scene_dir / frame["instance_mask_path"])).astype(np.int64)
        masks: Dict[str, List[np.ndarray]] = {}
        for instance_id, name in names.items():
            mask = label_image == instance_id
            if mask.any():
                masks.setdefault(name, []).append(mask)
        if not masks:
            continue
        label = frame_from_masks(Path(frame["file_path"]).name, masks, note=f"from {frame['instance_mask_path']}")
        path = Path(output_dir) / f"{Path(frame['file_path']).stem}.json"
        write_label_frame(path, label)
        written.append(path)
    if not written:
        raise ValueError(f"no object is visible in the chosen frames of {transforms_path}; no labels written")
    return written


# ----------------------------------------------------------------------------- CLI


@dataclass
class _RunArgs:
    load_config: Path
    """Path to the run's config.yml."""
    level: Optional[str] = None
    """Vote level whose instances are selected, by name or index (default: the first level)."""
    instances: Optional[Path] = None
    """Reuse the instances of a votesplat-export folder (its instance_ids.npz) instead of clustering again."""
    min_cluster_size: Optional[int] = None
    """Clustering as votesplat-export (ignored with --instances): smallest instance, in Gaussians."""
    min_samples: Optional[int] = None
    """HDBSCAN min_samples (default as votesplat-export)."""
    seed: int = 0
    """Seed of the clustering subsample."""

    def clustering(self) -> ClusteringOptions:
        return ClusteringOptions(min_cluster_size=self.min_cluster_size, min_samples=self.min_samples, seed=self.seed)

    def load_scene(self) -> QueryScene:
        return QueryScene.from_config(self.load_config, self.level, self.instances, self.clustering())


@dataclass
class _EncoderArgs(_RunArgs):
    clip_model: str = DEFAULT_CLIP_MODEL
    """open_clip architecture of the checkpoint (e.g. ViT-B-16, as LERF)."""
    clip_checkpoint: Optional[Path] = None
    """open_clip weights file (e.g. open_clip_pytorch_model.bin); never downloaded."""
    clip_random_init: bool = False
    """For testing the wiring only: random CLIP weights, so the ranking is meaningless."""
    threshold: Optional[float] = None
    """Select every instance with relevancy >= this (default: only the best one)."""
    negatives: Tuple[str, ...] = DEFAULT_NEGATIVES
    """LERF's canonical phrases the query must beat."""
    feature_views: Optional[int] = 64
    """Training views (evenly spaced) whose crops make the instance features; 0: all."""
    feature_width: int = 512
    """Width in pixels at which feature views are rendered and cropped."""
    min_pixels: int = 64
    """Pixels an instance must cover in a view for that view to count."""
    features_cache: Optional[Path] = None
    """Feature cache folder (default: <run>/votesplat_query)."""

    def encoder(self) -> ClipEncoder:
        return make_encoder(self.clip_model, self.clip_checkpoint, self.clip_random_init)

    def feature_options(self) -> FeatureOptions:
        return FeatureOptions(feature_views=self.feature_views, feature_width=self.feature_width, min_pixels=self.min_pixels)


@dataclass
class Query(_EncoderArgs):
    """Find the instances a text describes: print the ranking, write masks and renders of the selection."""

    text: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="TEXT")] = ""
    """What to look for, e.g. "red mug"."""
    views: Optional[Tuple[int, ...]] = None
    """Training views to write a mask and render for (default: 4 evenly spaced)."""
    output_dir: Optional[Path] = None
    """Where to write (default: <run>/votesplat_query/<query>)."""
    top_k: int = 5
    """Ranked instances to print."""

    def run(self, encoder: Optional[EncoderProtocol] = None, scene: Optional[QueryScene] = None) -> Dict[str, Any]:
        if not self.text.strip():
            raise ValueError(f"the text query is empty ({self.text!r}); pass the words to look for, e.g. votesplat query --load-config C \"red mug\"")
        if self.output_dir is not None:
            check_writable_folder(self.output_dir, "--output-dir")
        encoder = encoder or self.encoder()
        check_text_length = getattr(encoder, "check_text_length", None)
        if check_text_length is not None:  # before the run is loaded
            check_text_length([self.text, *self.negatives])
        scene = scene or self.load_scene()
        cache = features_cache_path(scene, self.features_cache)
        output_dir = self.output_dir if self.output_dir is not None else scene.run_dir or Path(".")
        with writing_into(output_dir, "--output-dir"):
            return run_query(scene, self.text, encoder, self.output_dir, self.views, self.top_k, self.threshold,
                             self.negatives, self.feature_options(), cache)


@dataclass
class Click(_RunArgs):
    """Select the instance under a pixel of a training view; write it alone (or the scene without it) as a PLY."""

    view: int = tyro.MISSING
    """Training view index (0-based, in the run's training image order)."""
    x: float = tyro.MISSING
    """Pixel column, continuous (column c spans [c, c+1)), at the training image's resolution."""
    y: float = tyro.MISSING
    """Pixel row, continuous."""
    output_dir: Path = tyro.MISSING
    """Where the PLY, the render and click.json go (created)."""
    isolate: bool = False
    """Write the clicked instance alone (the default when neither flag is given)."""
    remove: bool = False
    """Write the scene without the clicked instance."""

    def run(self, scene: Optional[QueryScene] = None) -> Dict[str, Any]:
        if self.isolate and self.remove:
            raise ValueError("--isolate and --remove exclude each other; pass one of them")
        check_writable_folder(self.output_dir, "--output-dir")  # before the run is loaded
        scene = scene or self.load_scene()
        with writing_into(self.output_dir, "--output-dir"):
            return run_click(scene, self.view, self.x, self.y, self.output_dir, "remove" if self.remove else "isolate")


@dataclass
class QueryEval(_EncoderArgs):
    """LERF-OVS style 3D selection score: per labelled frame and category, select by text, IoU of the silhouette."""

    labels: Path = tyro.MISSING
    """Folder of LERF-OVS label files (frame_*.json) of this run's images."""
    output: Optional[Path] = None
    """Also write the per-query scores as JSON here."""

    def run(self, encoder: Optional[EncoderProtocol] = None, scene: Optional[QueryScene] = None) -> Dict[str, Any]:
        if self.output is not None:
            check_writable_folder(Path(self.output).parent, "--output", given=self.output)
        frames = load_scene_labels(self.labels)
        encoder = encoder or self.encoder()
        scene = scene or self.load_scene()
        cache = features_cache_path(scene, self.features_cache)
        score, selections = evaluate_queries(scene, frames, encoder, self.threshold, self.negatives,
                                             self.feature_options(), cache, scene_name=self.labels.name)
        summary = score.to_dict()
        summary["selections"] = selections
        summary["encoder"] = dict(encoder.config)
        for query in score.queries:
            print(f"{query.frame:>16}  {query.category:<24} IoU {query.iou:.3f}  selected {selections.get(query.category)}")
        print(f"{score.scene or 'scene'}: {len(score.queries)} queries, mIoU {score.miou:.4f}, mAcc@0.25 {score.accuracy(0.25):.4f}")
        if self.output is not None:
            with writing_into(Path(self.output), "--output"):
                _write_json(Path(self.output), summary)
        return summary


@dataclass
class WriteLabels:
    """Write LERF-OVS label files from a scene's ground-truth instance masks and object names."""

    scene: Path
    """Scene folder with transforms.json listing 'instances' (id, name) and per-frame instance_mask_path."""
    output_dir: Path
    """Folder for the label files (<image stem>.json)."""
    frames: Optional[Tuple[str, ...]] = None
    """Image file names to label (default: the scene's evaluation frames)."""

    def run(self) -> List[Path]:
        paths = write_scene_labels(self.scene, self.output_dir, self.frames)
        print(f"Wrote {len(paths)} label files to {self.output_dir}")
        return paths


COMMANDS = {"query": Query, "click": Click, "query-eval": QueryEval, "write-labels": WriteLabels}


def main(args: Optional[Sequence[str]] = None) -> Any:
    """Parse ``args`` (default: sys.argv) and run the subcommand; bad input exits 1 with one line on stderr."""
    subcommands = Union[tuple(Annotated[cls, tyro.conf.subcommand(name=name)] for name, cls in COMMANDS.items())]  # type: ignore[misc]
    command = tyro.cli(subcommands, args=args, prog="votesplat")
    name = next(key for key, cls in COMMANDS.items() if isinstance(command, cls))
    with one_line_errors(catch=(ValueError,), prog=f"votesplat {name}"):  # also CheckpointNotFoundError
        return command.run()


def entrypoint() -> None:
    """Console script ``votesplat``."""
    tyro.extras.set_accent_color("bright_yellow")
    main()


if __name__ == "__main__":
    entrypoint()
