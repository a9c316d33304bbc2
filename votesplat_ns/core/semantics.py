"""Instance-level language features and selection (paper §3.4, "Semantic Construction").

VoteSplat gives every Gaussian an instance id (HDBSCAN over its 3D votes). Rendering those ids gives
per-view instance maps; this module turns (image, instance map) pairs into one CLIP feature per
instance and answers text queries (LERF relevancy) and click queries against them, then converts a
selection into per-Gaussian masks. The encoder (:class:`ClipEncoder`, :class:`EncoderProtocol`) is in
:mod:`votesplat_ns.core.clip_encoder` and importable from here too.

Pure torch/numpy (+ open_clip, imported lazily by :class:`ClipEncoder`); no nerfstudio import.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

from votesplat_ns.core.clip_encoder import (
    SMALLEST_OPEN_CLIP_MODEL as SMALLEST_OPEN_CLIP_MODEL,
    CheckpointNotFoundError as CheckpointNotFoundError,
    ClipEncoder as ClipEncoder,
    EncoderProtocol as EncoderProtocol,
    check_same_encoder as check_same_encoder,
)
from votesplat_ns.core.ply_io import atomic_write

ArrayLike = Union[np.ndarray, torch.Tensor]
# LERF's canonical negative phrases (Kerr et al. 2023, §3.4).
DEFAULT_NEGATIVES: Tuple[str, ...] = ("object", "things", "stuff", "texture")
# LERF's softmax temperature: relevancy uses softmax(10 * [pos.x, neg.x]).
LERF_SCALE = 10.0
CROP_MODES = ("masked_bbox", "bbox")
FEATURES_FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------------
# Per-instance features


class InstanceFeatures(dict):
    """``{instance_id: unit feature [D] float32}`` plus how it was made.

    ``config`` records the encoder config, crop mode and min_pixels; ``visible_pixels`` and
    ``view_count`` record, per instance, the total pixel weight and number of views that entered the mean.
    """

    def __init__(
        self,
        features: Mapping[int, torch.Tensor],
        config: Mapping[str, Any],
        visible_pixels: Mapping[int, int],
        view_count: Mapping[int, int],
    ) -> None:
        super().__init__({int(key): value for key, value in features.items()})
        self.config = dict(config)
        self.visible_pixels = {int(key): int(value) for key, value in visible_pixels.items()}
        self.view_count = {int(key): int(value) for key, value in view_count.items()}

    def matrix(self) -> Tuple[List[int], torch.Tensor]:
        """Ids in ascending order and the [n, D] stack of their features."""
        ids = sorted(self)
        if not ids:
            return ids, torch.zeros(0, 0)
        return ids, torch.stack([self[i] for i in ids])

    def save(self, path: Union[str, os.PathLike]) -> None:
        """Write an .npz (ids, features, pixel/view counts, JSON config) atomically."""
        path = Path(path)
        ids, matrix = self.matrix()
        arrays = {
            "instance_ids": np.asarray(ids, dtype=np.int64),
            "features": matrix.detach().cpu().numpy().astype(np.float32),
            "visible_pixels": np.asarray([self.visible_pixels.get(i, 0) for i in ids], dtype=np.int64),
            "view_count": np.asarray([self.view_count.get(i, 0) for i in ids], dtype=np.int64),
            "config_json": np.asarray(json.dumps(self.config, sort_keys=True)),
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as handle:
            np.savez(handle, **arrays)

    @classmethod
    def load(
        cls,
        path: Union[str, os.PathLike],
        encoder: Optional[EncoderProtocol] = None,
        crop_mode: Optional[str] = None,
        min_pixels: Optional[int] = None,
    ) -> "InstanceFeatures":
        """Read :meth:`save`'s file; with ``encoder``/``crop_mode``/``min_pixels`` given, refuse a mismatch."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(
                f"instance feature file not found: {path}; compute it with instance_features(...).save(path)"
            )
        with np.load(path, allow_pickle=False) as data:
            missing = {"instance_ids", "features", "visible_pixels", "view_count", "config_json"} - set(data.files)
            if missing:
                raise ValueError(f"{path} is not an instance feature file (missing {sorted(missing)}); recompute it")
            config = json.loads(str(data["config_json"]))
            ids = data["instance_ids"].tolist()
            matrix = torch.from_numpy(data["features"].astype(np.float32))
            pixels = data["visible_pixels"].tolist()
            views = data["view_count"].tolist()
        if config.get("format_version") != FEATURES_FORMAT_VERSION:
            raise ValueError(
                f"{path} has format_version {config.get('format_version')!r}, this code reads "
                f"{FEATURES_FORMAT_VERSION}; recompute the instance features"
            )
        if encoder is not None:
            check_same_encoder(config["encoder"], encoder, what=f"instance features in {path}")
        for key, expected in (("crop_mode", crop_mode), ("min_pixels", min_pixels)):
            if expected is not None and config.get(key) != expected:
                raise ValueError(
                    f"instance features in {path} were made with {key}={config.get(key)!r}, expected {expected!r}; "
                    "recompute them with the expected setting"
                )
        return cls(
            {i: matrix[row] for row, i in enumerate(ids)},
            config,
            dict(zip(ids, pixels)),
            dict(zip(ids, views)),
        )


def instance_crop(image: np.ndarray, instance_mask: np.ndarray, crop_mode: str = "masked_bbox") -> np.ndarray:
    """The square crop of one instance that is encoded.

    The crop is the instance's tight bounding box (inclusive of its extreme pixels). In
    ``"masked_bbox"`` mode pixels of the box not belonging to the instance are set to black (0, 0, 0),
    as LangSplat/OpenGaussian do for SAM masks, so CLIP sees the object without its neighbours;
    ``"bbox"`` keeps them as context. The box is then padded with black to a centred square so
    CLIP's centre crop does not cut the object.
    """
    if crop_mode not in CROP_MODES:
        raise ValueError(f"crop_mode must be one of {CROP_MODES}, got {crop_mode!r}")
    rows = np.flatnonzero(instance_mask.any(axis=1))
    cols = np.flatnonzero(instance_mask.any(axis=0))
    if rows.size == 0:
        raise ValueError("instance_crop got an empty instance mask; nothing to crop")
    top, bottom, left, right = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    crop = image[top:bottom, left:right].copy()
    if crop_mode == "masked_bbox":
        crop[~instance_mask[top:bottom, left:right]] = 0
    height, width = crop.shape[:2]
    side = max(height, width)
    square = np.zeros((side, side, 3), dtype=np.uint8)
    y0, x0 = (side - height) // 2, (side - width) // 2
    square[y0 : y0 + height, x0 : x0 + width] = crop
    return square


def _as_numpy(array: ArrayLike) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)


def instance_features(
    images: Sequence[ArrayLike],
    instance_maps: Sequence[ArrayLike],
    encoder: EncoderProtocol,
    min_pixels: int = 64,
    crop_mode: str = "masked_bbox",
) -> InstanceFeatures:
    """One CLIP feature per instance id from views of the scene (paper §3.4, last step).

    ``images[v]`` is [H, W, 3] uint8, ``instance_maps[v]`` is [H, W] integer (rendered instance ids,
    -1 or any negative = no instance). In every view where an instance covers at least
    ``min_pixels`` pixels, its crop (:func:`instance_crop`) is encoded. Aggregation rule over views:
    the mean of the per-view unit features weighted by the instance's visible pixel count in that
    view, renormalised to unit length, so large unoccluded views count more than glimpses. Instances
    never visible with enough pixels get no feature; an instance whose weighted mean cancels to ~0
    is dropped with a warning (its views disagree completely).
    """
    if crop_mode not in CROP_MODES:
        raise ValueError(f"crop_mode must be one of {CROP_MODES}, got {crop_mode!r}")
    if int(min_pixels) < 1:
        raise ValueError(f"min_pixels must be >= 1, got {min_pixels}")
    if len(images) != len(instance_maps):
        raise ValueError(f"got {len(images)} images but {len(instance_maps)} instance maps; pass one map per image")
    if len(images) == 0:
        raise ValueError("instance_features got no views; pass at least one image and instance map")

    weighted_sums: Dict[int, torch.Tensor] = {}
    visible_pixels: Dict[int, int] = {}
    view_count: Dict[int, int] = {}
    for view, (image, instance_map) in enumerate(zip(images, instance_maps)):
        image = _as_numpy(image)
        instance_map = _as_numpy(instance_map)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"image {view} has dtype {image.dtype} and shape {image.shape}; expected [H, W, 3] uint8")
        if instance_map.shape != image.shape[:2]:
            raise ValueError(
                f"instance map {view} has shape {instance_map.shape} but image {view} is {image.shape[:2]}; "
                "render the instance map at the image's resolution"
            )
        if not np.issubdtype(instance_map.dtype, np.integer):
            raise ValueError(f"instance map {view} has dtype {instance_map.dtype}; expected integer instance ids")
        ids, counts = np.unique(instance_map[instance_map >= 0], return_counts=True)
        kept = [(int(i), int(c)) for i, c in zip(ids, counts) if c >= min_pixels]
        if not kept:
            continue
        crops = [instance_crop(image, instance_map == i, crop_mode) for i, _ in kept]
        features = encoder.encode_images(crops).float().cpu()
        if features.shape[0] != len(crops):
            raise ValueError(f"encoder returned {features.shape[0]} features for {len(crops)} crops")
        for (i, count), feature in zip(kept, features):
            weighted_sums[i] = weighted_sums.get(i, torch.zeros_like(feature)) + count * feature
            visible_pixels[i] = visible_pixels.get(i, 0) + count
            view_count[i] = view_count.get(i, 0) + 1

    result: Dict[int, torch.Tensor] = {}
    for i, weighted_sum in weighted_sums.items():
        mean = weighted_sum / visible_pixels[i]
        if not torch.isfinite(mean).all() or mean.norm() < 1e-6:
            warnings.warn(f"instance {i}: its per-view features average to ~0 (views disagree); no feature kept")
            continue
        result[i] = F.normalize(mean, dim=0)
    config = {
        "format_version": FEATURES_FORMAT_VERSION,
        "encoder": dict(encoder.config),
        "crop_mode": crop_mode,
        "min_pixels": int(min_pixels),
        "aggregation": "pixel_count_weighted_mean",
    }
    kept_ids = set(result)
    return InstanceFeatures(
        result,
        config,
        {i: n for i, n in visible_pixels.items() if i in kept_ids},
        {i: n for i, n in view_count.items() if i in kept_ids},
    )


# --------------------------------------------------------------------------------------------------
# Text query


def lerf_relevancy(
    instance_matrix: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor, scale: float = LERF_SCALE
) -> torch.Tensor:
    """LERF relevancy of each row of ``instance_matrix`` [n, D] for one positive [D] vs negatives [m, D].

    Per negative j: p_j = softmax(scale * [pos.x, neg_j.x])[0] = sigmoid(scale * (pos.x - neg_j.x));
    relevancy = min_j p_j (the positive must beat every canonical phrase). Returns [n] in (0, 1).
    """
    if negatives.ndim != 2 or negatives.shape[0] == 0:
        raise ValueError("lerf_relevancy needs at least one negative phrase feature")
    if not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"relevancy scale must be a positive finite number, got {scale}")
    positive_similarity = instance_matrix @ positive  # [n]
    negative_similarity = instance_matrix @ negatives.T  # [n, m]
    pairs = torch.stack([positive_similarity[:, None].expand_as(negative_similarity), negative_similarity], dim=-1)
    positive_probability = torch.softmax(scale * pairs, dim=-1)[..., 0]
    return positive_probability.min(dim=-1).values


def query_text(
    text: str,
    instance_feats: Mapping[int, torch.Tensor],
    encoder: EncoderProtocol,
    negatives: Sequence[str] = DEFAULT_NEGATIVES,
    scale: Optional[float] = LERF_SCALE,
) -> List[Tuple[int, float]]:
    """Instances ranked by LERF relevancy to ``text``: [(instance_id, relevancy)], best first.

    ``scale`` is the softmax scale (LERF uses 10); ``None`` uses the encoder's own CLIP logit scale.
    Ties are ordered by ascending id so the ranking is deterministic.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"text query is empty ({text!r}); pass the words to look for, e.g. 'red apple'")
    if isinstance(negatives, str):
        raise ValueError("negatives must be a sequence of phrases, not a single string; wrap it: (phrase,)")
    negatives = [phrase for phrase in negatives]
    if not negatives or any(not isinstance(phrase, str) or not phrase.strip() for phrase in negatives):
        raise ValueError(f"negatives must be non-empty phrases, got {negatives!r}")
    if len(instance_feats) == 0:
        raise ValueError("no instance features to query; compute them with instance_features(...) first")
    stored_config = getattr(instance_feats, "config", None)
    if stored_config is not None and "encoder" in stored_config:
        check_same_encoder(stored_config["encoder"], encoder)
    if scale is None:
        if not hasattr(encoder, "logit_scale"):
            raise ValueError(
                "scale=None uses the encoder's logit_scale, which this encoder does not have; pass a number"
            )
        scale = float(getattr(encoder, "logit_scale"))  # optional, so not part of EncoderProtocol

    ids = sorted(int(i) for i in instance_feats)
    matrix = F.normalize(torch.stack([torch.as_tensor(instance_feats[i]).float().cpu() for i in ids]), dim=-1)
    phrases = encoder.encode_text([text, *negatives]).float().cpu()
    if phrases.shape[1] != matrix.shape[1]:
        raise ValueError(
            f"text features have dimension {phrases.shape[1]} but instance features {matrix.shape[1]}; "
            "use the encoder the instance features were made with"
        )
    relevancy = lerf_relevancy(matrix, phrases[0], phrases[1:], scale)
    ranked = sorted(zip(ids, relevancy.tolist()), key=lambda pair: (-pair[1], pair[0]))
    return [(i, float(r)) for i, r in ranked]


def select_instances(ranked: Sequence[Tuple[int, float]], threshold: Optional[float] = None) -> List[int]:
    """Selection rule over :func:`query_text`'s ranking: top-1, or every instance with relevancy >= threshold.

    With a threshold, the result may be empty (nothing relevant enough).
    """
    if len(ranked) == 0:
        raise ValueError("nothing to select from: the ranking is empty")
    if threshold is None:
        return [int(ranked[0][0])]
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"relevancy threshold must be in [0, 1], got {threshold}")
    return [int(i) for i, relevancy in ranked if relevancy >= threshold]


# --------------------------------------------------------------------------------------------------
# Click query and per-Gaussian masks


def click_select(instance_map: ArrayLike, x: float, y: float) -> Optional[int]:
    """The instance id under a click, or None for background (negative id).

    ``(x, y)`` are continuous pixel coordinates (project convention: pixel column c spans
    [c, c + 1) and has its centre at c + 0.5), so the click hits pixel (floor(x), floor(y)); an
    integer (column, row) pair hits that pixel.
    """
    instance_map = _as_numpy(instance_map)
    if instance_map.ndim != 2:
        raise ValueError(f"instance_map must be [H, W], got shape {instance_map.shape}")
    if not np.issubdtype(instance_map.dtype, np.integer):
        raise ValueError(f"instance_map has dtype {instance_map.dtype}; expected integer instance ids")
    height, width = instance_map.shape
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"click ({x}, {y}) is not a finite pixel position")
    if not (0 <= x < width and 0 <= y < height):
        raise ValueError(
            f"click ({x}, {y}) is outside the {width}x{height} image; x must be in [0, {width}), y in [0, {height})"
        )
    value = int(instance_map[int(math.floor(y)), int(math.floor(x))])
    return None if value < 0 else value


def _selected_ids(selected: Union[int, Iterable[int], None]) -> List[int]:
    if selected is None:
        raise ValueError("nothing selected (None); a click on the background selects no instance")
    if isinstance(selected, (int, np.integer)):
        selected = [selected]
    elif isinstance(selected, torch.Tensor):
        selected = selected.reshape(-1).tolist()
    ids = [int(i) for i in selected]
    if not ids:
        raise ValueError("the selection is empty; select at least one instance id")
    if any(i < 0 for i in ids):
        raise ValueError(f"selected ids {ids} include a negative id (background); select instance ids >= 0")
    return ids


def _membership(instance_ids_per_gaussian: ArrayLike, selected: Union[int, Iterable[int], None]) -> torch.Tensor:
    ids = torch.as_tensor(instance_ids_per_gaussian)
    if ids.ndim != 1 or ids.is_floating_point() or ids.dtype == torch.bool:
        raise ValueError(
            f"instance_ids_per_gaussian must be a 1-D integer array [N], got {ids.dtype} {tuple(ids.shape)}"
        )
    wanted = torch.as_tensor(_selected_ids(selected), dtype=ids.dtype, device=ids.device)
    present = torch.isin(wanted, ids)
    if not bool(present.all()):
        missing = wanted[~present].tolist()
        raise ValueError(
            f"selected instance ids {missing} own no Gaussian; select from the ids in instance_ids_per_gaussian"
        )
    return torch.isin(ids, wanted)


def _like_input(mask: torch.Tensor, reference: ArrayLike) -> ArrayLike:
    return mask if isinstance(reference, torch.Tensor) else mask.cpu().numpy()


def isolate(instance_ids_per_gaussian: ArrayLike, selected: Union[int, Iterable[int], None]) -> ArrayLike:
    """Bool [N]: True for Gaussians of the selected instance(s) (keep these to show only them)."""
    return _like_input(_membership(instance_ids_per_gaussian, selected), instance_ids_per_gaussian)


def remove(instance_ids_per_gaussian: ArrayLike, selected: Union[int, Iterable[int], None]) -> ArrayLike:
    """Bool [N]: True for Gaussians to keep after deleting the selected instance(s) (background stays)."""
    return _like_input(~_membership(instance_ids_per_gaussian, selected), instance_ids_per_gaussian)
