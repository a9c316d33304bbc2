"""A deterministic stand-in for SAM's prompt decoder, derived from label maps at three granularities.

``StandInPredictor`` has the ``SamPredictor`` interface the automatic mask generator uses, and the
``SamSteps`` interface (``encode_crops`` / ``decode_points`` / ``upscale_masks`` / ``stability_and_boxes``) that
``SamLevelsMaskGenerator`` uses; both give the same masks. For a point prompt it answers, per
granularity (output 0, 1, 2: fine, medium, coarse), the segment under the point as logits: a blurred
indicator of the segment (so stability scores fall below 1 on thin or small segments), plus a fixed
noise field near the segment's boundary (holes and islands there for the small-region removal) and
a per-point bias (the boundary moves by a pixel or so between prompts, so NMS sees near-duplicates).
Its predicted IoU is a hash of the segment and the point, quantised to 1/64 so that ties occur.
Many masks survive the filters, as with real weights. It replaces the decoder's outputs only in
tests and benchmarks: ``scene(...)`` builds an image and its three label maps.

Given a real ``model_predictor`` (a ``SamPredictor``), the model's encoder, decoder and upscaling
also run on the same prompts and masks, their outputs dropped, so that a timing pays their cost and
memory: ``decode_points`` hands out the model's low-resolution logits with the stand-in's segment
written into each mask's first three values, and ``upscale_masks`` upscales them as the model would
before making the stand-in's logits. Its own work, which real weights do not have, is on top: a copy of
each mask's precomputed segment logits plus the prompt's bias (``own_seconds`` adds up its time).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from types import SimpleNamespace
from typing import Iterator, List, Sequence, Tuple

import numpy as np
import torch


def scene(height: int, width: int, seed: int = 0, fine_cells: int = 40) -> Tuple[np.ndarray, List[np.ndarray]]:
    """An RGB uint8 image and three nested label maps (fine ⊂ medium ⊂ coarse): Voronoi cells merged twice."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    seeds = rng.uniform((0, 0), (height, width), size=(fine_cells, 2))
    fine = np.empty((height, width), dtype=np.int64)
    for top in range(0, height, 32):  # in bands of rows: [rows, width, cells] stays small at 4K
        rows = slice(top, top + 32)
        distance = (yy[rows, :, None] - seeds[:, 0]) ** 2 + (xx[rows, :, None] - seeds[:, 1]) ** 2
        fine[rows] = np.argmin(distance, axis=-1)
    maps = [fine]
    for groups in (max(2, fine_cells // 4), max(2, fine_cells // 12)):
        centres = rng.uniform((0, 0), (height, width), size=(groups, 2))
        group_of_seed = np.argmin(((seeds[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)
        maps.append(group_of_seed[fine])
    colours = rng.integers(0, 256, size=(fine_cells, 3))
    image = np.clip(colours[fine] + rng.normal(0, 12, size=(height, width, 3)), 0, 255).astype(np.uint8)
    return image, [m.astype(np.int64) for m in maps]


class StandInPredictor:
    """``SamPredictor``'s and ``SamSteps``' interfaces over label maps; ``image`` is the full image the generator crops."""

    def __init__(
        self,
        image: np.ndarray,
        label_maps: Sequence[np.ndarray],
        crop_n_layers: int,
        crop_overlap_ratio: float = 512 / 1500,
        device: str = "cpu",
        seed: int = 0,
        noise: float = 6.0,
        model_predictor=None,
        precision: str = "fp32",
        crops_per_encoder_pass=None,
        decoder: str = "folded",
        compile_decoder: bool = False,
    ):
        from segment_anything.utils.amg import generate_crop_boxes
        from segment_anything.utils.transforms import ResizeLongestSide

        from votesplat_ns.core.sam_masks import SamSteps

        assert len(label_maps) == 3
        self.model_predictor = model_predictor  # a real SamPredictor run alongside, for timing: its outputs are dropped
        self.model_steps = (
            SamSteps(model_predictor, precision, crops_per_encoder_pass, decoder, compile_decoder)
            if model_predictor is not None
            else None
        )
        self.precision = precision  # the generator holds tf32's matmul precision over each image, as for SamSteps
        self.image = image
        self.device = torch.device(device)
        self.transform = ResizeLongestSide(1024)
        self.model = SimpleNamespace(mask_threshold=0.0)
        self.mask_threshold = 0.0
        self.labels = torch.as_tensor(np.stack(label_maps), device=self.device)
        generator = torch.Generator().manual_seed(seed)
        self.noise = (noise * torch.randn(self.labels.shape, generator=generator)).to(self.device)
        self._maps = None  # [segments of every level, H, W]: each segment's logits before the prompt's bias
        self.own_seconds = None  # set to 0.0 to add up the time of the stand-in's own work (synchronised)
        self._first = torch.as_tensor(
            np.cumsum([0] + [int(m.max()) + 1 for m in label_maps[:2]]), device=self.device
        )  # each level's first segment in _maps
        self.crop_boxes: List[Tuple[int, int, int, int]] = [
            (box[0], box[1], box[2], box[3])
            for box in generate_crop_boxes(image.shape[:2], crop_n_layers, crop_overlap_ratio)[0]
        ]
        self.reset_image()

    # ---------------------------------------------------------------- the stand-in's masks
    def _crop_of(self, image: np.ndarray) -> Tuple[int, int, int, int]:
        h, w = image.shape[:2]
        matches = [
            box
            for box in self.crop_boxes
            if (box[3] - box[1], box[2] - box[0]) == (h, w)
            and np.array_equal(self.image[box[1] : box[3], box[0] : box[2]], image)
        ]
        assert len(matches) == 1, f"{len(matches)} crops of the stand-in's image match the image given"
        return matches[0]

    def segment_maps(self) -> torch.Tensor:
        """Every segment's logits over the whole image before the prompt's bias, level after level: its indicator
        box-blurred (5 x 5), ``12 (blurred - 0.5)``, plus the level's noise field times ``4 blurred (1 - blurred)``
        (1 on the segment's boundary, 0 two pixels away from it). Made once, on first use."""
        if self._maps is None:
            maps = []
            for index, level in enumerate(self.labels):
                for first in range(0, int(level.max()) + 1, 16):
                    segments = torch.arange(first, min(first + 16, int(level.max()) + 1), device=self.device)
                    inside = (level[None] == segments[:, None, None]).float()[:, None]
                    blurred = torch.nn.functional.avg_pool2d(inside, 5, stride=1, padding=2, count_include_pad=False)
                    blurred = blurred[:, 0]
                    band = 4.0 * blurred * (1.0 - blurred)
                    maps.append(12.0 * (blurred - 0.5) + band * self.noise[index])
            self._maps = torch.cat(maps)
        return self._maps

    def _segments(self, crop, original_size, transformed_points: torch.Tensor):
        """Per prompt (in the model's 1024 input frame) the segment under it at each level [B, 3], its predicted IoUs
        [B, 3] and the per-prompt bias code [B]."""
        x0, y0, _, _ = crop
        h, w = original_size
        new_h, new_w = self.transform.get_preprocess_shape(h, w, self.transform.target_length)
        with self._own_time():
            points = transformed_points.to(torch.float64)
            px = (points[:, 0] * (w / new_w)).floor().long().clamp(0, w - 1)
            py = (points[:, 1] * (h / new_h)).floor().long().clamp(0, h - 1)
            ids = self.labels[:, y0 + py, x0 + px].T  # [B, 3]
            # per-point bias from the point's pixel: a deterministic hash, in [-1.5, 1.5] once made a bias
            code = (px + 1) * 7919 + (py + x0 + 3) * 104729 + y0 * 31
            levels = torch.arange(3, device=ids.device)
            iou_code = (ids * 2654435761 + levels[None] * 40503 + code[:, None] * 97) % 64
            iou = (0.5 + 0.5 * iou_code.float() / 63.0).to(torch.float32)
            return ids, iou, code

    def _logits(self, crop, masks: torch.Tensor) -> torch.Tensor:
        """Logits [m, h, w] in the crop of masks given as rows (level, segment, code % 997)."""
        x0, y0, x1, y1 = crop
        with self._own_time():
            level, segment, bias_code = masks[:, 0].long(), masks[:, 1].long(), masks[:, 2].long()
            logits = self.segment_maps()[:, y0:y1, x0:x1].index_select(0, self._first[level] + segment)
            bias = (bias_code.double() / 996.0 * 3.0 - 1.5).float()
            return logits.add_(bias[:, None, None])

    @contextmanager
    def _own_time(self) -> Iterator[None]:
        if self.own_seconds is None:
            yield
            return
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        start = time.perf_counter()
        yield
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.own_seconds += time.perf_counter() - start

    @staticmethod
    def _mask_rows(ids: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """(level, segment, code % 997) of each prompt's three masks [B, 3, 3]."""
        levels = torch.arange(3, device=ids.device).expand_as(ids)
        return torch.stack([levels, ids, (code % 997)[:, None].expand_as(ids)], dim=-1)

    # ---------------------------------------------------------------- SamPredictor (the oracle's generator)
    def reset_image(self) -> None:
        self.features = None  # the crop box (x0, y0, x1, y1): what the encoder's features stand for
        self.original_size = None
        self.input_size = None
        self.is_image_set = False

    def set_image(self, image: np.ndarray, image_format: str = "RGB") -> None:
        crop = self._crop_of(image)
        if self.model_predictor is not None:
            self.model_predictor.set_image(image, image_format)
        h, w = image.shape[:2]
        self.features = crop
        self.original_size = (h, w)
        self.input_size = self.transform.get_preprocess_shape(h, w, self.transform.target_length)
        self.is_image_set = True

    def predict_torch(
        self, point_coords, point_labels, boxes=None, mask_input=None, multimask_output=True, return_logits=False
    ):
        assert self.is_image_set and multimask_output
        assert self.features is not None and self.original_size is not None
        if self.model_predictor is not None:
            self.model_predictor.predict_torch(
                point_coords, point_labels, multimask_output=True, return_logits=return_logits
            )
        ids, iou, code = self._segments(self.features, self.original_size, point_coords[:, 0, :])
        h, w = self.original_size
        logits = self._logits(self.features, self._mask_rows(ids, code).flatten(0, 1)).view(len(ids), 3, h, w)
        if not return_logits:
            logits = logits > self.model.mask_threshold
        return logits, iou, torch.zeros(len(ids), 3, 1, 1, device=self.device)

    # ---------------------------------------------------------------- SamSteps (SamLevelsMaskGenerator)
    def encode_crops(self, crops: Sequence[np.ndarray]):
        model_states = self.model_steps.encode_crops(crops) if self.model_steps is not None else [None] * len(crops)
        return [(self._crop_of(crop), tuple(crop.shape[:2]), state) for crop, state in zip(crops, model_states)]

    def decode_points(self, state, points: np.ndarray):
        crop, original_size, model_state = state
        transformed = torch.as_tensor(self.transform.apply_coords(points, original_size), device=self.device)
        ids, iou, code = self._segments(crop, original_size, transformed)
        rows = self._mask_rows(ids, code)
        if model_state is None or self.model_steps is None:
            return rows, iou
        low_res = self.model_steps.decode_points(model_state, points)[0].contiguous()
        low_res.view(len(points), 3, -1)[:, :, :3] = rows.to(low_res.dtype)  # exact: every value is below 2**24
        return low_res, iou

    def upscale_masks(self, state, low_res: torch.Tensor) -> torch.Tensor:
        crop, _, model_state = state
        if model_state is not None and self.model_steps is not None:
            self.model_steps.upscale_masks(model_state, low_res)
        return self._logits(crop, low_res.reshape(len(low_res), -1)[:, :3])

    def stability_and_boxes(self, logits: torch.Tensor, stability_offset: float):
        """The model's own function (compiled where it compiles) on the stand-in's logits."""
        from votesplat_ns.core.sam_masks import stability_and_boxes

        if self.model_steps is not None:
            return self.model_steps.stability_and_boxes(logits, stability_offset)
        return stability_and_boxes(logits, self.mask_threshold, stability_offset)
