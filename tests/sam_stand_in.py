"""A deterministic stand-in for SAM's prompt decoder, derived from label maps at three granularities.

``StandInPredictor`` has the ``SamPredictor`` interface the automatic mask generator uses. For a
point prompt it answers, per granularity (output 0, 1, 2: fine, medium, coarse), the segment under
the point as logits: a blurred indicator of the segment (so stability scores fall below 1 on thin
or small segments), plus a fixed noise field near the segment's boundary (holes and islands there for the small-region
removal) and
a per-point bias (the boundary moves by a pixel or so between prompts, so NMS sees near-duplicates).
Its predicted IoU is a hash of the segment and the point, quantised to 1/64 so that ties occur.
Many masks survive the filters, as with real weights. It replaces the decoder's outputs only in
tests and benchmarks: ``scene(...)`` builds an image and its three label maps. Given a real
``model_predictor``, its encoder and decoder also run (outputs dropped), so that a timing pays their cost.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import List, Sequence, Tuple

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
    """``SamPredictor``'s interface over label maps; ``image`` is the full image the generator crops from."""

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
    ):
        from segment_anything.utils.amg import generate_crop_boxes
        from segment_anything.utils.transforms import ResizeLongestSide

        assert len(label_maps) == 3
        self.model_predictor = model_predictor  # a real SamPredictor run alongside, for timing: its outputs are dropped
        self.image = image
        self.device = torch.device(device)
        self.transform = ResizeLongestSide(1024)
        self.model = SimpleNamespace(mask_threshold=0.0)
        self.labels = torch.as_tensor(np.stack(label_maps), device=self.device)
        generator = torch.Generator().manual_seed(seed)
        self.noise = (noise * torch.randn(self.labels.shape, generator=generator)).to(self.device)
        self._blurred_cache: dict = {}
        self.crop_boxes = generate_crop_boxes(image.shape[:2], crop_n_layers, crop_overlap_ratio)[0]
        self.reset_image()

    def reset_image(self) -> None:
        self.features = None  # the crop box (x0, y0, x1, y1): what the encoder's features stand for
        self.original_size = None
        self.input_size = None
        self.is_image_set = False

    def set_image(self, image: np.ndarray, image_format: str = "RGB") -> None:
        h, w = image.shape[:2]
        matches = [
            tuple(box)
            for box in self.crop_boxes
            if (box[3] - box[1], box[2] - box[0]) == (h, w)
            and np.array_equal(self.image[box[1] : box[3], box[0] : box[2]], image)
        ]
        assert len(matches) == 1, f"{len(matches)} crops of the stand-in's image match the image given"
        if self.model_predictor is not None:
            self.model_predictor.set_image(image, image_format)
        self.features = matches[0]
        self.original_size = (h, w)
        self.input_size = self.transform.get_preprocess_shape(h, w, self.transform.target_length)
        self.is_image_set = True

    def _blurred(self, level: int, segment: int) -> torch.Tensor:
        """The segment's indicator over the whole image, box-blurred (5 x 5): computed once per segment."""
        key = (level, segment)
        if key not in self._blurred_cache:
            inside = (self.labels[level] == segment).float()[None, None]
            blurred = torch.nn.functional.avg_pool2d(inside, 5, stride=1, padding=2, count_include_pad=False)
            self._blurred_cache[key] = blurred[0, 0]
        return self._blurred_cache[key]

    def predict_torch(
        self, point_coords, point_labels, boxes=None, mask_input=None, multimask_output=True, return_logits=False
    ):
        assert self.is_image_set and multimask_output
        if self.model_predictor is not None:
            self.model_predictor.predict_torch(
                point_coords, point_labels, multimask_output=True, return_logits=return_logits
            )
        x0, y0, x1, y1 = self.features
        h, w = self.original_size
        new_h, new_w = self.input_size
        points = point_coords[:, 0, :].to(torch.float64)
        px = (points[:, 0] * (w / new_w)).floor().long().clamp(0, w - 1)
        py = (points[:, 1] * (h / new_h)).floor().long().clamp(0, h - 1)
        labels = self.labels[:, y0:y1, x0:x1]  # [3, h, w]
        ids = labels[:, py, px].T  # [B, 3]
        blurred = torch.stack(
            [torch.stack([self._blurred(k, int(i))[y0:y1, x0:x1] for k, i in enumerate(row)]) for row in ids.tolist()]
        )  # [B, 3, h, w]
        # per-point bias from the point's pixel: a deterministic hash in [-1.5, 1.5]
        code = (px + 1) * 7919 + (py + x0 + 3) * 104729 + y0 * 31
        bias = ((code % 997).double() / 996.0 * 3.0 - 1.5).float()
        band = 4.0 * blurred * (1.0 - blurred)  # 1 on the segment's boundary, 0 two pixels away from it
        noise = band * self.noise[None, :, y0:y1, x0:x1]
        logits = 12.0 * (blurred - 0.5) + noise + bias[:, None, None, None]
        levels = torch.arange(3, device=ids.device)
        iou_code = (ids * 2654435761 + levels[None] * 40503 + code[:, None] * 97) % 64
        iou = (0.5 + 0.5 * iou_code.float() / 63.0).to(torch.float32)
        if not return_logits:
            logits = logits > self.model.mask_threshold
        return logits, iou, torch.zeros(len(ids), 3, 1, 1, device=self.device)
