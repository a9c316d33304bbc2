"""Masks from Segment Anything's automatic mask generator, one label image per granularity level.

The checkpoint is never downloaded: :func:`check_sam_checkpoint` names the official file to fetch.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from votesplat_ns.core.image_files import PathLike
from votesplat_ns.core.mask_source_base import MaskSource, validate_levels
from votesplat_ns.core.vote_maps import labels_from_binary_masks
from votesplat_ns.errors import VoteSplatInputError, load_failure_reason

SAM_CHECKPOINT_FILES = {
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_b": "sam_vit_b_01ec64.pth",
}
"""File names of the official SAM checkpoints, as listed in the README of facebookresearch/segment-anything."""


SAM_LEVELS = ("default", "s", "m", "l")


class _OneGranularityPredictor:
    """A SamPredictor whose ``predict_torch`` keeps one of SAM's three multimask outputs.

    SAM answers a point prompt with three masks; ordered by output index they are, empirically,
    subpart, part and whole. Running segment_anything's unmodified automatic mask generator
    once per output index gives masks of one granularity per run, with its NMS acting within
    that granularity only. Image embeddings are computed once per (crop) image and reused
    across the runs, so the encoder cost is paid once.
    ``output_index = None`` keeps all three (the standard generator).
    """

    _STATE = ("features", "original_size", "input_size", "is_image_set")

    def __init__(self, predictor: Any):
        self._predictor = predictor
        self.output_index: Optional[int] = None
        self._embeddings: Dict[str, Dict[str, Any]] = {}

    def set_image(self, image: np.ndarray, image_format: str = "RGB") -> None:
        key = f"{image.shape}:{image_format}:{hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()}"
        saved = self._embeddings.get(key)
        if saved is None:
            self._predictor.set_image(image, image_format)
            self._embeddings[key] = {name: getattr(self._predictor, name) for name in self._STATE}
        else:
            for name, value in saved.items():
                setattr(self._predictor, name, value)

    def clear_embeddings(self) -> None:
        self._embeddings.clear()
        self._predictor.reset_image()

    def predict_torch(
        self, point_coords, point_labels, boxes=None, mask_input=None, multimask_output=True, return_logits=False
    ):
        masks, iou_predictions, low_res = self._predictor.predict_torch(
            point_coords,
            point_labels,
            boxes,
            mask_input,
            multimask_output=multimask_output,
            return_logits=return_logits,
        )
        if self.output_index is None or not multimask_output:
            return masks, iou_predictions, low_res
        i = self.output_index
        return masks[:, i : i + 1], iou_predictions[:, i : i + 1], low_res[:, i : i + 1]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._predictor, name)


class SamMaskSource(MaskSource):
    """Segment Anything's automatic mask generator, LangSplat-style hierarchical levels.

    Levels (any subset, in any order, of ``("default", "s", "m", "l")``):
      - ``"s"``, ``"m"``, ``"l"``: masks from SAM's multimask output 0, 1, 2 (subpart, part,
        whole), one generator run per output so that NMS only compares masks of one
        granularity (LangSplat's modified generator likewise keeps the three apart);
      - ``"default"``: the standard generator run over all three outputs together.
    Each level's masks are merged with :func:`labels_from_binary_masks` (smaller mask wins).
    LangSplat additionally removes redundant masks by score/inner-overlap; that step is not done.

    The generator defaults are LangSplat's (points_per_side=32, pred_iou_thresh=0.7,
    box_nms_thresh=0.7, stability_score_thresh=0.85, crop_n_layers=1, min_mask_region_area=100).
    Images whose long side exceeds ``max_long_side`` are downscaled before SAM (masks come back
    at that size; the vote maps are resized to the training resolution later).

    The checkpoint is never downloaded. Tests may pass ``sam_model`` (an already-built ``Sam``).
    """

    def __init__(
        self,
        checkpoint: Optional[PathLike] = None,
        model_type: str = "vit_h",
        device: Optional[str] = None,
        levels: Sequence[str] = SAM_LEVELS,
        points_per_side: int = 32,
        points_per_batch: int = 64,
        pred_iou_thresh: float = 0.7,
        stability_score_thresh: float = 0.85,
        box_nms_thresh: float = 0.7,
        crop_n_layers: int = 1,
        crop_n_points_downscale_factor: int = 1,
        min_mask_region_area: int = 100,
        max_long_side: Optional[int] = 1080,
        sam_model: Any = None,
    ):
        if model_type not in SAM_CHECKPOINT_FILES:
            raise VoteSplatInputError(
                f"unknown SAM model type '{model_type}'; use one of {sorted(SAM_CHECKPOINT_FILES)}"
            )
        self.levels = validate_levels(levels, "SAM mask source")
        unknown = [level for level in self.levels if level not in SAM_LEVELS]
        if unknown:
            raise VoteSplatInputError(f"unknown SAM mask levels {unknown}; use a subset of {list(SAM_LEVELS)}")
        if max_long_side is not None and max_long_side < 16:
            raise VoteSplatInputError(f"max_long_side={max_long_side} is too small; use >= 16 or None")
        self.model_type = model_type
        self.device = device
        self.max_long_side = max_long_side
        self.generator_kwargs = dict(
            points_per_side=int(points_per_side),
            points_per_batch=int(points_per_batch),
            pred_iou_thresh=float(pred_iou_thresh),
            stability_score_thresh=float(stability_score_thresh),
            box_nms_thresh=float(box_nms_thresh),
            crop_n_layers=int(crop_n_layers),
            crop_n_points_downscale_factor=int(crop_n_points_downscale_factor),
            min_mask_region_area=int(min_mask_region_area),
        )
        self._sam_model = sam_model
        self._generator = None
        if sam_model is not None:
            self.checkpoint = None
            self._model_identity = {"model": "in-memory", "parameters_sha256": _state_dict_digest(sam_model)}
        else:
            self.checkpoint = check_sam_checkpoint(checkpoint, model_type)
            self._model_identity = {
                "model": model_type,
                "checkpoint_name": self.checkpoint.name,
                "checkpoint_bytes": self.checkpoint.stat().st_size,
                "checkpoint_sample_sha256": _sampled_digest(self.checkpoint),
            }

    def config_key(self) -> Dict[str, Any]:
        return {
            "type": "sam",
            "levels": list(self.levels),
            "max_long_side": self.max_long_side,
            **self._model_identity,
            **self.generator_kwargs,
        }

    def _resolve_device(self) -> str:
        if self.device:
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"

    def _build_generator(self):
        import torch
        from segment_anything import SamAutomaticMaskGenerator, sam_model_registry

        if self._sam_model is None:
            assert self.checkpoint is not None  # __init__ checks one whenever no sam_model is given
            try:
                # loaded before the model is built, so a wrong file fails fast
                state_dict = torch.load(self.checkpoint, map_location="cpu", weights_only=True)
                model = sam_model_registry[self.model_type](checkpoint=None)
                model.load_state_dict(state_dict)
            except Exception as error:
                raise VoteSplatInputError(
                    f"could not load SAM checkpoint {self.checkpoint} as model type '{self.model_type}' ({load_failure_reason(error, self.checkpoint)}); "
                    f"expected the official {SAM_CHECKPOINT_FILES[self.model_type]} from the segment-anything "
                    "repository's README (facebookresearch/segment-anything)"
                ) from error
            self._sam_model = model
        self._sam_model.to(self._resolve_device()).eval()
        generator = _empty_safe_generator_class(SamAutomaticMaskGenerator)(
            self._sam_model, output_mode="uncompressed_rle", **self.generator_kwargs
        )
        generator.predictor = _OneGranularityPredictor(generator.predictor)
        return generator

    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        from segment_anything.utils.amg import rle_to_mask

        image = _as_rgb_uint8(image, image_path)
        if self._generator is None:
            self._generator = self._build_generator()
        image = _limit_long_side(image, self.max_long_side)
        predictor: _OneGranularityPredictor = self._generator.predictor
        height, width = image.shape[:2]
        output_index = {"default": None, "s": 0, "m": 1, "l": 2}
        label_images = []
        try:
            for level in self.levels:
                predictor.output_index = output_index[level]
                annotations = self._generator.generate(image)
                label_images.append(_paint_rles(annotations, (height, width), rle_to_mask))
        finally:
            predictor.output_index = None
            predictor.clear_embeddings()
        return label_images


def _empty_safe_generator_class(base: type) -> type:
    """segment_anything 1.0's generator with crops (crop_n_layers >= 1) crashes in its cross-crop NMS
    (``box_area`` of an empty 1-D tensor) when no crop yields a mask; a view without masks is valid
    (no vote supervision there), so this subclass returns no masks instead. Otherwise unchanged."""

    class EmptySafeMaskGenerator(base):
        def _generate_masks(self, image: np.ndarray):
            # SamAutomaticMaskGenerator._generate_masks of segment_anything 1.0, plus the empty guard
            import torch
            from segment_anything.utils.amg import MaskData, generate_crop_boxes
            from torchvision.ops.boxes import batched_nms, box_area

            orig_size = image.shape[:2]
            crop_boxes, layer_idxs = generate_crop_boxes(orig_size, self.crop_n_layers, self.crop_overlap_ratio)
            data = MaskData()
            for crop_box, layer_idx in zip(crop_boxes, layer_idxs):
                data.cat(self._process_crop(image, crop_box, layer_idx, orig_size))
            if len(crop_boxes) > 1 and len(data["rles"]) > 0:
                # remove duplicates between crops, preferring masks from smaller crops
                scores = 1 / box_area(data["crop_boxes"])
                scores = scores.to(data["boxes"].device)
                keep_by_nms = batched_nms(
                    data["boxes"].float(), scores, torch.zeros(len(data["boxes"])), iou_threshold=self.crop_nms_thresh
                )
                data.filter(keep_by_nms)
            data.to_numpy()
            return data

    return EmptySafeMaskGenerator


def _paint_rles(annotations: List[Dict[str, Any]], shape: Tuple[int, int], rle_to_mask) -> np.ndarray:
    """Label image from RLE masks with the rule of :func:`labels_from_binary_masks`, one mask in memory at a time."""
    if not annotations:
        return labels_from_binary_masks([], shape=shape)
    areas = np.array([int(a["area"]) for a in annotations], dtype=np.int64)
    indices = np.arange(len(annotations))
    labels = np.zeros(shape, dtype=np.int32)
    for i in np.lexsort((-indices, -areas)):
        labels[rle_to_mask(annotations[i]["segmentation"])] = i + 1
    return labels


def _as_rgb_uint8(image: np.ndarray, image_path: PathLike) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise VoteSplatInputError(f"image {image_path} must be uint8 [H, W, 3], got {image.dtype} {tuple(image.shape)}")
    return np.ascontiguousarray(image[..., :3])


def _limit_long_side(image: np.ndarray, max_long_side: Optional[int]) -> np.ndarray:
    height, width = image.shape[:2]
    if max_long_side is None or max(height, width) <= max_long_side:
        return image
    scale = max_long_side / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return np.asarray(Image.fromarray(image).resize(size, resample=Image.Resampling.BILINEAR))


def check_sam_checkpoint(checkpoint: Optional[PathLike], model_type: str) -> Path:
    """The checkpoint path if it is a readable file, else a one-line ValueError naming the expected file."""
    expected = SAM_CHECKPOINT_FILES[model_type]
    hint = (
        f"expected the SAM {model_type} checkpoint file {expected} (the official checkpoints are listed in the "
        "segment-anything repository's README, facebookresearch/segment-anything); it is never downloaded automatically"
    )
    if checkpoint is None or str(checkpoint) == "":
        raise VoteSplatInputError(f"no SAM checkpoint given: pass the path to {expected}; {hint}")
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise VoteSplatInputError(f"SAM checkpoint {path} does not exist; {hint}")
    try:
        with open(path, "rb") as handle:
            handle.read(1)
    except OSError as error:
        raise VoteSplatInputError(f"SAM checkpoint {path} is not readable ({error.strerror}); {hint}") from error
    return path


def _sampled_digest(path: Path, sample: int = 1 << 20) -> str:
    """sha256 of a large file's size, first and last MiB (cheap identity for multi-GB checkpoints)."""
    size = path.stat().st_size
    digest = hashlib.sha256(str(size).encode())
    with open(path, "rb") as handle:
        digest.update(handle.read(sample))
        if size > sample:
            handle.seek(max(sample, size - sample))
            digest.update(handle.read(sample))
    return digest.hexdigest()


def _state_dict_digest(model: Any) -> str:
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()
