"""The options of the ``sam`` mask source, declared (and documented) once.

:class:`SamOptions` is a base of both configs that take them, ``ns-train``'s
:class:`~votesplat_ns.ns.datamanager.VoteDataManagerConfig` (``--pipeline.datamanager.sam-*``) and
``votesplat masks``' :class:`~votesplat_ns.ns.masks.MasksConfig` (``--sam-*``), so the two commands
offer the same flags, defaults and help, and a cache made by one is reused by the other. The field
names stay flat (``sam_points_per_side``, not ``sam.points_per_side``): the flags and the config.yml
of earlier runs name them so.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Dict, Literal, Optional

from votesplat_ns.core.sam_masks import DEFAULT_POINTS_PER_BATCH


@dataclass
class SamOptions:
    """Segment Anything's checkpoint, device and automatic mask generator settings."""

    sam_checkpoint: Optional[Path] = None
    """For the sam mask source: the SAM checkpoint file, e.g. sam_vit_h_4b8939.pth (never downloaded)."""
    sam_model_type: Literal["vit_h", "vit_l", "vit_b"] = "vit_h"
    """SAM backbone of that checkpoint."""
    sam_device: Optional[str] = None
    """Device SAM runs on (default: cuda when available, else cpu)."""
    sam_points_per_side: int = 32
    """SAM automatic mask generator: points per image side."""
    sam_pred_iou_thresh: float = 0.7
    """SAM automatic mask generator: lowest predicted IoU of a kept mask."""
    sam_stability_score_thresh: float = 0.85
    """SAM automatic mask generator: lowest stability score of a kept mask."""
    sam_crop_n_layers: int = 1
    """SAM automatic mask generator: layers of image crops (0: whole image only)."""
    sam_points_per_batch: int = DEFAULT_POINTS_PER_BATCH
    """SAM automatic mask generator: point prompts per decoder call (1024: faster with vit_b, twice the memory)."""
    sam_min_mask_region_area: int = 100
    """SAM automatic mask generator: smallest mask region kept, in pixels."""
    sam_max_long_side: Optional[int] = 1080
    """Images are shrunk to this long side before SAM (None: full size); LangSplat uses 1080."""
    sam_precision: Literal["auto", "fp32", "tf32", "bf16"] = "auto"
    """SAM encoder and decoder arithmetic. auto: bf16 on a GPU that has it (about 0.95 s per 1080p image with vit_h on an H200, masks at IoU 0.99 with fp32's), else fp32; fp32: segment_anything's own masks (about 1.9 s); tf32: 1.1-1.2 s, masks at IoU 0.999."""
    sam_compile: bool = True
    """On a GPU, run SAM's prompt decoder and the masks' stability scores through torch.compile: about half the decoder's time in fp32, a third in bf16, after some 15 s of compiling per process (False: uncompiled)."""

    def sam_settings(self) -> Dict[str, Any]:
        """Every SAM option by field name, to hand to another config that takes them."""
        return {option.name: getattr(self, option.name) for option in fields(SamOptions)}

    def sam_generator_options(self) -> Dict[str, Any]:
        """The automatic mask generator's settings, as ``make_mask_source(sam_options=...)`` takes them."""
        return dict(
            points_per_side=self.sam_points_per_side,
            points_per_batch=self.sam_points_per_batch,
            pred_iou_thresh=self.sam_pred_iou_thresh,
            stability_score_thresh=self.sam_stability_score_thresh,
            crop_n_layers=self.sam_crop_n_layers,
            min_mask_region_area=self.sam_min_mask_region_area,
            max_long_side=self.sam_max_long_side,
            precision=self.sam_precision,
            compile_decoder=self.sam_compile,
        )
