"""Masks from Segment Anything's automatic mask generator, one label image per granularity level.

The checkpoint is never downloaded: :func:`check_sam_checkpoint` names the official file to fetch.
"""

from __future__ import annotations

import copy
import hashlib
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from votesplat_ns.core.image_files import PathLike
from votesplat_ns.core.mask_source_base import MaskSource, validate_levels
from votesplat_ns.errors import VoteSplatInputError, load_failure_reason

SAM_CHECKPOINT_FILES = {
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_b": "sam_vit_b_01ec64.pth",
}
"""File names of the official SAM checkpoints, as listed in the README of facebookresearch/segment-anything."""


SAM_LEVELS = ("default", "s", "m", "l")


_OUTPUT_INDEX = {"default": None, "s": 0, "m": 1, "l": 2}
"""SAM multimask output index per level; ``None``: all three outputs together (the standard generator)."""


class SamMaskSource(MaskSource):
    """Segment Anything's automatic mask generator, LangSplat-style hierarchical levels.

    Levels (any subset, in any order, of ``("default", "s", "m", "l")``):
      - ``"s"``, ``"m"``, ``"l"``: masks from SAM's multimask output 0, 1, 2 (subpart, part,
        whole), each level filtered on its own so that NMS only compares masks of one
        granularity (LangSplat's modified generator likewise keeps the three apart);
      - ``"default"``: the standard generator's masks, all three outputs together.
    All levels come from one encoder pass per crop and one decoder pass per point batch
    (:class:`SamLevelsMaskGenerator`); each level's labels are those of segment_anything's
    ``SamAutomaticMaskGenerator`` run on that level alone.
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
        self.generator_kwargs: Dict[str, Any] = dict(
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

    def __getstate__(self) -> Dict[str, Any]:
        # sent to another process (vote_cache_ranks) without the generator: it holds the encoder's last features
        state = dict(self.__dict__)
        state["_generator"] = None
        return state

    def on_device(self, device: str) -> "SamMaskSource":
        """A copy that runs SAM on ``device`` (its model is built there at the first image)."""
        moved = copy.copy(self)
        moved.device = device
        moved._generator = None
        return moved

    def _resolve_device(self) -> str:
        if self.device:
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"

    def _build_generator(self):
        import torch
        from segment_anything import SamPredictor, sam_model_registry

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
        return SamLevelsMaskGenerator(SamPredictor(self._sam_model), self.levels, **self.generator_kwargs)

    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        image = _as_rgb_uint8(image, image_path)
        if self._generator is None:
            self._generator = self._build_generator()
        return self._generator.label_images(_limit_long_side(image, self.max_long_side))


class SamLevelsMaskGenerator:
    """segment_anything's ``SamAutomaticMaskGenerator`` for several granularity levels in one pass.

    Per crop the image encoder runs once and the prompt decoder once per point batch, keeping all
    three multimask outputs; each level then takes its masks from that one set (``"s"``, ``"m"``,
    ``"l"``: output 0, 1, 2; ``"default"``: all three, in the generator's point-major order) and
    goes through segment_anything's own filters: predicted IoU, stability score, crop-edge boxes,
    box NMS within the crop, NMS across crops, small-region removal with its NMS. Every step calls
    the same segment_anything/torchvision function on the same values in the same order as
    ``SamAutomaticMaskGenerator`` run once per level, so ties break the same way and the label
    images are the same. What is not repeated: the encoder and decoder per level, the per-mask
    quantities (computed once per mask and shared by the levels that hold it), the RLE round trip
    (a binary mask is kept as its bounding-box window instead: ``rle_to_mask(mask_to_rle(m)) == m``),
    and the small-region clean-up of a mask that several levels keep; that clean-up also works in the
    mask's box rather than the whole image (:func:`_small_regions_removed`, same result). A crop's
    masks that pass the filters stay on the device until its NMS; the kept ones move to the host.

    ``predictor`` is a ``SamPredictor`` (or anything with its ``set_image`` / ``predict_torch`` /
    ``reset_image`` / ``transform`` / ``device`` / ``model.mask_threshold``).
    Set ``stage_seconds = {}`` to accumulate seconds per stage (the device is synchronised at each
    stage boundary then, so only for measuring).
    """

    def __init__(
        self,
        predictor: Any,
        levels: Sequence[str],
        points_per_side: int = 32,
        points_per_batch: int = 64,
        pred_iou_thresh: float = 0.88,
        stability_score_thresh: float = 0.95,
        stability_score_offset: float = 1.0,
        box_nms_thresh: float = 0.7,
        crop_n_layers: int = 0,
        crop_nms_thresh: float = 0.7,
        crop_overlap_ratio: float = 512 / 1500,
        crop_n_points_downscale_factor: int = 1,
        min_mask_region_area: int = 0,
    ):
        from segment_anything.utils.amg import build_all_layer_point_grids

        unknown = [level for level in levels if level not in _OUTPUT_INDEX]
        if unknown:
            raise VoteSplatInputError(f"unknown SAM mask levels {unknown}; use a subset of {list(SAM_LEVELS)}")
        self.predictor = predictor
        self.levels = tuple(levels)
        self.point_grids = build_all_layer_point_grids(points_per_side, crop_n_layers, crop_n_points_downscale_factor)
        self.points_per_batch = points_per_batch
        self.pred_iou_thresh = pred_iou_thresh
        self.stability_score_thresh = stability_score_thresh
        self.stability_score_offset = stability_score_offset
        self.box_nms_thresh = box_nms_thresh
        self.crop_n_layers = crop_n_layers
        self.crop_nms_thresh = crop_nms_thresh
        self.crop_overlap_ratio = crop_overlap_ratio
        self.min_mask_region_area = min_mask_region_area
        self.stage_seconds: Optional[Dict[str, float]] = None

    @contextmanager
    def _stage(self, name: str) -> Iterator[None]:
        if self.stage_seconds is None:
            yield
            return
        self._synchronize()
        start = time.perf_counter()
        yield
        self._synchronize()
        self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - start

    def _synchronize(self) -> None:
        import torch

        device = torch.device(self.predictor.device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def label_images(self, image: np.ndarray) -> List[np.ndarray]:
        """One int32 label image per level for an RGB uint8 [H, W, 3] image (0: no mask)."""
        import torch

        with torch.no_grad():
            return self._label_images(image)

    def _label_images(self, image: np.ndarray) -> List[np.ndarray]:
        import torch
        from segment_anything.utils.amg import MaskData, generate_crop_boxes
        from torchvision.ops.boxes import batched_nms, box_area

        orig_size = (int(image.shape[0]), int(image.shape[1]))
        crop_boxes, layer_idxs = generate_crop_boxes(orig_size, self.crop_n_layers, self.crop_overlap_ratio)
        windows = _MaskWindows(orig_size)
        per_level = {level: MaskData() for level in self.levels}
        for crop_box, layer_idx in zip(crop_boxes, layer_idxs):
            crop_data = self._process_crop(image, crop_box, layer_idx, orig_size, windows)
            for level in self.levels:
                per_level[level].cat(crop_data[level])

        label_images = []
        for level in self.levels:
            data = per_level[level]
            with self._stage("nms"):
                # SamAutomaticMaskGenerator._generate_masks: duplicates between crops, smaller crops preferred;
                # skipped without masks (segment_anything 1.0's box_area fails on the empty 1-D tensor there)
                if len(crop_boxes) > 1 and len(data["ids"]) > 0:
                    scores = 1 / box_area(data["crop_boxes"])
                    scores = scores.to(data["boxes"].device)
                    keep_by_nms = batched_nms(
                        data["boxes"].float(),
                        scores,
                        torch.zeros(len(data["boxes"])),
                        iou_threshold=self.crop_nms_thresh,
                    )
                    data.filter(keep_by_nms)
                data.to_numpy()
            ids = [int(i) for i in data["ids"]]
            with self._stage("small_regions"):
                if self.min_mask_region_area > 0 and ids:
                    masks = self._remove_small_regions(ids, windows)
                else:
                    masks = [windows.original(i) for i in ids]
            with self._stage("paint"):
                label_images.append(_paint_windows(masks, orig_size))
        return label_images

    def _process_crop(self, image, crop_box, crop_layer_idx, orig_size, windows: "_MaskWindows") -> Dict[str, Any]:
        import torch
        from segment_anything.utils.amg import MaskData, batch_iterator, uncrop_boxes_xyxy
        from torchvision.ops.boxes import batched_nms

        x0, y0, x1, y1 = crop_box
        cropped_im = image[y0:y1, x0:x1, :]
        cropped_im_size = cropped_im.shape[:2]
        with self._stage("encoder"):
            self.predictor.set_image(cropped_im)
        points_scale = np.array(cropped_im_size)[None, ::-1]
        points_for_image = self.point_grids[crop_layer_idx] * points_scale

        per_level = {level: MaskData() for level in self.levels}
        batch_masks, batch_boxes = [], []
        first_id = windows.next_id
        for (points,) in batch_iterator(self.points_per_batch, points_for_image):
            with self._stage("decoder"):
                transformed_points = self.predictor.transform.apply_coords(points, cropped_im_size)
                in_points = torch.as_tensor(transformed_points, device=self.predictor.device)
                in_labels = torch.ones(in_points.shape[0], dtype=torch.int, device=in_points.device)
                logits, iou_preds, _ = self.predictor.predict_torch(
                    in_points[:, None, :], in_labels[:, None], multimask_output=True, return_logits=True
                )
            with self._stage("filter"):
                masks, boxes, iou, outputs = self._filter_batch(logits, iou_preds, crop_box, orig_size)
                del logits
                ids = torch.arange(windows.next_id, windows.next_id + len(iou), device=iou.device)
                windows.next_id += len(iou)
                for level in self.levels:
                    index = _OUTPUT_INDEX[level]
                    select = slice(None) if index is None else outputs == index
                    per_level[level].cat(MaskData(boxes=boxes[select], iou_preds=iou[select], ids=ids[select]))
                batch_masks.append(masks)
                batch_boxes.append(boxes)
        self.predictor.reset_image()

        with self._stage("nms"):
            for level in self.levels:
                data = per_level[level]
                # remove duplicates within this crop (SamAutomaticMaskGenerator._process_crop)
                keep_by_nms = batched_nms(
                    data["boxes"].float(),
                    data["iou_preds"],
                    torch.zeros(len(data["boxes"])),
                    iou_threshold=self.box_nms_thresh,
                )
                data.filter(keep_by_nms)
                data["boxes"] = uncrop_boxes_xyxy(data["boxes"], crop_box)
                data["crop_boxes"] = torch.tensor([crop_box for _ in range(len(data["ids"]))])
        with self._stage("keep_masks"):
            kept = sorted({int(i) for level in self.levels for i in per_level[level]["ids"].tolist()})
            windows.add(kept, first_id, batch_masks, batch_boxes, (x0, y0))
        return per_level

    def _filter_batch(self, logits, iou_preds, crop_box, orig_size):
        """SamAutomaticMaskGenerator._process_batch's filters on all outputs of a batch at once.

        Every quantity is per mask (integer pixel counts, the box), so a level's subset gets the
        values the generator computes for it; the outputs come back point-major like its flatten(0, 1).
        """
        import torch
        from segment_anything.utils.amg import batched_mask_to_box, calculate_stability_score, is_box_near_crop_edge

        orig_h, orig_w = orig_size
        n_points, n_outputs = logits.shape[:2]
        logits = logits.flatten(0, 1)
        iou = iou_preds.flatten(0, 1)
        outputs = torch.arange(n_outputs, device=iou.device).repeat(n_points)
        if self.pred_iou_thresh > 0.0:
            keep = iou > self.pred_iou_thresh
            logits, iou, outputs = logits[keep], iou[keep], outputs[keep]
        mask_threshold = self.predictor.model.mask_threshold
        stability = calculate_stability_score(logits, mask_threshold, self.stability_score_offset)
        if self.stability_score_thresh > 0.0:
            keep = stability >= self.stability_score_thresh
            logits, iou, outputs = logits[keep], iou[keep], outputs[keep]
        masks = logits > mask_threshold
        boxes = batched_mask_to_box(masks)
        keep = ~is_box_near_crop_edge(boxes, crop_box, [0, 0, orig_w, orig_h])
        if not torch.all(keep):
            masks, boxes, iou, outputs = masks[keep], boxes[keep], iou[keep], outputs[keep]
        return masks, boxes, iou, outputs

    def _remove_small_regions(self, ids: List[int], windows: "_MaskWindows") -> List["_Window"]:
        """SamAutomaticMaskGenerator.postprocess_small_regions on one level's masks, in its order."""
        import torch
        from torchvision.ops.boxes import batched_nms

        cleaned = [windows.cleaned(i, self.min_mask_region_area) for i in ids]
        boxes = torch.stack([torch.as_tensor(window.box_xyxy()) for window, _ in cleaned])
        scores = [float(unchanged) for _, unchanged in cleaned]
        keep_by_nms = batched_nms(
            boxes.float(),
            torch.as_tensor(scores),
            torch.zeros(len(boxes)),
            iou_threshold=max(self.box_nms_thresh, self.crop_nms_thresh),
        )
        return [cleaned[int(i)][0] for i in keep_by_nms]


class _Window:
    """A binary mask of the whole image held as its bounding-box window: rows y0.., columns x0.."""

    __slots__ = ("x0", "y0", "mask")

    def __init__(self, x0: int, y0: int, mask: np.ndarray):
        self.x0, self.y0, self.mask = x0, y0, mask

    def area(self) -> int:
        return int(np.count_nonzero(self.mask))

    def box_xyxy(self) -> np.ndarray:
        """batched_mask_to_box's box (inclusive max corner; zeros for an empty mask)."""
        rows = np.flatnonzero(self.mask.any(axis=1))
        cols = np.flatnonzero(self.mask.any(axis=0))
        if rows.size == 0:
            return np.zeros(4, dtype=np.int64)
        return np.array([self.x0 + cols[0], self.y0 + rows[0], self.x0 + cols[-1], self.y0 + rows[-1]], dtype=np.int64)

    def full(self, shape: Tuple[int, int]) -> np.ndarray:
        out = np.zeros(shape, dtype=bool)
        h, w = self.mask.shape
        out[self.y0 : self.y0 + h, self.x0 : self.x0 + w] = self.mask
        return out

    @staticmethod
    def of_window(x0: int, y0: int, mask: np.ndarray) -> "_Window":
        """The window of a mask given on a window at (x0, y0), trimmed to its bounding box."""
        trimmed = _Window.of(mask)
        return _Window(x0 + trimmed.x0, y0 + trimmed.y0, trimmed.mask)

    @staticmethod
    def of(mask: np.ndarray) -> "_Window":
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            return _Window(0, 0, np.zeros((0, 0), dtype=bool))
        y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        return _Window(int(x0), int(y0), np.ascontiguousarray(mask[y0:y1, x0:x1]))


class _MaskWindows:
    """The masks some level keeps, by candidate id, as windows on the host; small-region results cached."""

    def __init__(self, shape: Tuple[int, int]):
        self.shape = shape
        self.next_id = 0
        self._windows: Dict[int, _Window] = {}
        self._cleaned: Dict[int, Tuple[_Window, bool]] = {}

    def add(self, kept: List[int], first_id: int, batch_masks, batch_boxes, offset: Tuple[int, int]) -> None:
        import torch

        start = first_id
        kept_array = np.asarray(kept, dtype=np.int64)
        for masks, boxes in zip(batch_masks, batch_boxes):
            stop = start + len(masks)
            local = kept_array[(kept_array >= start) & (kept_array < stop)] - start
            if local.size:
                index = torch.as_tensor(local, device=masks.device)
                host_masks = masks[index].cpu().numpy()
                host_boxes = boxes[index].long().cpu().numpy()
                for j, mask, box in zip(local.tolist(), host_masks, host_boxes):
                    bx0, by0, bx1, by1 = (int(v) for v in box)
                    window = np.ascontiguousarray(mask[by0 : by1 + 1, bx0 : bx1 + 1])
                    self._windows[start + j] = _Window(offset[0] + bx0, offset[1] + by0, window)
            start = stop

    def original(self, mask_id: int) -> _Window:
        return self._windows[mask_id]

    def cleaned(self, mask_id: int, min_area: int) -> Tuple[_Window, bool]:
        """segment_anything's hole then island removal of one mask, and whether it left the mask unchanged."""
        saved = self._cleaned.get(mask_id)
        if saved is None:
            saved = _small_regions_removed(self._windows[mask_id], self.shape, min_area)
            self._cleaned[mask_id] = saved
        return saved


def _small_regions_removed_whole_image(window: _Window, shape: Tuple[int, int], min_area: int) -> Tuple[_Window, bool]:
    """SamAutomaticMaskGenerator.postprocess_small_regions on one mask: segment_anything's routine on the whole image."""
    from segment_anything.utils.amg import remove_small_regions

    mask = window.full(shape)
    mask, changed = remove_small_regions(mask, min_area, mode="holes")
    unchanged = not changed
    mask, changed = remove_small_regions(mask, min_area, mode="islands")
    unchanged = unchanged and not changed
    return _Window.of(mask), unchanged


def _outside_pieces(box: Tuple[int, int, int, int], shape: Tuple[int, int]) -> List[int]:
    """Pixel counts of the connected pieces of the image outside a box (x0, y0, x1, y1 exclusive)."""
    x0, y0, x1, y1 = box
    height, width = shape
    top, bottom = y0 * width, (height - y1) * width
    left, right = (y1 - y0) * x0, (y1 - y0) * (width - x1)
    if (top or bottom) and (left or right):
        return [top + bottom + left + right]  # a side strip joins the top and bottom strips
    return [size for size in (top, bottom, left, right) if size]


def _small_regions_removed(window: _Window, shape: Tuple[int, int], min_area: int) -> Tuple[_Window, bool]:
    """The result of segment_anything's ``remove_small_regions`` (holes, then islands) on the whole image, computed
    in the mask's box grown by one pixel, so that its cost follows the mask's size, not the image's.

    Why it is the same: every pixel outside the box is background, so each connected piece of the image outside the
    box lies in one background component, reached through the one-pixel ring; a ring-touching component is at least
    as large as that piece, and when every piece has ``min_area`` pixels or more none of them is a small hole, as on
    the whole image. The other background components and all mask components lie inside the box, with the same
    pixels as on the whole image. segment_anything keeps the first largest island when all are small; labels are
    numbered in scan order, which a window could change, so a tie for the largest goes to the whole-image routine,
    as does a piece outside the box smaller than ``min_area``.
    """
    import cv2

    height, width = shape
    h, w = window.mask.shape
    x0, y0 = window.x0, window.y0
    if h == 0 or w == 0 or min(_outside_pieces((x0, y0, x0 + w, y0 + h), shape), default=min_area) < min_area:
        return _small_regions_removed_whole_image(window, shape, min_area)
    px0, py0 = max(0, x0 - 1), max(0, y0 - 1)
    px1, py1 = min(width, x0 + w + 1), min(height, y0 + h + 1)
    padded = np.zeros((py1 - py0, px1 - px0), dtype=bool)
    inner = (slice(y0 - py0, y0 - py0 + h), slice(x0 - px0, x0 - px0 + w))
    padded[inner] = window.mask

    # holes: background components inside the box smaller than min_area are filled
    _, regions, stats, _ = cv2.connectedComponentsWithStats((~padded).astype(np.uint8), connectivity=8)
    ring = np.ones(padded.shape, dtype=bool)
    ring[inner] = False
    touching = np.zeros(len(stats), dtype=bool)
    touching[np.unique(regions[ring])] = True
    small = np.flatnonzero((stats[:, -1] < min_area) & ~touching)
    small = small[small > 0]  # label 0: the mask's own pixels
    mask = window.mask
    holes_changed = small.size > 0
    if holes_changed:
        mask = mask | np.isin(regions[inner], small)

    # islands: mask components smaller than min_area are dropped, the largest one kept if all are
    _, regions, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    sizes = stats[1:, -1]
    small_islands = sizes < min_area
    if not small_islands.any():
        return _Window.of_window(x0, y0, mask), not holes_changed
    if small_islands.all() and np.count_nonzero(sizes == sizes.max()) > 1:
        return _small_regions_removed_whole_image(_Window(x0, y0, mask), shape, min_area)[0], False
    keep = np.flatnonzero(~small_islands) + 1 if not small_islands.all() else [int(np.argmax(sizes)) + 1]
    return _Window.of_window(x0, y0, np.isin(regions, keep)), False


def _paint_windows(masks: List[_Window], shape: Tuple[int, int]) -> np.ndarray:
    """Label image with the rule of :func:`labels_from_binary_masks`: a smaller mask wins, then the earlier one."""
    labels = np.zeros(shape, dtype=np.int32)
    if not masks:
        return labels
    areas = np.array([window.area() for window in masks], dtype=np.int64)
    indices = np.arange(len(masks))
    for i in np.lexsort((-indices, -areas)):
        window = masks[i]
        h, w = window.mask.shape
        labels[window.y0 : window.y0 + h, window.x0 : window.x0 + w][window.mask] = i + 1
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
