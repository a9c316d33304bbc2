"""The oracle for SAM masks: segment_anything's unmodified ``SamAutomaticMaskGenerator``, run once per level.

Each level ``"s"``, ``"m"``, ``"l"`` is one generator run that keeps one multimask output of the
predictor (``OneGranularityPredictor``), ``"default"`` a run over all three; the kept masks are
painted with the smaller mask winning, then the earlier one. ``SamLevelsMaskGenerator`` must give
the same label images. Test code, also timed by ``benchmarks/bench_sam.py`` as the per-level path.
"""

from __future__ import annotations

import hashlib
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

OUTPUT_INDEX = {"default": None, "s": 0, "m": 1, "l": 2}


class OneGranularityPredictor:
    """A predictor whose ``predict_torch`` keeps one of SAM's three multimask outputs (all when ``None``).

    Image embeddings are computed once per (crop) image and reused by the runs of the other levels.
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


def empty_safe_generator_class():
    """segment_anything 1.0's generator, except that its cross-crop NMS is skipped when no crop kept a mask
    (there ``box_area`` of an empty 1-D tensor raises); otherwise unchanged."""
    import torch
    from segment_anything import SamAutomaticMaskGenerator
    from segment_anything.utils.amg import MaskData, generate_crop_boxes
    from torchvision.ops.boxes import batched_nms, box_area

    class EmptySafeMaskGenerator(SamAutomaticMaskGenerator):
        def _generate_masks(self, image: np.ndarray):
            orig_size = image.shape[:2]
            crop_boxes, layer_idxs = generate_crop_boxes(orig_size, self.crop_n_layers, self.crop_overlap_ratio)
            data = MaskData()
            for crop_box, layer_idx in zip(crop_boxes, layer_idxs):
                data.cat(self._process_crop(image, crop_box, layer_idx, orig_size))
            if len(crop_boxes) > 1 and len(data["rles"]) > 0:
                scores = 1 / box_area(data["crop_boxes"])
                scores = scores.to(data["boxes"].device)
                keep_by_nms = batched_nms(
                    data["boxes"].float(), scores, torch.zeros(len(data["boxes"])), iou_threshold=self.crop_nms_thresh
                )
                data.filter(keep_by_nms)
            data.to_numpy()
            return data

    return EmptySafeMaskGenerator


def paint_annotations(annotations: List[Dict[str, Any]], shape: Tuple[int, int]) -> np.ndarray:
    """Label image from the generator's RLE records: the smaller mask wins, then the earlier one."""
    from segment_anything.utils.amg import rle_to_mask

    labels = np.zeros(shape, dtype=np.int32)
    if not annotations:
        return labels
    areas = np.array([int(a["area"]) for a in annotations], dtype=np.int64)
    indices = np.arange(len(annotations))
    for i in np.lexsort((-indices, -areas)):
        labels[rle_to_mask(annotations[i]["segmentation"])] = i + 1
    return labels


class ReferenceGenerator:
    """``label_images(image)`` by segment_anything's own generator, one run per level."""

    def __init__(self, model: Any, predictor: Any, levels: Sequence[str], **generator_kwargs):
        self.generator = empty_safe_generator_class()(model, output_mode="uncompressed_rle", **generator_kwargs)
        self.predictor = OneGranularityPredictor(predictor if predictor is not None else self.generator.predictor)
        self.generator.predictor = self.predictor
        self.levels = tuple(levels)
        self.annotations: Dict[str, List[Dict[str, Any]]] = {}

    def label_images(self, image: np.ndarray) -> List[np.ndarray]:
        label_images = []
        try:
            for level in self.levels:
                self.predictor.output_index = OUTPUT_INDEX[level]
                self.annotations[level] = self.generator.generate(image)
                label_images.append(paint_annotations(self.annotations[level], image.shape[:2]))
        finally:
            self.predictor.output_index = None
            self.predictor.clear_embeddings()
        return label_images
